#!/usr/bin/env bash
# The paper's experiment (Chow et al. 2018, Tables 1-2) on the simulator:
# a Nikon-like normal lens (75 deg, 44 images) and a GoPro-like wide lens
# (150 deg Kannala-Brandt with decentering, a 2 mm non-central pupil and a
# 2 px smooth error field, 52 images). Writes OUT/{nikon,gopro}/compare.{md,json}.
set -euo pipefail
OUT=${1:-paper_experiment}
for cam in nikon gopro; do
  gtsam-sphere simulate --preset "$cam" --seed 0 -o "$OUT/$cam"
  gtsam-sphere compare "$OUT/$cam/dataset.json" --checkpoints "$OUT/$cam/checkpoints.json" \
    -o "$OUT/$cam/compare.json" | tee "$OUT/$cam/compare.md"
done
