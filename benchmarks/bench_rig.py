"""Rig benchmark: the current rig calibration on the simulated rigs (issue 11, item 4).

For each simulated rig of :mod:`gtsam_sphere.simulate.rigs` (stereo, dual360, ring4,
mixed; seeded, in the paper's room) the dataset@2 file is calibrated exactly as
``gtsam-sphere calibrate RIG.json -o CALIB.json`` does (the current rig path,
:mod:`gtsam_sphere.estimation.rig`: each camera alone, then averaged extrinsics), and
a table gives per camera

- the exit code of the run (0 trusted, 1 written but not trusted), the model;
- ``rms`` the reprojection RMS (px) of the camera's own adjustment and ``rms rig``
  with the rig-composed poses and the mean targets;
- ``3D`` the check-point RMSE (mm, after a 7-parameter similarity,
  :mod:`gtsam_sphere.analysis.evaluate`) of the rig's adjusted targets that this
  camera observes; the rig's row, all check points;
- the error of ``cam_from_rig`` against the truth, rotation (deg) and translation
  (mm), next to the sigma the calibration@2 file reports
  (``cam_from_rig_precision``: standard error of the mean over the frames,
  rotation deg and the norm of the per-axis translation sigmas, mm); ``ref`` for the
  reference camera (identity by definition).

    python benchmarks/bench_rig.py --quick          # 6 frames per rig
    python benchmarks/bench_rig.py [--frames 12] [--seed 1] [--only ring4]
                                   [--model radial] [--max-iterations 400] [--json out.json]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core: timings comparable on a shared host

import argparse  # noqa: E402
import contextlib  # noqa: E402
import io  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from gtsam_sphere import load_calibration  # noqa: E402
from gtsam_sphere.analysis.evaluate import evaluate_checkpoints  # noqa: E402
from gtsam_sphere.cli import main as cli_main  # noqa: E402
from gtsam_sphere.io.dataset import load_checkpoints  # noqa: E402
from gtsam_sphere.simulate import RIG_KINDS, RigOptions, simulate_rig, write_rig_simulation  # noqa: E402


def _pose(doc) -> tuple[np.ndarray, np.ndarray]:
    return np.array(doc["R"], float), np.array(doc["t"], float)


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def _fmt(v, spec: str = ".3f") -> str:
    return "-" if v is None else format(v, spec)


def run_rig(kind: str, args: argparse.Namespace, work: Path) -> dict:
    """Simulate, calibrate through the command line, compare with the truth."""
    opts = RigOptions(rig=kind, n_frames=args.frames, seed=args.seed, noise_px=args.noise_px)
    paths = write_rig_simulation(simulate_rig(opts), work / kind)
    out = work / kind / "calib.json"
    argv = ["calibrate", str(paths["dataset"]), "-o", str(out), "--quiet"]
    if args.model:
        argv += ["--model", args.model]
    if args.max_iterations:
        argv += ["--max-iterations", str(args.max_iterations)]
    t0 = time.perf_counter()
    sink = io.StringIO()
    with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
        try:
            code = cli_main(argv)
        except Exception as exc:  # a crash is a row, never the end of the table
            return {"rig": kind, "error": f"{type(exc).__name__}: {exc}"}
    seconds = time.perf_counter() - t0
    if not out.exists():
        return {"rig": kind, "exit": code, "error": sink.getvalue().strip().splitlines()[-1:]}
    calib = load_calibration(out)
    truth = json.loads(paths["truth"].read_text())
    dataset = json.loads(paths["dataset"].read_text())
    cp_ids, cp_xyz, units = load_checkpoints(paths["checkpoints"])
    scale = 1000.0 if units == "m" else 1.0  # report millimetres
    rig_3d = evaluate_checkpoints(calib.target_ids, calib.target_xyz, cp_ids, cp_xyz).rmse_3d
    cams = []
    for cam in truth["cameras"]:
        cid = cam["id"]
        cs = calib.statistics["cameras"][cid]
        seen = {
            o["target"]
            for im in dataset["images"]
            if im["camera"] == cid
            for o in im["observations"]
        }
        keep = [k for k, t in enumerate(cp_ids) if t in seen]
        try:
            cam_3d = evaluate_checkpoints(
                calib.target_ids, calib.target_xyz, [cp_ids[k] for k in keep], cp_xyz[keep]
            ).rmse_3d
        except ValueError:  # fewer than 3 check points seen by this camera
            cam_3d = None
        R_true, t_true = _pose(cam["cam_from_rig"])
        R, t = calib.cam_from_rig[cid]
        pr = cs.get("cam_from_rig_precision", {})
        t_sigma = pr.get("translation_sigma")
        cams.append(
            {
                "camera": cid,
                "model": cs.get("model"),
                "trusted": bool(cs.get("trusted", cs.get("converged"))),
                "n_images": cs.get("n_images"),
                "rms_px": cs.get("rms_px"),
                "rms_px_rig": cs.get("rms_px_rig"),
                "checkpoint_rmse_mm": None if cam_3d is None else cam_3d * scale,
                "reference": pr.get("parent") is None,
                "rot_err_deg": _angle_deg(R @ R_true.T),
                "rot_sigma_deg": pr.get("rotation_sigma_deg"),
                "trans_err_mm": float(np.linalg.norm(t - t_true)) * scale,
                "trans_sigma_mm": None
                if t_sigma is None
                else float(np.linalg.norm(t_sigma)) * scale,
            }
        )
    return {
        "rig": kind,
        "exit": code,
        "seconds": seconds,
        "n_frames": calib.statistics.get("n_frames"),
        "rms_px": calib.statistics.get("rms_px"),
        "rms_px_rig": calib.statistics.get("rms_px_rig"),
        "checkpoint_rmse_mm": rig_3d * scale,
        "n_checkpoints": len(cp_ids),
        "cameras": cams,
    }


def print_table(rows: list[dict]) -> None:
    head = (
        f"{'rig':8} {'camera':8} {'exit':>4} {'model':10} {'img':>3} {'rms px':>7} "
        f"{'rms rig':>7} {'3D mm':>7} {'rot deg':>8} {'sig deg':>8} {'t mm':>7} {'sig mm':>7}"
    )
    print(head)
    print("-" * len(head))
    for row in rows:
        if "error" in row:
            print(f"{row['rig']:8} error: {row['error']}")
            continue
        print(
            f"{row['rig']:8} {'(rig)':8} {row['exit']:>4} {'':10} {row['n_frames']:>3} "
            f"{_fmt(row['rms_px']):>7} {_fmt(row['rms_px_rig']):>7} "
            f"{_fmt(row['checkpoint_rmse_mm'], '.2f'):>7}   ({row['seconds']:.0f} s)"
        )
        for c in row["cameras"]:
            rot = "ref" if c["reference"] else _fmt(c["rot_err_deg"], ".4f")
            trans = "ref" if c["reference"] else _fmt(c["trans_err_mm"], ".2f")
            print(
                f"{'':8} {c['camera']:8} {'' if c['trusted'] else 'NT':>4} "
                f"{c['model'] or '-':10} {c['n_images']:>3} {_fmt(c['rms_px']):>7} "
                f"{_fmt(c['rms_px_rig']):>7} {_fmt(c['checkpoint_rmse_mm'], '.2f'):>7} "
                f"{rot:>8} {_fmt(c['rot_sigma_deg'], '.4f'):>8} {trans:>7} "
                f"{_fmt(c['trans_sigma_mm'], '.2f'):>7}"
            )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--quick", action="store_true", help="6 frames per rig")
    p.add_argument("--frames", type=int, default=None, help="frames per rig (default 12)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--noise-px", type=float, default=0.3)
    p.add_argument("--only", default=None, help="comma-separated rigs")
    p.add_argument("--model", default=None, help="calibrate --model (default: the CLI's)")
    p.add_argument("--max-iterations", type=int, default=None, help="calibrate --max-iterations")
    p.add_argument("--json", default=None, help="write the rows to this file")
    args = p.parse_args(argv)
    if args.frames is None:
        args.frames = 6 if args.quick else 12
    kinds = RIG_KINDS if not args.only else tuple(args.only.split(","))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for kind in kinds:
            rows.append(run_rig(kind, args, Path(tmp)))
            print(f"done {kind}", file=sys.stderr, flush=True)
    print(
        f"rig benchmark: {args.frames} frames, seed {args.seed}, noise {args.noise_px} px, "
        f"model {args.model or 'CLI default'}, max iterations "
        f"{args.max_iterations or 'CLI default'}; 3D = check-point RMSE (all for the rig "
        "row, those the camera sees otherwise); rot/t = cam_from_rig error vs truth; sig = "
        "reported standard error; NT = camera not trusted"
    )
    print_table(rows)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
