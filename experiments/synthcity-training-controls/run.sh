#!/usr/bin/env bash
# SynthCity's content controls as trained: SRAL trained, and tested, with as many cells removed at random as the
# student's mask removes, or with another image's mask (mask.control=random, shuffled at training: the checkpoint
# records its control and every evaluation of it applies it), beside SRAL trained with the student's own mask
# (filter=unet) and without a mask (filter=attention). Per training seed and city draw (data.seed), one training
# sweep, then one evaluation sweep of its best checkpoints on that draw's test split (each keeping every query's
# hits). summarize.py pairs them.
# Usage, from the repository root (each step is cached; a rerun skips every finished sweep):
#   [CACHE=DIR] bash experiments/synthcity-training-controls/run.sh OUT [SEEDS] [DRAWS]   (defaults: 3 seeds, 3 draws)
# One job at a time with one thread; draws in the outer loop (a draw's first cell builds its city, teacher and
# student). CACHE: the cache folder (default OUT/cache), e.g. one another SynthCity experiment has filled.
set -euo pipefail
source "$(dirname "$0")/../sweeps.sh"
OUT=$(realpath -m "${1:?usage: run.sh OUT [SEEDS] [DRAWS]}")
SEEDS=${2:-3}
DRAWS=${3:-3}
CACHE=$(realpath -m "${CACHE:-$OUT/cache}")
export HF_HUB_OFFLINE=1

for ((draw = 0; draw < DRAWS; draw++)); do
  for ((seed = 0; seed < SEEDS; seed++)); do
    name="seed=$seed,draw=$draw"
    common=(data.seed="$draw" seed="$seed" threads=1 hydra.launcher.n_jobs=1 "paths.cache_dir=$(hq "$CACHE")")
    sweep "$OUT/train/$name/mask" python -m semvpr.train -m filter=attention,unet \
      "${common[@]}" "hydra.sweep.dir=$(hq "$OUT/train/$name/mask")"
    sweep "$OUT/train/$name/control" python -m semvpr.train -m filter=unet mask.control=random,shuffled \
      mask.control_seed="$seed" "${common[@]}" "hydra.sweep.dir=$(hq "$OUT/train/$name/control")"
    runs=("$OUT/train/$name"/mask/*/checkpoints/best.ckpt "$OUT/train/$name"/control/*/checkpoints/best.ckpt)
    ckpts=()
    for run in "${runs[@]}"; do ckpts+=("$(hq "$run")"); done
    dir="$OUT/test/$name"
    sweep "$dir" python -m semvpr.eval -m "ckpt=$(IFS=,; echo "${ckpts[*]}")" "${common[@]}" \
      "hydra.sweep.dir=$(hq "$dir")"
  done
done
sweeps_done
echo "done: python experiments/synthcity-training-controls/summarize.py $OUT"
