#!/usr/bin/env bash
# Real fisheye images -> calibration -> report, with the command line only.
#
# ../shared/data/images/fish_1 (15 images, 1032x778) and fish_2 (16 images, 748x480):
# py-OCamCalib's test images (not part of this repository). The printed boards have
# 7x9 squares, i.e. 6x8 inner corners (checkerboard_sizes.txt says 5x7 squares: a 4x6
# search locks onto arbitrary sub-grids). Squares: 32.5 mm (fish_1), 117 mm (fish_2);
# the square size scales the poses only, not the intrinsics or the pixel RMS.
# fish_2/Fisheye2_16.jpg is the same file as Fisheye2_1.jpg; it is left out here.
#
#   examples/fish_images.sh [OUTDIR]      (MODEL=brown+knn examples/fish_images.sh ...)
#
# The boards' corners are estimated around their nominal coordinates with a sigma of
# CONTROL_SIGMA metres (default 0.0005; CONTROL_SIGMA= keeps them exact): these printed
# boards are not flat and true to scale to 0.1 mm, and taking them as exact roughly
# doubles the held-out RMS (benchmarks/holdout.py).
#
# detect --recover calibrates the detections, predicts the corners the detector missed
# (and chessboards it found only in part), refines them and recalibrates; it prints
# how many corners it added per image. Hold-out numbers: benchmarks/holdout.py.
set -euo pipefail
DATA=${DATA:-../shared/data}
OUT=${1:-fish_images}
MODEL=${MODEL:-radial+knn}
CONTROL_SIGMA=${CONTROL_SIGMA-0.0005}
board_args=()
[ -n "$CONTROL_SIGMA" ] && board_args=(--control-sigma "$CONTROL_SIGMA")
[ -d "$DATA/images" ] || { echo "no real images at $DATA/images: see ../shared/data/README.md" >&2; exit 0; }
mkdir -p "$OUT"
for spec in "fish_1 0.0325" "fish_2 0.117"; do
  read -r name square <<<"$spec"
  images=()
  for f in "$DATA/images/$name"/*.jpg; do
    [ "$(basename "$f")" = Fisheye2_16.jpg ] || images+=("$f")
  done
  gtsam-sphere detect "${images[@]}" --board "chessboard:6x8:$square" \
    -o "$OUT/$name.dataset.json" --no-progress --recover
  gtsam-sphere calibrate "$OUT/$name.dataset.json" -o "$OUT/$name.$MODEL.json" \
    --model "$MODEL" "${board_args[@]}" --quiet
  gtsam-sphere report "$OUT/$name.$MODEL.json" -o "$OUT/report_$name" \
    --title "$name ($MODEL)"
done
