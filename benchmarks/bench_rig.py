"""Rig benchmark: the rig calibration on the simulated rigs against their oracle (issue 11).

For each simulated rig of :mod:`gtsam_sphere.simulate.rigs` (stereo, dual360, ring4,
mixed; seeded, in the paper's room) and each of ``--seeds`` seeds, the dataset@2 file is
calibrated exactly as ``gtsam-sphere calibrate RIG.json -o CALIB.json`` does (the default
model unless ``--model``), and compared with two references computed on the same data
(:func:`gtsam_sphere.simulate.oracle.oracle_rig_calibration`):

- the **oracle**: true lenses and true ``cam_from_rig`` held, only the frames and the
  targets adjusted; the issue's goal: check-point RMSE within 1.15x of it;
- the **known-family** adjustment: the measurements mapped through each true lens onto
  an ideal model whose principal point and distance are estimated, extrinsics free;
  the marginal covariance of its joint stage is the *expected* error of
  ``cam_from_rig`` (goal: the true error within 1.6x of it, as RMS over the seeds).

The first table details the first seed, per camera:

- the exit code of the run (0 trusted, 1 written but not trusted; ``NT`` marks an
  untrusted camera), the model;
- ``rms`` the reprojection RMS (px) of the camera's own adjustment and ``rms rig``
  with the rig's poses;
- ``3D`` the check-point RMSE (mm, after a 7-parameter similarity,
  :mod:`gtsam_sphere.analysis.evaluate`) of the rig's adjusted targets that this
  camera observes; the rig's row, all check points;
- the error of ``cam_from_rig`` against the truth, rotation (deg) and translation
  (mm), next to the sigma the calibration@2 file reports (``cam_from_rig_precision``:
  the joint stage's marginal covariance; the RMS length of the 3-D error); ``ref`` for
  the reference camera (identity by definition).

The second table gives, over the seeds, per rig the check-point RMSE (RMS over the
seeds) of the calibration and of the oracle and their ratio, and per camera the RMS
over the seeds of the true extrinsic errors, of the reported sigma and of the
known-family sigma, with ``err/exp`` (true error over the known-family sigma, goal
<= 1.6) and ``err/sig`` (over the calibration's own sigma).

The lens zoo's rigs (``--zoo``, :data:`gtsam_sphere.simulate.rigs.ZOO_RIG_KINDS`) put
the single-camera zoo's harder lenses on rigs: circular fisheyes on a third of the
sensor, catadioptric and double-sphere pairs, a ring of FOV-model lenses, a 300 degree
fisheye with a pinhole, full-frame circles the sensor crops.

    python benchmarks/bench_rig.py --quick                 # 6 frames, 2 seeds
    python benchmarks/bench_rig.py --zoo --seeds 1         # the zoo's rigs
    python benchmarks/bench_rig.py --random 12 --seed 5    # drawn rigs and lenses
    python benchmarks/bench_rig.py [--frames 12] [--seed 1] [--seeds 2] [--only ring4]
                                   [--model radial] [--max-iterations 400]
                                   [--no-oracle] [--json out.json]
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

import gtsam  # noqa: E402
import numpy as np  # noqa: E402

from gtsam_sphere import load_calibration  # noqa: E402
from gtsam_sphere.analysis.evaluate import evaluate_checkpoints  # noqa: E402
from gtsam_sphere.cli import main as cli_main  # noqa: E402
from gtsam_sphere.core.errors import GtsamSphereError  # noqa: E402
from gtsam_sphere.io.dataset import load_checkpoints  # noqa: E402
from gtsam_sphere.simulate import (  # noqa: E402
    RIG_KINDS,
    ZOO_RIG_KINDS,
    RigCamera,
    RigOptions,
    simulate_rig,
    write_rig_simulation,
)
from gtsam_sphere.simulate.lenses import make_lens  # noqa: E402
from gtsam_sphere.simulate.oracle import oracle_rig_calibration  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_lens_zoo as zoo  # noqa: E402  (the lens draws of the stress cases)

#: ``--random``: layouts of a drawn rig, with the field of view each needs (deg): a
#: forward-looking pair or trio (baseline 6-20 cm, a few degrees apart), two lenses back
#: to back, a ring of 3-4 around the vertical (5 cm radius) whose neighbours overlap
RANDOM_LAYOUTS = {"forward": 40.0, "back-to-back": 190.0, "ring": None}
#: ``--random``: a drawn rig that the simulator cannot frame (a camera that sees too few
#: targets in every frame) is drawn again, at most this many times
RANDOM_TRIES = 20


def _pose(doc) -> tuple[np.ndarray, np.ndarray]:
    return np.array(doc["R"], float), np.array(doc["t"], float)


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def _fmt(v, spec: str = ".3f") -> str:
    return "-" if v is None else format(v, spec)


def _rms(values) -> float | None:
    v = [x for x in values if x is not None]
    return float(np.sqrt(np.mean(np.square(v)))) if v else None


def _ratio(a, b) -> float | None:
    return None if a is None or b is None or b == 0 else a / b


def _references(sim, calib_ids, cp_ids, cp_xyz, scale: float) -> dict:
    """The oracle's check-point RMSE and the known-family adjustment's extrinsics."""
    oracle = oracle_rig_calibration(sim)
    family = oracle_rig_calibration(sim, known_lenses=False)
    out = {
        "oracle_checkpoint_rmse_mm": evaluate_checkpoints(
            oracle.target_ids, oracle.target_xyz, cp_ids, cp_xyz
        ).rmse_3d
        * scale,
        "family_checkpoint_rmse_mm": evaluate_checkpoints(
            family.target_ids, family.target_xyz, cp_ids, cp_xyz
        ).rmse_3d
        * scale,
        "cameras": {},
    }
    truth = {cam.id: cam.cam_from_rig for cam in sim.cameras}
    for cid in calib_ids:
        pr = family.statistics["cameras"][cid].get("cam_from_rig_precision", {})
        t_sigma = pr.get("translation_sigma")
        R, t = family.cam_from_rig[cid]
        out["cameras"][cid] = {
            "rot_sigma_deg": pr.get("rotation_sigma_deg"),
            "trans_sigma_mm": None if t_sigma is None else float(np.linalg.norm(t_sigma)) * scale,
            "rot_err_deg": _angle_deg(R @ truth[cid][0].T),
            "trans_err_mm": float(np.linalg.norm(t - truth[cid][1])) * scale,
        }
    return out


def _rig_from_cam(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """``rig_from_cam`` rotation ``Rz(roll) Ry(yaw) Rx(pitch)``: yaw about the rig's y
    (down) axis turns the camera's axis (z) in the horizontal plane."""
    angles = np.radians([pitch_deg, yaw_deg, roll_deg])
    return gtsam.Rot3.RzRyRx(*angles).matrix()


