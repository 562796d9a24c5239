#!/usr/bin/env bash
# SynthCity's mask controls: is it the mask's content or only the area it removes? Per training seed and city
# draw (data.seed: another city, its embedded teacher and student retrained on it), one training sweep of the
# three SRAL filters of synthcity-power (attention = no mask, unet = the student's, mask2former = the teacher's),
# then four evaluation sweeps of their best checkpoints on that draw's test split, each keeping every query's
# hits: `own` (each checkpoint with the mask it was trained with), `classes` (the masked checkpoints with their
# mask's objects only, or its sky only), `drawn` (as many cells at random, another image's mask; control seed =
# the training seed) and `sides` (the mask on the database only, on the queries only). summarize.py pairs them.
# Usage, from the repository root (each step is cached; a rerun skips every finished sweep):
#   bash experiments/synthcity-controls/run.sh OUT [SEEDS] [DRAWS] [FIRST]   (defaults: 3 seeds, 3 draws, from 0)
# One job at a time with one thread; seeds in the outer loop, so a stopped run has every draw at equal depth.
# FIRST: the first seed this run takes, so that two runs on one OUT share its cache and take disjoint seeds
# (run.sh OUT 3 3 2 beside run.sh OUT 2).
set -euo pipefail
source "$(dirname "$0")/../sweeps.sh"
OUT=$(realpath -m "${1:?usage: run.sh OUT [SEEDS] [DRAWS] [FIRST]}")
SEEDS=${2:-3}
DRAWS=${3:-3}
FIRST=${4:-0}
CACHE="$OUT/cache"
export HF_HUB_OFFLINE=1

for ((seed = FIRST; seed < SEEDS; seed++)); do
  for ((draw = 0; draw < DRAWS; draw++)); do
    name="seed=$seed,draw=$draw"
    common=(data.seed="$draw" threads=1 hydra.launcher.n_jobs=1 "paths.cache_dir=$(hq "$CACHE")")
    sweep "$OUT/train/$name" python -m semvpr.train -m filter=attention,unet,mask2former seed="$seed" \
      "${common[@]}" "hydra.sweep.dir=$(hq "$OUT/train/$name")"
    best() { hq "$(echo "$OUT/train/$name"/*filter="$1"*/checkpoints/best.ckpt)"; }
    all="ckpt=$(best attention),$(best unet),$(best mask2former)"
    masked="ckpt=$(best unet),$(best mask2former)"
    evaluate() {  # evaluate SWEEP OVERRIDES...: one evaluation sweep of this cell on its draw's test split
      local dir="$OUT/test/$name/$1"
      shift
      sweep "$dir" python -m semvpr.eval -m "$@" "${common[@]}" "hydra.sweep.dir=$(hq "$dir")"
    }
    evaluate own "$all"
    evaluate classes "$masked" mask.control=objects,sky
    evaluate drawn "$masked" mask.control=random,shuffled mask.control_seed="$seed"
    evaluate sides "$masked" mask.apply=database,queries
  done
done
sweeps_done
echo "done: python experiments/synthcity-controls/summarize.py $OUT"
