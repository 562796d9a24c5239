#!/usr/bin/env bash
# Untrained retrievers on Gardens Point Walking (a test set) with no mask and with the static mask of ESPNetv2,
# the Cityscapes segmenter its authors trained (a teacher nobody here trained). One evaluation sweep per pair;
# each masked row's R@1 gain is paired by query against the same model without a mask.
# Usage, from the repository root (each step is cached; a second run only re-reads):
#   bash experiments/espnetv2-streets/run.sh OUT [GARDENS_ROOT] [ESPNETV2_FILE]
set -euo pipefail
OUT=$(realpath -m "${1:?usage: run.sh OUT [GARDENS_ROOT] [ESPNETV2_FILE]}")
GARDENS=${2:-../shared/realdata/gardens_point}
# As given (relative to the repository root by default): the tables name the file by this path.
ESPNET=${3:-../shared/realdata/segmenters/espnetv2/espnetv2_s_2.0_city_1024x512.pth}
export HF_HUB_OFFLINE=1
for pair in day_left:night_right day_right:night_right day_left:day_right; do
  db=${pair%%:*}; q=${pair##*:}
  dir="$OUT/${db}-${q}"
  # Done where all four jobs ended ok; a stopped or failed sweep runs again (its table says what it holds).
  done_jobs() { grep -l '"status": "ok"' "$dir"/*/eval.json 2>/dev/null | wc -l; }
  [ "$(done_jobs)" -eq 4 ] || python -m semvpr.eval -m ckpt=none aggregator=gem,netvlad mask=none,teacher \
    teacher=espnetv2 teacher.checkpoint="$ESPNET" data=gardens_point data.root="$GARDENS" data.database="$db" \
    data.queries="$q" paths.cache_dir="$OUT/cache" threads=1 hydra.sweep.dir="$dir"
  [ "$(done_jobs)" -eq 4 ] || { echo "run.sh: $dir holds fewer than 4 finished evaluations" >&2; exit 1; }
done
echo "done: results in $OUT/<pair>/results.md"