def _draw_lens(rng: np.random.Generator, fov_min: float):
    """One lens of the stress draws (family, field of view, image size, circle, principal
    point within 5 %, shape parameters of :data:`bench_lens_zoo.SHAPE_RANGES`) whose
    field of view is at least ``fov_min`` deg; ``(lens, width, height, fov, label)``."""
    families = [f for f, fovs in zoo.FAMILIES.items() if max(fovs) >= fov_min]
    family = families[int(rng.integers(len(families)))]
    fovs = zoo.FAMILIES[family]
    low = max(fov_min, 40.0 if family == "pinhole" else min(fovs))
    fov = float(np.round(rng.uniform(low, max(fovs))))
    width, height = zoo.STRESS_SIZES[int(rng.integers(len(zoo.STRESS_SIZES)))]
    circles = zoo.STRESS_CIRCLES if fov < 180.0 else zoo.STRESS_CIRCLES[1:]
    circle = circles[int(rng.integers(len(circles)))]
    radius = zoo.circle_radius_px(circle, width, height)
    shape, _ = zoo.draw_shape(family, fov, rng)
    cx = (width - 1) / 2.0 + float(rng.uniform(-0.05, 0.05)) * width
    cy = (height - 1) / 2.0 + float(rng.uniform(-0.05, 0.05)) * height
    lens = make_lens(family, fov, width, height, circle_radius_px=radius, cx=cx, cy=cy, **shape)
    return lens, width, height, fov, f"{family}-{fov:g}"


