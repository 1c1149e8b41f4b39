"""Held-out stereo transfer on the real catadioptric pair (issue 11, "What must be shown").

Data: ``../shared/data/opencv_omnidir_stereo.dataset.json`` (dataset@2, OpenCV's omnidir
stereo tutorial data, cam0 = left, cam1 = right, 39 frames of a 6x8 chessboard). Skipped
with a message when the file is absent.

For each held-out frame (by default the data README's eight, spread evenly through the
set: 00 05 11 16 22 27 33 38; leave-one-frame-out on each of them):

1. calibrate the rig on the other frames:
   - ours: :func:`gtsam_sphere.estimation.rig.calibrate_rig` (default options, i.e.
     exactly ``gtsam-sphere calibrate`` on the subset ``dataset@2``);
   - OpenCV: ``cv2.omnidir.stereoCalibrate`` alone (Mei's unified model, flags 0,
     criteria COUNT+EPS 200 / 1e-8, as the data README's reference run);
2. resect the held-out frame's rig pose from camera 0's corners only, calibration fixed:
   - ours: :func:`gtsam_sphere.estimation.resect.resect` (P3P + RANSAC, robust LM);
   - OpenCV: ``cv2.omnidir.undistortPoints`` to normalised perspective points,
     ``cv2.solvePnP`` on them with K = I, then Levenberg-Marquardt on the 6 pose
     parameters minimising the raw-pixel error of ``cv2.omnidir.projectPoints``
     (plain least squares, OpenCV's own criterion);
3. predict camera 1's corners through the extrinsics (ours ``cam_from_rig``, OpenCV's
   ``(rvec, tvec)``) and camera 1's model (ours ``cameras["cam1"].project``, OpenCV
   ``cv2.omnidir.projectPoints``), and report the RMS ``sqrt(mean(du^2 + dv^2))`` px
   against camera 1's measured corners.

Also printed per frame: the cam0 resection RMS (how well camera 0 alone is fitted).
Every corner of the held-out frame is scored for both methods (no outlier rejection in
the score).

Run::

    python benchmarks/bench_transfer.py [--frames 00,05,...] [--loo] [--json OUT]

``--loo`` holds out every frame in turn (39 calibrations of each kind: long).
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from pathlib import Path

import numpy as np

from gtsam_sphere.estimation.calibrate import CalibrationOptions
from gtsam_sphere.estimation.resect import resect
from gtsam_sphere.estimation.rig import calibrate_rig
from gtsam_sphere.io.dataset import parse_rig_dataset, read_json

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "opencv_omnidir_stereo.dataset.json"
HELD_FRAMES = ("00", "05", "11", "16", "22", "27", "33", "38")
#: the data README's OpenCV figure for the same protocol (left -> right, 8 frames)
README_OPENCV_L2R = 0.7005

_T0 = time.perf_counter()


def log(msg: str) -> None:
    """Progress line on standard error with the elapsed time."""
    print(f"[{time.perf_counter() - _T0:7.1f} s] {msg}", file=sys.stderr, flush=True)


def rms(residuals_px: np.ndarray) -> float:
    """``sqrt(mean(du^2 + dv^2))`` over the finite rows of residuals (N, 2)."""
    r = np.asarray(residuals_px, float).reshape(-1, 2)
    if not np.all(np.isfinite(r)):
        return float("nan")
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1))))


def frame_corners(doc: dict) -> dict[str, dict[str, dict[str, np.ndarray]]]:
    """frame id -> camera id -> {target id: uv (2,)} from a dataset@2 document."""
    out: dict[str, dict[str, dict[str, np.ndarray]]] = {}
    for im in doc["images"]:
        obs = {o["target"]: np.asarray(o["uv"], float) for o in im["observations"]}
        out.setdefault(im["frame"], {})[im["camera"]] = obs
    return out


def without_frame(doc: dict, frame: str) -> dict:
    """The dataset@2 document with every image of ``frame`` left out."""
    sub = copy.copy(doc)
    sub["images"] = [im for im in doc["images"] if im.get("frame") != frame]
    return sub


def pair(corners: dict, xyz_of: dict, frame: str, cams: list[str]):
    """The targets both cameras see in ``frame``: (ids, xyz (N,3), uv0 (N,2), uv1 (N,2))."""
    c0, c1 = corners[frame][cams[0]], corners[frame][cams[1]]
    ids = [t for t in c0 if t in c1]
    xyz = np.array([xyz_of[t] for t in ids])
    return ids, xyz, np.array([c0[t] for t in ids]), np.array([c1[t] for t in ids])


# --------------------------------------------------------------------------------------
# ours
# --------------------------------------------------------------------------------------


def ours_fold(doc: dict, frame: str, held, cams: list[str], seed: int) -> dict:
    """Calibrate the rig without ``frame``, resect from cam0, transfer to cam1."""
    t0 = time.perf_counter()
    rig = parse_rig_dataset(without_frame(doc, frame), source=f"<without frame {frame}>")
    cal = calibrate_rig(rig, CalibrationOptions(seed=seed))
    seconds = time.perf_counter() - t0
    _ids, xyz, uv0, uv1 = held
    cam0, cam1 = cal.cameras[cams[0]], cal.cameras[cams[1]]
    res = resect(cam0, uv0, xyz, np.random.default_rng(seed))
    if not np.all(np.isfinite(res.R)):
        return {"resect": float("nan"), "transfer": float("nan"), "seconds": seconds}
    # rig_from_world = inverse(cam0_from_rig) * cam0_from_world
    R0, t0_ = cal.cam_from_rig[cams[0]]
    R_rw = R0.T @ res.R
    t_rw = R0.T @ (res.t - t0_)
    R1, t1 = cal.cam_from_rig[cams[1]]
    p1 = (xyz @ R_rw.T + t_rw) @ R1.T + t1
    pred = cam1.project(p1)
    return {
        "resect": rms(res.residuals_px),
        "transfer": rms(uv1 - pred),
        "seconds": seconds,
        "baseline_m": float(np.linalg.norm(-R1.T @ t1 + R0.T @ t0_)),
    }


# --------------------------------------------------------------------------------------
# OpenCV omnidir
# --------------------------------------------------------------------------------------


def _cv2():
    import cv2

    return cv2


def cv_stereo(obj, img0, img1, size0, size1):
    """``cv2.omnidir.stereoCalibrate`` with the README's settings; None on failure."""
    cv2 = _cv2()
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-8)
    try:
        out = cv2.omnidir.stereoCalibrate(
            obj,
            img0,
            img1,
            size0,
            size1,
            np.eye(3),
            np.zeros((1, 1)),
            np.zeros((1, 4)),
            np.eye(3),
            np.zeros((1, 1)),
            np.zeros((1, 4)),
            0,
            crit,
        )
    except cv2.error as exc:
        log(f"cv2.omnidir.stereoCalibrate failed: {' '.join(str(exc).split())[:200]}")
        return None
    _rms, _o, _i1, _i2, K1, xi1, D1, K2, xi2, D2, rvec, tvec, _rv, _tv, idx = out
    return {
        "K1": K1,
        "xi1": float(np.ravel(xi1)[0]),
        "D1": D1,
        "K2": K2,
        "xi2": float(np.ravel(xi2)[0]),
        "D2": D2,
        "rvec": np.asarray(rvec, float).reshape(3, 1),
        "tvec": np.asarray(tvec, float).reshape(3, 1),
        "n_used": int(np.size(idx)),
    }


