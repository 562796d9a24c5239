#!/usr/bin/env bash
# Untrained retrievers on Gardens Point Walking (a test set) with no mask, with the static mask of ESPNetv2 (the
# Cityscapes segmenter its authors trained: a teacher nobody here trained) and with that mask's controls (its
# objects only, its sky only, as many cells at random, another image's mask; the database or the queries alone).
# Four evaluation sweeps per pair; with STUDENT_DIR (the student semvpr.segment distils from ESPNetv2's labels of
# CamVid train, experiments/camvid-espnetv2), a fifth: that student's mask. summarize.py pairs every masked job by
# query with the same model unmasked.
# Usage, from the repository root (each step is cached; a second run only re-reads, and reruns what did not end):
#   bash experiments/espnetv2-streets/run.sh OUT [GARDENS_ROOT] [ESPNETV2_FILE] [STUDENT_DIR]
set -euo pipefail
source "$(dirname "$0")/../sweeps.sh"
OUT=$(realpath -m "${1:?usage: run.sh OUT [GARDENS_ROOT] [ESPNETV2_FILE] [STUDENT_DIR]}")
GARDENS=${2:-../shared/realdata/gardens_point}
# As given (relative to the repository root by default): the tables name the file by this path.
ESPNET=${3:-../shared/realdata/segmenters/espnetv2/espnetv2_s_2.0_city_1024x512.pth}
STUDENT=${4:-}
export HF_HUB_OFFLINE=1

CACHE="$OUT/cache"
for pair in day_left:night_right day_right:night_right day_left:day_right; do
  dir="$OUT/${pair/:/-}"
  evaluate() {  # evaluate NAME OVERRIDES...: one sweep of the pair over both models
    local name=$1
    shift
    gardens_point "$dir/$name" "$pair" ckpt=none aggregator=gem,netvlad teacher=espnetv2 \
      "teacher.checkpoint=$(hq "$ESPNET")" "$@"
  }
  evaluate masks mask=none,teacher
  evaluate classes mask=teacher mask.control=objects,sky
  evaluate drawn mask=teacher mask.control=random,shuffled mask.control_seed=0,1,2
  evaluate sides mask=teacher mask.apply=database,queries
  if [ -n "$STUDENT" ]; then evaluate student mask=student "student.checkpoint=$(hq "$(realpath "$STUDENT")")"; fi
done
sweeps_done
echo "done: python experiments/espnetv2-streets/summarize.py $OUT"