def draw_random_rig(rng: np.random.Generator) -> tuple[str, list[RigCamera]]:
    """A rig of 2-4 drawn cameras in one of :data:`RANDOM_LAYOUTS`, each lens drawn as
    the lens zoo's stress cases draw theirs (the same lens on every camera half the
    time); ``(label, cameras)``."""
    layout = list(RANDOM_LAYOUTS)[int(rng.integers(len(RANDOM_LAYOUTS)))]
    if layout == "back-to-back":
        n = 2
    elif layout == "ring":
        n = int(rng.integers(3, 5))
    else:
        n = int(rng.choice([2, 2, 3]))
    fov_min = RANDOM_LAYOUTS[layout] or 360.0 / n + 40.0
    twin = rng.uniform() < 0.5
    first = _draw_lens(rng, fov_min)
    cams, labels = [], []
    for k in range(n):
        lens, w, h, fov, label = first if (twin or k == 0) else _draw_lens(rng, fov_min)
        labels.append(label)
        if layout == "forward":
            yaw = float(rng.uniform(-8.0, 8.0))
            R = _rig_from_cam(yaw, float(rng.uniform(-3, 3)), float(rng.uniform(-3, 3)))
            centre = np.array([k * float(rng.uniform(0.06, 0.20)), 0.0, 0.0])
        else:
            yaw = 360.0 * k / n + (float(rng.uniform(-5.0, 5.0)) if k else 0.0)
            R = _rig_from_cam(yaw, float(rng.uniform(-3, 3)) if k else 0.0, 0.0)
            radius = 0.03 if layout == "back-to-back" else 0.05
            centre = radius * R[:, 2] - radius * np.array([0.0, 0.0, 1.0])
        if k == 0:
            R, centre = np.eye(3), np.zeros(3)
        cams.append(RigCamera(f"c{k}", lens, w, h, fov, (R.T, -R.T @ centre)))
    kind = labels[0] if twin else "mixed"
    return f"{layout}{n}-{kind}", cams


def random_rigs(seed: int, n: int, frames: int) -> list[tuple[str, list[RigCamera]]]:
    """``n`` drawn rigs (:func:`draw_random_rig`) from ``seed``, each one the simulator
    can frame in ``frames`` frames with simulation seed 1 (drawn again otherwise,
    :data:`RANDOM_TRIES`; another seed that cannot frame it is a row with an error in
    :func:`run_rig`); labels ``rNN-layout-lens``."""
    rng = np.random.default_rng([seed, 0x216])
    out = []
    for i in range(n):
        for _ in range(RANDOM_TRIES):
            label, cams = draw_random_rig(rng)
            try:
                simulate_rig(RigOptions(rig=label, cameras=tuple(cams), n_frames=frames, seed=1))
            except (GtsamSphereError, ValueError):
                continue
            out.append((f"r{i:02d}-{label}", cams))
            break
    return out


