#!/usr/bin/env bash
# Calibrate the real datasets of ../shared/data (not part of this repository).
set -euo pipefail
DATA=${DATA:-../shared/data}
OUT=${1:-real_data}
[ -d "$DATA" ] || { echo "no real data at $DATA: see ../shared/data/README.md" >&2; exit 0; }
for d in opencv_fisheye_left ov_plane_train; do
  for model in sphere brown brown+knn radial radial+knn; do
    gtsam-sphere calibrate "$DATA/$d.dataset.json" -o "$OUT/$d.$model.json" --model "$model" --quiet
  done
  # the printed boards are not exactly their nominal coordinates: estimate their shape
  gtsam-sphere calibrate "$DATA/$d.dataset.json" -o "$OUT/$d.radial+knn.board.json" \
    --control-sigma 0.0005 --quiet
done
gtsam-sphere report "$OUT/ov_plane_train.radial+knn.board.json" -o "$OUT/report_ov_plane"
