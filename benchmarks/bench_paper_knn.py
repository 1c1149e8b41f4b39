"""The paper's own method (``sphere+knn``) on the paper's simulated experiment.

Simulates the GoPro-like and Nikon-like presets (seed 0, as
``examples/paper_experiment.sh``), calibrates them from one shared
initialisation with each model and prints the grey-box loop round by round
and the 3D check-point RMSE after a 7-parameter similarity.

    python benchmarks/bench_paper_knn.py [--cases gopro,nikon] [--models sphere+knn,radial+knn]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from gtsam_sphere.analysis.evaluate import evaluate_calibration
from gtsam_sphere.core.camera import Model
from gtsam_sphere.estimation.calibrate import CalibrationOptions, calibrate, initialise
from gtsam_sphere.io.dataset import parse_dataset
from gtsam_sphere.simulate import gopro_like, simulate_room
from gtsam_sphere.simulate.room import nikon_like

CASES = {"gopro": gopro_like, "nikon": nikon_like}


def run_case(name: str, models, seed: int, verbose: bool, knn: dict) -> list[tuple]:
    """Calibrate one preset with each model; rows of the table."""
    sim = simulate_room(CASES[name](seed=seed))
    dataset = parse_dataset(sim.dataset)
    ids = [t["id"] for t in sim.checkpoints["targets"]]
    xyz = np.array([t["xyz"] for t in sim.checkpoints["targets"]], float)
    init = initialise(dataset, seed)
    rows = []
    for m in models:
        t0 = time.perf_counter()

        def say(line, m=m):
            if verbose and "kNN" in line:
                print(f"  [{name} {m}] {line}", flush=True)

        calib = calibrate(
            dataset, CalibrationOptions(model=Model(m), seed=seed, knn=knn), say, init=init
        )
        rep = evaluate_calibration(calib, ids, xyz)
        st = calib.statistics
        rows.append((name, m, st["rms_px"], rep.rmse_3d, st["converged"], time.perf_counter() - t0))
        print(f"{name} {m}: RMS {st['rms_px']:.3f} px, 3D {rep.rmse_3d * 1e3:.3f} mm", flush=True)
    return rows


def main() -> None:
    """Print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="gopro,nikon")
    ap.add_argument("--models", default="sphere+knn,radial+knn")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--knn", default="{}", help='grey-box options as JSON, e.g. {"degree": 1}')
    ap.add_argument("--quiet", action="store_true", help="no per-round lines")
    args = ap.parse_args()
    rows = []
    for case in args.cases.split(","):
        rows += run_case(
            case, args.models.split(","), args.seed, not args.quiet, json.loads(args.knn)
        )
    print("\n| case | model | RMS (px) | 3D RMSE (mm) | converged | time (s) |")
    print("|---|---|---|---|---|---|")
    for case, m, rms, r3, conv, dt in rows:
        print(f"| {case} | {m} | {rms:.3f} | {r3 * 1e3:.3f} | {conv} | {dt:.0f} |")


if __name__ == "__main__":
    main()
