#!/usr/bin/env bash
# Masks on released models: each author's released file, evaluated without a mask, with the CamVid
# teacher's mask and with a CamVid student's, on every place set given; one table per release and set
# (with R@1 vs no mask, paired by query) and OUT/results.md gathering them.
# Usage, from the repository root:
#   [PITTS30K=DIR] [TOKYO247=DIR] [MSLS_VAL=GT_DIR:MSLS_ROOT] [NORDLAND=DIR] [GARDENS=DIR] [FOLDER=DIR] \
#     bash experiments/published-masks/run.sh OUT TEACHER_DIR STUDENT_DIR RELEASE...
# TEACHER_DIR / STUDENT_DIR: directories saved by semvpr.segment ("-": leave that mask out).
# RELEASE: FILE[:FORMAT][=STUDENT_DIR]. FORMAT (netvlad, mixvpr, cosplace, eigenplaces, boq, boq_dinov2,
# salad) where its keys do not say (cosplace and eigenplaces files share a layout); STUDENT_DIR: a student
# trained on this release's trunk (semvpr.segment with backbones.<arch>.weights=FILE), in place of the common
# one, which decodes another trunk, or "-" (no student row: the DINOv2 releases, salad and boq_dinov2, whose
# token maps no student decodes).
# EVAL_ARGS: more semvpr.eval overrides for every job (e.g. "threads=1").
set -euo pipefail
source "$(dirname "$0")/../sweeps.sh"
usage="usage: run.sh OUT TEACHER_DIR STUDENT_DIR RELEASE..."
OUT=$(realpath -m "${1:?$usage}")
TEACHER="${2:?$usage}"
STUDENT="${3:?$usage}"
shift 3
[ "$#" -gt 0 ] || { echo "$usage" >&2; exit 2; }
export HF_HUB_OFFLINE=1
read -r -a extra <<< "${EVAL_ARGS:-}"

# Each place set given, by name; place_set NAME puts the overrides that read it into DATA.
sets=()
for name in PITTS30K TOKYO247 MSLS_VAL NORDLAND GARDENS FOLDER; do [ -z "${!name:-}" ] || sets+=("$name"); done
[ "${#sets[@]}" -gt 0 ] || { echo "run.sh: no place set given (PITTS30K=DIR, ...)" >&2; exit 2; }
place_set() {
  case $1 in
    MSLS_VAL) DATA=(data=msls_val "data.gt_dir=$(hq "$(realpath "${MSLS_VAL%%:*}")")"
                    "data.root=$(hq "$(realpath "${MSLS_VAL#*:}")")") ;;
    GARDENS) DATA=(data=gardens_point "data.root=$(hq "$(realpath "$GARDENS")")") ;;
    *) DATA=("data=${1,,}" "data.root=$(hq "$(realpath "${!1}")")") ;;
  esac
}

for release in "$@"; do
  spec="$release"
  student="$STUDENT"
  if [[ "$spec" == *=* ]]; then student="${spec#*=}"; spec="${spec%%=*}"; fi
  file="${spec%%:*}"
  format=auto
  [ "$file" != "$spec" ] && format="${spec#*:}"
  name=$(basename "$file")
  masks=(none)
  segmenters=()
  if [ "$TEACHER" != "-" ]; then masks+=(teacher); segmenters+=("teacher.checkpoint=$(hq "$(realpath "$TEACHER")")"); fi
  if [ "$student" != "-" ]; then masks+=(student); segmenters+=("student.checkpoint=$(hq "$(realpath "$student")")"); fi
  mask_list=$(IFS=,; echo "${masks[*]}")
  for set_name in "${sets[@]}"; do
    place_set "$set_name"
    dir="$OUT/eval/$name/${DATA[0]#data=}"
    sweep "$dir" python -m semvpr.eval -m "ckpt=$(hq "$(realpath "$file")")" ckpt_format="$format" "${DATA[@]}" \
      mask="$mask_list" "${segmenters[@]}" "paths.cache_dir=$(hq "$OUT/cache")" "hydra.sweep.dir=$(hq "$dir")" \
      "${extra[@]}"
  done
done

{
  echo "# Masks on released models"
  for table in "$OUT"/eval/*/*/results.md; do
    echo
    echo "## $(basename "$(dirname "$(dirname "$table")")") on $(basename "$(dirname "$table")")"
    echo
    cat "$table"
  done
} > "$OUT/results.md"
echo "wrote $OUT/results.md"
sweeps_done