def _project(obj, rvec, tvec, K, xi, D):
    cv2 = _cv2()
    p, _ = cv2.omnidir.projectPoints(
        obj.reshape(1, -1, 3), rvec.reshape(3, 1), tvec.reshape(3, 1), K, xi, D
    )
    return p.reshape(-1, 2)


def cv_pose(xyz, uv, K, xi, D):
    """cam_from_world (rvec, tvec) with the omnidir calibration fixed, or None."""
    cv2 = _cv2()
    und = cv2.omnidir.undistortPoints(uv.reshape(1, -1, 2), K, D, np.array([[xi]]), np.eye(3))
    und = und.reshape(-1, 2).astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(xyz.astype(np.float64), und, np.eye(3), None)
    if not ok:
        return None
    x = np.concatenate([rvec.ravel(), tvec.ravel()]).astype(float)

    def resid(p):
        return (uv - _project(xyz, p[:3], p[3:], K, xi, D)).ravel()

    e = resid(x)
    cost, lam = float(e @ e), 1e-3
    for _ in range(100):
        A = np.empty((len(e), 6))  # d predicted / d x, central differences
        for j in range(6):
            d = np.zeros(6)
            d[j] = 1e-6
            A[:, j] = (resid(x - d) - resid(x + d)) / 2e-6
        H, g = A.T @ A, A.T @ e
        for _try in range(10):
            step = np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), g)
            en = resid(x + step)
            cn = float(en @ en)
            if np.isfinite(cn) and cn <= cost:
                converged = cost - cn <= 1e-12 * max(cost, 1e-300)
                x, e, cost, lam = x + step, en, cn, max(lam / 10, 1e-12)
                break
            lam *= 10
        else:
            break
        if converged:
            break
    return x[:3].reshape(3, 1), x[3:].reshape(3, 1)