def run_rig(
    kind: str,
    args: argparse.Namespace,
    work: Path,
    seed: int | None = None,
    cameras: list[RigCamera] | None = None,
) -> dict:
    """Simulate, calibrate through the command line, compare with the truth (and the
    oracle and the known-family adjustment unless ``--no-oracle``); ``cameras``: a rig
    of one's own named ``kind``."""
    seed = args.seed if seed is None else seed
    opts = RigOptions(
        rig=kind,
        n_frames=args.frames,
        seed=seed,
        noise_px=args.noise_px,
        cameras=None if cameras is None else tuple(cameras),
    )
    try:
        sim = simulate_rig(opts)
    except (GtsamSphereError, ValueError) as exc:  # a drawn rig this seed cannot frame
        return {"rig": kind, "error": f"simulation: {type(exc).__name__}: {exc}"}
    paths = write_rig_simulation(sim, work / kind)
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
                "sigma_px": cs.get("sigma_px"),
                "sigma_px_rig": cs.get("sigma_px_rig"),
                "n_observations": cs.get("n_observations"),
                "n_outliers": cs.get("n_outliers"),
                "n_outliers_rig": cs.get("n_outliers_rig"),
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
    refs = None
    if not args.no_oracle:
        t1 = time.perf_counter()
        refs = _references(sim, calib.camera_ids, cp_ids, cp_xyz, scale)
        refs["seconds"] = time.perf_counter() - t1
    return {
        "rig": kind,
        "seed": seed,
        "exit": code,
        "seconds": seconds,
        "references": refs,
        "n_frames": calib.statistics.get("n_frames"),
        "rms_px": calib.statistics.get("rms_px"),
        "rms_px_rig": calib.statistics.get("rms_px_rig"),
        "checkpoint_rmse_mm": rig_3d * scale,
        "n_checkpoints": len(cp_ids),
        "distrust": calib.statistics.get("distrust", []),
        "joint": calib.statistics.get("joint"),
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


def summarise(runs: list[dict]) -> list[dict]:
    """Per rig, over its seeds: check-point RMSE vs the oracle, extrinsic errors vs sigma."""
    out = []
    for kind in dict.fromkeys(r["rig"] for r in runs):
        rows = [r for r in runs if r["rig"] == kind and "error" not in r]
        if not rows:
            out.append({"rig": kind, "error": "every run failed"})
            continue
        ok = [r for r in rows if r.get("references")]
        cp = _rms(r["checkpoint_rmse_mm"] for r in ok)
        cp_oracle = _rms(r["references"]["oracle_checkpoint_rmse_mm"] for r in ok)
        summary = {
            "rig": kind,
            "n_seeds": len(rows),
            "n_untrusted_runs": sum(r["exit"] != 0 for r in rows),
            "checkpoint_rmse_mm": cp,
            "oracle_checkpoint_rmse_mm": cp_oracle,
            "checkpoint_ratio": _ratio(cp, cp_oracle),
            "cameras": [],
        }
        for k, cam in enumerate(rows[0]["cameras"]):
            if cam["reference"]:
                continue
            cid = cam["camera"]
            mine = [r["cameras"][k] for r in ok]
            fam = [r["references"]["cameras"][cid] for r in ok]
            entry = {"camera": cid}
            for q, unit in (("rot", "deg"), ("trans", "mm")):
                err = _rms(c[f"{q}_err_{unit}"] for c in mine)
                sig = _rms(c[f"{q}_sigma_{unit}"] for c in mine)
                exp = _rms(c[f"{q}_sigma_{unit}"] for c in fam)
                entry.update(
                    {
                        f"{q}_err_{unit}": err,
                        f"{q}_sigma_{unit}": sig,
                        f"{q}_expected_{unit}": exp,
                        f"{q}_family_err_{unit}": _rms(c[f"{q}_err_{unit}"] for c in fam),
                        f"{q}_err_over_expected": _ratio(err, exp),
                        f"{q}_err_over_sigma": _ratio(err, sig),
                    }
                )
            summary["cameras"].append(entry)
        out.append(summary)
    return out


def print_summary(summaries: list[dict]) -> None:
    head = (
        f"{'rig':8} {'camera':8} {'3D mm':>6} {'oracle':>6} {'ratio':>5} | "
        f"{'rot deg':>7} {'sig':>7} {'exp':>7} {'err/exp':>7} {'err/sig':>7} | "
        f"{'t mm':>6} {'sig':>6} {'exp':>6} {'err/exp':>7} {'err/sig':>7}"
    )
    print(head)
    print("-" * len(head))
    for s in summaries:
        if "error" in s:
            print(f"{s['rig']:8} error: {s['error']}")
            continue
        print(
            f"{s['rig']:8} {'(rig)':8} {_fmt(s['checkpoint_rmse_mm'], '.2f'):>6} "
            f"{_fmt(s['oracle_checkpoint_rmse_mm'], '.2f'):>6} "
            f"{_fmt(s['checkpoint_ratio'], '.2f'):>5} |   ({s['n_seeds']} seeds, "
            f"{s['n_untrusted_runs']} not trusted)"
        )
        for c in s["cameras"]:
            print(
                f"{'':8} {c['camera']:8} {'':6} {'':6} {'':5} | "
                f"{_fmt(c['rot_err_deg'], '.4f'):>7} {_fmt(c['rot_sigma_deg'], '.4f'):>7} "
                f"{_fmt(c['rot_expected_deg'], '.4f'):>7} "
                f"{_fmt(c['rot_err_over_expected'], '.2f'):>7} "
                f"{_fmt(c['rot_err_over_sigma'], '.2f'):>7} | "
                f"{_fmt(c['trans_err_mm'], '.2f'):>6} {_fmt(c['trans_sigma_mm'], '.2f'):>6} "
                f"{_fmt(c['trans_expected_mm'], '.2f'):>6} "
                f"{_fmt(c['trans_err_over_expected'], '.2f'):>7} "
                f"{_fmt(c['trans_err_over_sigma'], '.2f'):>7}"
            )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--quick", action="store_true", help="6 frames per rig")
    p.add_argument("--frames", type=int, default=None, help="frames per rig (default 12)")
    p.add_argument("--seed", type=int, default=1, help="first seed")
    p.add_argument("--seeds", type=int, default=2, help="seeds per rig (default 2)")
    p.add_argument(
        "--no-oracle",
        action="store_true",
        help="skip the oracle and the known-family references (the first table only)",
    )
    p.add_argument("--noise-px", type=float, default=0.3)
    p.add_argument(
        "--zoo",
        action="store_true",
        help="the lens zoo's rigs (small circles, catadioptric, double sphere, FOV ring, "
        "300 deg + pinhole, cropped circles) instead of the four base rigs",
    )
    p.add_argument(
        "--random",
        type=int,
        default=0,
        metavar="N",
        help="N drawn rigs instead (2-4 cameras forward, back to back or in a ring, each "
        "lens drawn as the lens zoo's stress cases with --shapes), from --seed",
    )
    p.add_argument("--only", default=None, help="comma-separated rigs")
    p.add_argument("--model", default=None, help="calibrate --model (default: the CLI's)")
    p.add_argument("--max-iterations", type=int, default=None, help="calibrate --max-iterations")
    p.add_argument("--json", default=None, help="write the rows to this file")
    args = p.parse_args(argv)
    if args.frames is None:
        args.frames = 6 if args.quick else 12
    kinds = (
        (ZOO_RIG_KINDS if args.zoo else RIG_KINDS) if not args.only else tuple(args.only.split(","))
    )
    drawn: dict[str, list[RigCamera]] = {}
    if args.random:
        drawn = dict(random_rigs(args.seed, args.random, args.frames))
        wanted = args.only.split(",") if args.only else None
        kinds = tuple(k for k in drawn if wanted is None or any(o in k for o in wanted))
        for kind in kinds:
            lenses = "; ".join(
                f"{c.id} {c.lens.to_dict()['kind']} {c.fov_deg:g} deg {c.width}x{c.height}"
                for c in drawn[kind]
            )
            print(f"{kind}: {lenses}", file=sys.stderr, flush=True)
    runs = []
    seeds = list(range(args.seed, args.seed + max(1, args.seeds)))
    with tempfile.TemporaryDirectory() as tmp:
        for kind in kinds:
            for seed in seeds:
                t0 = time.perf_counter()
                runs.append(run_rig(kind, args, Path(tmp) / f"s{seed}", seed, drawn.get(kind)))
                print(
                    f"done {kind} seed {seed} ({time.perf_counter() - t0:.0f} s)",
                    file=sys.stderr,
                    flush=True,
                )
    print(
        f"rig benchmark: {args.frames} frames, seed {seeds[0]}, noise {args.noise_px} px, "
        f"model {args.model or 'CLI default'}, max iterations "
        f"{args.max_iterations or 'CLI default'}; 3D = check-point RMSE (all for the rig "
        "row, those the camera sees otherwise); rot/t = cam_from_rig error vs truth; sig = "
        "reported sigma (joint stage's marginal covariance); NT = camera not trusted"
    )
    print_table([r for r in runs if r.get("seed", seeds[0]) == seeds[0]])
    summaries = []
    if not args.no_oracle:
        summaries = summarise(runs)
        print()
        print(
            f"over seeds {seeds[0]}..{seeds[-1]} (RMS over the seeds): 3D vs the oracle (true "
            "lenses and extrinsics held), goal ratio <= 1.15; cam_from_rig error vs sig "
            "(reported) and exp (expected: the known-family adjustment's sigma), goal "
            "err/exp <= 1.6"
        )
        print_summary(summaries)
    if args.json:
        doc = {"runs": runs, "summary": summaries}
        Path(args.json).write_text(json.dumps(doc, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
