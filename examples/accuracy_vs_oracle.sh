#!/usr/bin/env bash
# Issue 3's accuracy goal: each model's 3D check-point RMSE against the oracle (the same
# simulated data adjusted with the true lens known) on a 150 deg GoPro-like lens and the
# same lens family opened to 200 and 250 degrees (decentering, 2 mm pupil shift, 2 px
# smooth error field). Prints a markdown table (~15 min on 2 cores).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
python "$here/benchmarks/bench_accuracy.py" --models radial+knn,radial,brown+knn,sphere+knn "$@"
