#!/usr/bin/env bash
# The occluded-streets experiment: real CamVid test objects pasted into Gardens Point Walking's frames
# (data.occluders), every pair at coverage 0 (the frames as they are), 10, 20 and 35 % with 3 occluder seeds,
# evaluated with no mask and the ground-truth mask of the pasted pixels (mask=oracle); the artefact control
# (paste=false: the same draws' masks on the frames without objects: the cost of the holes alone); and, where
# given, the CamVid student's and teacher's masks and trained checkpoints.
# Usage, from the repository root (each evaluation is cached; a second run only re-reads):
#   [CAMVID_STUDENT=DIR] [CAMVID_TEACHER=DIR] [CKPTS="'a.ckpt','b.ckpt'"] \
#     bash experiments/occluded-streets/run.sh OUT [GARDENS_ROOT] [CAMVID_ROOT]
# CAMVID_STUDENT / CAMVID_TEACHER: segmenter directories saved by `python -m semvpr.segment` on CamVid
# (experiments/camvid-semantic; real-streets' run.sh step 2 makes them). CKPTS: a Hydra sweep of checkpoints
# (e.g. real-streets' OUT/synthcity/filter=*,seed=*/checkpoints/best.ckpt), evaluated as the untrained model is.
# CACHE (default OUT/cache), PAIRS, COVERAGES, SEEDS and EXTRA (more overrides for every evaluation, e.g. data.image_size=[64,96]) may
# be set in the environment; the defaults are the experiment's. OUT/eval/<pair>/<sweep>/ holds one evaluation
# multirun each; summarize.py reads them.
set -euo pipefail
source "$(dirname "$0")/../sweeps.sh"
OUT=$(realpath -m "${1:?usage: run.sh OUT [GARDENS_ROOT] [CAMVID_ROOT]}")
GARDENS=$(realpath "${2:-../shared/realdata/gardens_point}")
CAMVID=$(realpath "${3:-../shared/realdata/camvid}")
CACHE=$(realpath -m "${CACHE:-$OUT/cache}")
PAIRS=${PAIRS:-day_left:night_right day_right:night_right day_left:day_right}
COVERAGES=${COVERAGES:-0.1,0.2,0.35}
SEEDS=${SEEDS:-0,1,2}
read -r -a EXTRA <<< "${EXTRA:-}"
export HF_HUB_OFFLINE=1

# The models: NetVLAD from k-means on SynthCity's training database (no VPR training), and CKPTS where given
# (model M's overrides: model M).
models=(0)
if [ -n "${CKPTS:-}" ]; then models+=(1); fi
model() { if [ "$1" = 0 ]; then MODEL=(ckpt=none aggregator=netvlad); else MODEL=("ckpt=$CKPTS"); fi; }
# The mask sources besides none and the oracle, by name (mask_source NAME: its overrides into MASK).
masks=()
if [ -n "${CAMVID_STUDENT:-}" ]; then masks+=(student); fi
if [ -n "${CAMVID_TEACHER:-}" ]; then masks+=(teacher); fi
mask_source() {
  local dir
  if [ "$1" = student ]; then dir=$CAMVID_STUDENT; else dir=$CAMVID_TEACHER; fi
  MASK=("mask=$1" "$1.checkpoint=$(hq "$(realpath "$dir")")")
}

# evaluate PAIR NAME OVERRIDES...: one evaluation sweep of a pair (sweeps.sh: rerun unless every job ended ok)
evaluate() {
  local db=${1%%:*} q=${1##*:} name=$2; shift 2
  local dir="$OUT/eval/${db}-${q}/$name"
  sweep "$dir" python -m semvpr.eval -m data=gardens_point "data.root=$(hq "$GARDENS")" data.database="$db" \
    data.queries="$q" "paths.cache_dir=$(hq "$CACHE")" threads=1 "${EXTRA[@]}" "$@" "hydra.sweep.dir=$(hq "$dir")"
}
occluders=(data.occluders.source=camvid "data.occluders.root=$(hq "$CAMVID")" data.occluders.coverage="$COVERAGES"
           data.occluders.seed="$SEEDS")

# 1. Every pair and model: the frames as they are (coverage 0: the oracle's mask keeps every pixel there, so it
#    is the no-mask run), then with the objects, without a mask and with each mask source.
for pair in $PAIRS; do
  for m in "${models[@]}"; do
    model "$m"
    evaluate "$pair" "m$m-clean-none" "${MODEL[@]}" mask=none
    evaluate "$pair" "m$m-occluded-none" "${MODEL[@]}" mask=none "${occluders[@]}"
    evaluate "$pair" "m$m-occluded-oracle" "${MODEL[@]}" mask=oracle "${occluders[@]}"
    for name in "${masks[@]}"; do
      mask_source "$name"
      evaluate "$pair" "m$m-clean-$name" "${MODEL[@]}" "${MASK[@]}"
      evaluate "$pair" "m$m-occluded-$name" "${MODEL[@]}" "${MASK[@]}" "${occluders[@]}"
    done
  done
done

# 2. The artefact control: the oracle's masks of the same draws on the frames without the objects (the cost
#    of the holes alone; a new trunk pass per draw, as the set's key holds its label maps).
for pair in $PAIRS; do
  for m in "${models[@]}"; do
    model "$m"
    evaluate "$pair" "m$m-holes-oracle" "${MODEL[@]}" mask=oracle "${occluders[@]}" data.occluders.paste=false
  done
done
sweeps_done
echo "done: python experiments/occluded-streets/summarize.py $OUT"
sources=()
if [ -n "${CAMVID_STUDENT:-}" ]; then sources+=(--source "student=$(realpath "$CAMVID_STUDENT")"); fi
if [ -n "${CAMVID_TEACHER:-}" ]; then sources+=(--source "teacher=$(realpath "$CAMVID_TEACHER")"); fi
if [ ${#sources[@]} -gt 0 ]; then
  echo "masks against the pasted pixels: python experiments/occluded-streets/mask_iou.py $OUT ${sources[*]}" \
    "--camvid $CAMVID --cache $CACHE"
fi