def cv_fold(corners, xyz_of, frame, held, cams, sizes) -> dict:
    """stereoCalibrate without ``frame``, resect from cam0, transfer to cam1."""
    cv2 = _cv2()
    t0 = time.perf_counter()
    obj, img0, img1 = [], [], []
    for f in corners:
        if f == frame or len(corners[f]) < 2:
            continue
        _ids, xyz, uv0, uv1 = pair(corners, xyz_of, f, cams)
        obj.append(xyz.reshape(1, -1, 3).astype(np.float64))
        img0.append(uv0.reshape(1, -1, 2).astype(np.float64))
        img1.append(uv1.reshape(1, -1, 2).astype(np.float64))
    fit = cv_stereo(obj, img0, img1, sizes[0], sizes[1])
    seconds = time.perf_counter() - t0
    nan = {"resect": float("nan"), "transfer": float("nan"), "seconds": seconds}
    if fit is None:
        return nan
    _ids, xyz, uv0, uv1 = held
    pose = cv_pose(xyz, uv0, fit["K1"], fit["xi1"], fit["D1"])
    if pose is None:
        return nan
    rvec, tvec = pose
    resect_res = uv0 - _project(xyz, rvec, tvec, fit["K1"], fit["xi1"], fit["D1"])
    # cam1_from_world = (R, T) * cam0_from_world (OpenCV: x1 = R x0 + T)
    R0, _ = cv2.Rodrigues(rvec)
    R, _ = cv2.Rodrigues(fit["rvec"])
    R1 = R @ R0
    t1 = R @ tvec + fit["tvec"]
    pred = _project(xyz, cv2.Rodrigues(R1)[0], t1, fit["K2"], fit["xi2"], fit["D2"])
    return {
        "resect": rms(resect_res),
        "transfer": rms(uv1 - pred),
        "seconds": seconds,
        "n_used": fit["n_used"],
        "n_pairs": len(obj),
        "baseline_m": float(np.linalg.norm(fit["tvec"])),
    }


