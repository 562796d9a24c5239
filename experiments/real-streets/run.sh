#!/usr/bin/env bash
# The real-streets experiment: SynthCity-trained checkpoints (the four-way comparison, and GeM, MixVPR,
# SALAD and BoQ on recipe=gsv) and off-the-shelf baselines on Gardens Point Walking, each with no mask, its
# own SynthCity mask, the CamVid student's and the CamVid teacher's.
# Usage, from the repository root (each step is cached; a second run only re-reads):
#   [CAMVID_TEACHER=DIR] bash experiments/real-streets/run.sh OUT [GARDENS_ROOT] [CAMVID_ROOT]
# OUT receives the training sweeps (OUT/synthcity, OUT/gsv, OUT/learned), the CamVid segmenters (OUT/camvid)
# and one evaluation sweep per pair and mask source (OUT/eval/<pair>/<mask>; gsv-<mask> for the recipe=gsv
# checkpoints trained without a mask or with the student's, gsv-teacher-<mask> for those trained with the
# teacher's, learned-<mask> for those with learned class weights); summarize.py and figure.py read OUT.
set -euo pipefail
source "$(dirname "$0")/../sweeps.sh"
OUT=$(realpath -m "${1:?usage: run.sh OUT [GARDENS_ROOT] [CAMVID_ROOT]}")
GARDENS=$(realpath "${2:-../shared/realdata/gardens_point}")
CAMVID=$(realpath "${3:-../shared/realdata/camvid}")
CACHE="$OUT/cache"
export HF_HUB_OFFLINE=1

# 1. The checkpoints: the four-way comparison on SynthCity, 3 seeds (synthcity-default's command; the
#    oracle's checkpoints are not evaluated here: Gardens Point has no label maps).
sweep "$OUT/synthcity" python -m semvpr.train -m seed=0,1,2 filter=none,attention,unet,mask2former,oracle \
  "paths.cache_dir=$(hq "$CACHE")" "hydra.sweep.dir=$(hq "$OUT/synthcity")"

# 1b. GeM, MixVPR, SALAD and BoQ on their authors' recipe, 3 seeds: the command of aggregators-x-masks
#     (its converged matrix); the checkpoints trained without a mask, with the student's and with the
#     teacher's are evaluated here.
sweep "$OUT/gsv" python -m semvpr.train -m recipe=gsv aggregator=gem,mixvpr,salad,boq \
  mask=none,student,teacher seed=0,1,2 "paths.cache_dir=$(hq "$CACHE")" "hydra.sweep.dir=$(hq "$OUT/gsv")"

# 1c. The student's and the teacher's masks with learned class weights (mask.weights=learned), 3 seeds: the
#     learned half of synthcity-class-weights' command.
sweep "$OUT/learned" python -m semvpr.train -m seed=0,1,2 filter=unet,mask2former \
  filter.weights=learned "paths.cache_dir=$(hq "$CACHE")" "hydra.sweep.dir=$(hq "$OUT/learned")"
sweeps_done  # the evaluations below read these sweeps' checkpoints

# 2. The real-street segmenters: the CamVid teacher and student (camvid-semantic's command: about 2 h of
#    teacher training and 20 min of student on one thread, as they trained; another thread count trains other
#    weights). CAMVID_TEACHER=DIR uses a teacher that command saved instead of training one (its student is
#    still trained, or read from the cache). The student evaluated here trains 20 epochs (student.epochs=20);
#    camvid-semantic's 40-epoch student (conf/segment.yaml) is not evaluated on Gardens Point.
if [ ! -f "$OUT/camvid/results.json" ]; then
  given=()
  if [ -n "${CAMVID_TEACHER:-}" ]; then given=("teacher.checkpoint=$(hq "$(realpath "$CAMVID_TEACHER")")"); fi
  python -m semvpr.segment "seg.root=$(hq "$CAMVID")" "paths.cache_dir=$(hq "$CACHE")" threads=1 \
    "hydra.run.dir=$(hq "$OUT/camvid")" student.epochs=20 "${given[@]}"
fi
# The teacher that run scored and labelled the student's training images with (trained there, or given).
TEACHER=$(python -c 'import json, sys; print(json.load(open(sys.argv[1]))["teacher"]["checkpoint"])' \
  "$OUT/camvid/results.json")
