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
OUT=$(realpath -m "${1:?usage: run.sh OUT [GARDENS_ROOT] [CAMVID_ROOT]}")
GARDENS=$(realpath "${2:-../shared/realdata/gardens_point}")
CAMVID=$(realpath "${3:-../shared/realdata/camvid}")
CACHE=$(realpath -m "${CACHE:-$OUT/cache}")
PAIRS=${PAIRS:-day_left:night_right day_right:night_right day_left:day_right}
COVERAGES=${COVERAGES:-0.1,0.2,0.35}
SEEDS=${SEEDS:-0,1,2}
read -r -a EXTRA <<< "${EXTRA:-}"
export HF_HUB_OFFLINE=1

# The models: NetVLAD from k-means on SynthCity's training database (no VPR training), and CKPTS where given.
models=("ckpt=none aggregator=netvlad")
if [ -n "${CKPTS:-}" ]; then models+=("ckpt=$CKPTS"); fi
# The mask sources besides none and the oracle.
masks=()
if [ -n "${CAMVID_STUDENT:-}" ]; then masks+=("student mask=student student.checkpoint=$(realpath "$CAMVID_STUDENT")"); fi
if [ -n "${CAMVID_TEACHER:-}" ]; then masks+=("teacher mask=teacher teacher.checkpoint=$(realpath "$CAMVID_TEACHER")"); fi

FAILED='"status": "failed"'  # what eval.json says of a job that failed (a sweep goes on past it)
# evaluate PAIR NAME OVERRIDES...: one evaluation sweep of a pair, skipped when its table exists and no job failed
evaluate() {
  local db=${1%%:*} q=${1##*:} name=$2; shift 2
  local dir="$OUT/eval/${db}-${q}/$name"
  if [ -f "$dir/results.md" ] && ! grep -qs "$FAILED" "$dir"/*/eval.json; then return; fi
  python -m semvpr.eval -m data=gardens_point data.root="$GARDENS" data.database="$db" \
    data.queries="$q" paths.cache_dir="$CACHE" threads=1 "${EXTRA[@]}" "$@" hydra.sweep.dir="$dir"
}
occluders=(data.occluders.source=camvid data.occluders.root="$CAMVID" data.occluders.coverage="$COVERAGES"
           data.occluders.seed="$SEEDS")

# 1. Every pair and model: the frames as they are (coverage 0: the oracle's mask keeps every pixel there, so it
#    is the no-mask run), then with the objects, without a mask and with each mask source.
for pair in $PAIRS; do
  for m in "${!models[@]}"; do
    read -r -a model <<< "${models[$m]}"
    evaluate "$pair" "m$m-clean-none" "${model[@]}" mask=none
    evaluate "$pair" "m$m-occluded-none" "${model[@]}" mask=none "${occluders[@]}"
    evaluate "$pair" "m$m-occluded-oracle" "${model[@]}" mask=oracle "${occluders[@]}"
    for spec in "${masks[@]}"; do
      read -r -a mask <<< "$spec"
      evaluate "$pair" "m$m-clean-${mask[0]}" "${model[@]}" "${mask[@]:1}"
      evaluate "$pair" "m$m-occluded-${mask[0]}" "${model[@]}" "${mask[@]:1}" "${occluders[@]}"
    done
  done
done

# 2. The artefact control: the oracle's masks of the same draws on the frames without the objects (the cost
#    of the holes alone; a new trunk pass per draw, as the set's key holds its label maps).
for pair in $PAIRS; do
  for m in "${!models[@]}"; do
    read -r -a model <<< "${models[$m]}"
    evaluate "$pair" "m$m-holes-oracle" "${model[@]}" mask=oracle "${occluders[@]}" data.occluders.paste=false
  done
done
failed=$(grep -ls "$FAILED" "$OUT"/eval/*/*/*/eval.json || true)
if [ -n "$failed" ]; then  # each job's error is in its eval.json; a rerun redoes their sweeps only
  echo "run.sh: these evaluations failed (their eval.json says why; rerun run.sh once that is fixed):" >&2
  echo "$failed" >&2
  exit 1
fi
echo "done: python experiments/occluded-streets/summarize.py $OUT"
sources=()
if [ -n "${CAMVID_STUDENT:-}" ]; then sources+=(--source "student=$(realpath "$CAMVID_STUDENT")"); fi
if [ -n "${CAMVID_TEACHER:-}" ]; then sources+=(--source "teacher=$(realpath "$CAMVID_TEACHER")"); fi
if [ ${#sources[@]} -gt 0 ]; then
  echo "masks against the pasted pixels: python experiments/occluded-streets/mask_iou.py $OUT ${sources[*]}" \
    "--camvid $CAMVID --cache $CACHE"
fi