# --------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=str(DATA), help="the dataset@2 file")
    ap.add_argument("--frames", default=",".join(HELD_FRAMES), help="held-out frame ids")
    ap.add_argument("--loo", action="store_true", help="hold out every frame in turn")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-opencv", action="store_true")
    ap.add_argument("--json", help="write the per-frame figures here")
    args = ap.parse_args(argv)

    path = Path(args.data)
    if not path.is_file():
        print(
            f"bench_transfer: skipped: {path} is absent (the real catadioptric stereo pair; "
            "see ../shared/data/README.md)"
        )
        return 0
    doc = read_json(path)
    cams = [c["id"] for c in doc["cameras"]]
    sizes = [(int(c["width"]), int(c["height"])) for c in doc["cameras"]]
    xyz_of = {t["id"]: np.asarray(t["xyz"], float) for t in doc["targets"]}
    corners = frame_corners(doc)
    frames = list(corners) if args.loo else [f for f in args.frames.split(",") if f]
    missing = [f for f in frames if f not in corners or len(corners[f]) < 2]
    if missing:
        ap.error(f"frames not seen by both cameras: {missing}")

    use_cv = not args.no_opencv
    if use_cv:
        try:
            cv2 = _cv2()
            use_cv = hasattr(cv2, "omnidir")
        except ImportError:
            use_cv = False
        if not use_cv:
            log("cv2.omnidir is absent (opencv-contrib provides it): OpenCV column skipped")

    rows = []
    for f in frames:
        held = pair(corners, xyz_of, f, cams)
        log(f"frame {f}: ours (calibrate_rig on {len(corners) - 1} frames) ...")
        ours = ours_fold(doc, f, held, cams, args.seed)
        log(
            f"frame {f}: ours transfer {ours['transfer']:.4f} px "
            f"(resect {ours['resect']:.4f}, {ours['seconds']:.0f} s)"
        )
        cv = None
        if use_cv:
            cv = cv_fold(corners, xyz_of, f, held, cams, sizes)
            log(f"frame {f}: OpenCV transfer {cv['transfer']:.4f} px ({cv['seconds']:.0f} s)")
        rows.append({"frame": f, "n": len(held[0]), "ours": ours, "opencv": cv, "held": held})

    def pooled(key: str, field: str) -> float:
        sq, n = 0.0, 0
        for r in rows:
            if r[key] is None or not np.isfinite(r[key][field]):
                return float("nan")
            sq += r[key][field] ** 2 * r["n"]
            n += r["n"]
        return float(np.sqrt(sq / n)) if n else float("nan")

    mode = "leave-one-frame-out, every frame" if args.loo else "leave-one-frame-out"
    print()
    print(
        f"Stereo transfer, {path.name}: {mode} on {len(rows)} held-out frames; "
        f"rig pose resected from {cams[0]} only, {cams[1]}'s corners predicted"
    )
    print("RMS sqrt(mean(du^2+dv^2)) px; resect = the cam0 fit of the held-out frame")
    print()
    hdr = "| frame | corners | ours transfer | OpenCV transfer | ours resect | OpenCV resect |"
    print(hdr)
    print("|---|---|---|---|---|---|")

    def fmt(r, k, field):
        return "n/a" if r[k] is None else f"{r[k][field]:.4f}"

    for r in rows:
        print(
            f"| {r['frame']} | {r['n']} | {fmt(r, 'ours', 'transfer')} | "
            f"{fmt(r, 'opencv', 'transfer')} | {fmt(r, 'ours', 'resect')} | "
            f"{fmt(r, 'opencv', 'resect')} |"
        )
    n = sum(r["n"] for r in rows)
    cv_t = f"{pooled('opencv', 'transfer'):.4f}" if use_cv else "n/a"
    cv_r = f"{pooled('opencv', 'resect'):.4f}" if use_cv else "n/a"
    print(
        f"| **all** | {n} | **{pooled('ours', 'transfer'):.4f}** | **{cv_t}** | "
        f"{pooled('ours', 'resect'):.4f} | {cv_r} |"
    )
    print()
    t_ours = sum(r["ours"]["seconds"] for r in rows)
    line = f"calibration time: ours {t_ours:.0f} s"
    if use_cv:
        t_cv = sum(r["opencv"]["seconds"] for r in rows)
        used = [f"{r['opencv'].get('n_used')}/{r['opencv'].get('n_pairs')}" for r in rows]
        line += f", OpenCV {t_cv:.0f} s (pairs stereoCalibrate kept: {' '.join(used)})"
    print(line)
    base = [r["ours"].get("baseline_m") for r in rows]
    print("ours baseline per fold (m): " + ", ".join(f"{b:.4f}" for b in base if b))
    if use_cv:
        base = [r["opencv"].get("baseline_m") for r in rows]
        print("OpenCV baseline per fold (m): " + ", ".join(f"{b:.4f}" for b in base if b))
    print(
        f"(data README: OpenCV left->right {README_OPENCV_L2R} px on frames "
        f"{' '.join(HELD_FRAMES)})"
    )
    print("command: python benchmarks/bench_transfer.py " + " ".join(argv or sys.argv[1:]))
    if args.json:
        out = [{k: v for k, v in r.items() if k != "held"} for r in rows]
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
