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
usage="usage: run.sh OUT TEACHER_DIR STUDENT_DIR RELEASE..."
OUT=$(realpath -m "${1:?$usage}")
TEACHER="${2:?$usage}"
STUDENT="${3:?$usage}"
shift 3
[ "$#" -gt 0 ] || { echo "$usage" >&2; exit 2; }
export HF_HUB_OFFLINE=1
read -r -a extra <<< "${EVAL_ARGS:-}"


# Each place set given: its name and the overrides that read it.
sets=()
[ -n "${PITTS30K:-}" ] && sets+=("pitts30k|data=pitts30k data.root='$(realpath "$PITTS30K")'")
[ -n "${TOKYO247:-}" ] && sets+=("tokyo247|data=tokyo247 data.root='$(realpath "$TOKYO247")'")
if [ -n "${MSLS_VAL:-}" ]; then
  sets+=("msls_val|data=msls_val data.gt_dir='$(realpath "${MSLS_VAL%%:*}")' data.root='$(realpath "${MSLS_VAL#*:}")'")
fi
[ -n "${NORDLAND:-}" ] && sets+=("nordland|data=nordland data.root='$(realpath "$NORDLAND")'")
[ -n "${GARDENS:-}" ] && sets+=("gardens_point|data=gardens_point data.root='$(realpath "$GARDENS")'")
[ -n "${FOLDER:-}" ] && sets+=("folder|data=folder data.root='$(realpath "$FOLDER")'")
[ "${#sets[@]}" -gt 0 ] || { echo "run.sh: no place set given (PITTS30K=DIR, ...)" >&2; exit 2; }

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
  if [ "$TEACHER" != "-" ]; then masks+=(teacher); segmenters+=("teacher.checkpoint='$(realpath "$TEACHER")'"); fi
  if [ "$student" != "-" ]; then masks+=(student); segmenters+=("student.checkpoint='$(realpath "$student")'"); fi
  mask_list=$(IFS=,; echo "${masks[*]}")
  for entry in "${sets[@]}"; do
    set_name="${entry%%|*}"
    read -r -a data <<< "${entry#*|}"
    sweep="$OUT/eval/$name/$set_name"
    [ -f "$sweep/results.md" ] && continue
    python -m semvpr.eval -m ckpt="'$(realpath "$file")'" ckpt_format="$format" "${data[@]}" mask="$mask_list" \
      "${segmenters[@]}" paths.cache_dir="$OUT/cache" hydra.sweep.dir="$sweep" "${extra[@]}"
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
