"""Where the lens zoo's "imperfect" cases lose against the oracle: the error field or the model?

The zoo's oracle (``gtsam_sphere.simulate.oracle``) knows the whole lens, its smooth
error field included: the field is removed from its measurements. The default
calibration must learn the field from the residuals (the kNN correction), but an
adjustment absorbs the part of a smooth field that looks like a change of the principal
point, the principal distance or the poses before any residual shows it. This script
separates the two causes per case, each a 3D RMSE ratio to the oracle (check points in
the room, camera stations for the exact board and object):

- ``default``: ``gtsam-sphere calibrate`` without options (the zoo's figure);
- ``shape+xyc``: the true lens shape, field removed, ``xp, yp, c`` estimated: what
  three intrinsics cost on this geometry;
- ``field, xyc fixed``: the true lens with ``xp, yp, c`` held at the truth, the field
  left in the measurements and unmodelled: what the field does to the poses alone;
- ``field+xyc``: the true lens shape, field left in, ``xp, yp, c`` estimated: the best a
  perfect radial model without a field model can do;
- ``field+xyc+knn``: the same with the kNN correction rounds (does the kNN get the
  field back once the radial model is exact?).

When ``field+xyc`` is as far from the oracle as ``default``, the loss is the field
(absorbed by the principal point and the poses), not the radial model; when
``field+xyc+knn`` does not recover it, the residuals no longer hold it.

Run ``python benchmarks/bench_field_absorption.py [--seed 0] [--only 49-,36-]`` (default:
the imperfect cases of the seed's zoo list; about 1-2 minutes a case on a loaded core).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_lens_zoo as zoo  # noqa: E402


def run(case, workdir: Path) -> dict:
    """The five ratios of one case (module docstring), each an
    :func:`~gtsam_sphere.simulate.oracle.oracle_calibration` variant but ``default``."""
    from gtsam_sphere.simulate import simulate_room, write_simulation
    from gtsam_sphere.simulate.oracle import oracle_calibration

    sim = simulate_room(case.options())
    exact = all(t.get("sigma") == 0.0 for t in sim.dataset["targets"])
    metric = "stations" if exact else "checkpoints"
    paths = write_simulation(sim, workdir / case.id)
    oracle = zoo._rmse_3d(oracle_calibration(sim, case.seed), sim, metric)
    row = {"id": case.id, "field_px": case.error_field_px, "pupil_m": case.pupil_shift_m}
    calib, status = zoo._default_calibration(
        paths["dataset"], workdir / case.id / "calibration.json", None
    )
    row["default"] = zoo._rmse_3d(calib, sim, metric) / oracle
    variants = {
        "shape+xyc": {"known_lens": False},
        "field, xyc fixed": {"known_field": False},
        "field+xyc": {"known_lens": False, "known_field": False},
        "field+xyc+knn": {"known_lens": False, "known_field": False, "learn_correction": True},
    }
    for name, knowledge in variants.items():
        result = oracle_calibration(sim, case.seed, **knowledge)
        row[name] = zoo._rmse_3d(result, sim, metric) / oracle
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=0, help="seed of the zoo's case list")
    ap.add_argument("--only", default=None, help="comma-separated substrings of case ids")
    args = ap.parse_args(argv)
    # (the sphere lens's two hemispheres share its image: its oracle maps it differently)
    cases = [c for c in zoo.build_cases(args.seed) if c.error_field_px > 0 and c.family != "sphere"]
    if args.only:
        wanted = [w for w in args.only.split(",") if w]
        cases = [c for c in cases if any(w in c.id for w in wanted)]
    names = ["default", "shape+xyc", "field, xyc fixed", "field+xyc", "field+xyc+knn"]
    rows = []
    with tempfile.TemporaryDirectory(prefix="field_absorption_") as tmp:
        for case in cases:
            print(f"{case.id} ...", file=sys.stderr, flush=True)
            rows.append(run(case, Path(tmp)))
            print("  " + ", ".join(f"{n} {rows[-1][n]:.2f}" for n in names), file=sys.stderr)
    print("3D RMSE / oracle (the oracle knows the error field)")
    print("| case | field px | pupil mm | " + " | ".join(names) + " |")
    print("|---|---|---|" + "---|" * len(names))
    for r in rows:
        cells = " | ".join(f"{r[n]:.2f}" for n in names)
        print(f"| {r['id']} | {r['field_px']:g} | {1e3 * r['pupil_m']:g} | {cells} |")
    if rows:
        for n in names:
            print(f"median {n}: {np.median([r[n] for r in rows]):.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
