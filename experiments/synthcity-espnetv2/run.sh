#!/usr/bin/env bash
# How a segmenter trained on real streets sees SynthCity: ESPNetv2 from its authors' Cityscapes weights (s=2.0,
# ../shared/realdata/segmenters/espnetv2/) scored on the segmentation val split of three SynthCity draws (the
# default preset, --seed 0, 1, 2: the cities of synthcity-power's data.seed), against SynthCity's own labels, at
# the images' 180x240; ESPNetv2 infers at its authors' 1024x512 in fp32. The U-Net student (its default settings, on
# the default trunk's frozen features) learns ESPNetv2's labels of the draw's segmentation train images (SynthCity's
# own labels unused) and is scored the same way. Nothing is chosen here.
# Usage, from the repository root:
#   bash experiments/synthcity-espnetv2/run.sh OUT      (then: python experiments/synthcity-espnetv2/summarize.py OUT)
set -euo pipefail
source "$(dirname "$0")/../sweeps.sh"  # hq
# The generator writes a city whole or not at all (its folder appears once complete).
OUT=$(realpath -m "${1:?usage: run.sh OUT}")
ESPNET=${ESPNET:-../shared/realdata/segmenters/espnetv2/espnetv2_s_2.0_city_1024x512.pth}
export HF_HUB_OFFLINE=1

for draw in 0 1 2; do
  city="$OUT/synthcity-s$draw"
  [ -d "$city" ] || python -m semvpr.data.synthcity --out "$city" --preset default --seed "$draw"
  [ -f "$OUT/segment-s$draw/results.json" ] && continue
  python -m semvpr.segment seg=cityscapes "seg.root=$(hq "$city/seg")" "seg.image_size=[180,240]" teacher=espnetv2 \
    "teacher.checkpoint=$(hq "$(realpath "$ESPNET")")" threads=1 \
    "paths.cache_dir=$(hq "$OUT/cache")" "hydra.run.dir=$(hq "$OUT/segment-s$draw")"
done
echo "done: python experiments/synthcity-espnetv2/summarize.py $OUT"
