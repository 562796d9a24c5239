# Shell functions the experiments' run.sh scripts share (sourced, not run):
#   hq PATH             PATH quoted for a Hydra override (key=$(hq "$dir")): spaces, '=' and ',' stay in it
#   sweep DIR CMD...    run the sweep CMD (a semvpr.train -m or semvpr.eval -m writing into DIR) unless DIR holds
#                       it finished already; a stop of the script (SIGINT, SIGTERM) stops the sweep first
#   sweeps_done         exit 1 naming every sweep that did not end with all its jobs ok
#   gardens_point DIR DB:Q OVERRIDES...   the evaluation sweep OVERRIDES on Gardens Point's traversals DB
#                       (database) and Q (queries) under $GARDENS, cached in $CACHE, one thread a job, into DIR
# A sweep is finished where its table (results.md, written when it ends) counts every job it was given (no
# "Incomplete" or "Partial" line: none stopped, killed or never started) and no job failed. A stopped or
# failed sweep runs again on a rerun: its finished jobs read their caches.

hq() {
  printf "'%s'" "${1//\'/\\\'}"
}

finished() {
  local md="$1/results.md"
  [ -f "$md" ] || return 1
  ! grep -qE '^\*\*(Incomplete|Partial)' "$md" || return 1
  ! grep -qs '"status": "failed"' "$1"/*/eval.json "$1"/*/metrics.json
}

INCOMPLETE=()
SWEEP_PID=
trap '[ -z "$SWEEP_PID" ] || { kill -TERM "$SWEEP_PID" 2>/dev/null; wait "$SWEEP_PID"; }; exit 143' INT TERM

sweep() {
  local dir=$1
  shift
  finished "$dir" && return 0
  "$@" &
  SWEEP_PID=$!
  wait "$SWEEP_PID" || true  # a failed job is in its sweep's table, counted below
  SWEEP_PID=
  finished "$dir" || INCOMPLETE+=("$dir")
}

sweeps_done() {
  [ "${#INCOMPLETE[@]}" -eq 0 ] && return 0
  echo "run.sh: ${#INCOMPLETE[@]} sweep(s) did not end with every job ok (each results.md says which and why);" \
    "rerun run.sh once that is fixed: ${INCOMPLETE[*]}" >&2
  exit 1
}

gardens_point() {
  local dir=$1 db=${2%%:*} q=${2##*:}
  shift 2
  sweep "$dir" python -m semvpr.eval -m data=gardens_point "data.root=$(hq "$GARDENS")" data.database="$db" \
    data.queries="$q" "paths.cache_dir=$(hq "$CACHE")" threads=1 "$@" "hydra.sweep.dir=$(hq "$dir")"
}
