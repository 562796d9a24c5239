#!/usr/bin/env bash
# SynthCity with power: the mask-over-SRAL contrast (the student's and the teacher's mask against SRAL without
# one, synthcity-default's protocol) over training seeds × city draws (data.seed: another city, its teacher and
# student trained on it: their caches are per draw). Per seed and draw, one training sweep of the three filters
# (attention = sral · none, unet = sral · student, mask2former = sral · teacher) and one evaluation sweep of
# their best checkpoints on that draw's test split, which keeps each query's hits (hits.npz) for the pooled
# estimate (summarize.py). Seeds run in the outer loop, so a stopped run has every draw at equal depth.
# A cell recorded in cells/ (summarize.py OUT records the finished ones) is skipped: a run goes on from another
# machine's records. Usage, from the repository root (each step is cached; a rerun skips every finished sweep):
#   bash experiments/synthcity-power/run.sh OUT [SEEDS] [DRAWS] [FIRST]   (defaults: 24 seeds, 3 draws, from 0)
# One job at a time with one thread (the other core stays free). FIRST: the first seed this run takes, so that
# two runs on one OUT share its cache and take disjoint seeds (run.sh OUT 24 3 12 beside run.sh OUT 12).
set -euo pipefail
source "$(dirname "$0")/../sweeps.sh"
OUT=$(realpath -m "${1:?usage: run.sh OUT [SEEDS] [DRAWS]}")
SEEDS=${2:-24}
DRAWS=${3:-3}
FIRST=${4:-0}
CACHE="$OUT/cache"
CELLS="$(dirname "$0")/cells"
export HF_HUB_OFFLINE=1

for ((seed = FIRST; seed < SEEDS; seed++)); do
  for ((draw = 0; draw < DRAWS; draw++)); do
    name="seed=$seed,draw=$draw"
    [ -f "$CELLS/$name.npz" ] && continue
    sweep "$OUT/train/$name" python -m semvpr.train -m filter=attention,unet,mask2former seed="$seed" \
      data.seed="$draw" threads=1 hydra.launcher.n_jobs=1 "paths.cache_dir=$(hq "$CACHE")" \
      "hydra.sweep.dir=$(hq "$OUT/train/$name")"
    ckpts=()
    for f in attention unet mask2former; do
      ckpts+=("$(hq "$(echo "$OUT/train/$name"/*filter="$f"*/checkpoints/best.ckpt)")")
    done
    sweep "$OUT/test/$name" python -m semvpr.eval -m "ckpt=$(IFS=,; echo "${ckpts[*]}")" data.seed="$draw" \
      threads=1 hydra.launcher.n_jobs=1 "paths.cache_dir=$(hq "$CACHE")" "hydra.sweep.dir=$(hq "$OUT/test/$name")"
  done
done
sweeps_done
echo "done: python experiments/synthcity-power/summarize.py $OUT"
