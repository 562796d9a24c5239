#!/usr/bin/env bash
# Occluders at real coverage: CamVid test objects pasted into Gardens Point Walking's frames (a test set), each
# frame's covered fraction drawn from CamVid train's frames (data.occluders.coverage=camvid), 3 occluder seeds;
# untrained GeM and NetVLAD without a mask, with the ground-truth mask of the pasted pixels (mask=oracle), with
# ESPNetv2's mask, and with their controls (as many cells at random, another image's mask; ESPNetv2's objects
# only). summarize.py pairs every job by query with the same model on the same draw unmasked.
# Usage, from the repository root (each step is cached; a second run only re-reads, and reruns what did not end):
#   [PAIRS="day_left:night_right ..."] bash experiments/occluded-real-coverage/run.sh OUT [GARDENS_ROOT] \
#     [CAMVID_ROOT] [ESPNETV2_FILE]
# PAIRS: the database:queries pairs (default the three of real-streets).
set -euo pipefail
source "$(dirname "$0")/../sweeps.sh"
OUT=$(realpath -m "${1:?usage: run.sh OUT [GARDENS_ROOT] [CAMVID_ROOT] [ESPNETV2_FILE]}")
GARDENS=$(realpath "${2:-../shared/realdata/gardens_point}")
CAMVID=$(realpath "${3:-../shared/realdata/camvid}")
# As given (relative to the repository root by default): the tables name the file by this path.
ESPNET=${4:-../shared/realdata/segmenters/espnetv2/espnetv2_s_2.0_city_1024x512.pth}
PAIRS=${PAIRS:-day_left:night_right day_right:night_right day_left:day_right}
export HF_HUB_OFFLINE=1
occluders=(data.occluders.source=camvid "data.occluders.root=$(hq "$CAMVID")" data.occluders.coverage=camvid
           data.occluders.seed=0,1,2)
espnet=(mask=teacher teacher=espnetv2 "teacher.checkpoint=$(hq "$ESPNET")")

CACHE="$OUT/cache"
for pair in $PAIRS; do
  dir="$OUT/${pair/:/-}"
  evaluate() {  # evaluate NAME OVERRIDES...: one sweep of the pair over both models
    local name=$1
    shift
    gardens_point "$dir/$name" "$pair" ckpt=none aggregator=gem,netvlad "$@"
  }
  evaluate clean mask=none
  evaluate occluded mask=none,oracle "${occluders[@]}"
  evaluate espnetv2 "${espnet[@]}" "${occluders[@]}"
  evaluate oracle-controls mask=oracle mask.control=random,shuffled "${occluders[@]}"
  evaluate espnetv2-controls "${espnet[@]}" mask.control=objects,random "${occluders[@]}"
done
sweeps_done
echo "done: python experiments/occluded-real-coverage/summarize.py $OUT"
