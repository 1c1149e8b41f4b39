"""``gtsam-sphere demo``: simulate a room and calibrate it, printing a result table."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..core.camera import DEFAULT_MODEL, Model
from ..estimation.optimize import stderr_progress
from .common import print_statistics

NAME = "demo"
HELP = "simulate a room and calibrate it, printing a result table"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of ``gtsam-sphere demo``."""
    p.add_argument("-o", "--output", default="gtsam_sphere_demo")
    p.add_argument("--lens", default="kannala-brandt", help="simulated lens family")
    p.add_argument("--fov-deg", type=float, default=200.0)
    p.add_argument("--noise-px", type=float, default=0.3)
    p.add_argument("--images", type=int, default=52)
    p.add_argument("--model", choices=[m.value for m in Model], default=DEFAULT_MODEL.value)
    p.add_argument("--no-oracle", action="store_true", help="skip the true-lens adjustment")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true")


def run(args) -> int:
    """Run ``gtsam-sphere demo``: 0 trusted, 1 not to be trusted (as ``calibrate``)."""
    import numpy as np

    from ..analysis.evaluate import evaluate_calibration
    from ..estimation.calibrate import CalibrationOptions, calibrate
    from ..io.dataset import parse_dataset
    from ..simulate import gopro_like, simulate_room, write_simulation
    from ..simulate.oracle import oracle_calibration

    out = Path(args.output)
    say = None if args.quiet else stderr_progress
    sim_options = gopro_like(
        lens=args.lens,
        fov_deg=args.fov_deg,
        fill="circle" if args.fov_deg >= 180 else "diagonal",
        lens_options=gopro_like().lens_options if args.lens == "kannala-brandt" else {},
        noise_px=args.noise_px,
        n_images=args.images,
        seed=args.seed,
    )
    print(
        f"simulating the paper's room: {args.lens} lens, {args.fov_deg:.0f} deg field of view, "
        f"decentering, {sim_options.pupil_shift_m * 1e3:.0f} mm pupil shift, "
        f"{sim_options.error_field_px:.0f} px smooth error field, noise {args.noise_px} px, "
        f"{args.images} images, seed {args.seed}"
    )
    sim = simulate_room(sim_options)
    paths = write_simulation(sim, out)
    dataset = parse_dataset(sim.dataset, str(paths["dataset"]))
    calib = calibrate(dataset, CalibrationOptions(model=Model(args.model), seed=args.seed), say)
    calib.save(out / "calibration.json")
    ids = [t["id"] for t in sim.checkpoints["targets"]]
    xyz = np.array([t["xyz"] for t in sim.checkpoints["targets"]], float)
    rep = evaluate_calibration(calib, ids, xyz)
    print(f"\nwrote {out / 'calibration.json'} (dataset, check points and truth beside it)\n")
    lens = sim.lens
    print(f"  {'':22}{'estimated':>12}{'truth':>12}")
    for name, est, true in (
        ("xp (px)", calib.camera.xp, lens.cx),
        ("yp (px)", calib.camera.yp, lens.cy),
        ("c (px)", calib.camera.c, lens.f),
    ):
        print(f"  {name:<22}{est:>12.3f}{true:>12.3f}")
    rows = [(f"{args.model} (estimated lens)", calib.statistics["rms_px"], rep)]
    if not args.no_oracle:
        if say:
            say("oracle: the same data with the true lens held fixed")
        oracle = oracle_calibration(sim, args.seed)
        rows.append(
            (
                "oracle (true lens)",
                oracle.statistics["rms_px"],
                evaluate_calibration(oracle, ids, xyz),
            )
        )
    print(f"\n  check points ({len(rep.ids)}), RMSE after a 7-parameter similarity:")
    print(f"  {'':30}{'RMS px':>8}{'X mm':>8}{'Y mm':>8}{'Z mm':>8}{'3D mm':>8}")
    for label, rms, r in rows:
        x, y, z = (v * 1e3 for v in r.rmse_xyz)
        print(f"  {label:<30}{rms:>8.3f}{x:>8.3f}{y:>8.3f}{z:>8.3f}{r.rmse_3d * 1e3:>8.3f}")
    if len(rows) == 2:
        print(f"  3D RMSE / oracle: {rep.rmse_3d / rows[1][2].rmse_3d:.2f}")
    print()
    print_statistics(calib.statistics)
    # the same rule as ``calibrate``: 0 only for a result that can be trusted
    st = calib.statistics
    trusted = st.get("trusted", st["converged"])
    print(f"\n  {'trusted' if trusted else 'NOT trusted'}")
    for reason in st.get("distrust", []):
        print(f"    - {reason}")
    return 0 if trusted else 1
