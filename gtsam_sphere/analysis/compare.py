"""The paper's Tables 1-2: several models on one dataset, judged at check points."""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..core.camera import Model
from ..core.errors import OptionsError
from ..estimation.calibrate import CalibrationOptions, calibrate, initialise
from ..io.dataset import Dataset, load_checkpoints, load_dataset, write_json_atomic
from .evaluate import evaluate_calibration

# (label, model, Brown terms): the rows of Chow et al. (2018) Tables 1-2, then ours
PAPER_ROWS: tuple[tuple[str, Model, tuple[str, ...]], ...] = (
    ("XYZ,EOP,IOP", Model.SPHERE, ()),
    ("+K1", Model.BROWN, ("k1",)),
    ("+K1,K2", Model.BROWN, ("k1", "k2")),
    ("+K1,K2,K3", Model.BROWN, ("k1", "k2", "k3")),
    ("+K1-K3,P1,P2", Model.BROWN, ("k1", "k2", "k3", "p1", "p2")),
    ("+K1-K3,P1,P2,A1", Model.BROWN, ("k1", "k2", "k3", "p1", "p2", "a1")),
    ("+K1-K3,P1,P2,A1,A2", Model.BROWN, ("k1", "k2", "k3", "p1", "p2", "a1", "a2")),
    ("kNN (paper)", Model.SPHERE_KNN, ()),
    ("Brown K1-K3,P1,P2 + kNN", Model.BROWN_KNN, ("k1", "k2", "k3", "p1", "p2")),
    ("radial g3-g9,P1,P2,A1,A2", Model.RADIAL, ("p1", "p2", "a1", "a2")),
    ("radial + kNN (default)", Model.RADIAL_KNN, ("p1", "p2", "a1", "a2")),
)


@dataclass
class CompareRow:
    """One model's result: image-space and 3D check-point errors."""

    label: str
    model: str
    sum_squares_px2: float
    rms_px: float
    rmse_xyz: np.ndarray
    rmse_3d: float
    converged: bool


def compare(
    dataset: Dataset,
    checkpoint_ids: list[str],
    checkpoint_xyz: np.ndarray,
    rows=PAPER_ROWS,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> list[CompareRow]:
    """Calibrate ``dataset`` with each row's model from one shared initialisation.

    Returns
    -------
    list of CompareRow
        Image-space error (sum of squared residuals, px^2; RMS px) and RMSE
        per axis at the check points after a 7-parameter similarity.
    """
    say = progress or (lambda _line: None)
    init = initialise(dataset, seed, say)
    out = []
    for label, model, terms in rows:
        say(f"== {label}")
        options = CalibrationOptions(model=model, brown_terms=terms, seed=seed, covariance=False)
        calib = calibrate(dataset, options, None, init=init)
        rep = evaluate_calibration(calib, checkpoint_ids, checkpoint_xyz)
        res = np.asarray(calib.extra["observations"]["residual_px"])
        out.append(
            CompareRow(
                label,
                str(model),
                float(np.sum(res**2)),
                calib.statistics["rms_px"],
                rep.rmse_xyz,
                rep.rmse_3d,
                calib.statistics["converged"],
            )
        )
        say(f"   RMS {out[-1].rms_px:.3f} px, 3D RMSE {rep.rmse_3d * 1e3:.2f} mm")
    return out


def format_table(rows: list[CompareRow], units: str = "m") -> str:
    """Markdown table of :func:`compare` rows (RMSE in mm when units are metres)."""
    f, u = (1e3, "mm") if units == "m" else (1.0, units)
    lines = [
        f"| model | image-space error (px^2) | RMS (px) | RMSE X ({u}) | RMSE Y ({u}) "
        f"| RMSE Z ({u}) | 3D ({u}) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        flag = "" if r.converged else " (not converged)"
        lines.append(
            f"| {r.label}{flag} | {r.sum_squares_px2:.2e} | {r.rms_px:.3f} | "
            f"{r.rmse_xyz[0] * f:.2f} | {r.rmse_xyz[1] * f:.2f} | {r.rmse_xyz[2] * f:.2f} | "
            f"{r.rmse_3d * f:.2f} |"
        )
    return "\n".join(lines)


def add_cli_arguments(parser) -> None:
    """Arguments of ``gtsam-sphere compare``."""
    parser.add_argument(
        "dataset", help="DATASET.json (with --checkpoints) or CALIB.json (with --with)"
    )
    parser.add_argument("--checkpoints", help="check points (the paper's tables; required then)")
    parser.add_argument("-o", "--output", help="write the table as JSON here")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quiet", action="store_true")


def run_cli(args) -> int:
    """``gtsam-sphere compare DATASET --checkpoints CP [-o OUT.json]``."""
    if not getattr(args, "checkpoints", None):
        raise OptionsError("compare DATASET needs --checkpoints CP.json (or CALIB.json --with)")
    dataset = load_dataset(args.dataset)
    ids, xyz, units = load_checkpoints(args.checkpoints)
    say = None if args.quiet else (lambda line: print(line, file=sys.stderr, flush=True))
    rows = compare(dataset, ids, xyz, seed=args.seed, progress=say)
    print(format_table(rows, units))
    if args.output:
        write_json_atomic(
            args.output,
            {
                "dataset": str(args.dataset),
                "rows": [
                    {
                        "label": r.label,
                        "model": r.model,
                        "sum_squares_px2": r.sum_squares_px2,
                        "rms_px": r.rms_px,
                        "rmse_xyz": r.rmse_xyz,
                        "rmse_3d": r.rmse_3d,
                        "converged": r.converged,
                    }
                    for r in rows
                ],
            },
        )
    return 0
