#!/usr/bin/env bash
# SynthCity-trained retrievers on Gardens Point Walking (a test set) with ESPNetv2's mask (the Cityscapes segmenter
# its authors trained) and that mask's controls. Four models, each over SEEDS: NetVLAD and SRAL trained without a
# mask (filter=none, filter=attention), SRAL trained with ESPNetv2's mask of SynthCity's images
# (filter=mask2former teacher=espnetv2), and SRAL with the seed's U-Net student, distilled from ESPNetv2's labels
# of SynthCity's training images on the retriever's own trunk (filter=unet teacher=espnetv2). Each checkpoint is
# evaluated on each pair without a mask, with ESPNetv2's mask, with that mask's controls (its objects only, its
# sky only, as many cells at random, another image's mask) and, for the student's checkpoints, with its own mask.
# summarize.py pairs every masked job by query with the same checkpoint unmasked.
# Usage, from the repository root (each step is cached; a second run only re-reads, and reruns what did not end):
#   [SEEDS=0,1,2] bash experiments/espnetv2-trained-streets/run.sh OUT [GARDENS_ROOT] [ESPNETV2_FILE]
set -euo pipefail
source "$(dirname "$0")/../sweeps.sh"
OUT=$(realpath -m "${1:?usage: run.sh OUT [GARDENS_ROOT] [ESPNETV2_FILE]}")
GARDENS=${2:-../shared/realdata/gardens_point}
# As given (relative to the repository root by default): the tables name the file by this path.
ESPNET=${3:-../shared/realdata/segmenters/espnetv2/espnetv2_s_2.0_city_1024x512.pth}
SEEDS=${SEEDS:-0,1,2}
export HF_HUB_OFFLINE=1
CACHE="$OUT/cache"
espnet=(teacher=espnetv2 "teacher.checkpoint=$(hq "$ESPNET")")

# 1. The checkpoints, on SynthCity's default preset: synthcity-default's command for the two trained without a
#    mask, and the two masked ones with ESPNetv2 as their teacher.
sweep "$OUT/train" python -m semvpr.train -m "seed=$SEEDS" filter=none,attention \
  "paths.cache_dir=$(hq "$CACHE")" "hydra.sweep.dir=$(hq "$OUT/train")"
sweep "$OUT/train-espnetv2" python -m semvpr.train -m "seed=$SEEDS" filter=unet,mask2former "${espnet[@]}" \
  "paths.cache_dir=$(hq "$CACHE")" "hydra.sweep.dir=$(hq "$OUT/train-espnetv2")"
sweeps_done  # the evaluations below read these sweeps' checkpoints

ckpts() {  # the best checkpoints of sweep $1 whose filter is one of the rest: a Hydra sweep of quoted paths
  local sweep=$1 out=() f s job found
  shift
  for f in "$@"; do for s in ${SEEDS//,/ }; do
    found=()
    for job in "$OUT/$sweep/filter=$f,seed=$s" "$OUT/$sweep/filter=$f,seed=$s,"*; do
      if [ -f "$job/checkpoints/best.ckpt" ]; then found+=("$job/checkpoints/best.ckpt"); fi
    done
    [ "${#found[@]}" -eq 1 ] || { echo "run.sh: $OUT/$sweep: not one checkpoint of filter=$f seed=$s" >&2; exit 1; }
    out+=("$(hq "${found[0]}")")
  done; done
  local IFS=,; echo "${out[*]}"
}
ALL="$(ckpts train none attention),$(ckpts train-espnetv2 unet mask2former)"
STUDENTS=$(ckpts train-espnetv2 unet)

# 2. Every checkpoint on every pair (one thread a job, two jobs side by side).
for pair in day_left:night_right day_right:night_right day_left:day_right; do
  dir="$OUT/${pair/:/-}"
  gardens_point "$dir/none" "$pair" "ckpt=$ALL" mask=none
  gardens_point "$dir/espnetv2" "$pair" "ckpt=$ALL" mask=teacher "${espnet[@]}" mask.control=none,objects,sky
  gardens_point "$dir/drawn" "$pair" "ckpt=$ALL" mask=teacher "${espnet[@]}" mask.control=random,shuffled
  gardens_point "$dir/student" "$pair" "ckpt=$STUDENTS"
done
sweeps_done
echo "done: python experiments/espnetv2-trained-streets/summarize.py $OUT"
