#!/usr/bin/env bash
# SynthCity-trained retrievers on Gardens Point Walking (a test set) with ESPNetv2's mask (the Cityscapes segmenter
# its authors trained) and that mask's controls: synthcity-default's four checkpoints over SEEDS (NetVLAD and SRAL
# trained without a mask, SRAL trained with the SynthCity student's and with the SynthCity teacher's mask), each
# evaluated on each pair without a mask, with ESPNetv2's mask in place of any it was trained with, and with that
# mask's controls (its objects only, its sky only, as many cells at random, another image's mask); then, on one pair
# with CamVid test's objects pasted into its frames at CamVid train's coverage (occluded-real-coverage's occluders,
# draw 0) and at 10 % of each image, without a mask, with the pasted pixels' mask, with ESPNetv2's and with as many
# cells at random.
# summarize.py pairs every masked job by query with the same checkpoint unmasked.
# Usage, from the repository root (each step is cached; a second run only re-reads, and reruns what did not end):
#   [SEEDS=0,1,2] [OCCLUDED_PAIR=day_left:night_right] bash experiments/espnetv2-trained-streets/run.sh OUT \
#     [GARDENS_ROOT] [ESPNETV2_FILE] [CAMVID_ROOT]
set -euo pipefail
source "$(dirname "$0")/../sweeps.sh"
OUT=$(realpath -m "${1:?usage: run.sh OUT [GARDENS_ROOT] [ESPNETV2_FILE]}")
GARDENS=${2:-../shared/realdata/gardens_point}
# As given (relative to the repository root by default): the tables name the file by this path.
ESPNET=${3:-../shared/realdata/segmenters/espnetv2/espnetv2_s_2.0_city_1024x512.pth}
CAMVID=$(realpath "${4:-../shared/realdata/camvid}")
SEEDS=${SEEDS:-0,1,2}
export HF_HUB_OFFLINE=1
CACHE="$OUT/cache"
espnet=(mask=teacher teacher=espnetv2 "teacher.checkpoint=$(hq "$ESPNET")")

# 1. The checkpoints: synthcity-default's command (two sweeps: those trained without a mask, then with one).
sweep "$OUT/train" python -m semvpr.train -m "seed=$SEEDS" filter=none,attention \
  "paths.cache_dir=$(hq "$CACHE")" "hydra.sweep.dir=$(hq "$OUT/train")"
sweep "$OUT/masked" python -m semvpr.train -m "seed=$SEEDS" filter=unet,mask2former \
  "paths.cache_dir=$(hq "$CACHE")" "hydra.sweep.dir=$(hq "$OUT/masked")"
sweeps_done  # the evaluations below read these sweeps' checkpoints

ckpts() {  # the best checkpoints of sweep $1 whose filter is one of the rest: a Hydra sweep of quoted paths
  local sweep=$1 out=() f s
  shift
  for f in "$@"; do for s in ${SEEDS//,/ }; do out+=("$(hq "$OUT/$sweep/filter=$f,seed=$s/checkpoints/best.ckpt")"); done; done
  local IFS=,; echo "${out[*]}"
}
TRAINED=$(ckpts train none attention)
MASKED=$(ckpts masked unet mask2former)
ALL="$TRAINED,$MASKED"

# 2. Every checkpoint on every pair (one thread a job, two jobs side by side).
for pair in day_left:night_right day_right:night_right day_left:day_right; do
  dir="$OUT/${pair/:/-}"
  gardens_point "$dir/none" "$pair" "ckpt=$ALL" mask=none
  gardens_point "$dir/espnetv2" "$pair" "ckpt=$ALL" "${espnet[@]}" mask.control=none,objects,sky
  gardens_point "$dir/drawn" "$pair" "ckpt=$ALL" "${espnet[@]}" mask.control=random,shuffled
done

# 3. The occluded pair: the same checkpoints, one occluder draw, at CamVid train's coverage and at 10 % of each image.
occluders=(data.occluders.source=camvid "data.occluders.root=$(hq "$CAMVID")" data.occluders.seed=0)
pair=${OCCLUDED_PAIR:-day_left:night_right}
for level in occluded:camvid occluded-10:0.1; do
  dir="$OUT/${level%%:*}/${pair/:/-}"
  at=("${occluders[@]}" "data.occluders.coverage=${level#*:}")
  gardens_point "$dir/none" "$pair" "ckpt=$ALL" mask=none,oracle "${at[@]}"
  gardens_point "$dir/espnetv2" "$pair" "ckpt=$ALL" "${espnet[@]}" mask.control=none,random "${at[@]}"
done
sweeps_done
echo "done: python experiments/espnetv2-trained-streets/summarize.py $OUT"