STUDENT="$OUT/camvid/student_efficientnet_lite0"

# 3. Every checkpoint and baseline on every pair, with each mask source.
ckpts() {  # the sweep's best checkpoints whose filter is one of "$@": a Hydra sweep of quoted paths
  local out=()
  for f in "$@"; do for s in 0 1 2; do out+=("$(hq "$OUT/synthcity/filter=$f,seed=$s/checkpoints/best.ckpt")"); done; done
  local IFS=,; echo "${out[*]}"
}
gsv_ckpts() {  # the recipe=gsv sweep's best checkpoints trained with a mask of "$@" (none: without one)
  local out=()
  for m in "$@"; do for a in gem mixvpr salad boq; do for s in 0 1 2; do
    out+=("$(hq "$OUT/gsv/aggregator=$a,mask=$m,recipe=gsv,seed=$s/checkpoints/best.ckpt")")
  done; done; done
  local IFS=,; echo "${out[*]}"
}
learned_ckpts() {  # the learned class-weights sweep's best checkpoints
  local out=()
  for f in unet mask2former; do for s in 0 1 2; do
    out+=("$(hq "$OUT/learned/filter.weights=learned,filter=$f,seed=$s/checkpoints/best.ckpt")")
  done; done
  local IFS=,; echo "${out[*]}"
}
ALL=$(ckpts none attention unet mask2former)
LEARNED=$(learned_ckpts)
OWN=$(ckpts unet mask2former)
GSV_ALL=$(gsv_ckpts none student)
GSV_OWN=$(gsv_ckpts student)
GSV_TEACHER=$(gsv_ckpts teacher)
for pair in day_left:night_right day_right:night_right day_left:day_right; do
  db=${pair%%:*}; q=${pair##*:}
  data=(data=gardens_point "data.root=$(hq "$GARDENS")" data.database="$db" data.queries="$q"
        "paths.cache_dir=$(hq "$CACHE")")
  dir="$OUT/eval/${db}-${q}"
  run() {  # run NAME OVERRIDES...: one evaluation sweep (sweeps.sh: rerun unless every job ended ok)
    local name=$1; shift
    sweep "$dir/$name" python -m semvpr.eval -m "${data[@]}" "$@" "hydra.sweep.dir=$(hq "$dir/$name")"
  }
  run none ckpt="$ALL" mask=none
  run own ckpt="$OWN"
  run camvid-student ckpt="$ALL" mask=student "student.checkpoint=$(hq "$STUDENT")"
  run camvid-teacher ckpt="$ALL" mask=teacher "teacher.checkpoint=$(hq "$TEACHER")"
  run gsv-none ckpt="$GSV_ALL" mask=none
  run gsv-own ckpt="$GSV_OWN"
  run gsv-camvid-student ckpt="$GSV_ALL" mask=student "student.checkpoint=$(hq "$STUDENT")"
  run gsv-camvid-teacher ckpt="$GSV_ALL" mask=teacher "teacher.checkpoint=$(hq "$TEACHER")"
  run gsv-teacher-none ckpt="$GSV_TEACHER" mask=none
  run gsv-teacher-own ckpt="$GSV_TEACHER"
  run gsv-teacher-camvid-student ckpt="$GSV_TEACHER" mask=student "student.checkpoint=$(hq "$STUDENT")"
  run gsv-teacher-camvid-teacher ckpt="$GSV_TEACHER" mask=teacher "teacher.checkpoint=$(hq "$TEACHER")"
  run learned-none ckpt="$LEARNED" mask=none
  run learned-own ckpt="$LEARNED"
  run learned-camvid-student ckpt="$LEARNED" mask=student "student.checkpoint=$(hq "$STUDENT")"
  run learned-camvid-teacher ckpt="$LEARNED" mask=teacher "teacher.checkpoint=$(hq "$TEACHER")"
  run untrained-none ckpt=none aggregator=gem,netvlad mask=none
  run untrained-camvid-student ckpt=none aggregator=gem,netvlad mask=student "student.checkpoint=$(hq "$STUDENT")"
  run untrained-camvid-teacher ckpt=none aggregator=gem,netvlad mask=teacher "teacher.checkpoint=$(hq "$TEACHER")"
done
sweeps_done
echo "done: python experiments/real-streets/summarize.py $OUT"
