"""Accuracy against the oracle on simulated wide-angle rooms (issue 3's goal).

For each case the same simulated data is calibrated with several models from
one shared initialisation, and once more with the true lens known (the
oracle, :mod:`gtsam_sphere.simulate.oracle`). Prints the 3D check-point RMSE
after a 7-parameter similarity and its ratio to the oracle's. Goal: the
default model within 1.15x of the oracle.

    python benchmarks/bench_accuracy.py [--cases gopro,kb200,kb250] [--models radial+knn,...]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from gtsam_sphere.analysis.evaluate import evaluate_calibration
from gtsam_sphere.core.camera import Model
from gtsam_sphere.estimation.calibrate import CalibrationOptions, calibrate, initialise
from gtsam_sphere.io.dataset import parse_dataset
from gtsam_sphere.simulate import gopro_like, simulate_room
from gtsam_sphere.simulate.oracle import oracle_calibration

CASES = {
    # the paper's GoPro: Kannala-Brandt 150 deg, decentering, 2 mm pupil shift, 2 px field
    "gopro": lambda seed: gopro_like(seed=seed),
    # the same lens family and errors opened to 200 and 250 degrees (circular fisheyes)
    "kb200": lambda seed: gopro_like(seed=seed, fov_deg=200.0, fill="circle"),
    "kb250": lambda seed: gopro_like(seed=seed, fov_deg=250.0, fill="circle"),
}
MODELS = ("radial+knn", "radial", "brown+knn", "sphere+knn")


def run_case(name: str, models, seed: int) -> list[tuple]:
    """Calibrate one simulated case with each model and the oracle; rows of the table."""
    sim = simulate_room(CASES[name](seed))
    dataset = parse_dataset(sim.dataset)
    ids = [t["id"] for t in sim.checkpoints["targets"]]
    xyz = np.array([t["xyz"] for t in sim.checkpoints["targets"]], float)
    t0 = time.perf_counter()
    oracle = oracle_calibration(sim, seed)
    ref = evaluate_calibration(oracle, ids, xyz).rmse_3d
    max_inc = oracle.statistics["max_incidence_deg"]
    rows = [(name, "oracle", oracle.statistics["rms_px"], ref, 1.0, True, time.perf_counter() - t0)]
    print(f"{name}: {dataset.n_observations} observations, incidence up to {max_inc:.0f} deg")
    init = initialise(dataset, seed)
    for m in models:
        t0 = time.perf_counter()
        calib = calibrate(dataset, CalibrationOptions(model=Model(m), seed=seed), init=init)
        rmse = evaluate_calibration(calib, ids, xyz).rmse_3d
        st = calib.statistics
        rows.append(
            (name, m, st["rms_px"], rmse, rmse / ref, st["converged"], time.perf_counter() - t0)
        )
        print(f"  {m}: 3D {rmse * 1e3:.3f} mm ({rmse / ref:.2f}x oracle)", flush=True)
    return rows


def main() -> None:
    """Print the accuracy table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--models", default=",".join(MODELS))
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rows = []
    for case in args.cases.split(","):
        rows += run_case(case, args.models.split(","), args.seed)
    print("\n| case | model | RMS (px) | 3D RMSE (mm) | / oracle | converged | time (s) |")
    print("|---|---|---|---|---|---|---|")
    for case, m, rms, r3, ratio, conv, dt in rows:
        print(f"| {case} | {m} | {rms:.3f} | {r3 * 1e3:.3f} | {ratio:.2f} | {conv} | {dt:.0f} |")


if __name__ == "__main__":
    main()
