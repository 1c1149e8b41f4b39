"""Hold-out accuracy on the real data of ``../shared/data``, side by side with OpenCV.

A calibration is tested on images it was not estimated from: each test image is
resected (:func:`gtsam_sphere.estimation.resect.resect`, pose only, calibration fixed,
targets at the calibration's board coordinates) and its reprojection error in raw
pixels is pooled as ``sqrt(mean(du^2 + dv^2))`` over all test corners
(OpenCV's RMS, the definition of ``../shared/data/README.md``).

a. ``ov_plane``: calibrate ``ov_plane_train``, resect every image of
   ``ov_plane_test``. The README's OpenCV figure (0.470 px) was measured on the
   corners under 85 deg only (``cv2.fisheye`` cannot use the others), so the
   table gives our RMS on that same subset (incidence from our resected pose)
   and on every corner, and re-runs OpenCV here on the same subsets
   (``cv2.fisheye.calibrate`` from a rough guess, test poses by
   ``cv2.fisheye.solvePnP`` then least squares on the pixel error).
b. ``opencv_fisheye_left``: ours and ``cv2.fisheye.calibrate`` (flags of the
   README: RECOMPUTE_EXTRINSIC | CHECK_COND | FIX_SKEW) on all 34 views, and
   leave-one-view-out: calibrate on the other views, resect the held-out view
   with the calibration fixed, pool its residuals.
c. ``fish_1`` / ``fish_2`` real images: chessboard detection (6x8 inner
   corners), then the same two measurements. Identical image files are
   dropped first (fish_2 holds one image twice, which would leak into its own
   hold-out). OpenCV's own initialisation diverges on these lenses; it is then
   started from a rough guess (f of our lens-unknown initialisation, centred
   principal point) and labelled so.

e. ``opencv_omnidir_stereo``: each camera of the real catadioptric rig alone, ours
   and ``cv2.omnidir.calibrate`` (Mei's unified model, flags 0 and the criteria of
   the data README; needs opencv-contrib, else the README's figures only), all views
   and leave-one-view-out over the README's 8 frames (00 05 11 16 22 27 33 38), each
   held-out view resected with the calibration fixed.

d. periphery recovery (``gtsam-sphere detect --recover``) on the fish images:
   corners it adds, and an occlusion check (a column of corners painted over so
   the full-board detection fails: how many visible corners the partial-board
   rescue recovers, how many it invents).

Every RMS is in raw pixels, computed here from the poses and
``camera.project`` (for the Brown models ``statistics.rms_px`` is measured
after the Brown correction and is not OpenCV's reprojection RMS).

Leave-one-out calibrations reuse the lens-unknown initialisation of the full
set (P3P poses, ``calibrate(..., init=...)``, the held-out image removed from
it) and skip the covariance; they are only starting values.

    python benchmarks/holdout.py [--model radial+knn [brown+knn ...]] [--quick]
        [--control-sigma exact auto 0.0005] [--max-views N]
        [--only ov_plane,opencv,omnidir,fish,recovery] [--json OUT.json]

``--control-sigma``: each model runs with the board's nominal coordinates taken as
exact (``exact``: ``gtsam-sphere calibrate --exact-targets``), with the defaults
(``auto``: the corners estimated with a sigma of 1e-3 of the board's size) and/or with
a given sigma in metres (``--control-sigma``); held-out images are then resected
against the calibration's estimated board.

Default: ``--model radial+knn``, every view; about 6-8 minutes per model on 2
cores. ``--quick`` holds out 6 views per set.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from gtsam_sphere.core.camera import Model
from gtsam_sphere.estimation.calibrate import (
    CalibrationOptions,
    Initialisation,
    calibrate,
    initialise,
)
from gtsam_sphere.estimation.resect import resect
from gtsam_sphere.io.dataset import load_dataset, parse_dataset

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
#: reference figures of ../shared/data/README.md and py-OCamCalib
OPENCV_OV_PLANE_TEST_RMS = 0.470
OPENCV_OV_PLANE_TRAIN_RMS = 0.473
OPENCV_LEFT_RMS = 0.2638
OCAMCALIB_FISH1_RMS = 0.241
FISH = {"fish_1": 0.0325, "fish_2": 0.117}  # square side (m), checkerboard_sizes.txt
FISH_BOARD = "chessboard:6x8:{square}"  # 7x9 squares, not the 5x7 of checkerboard_sizes.txt
MAX_INCIDENCE_OPENCV_DEG = 85.0
# opencv_omnidir_stereo: the data README's held-out frames and mono reference figures
OMNI_HELD_FRAMES = ("00", "05", "11", "16", "22", "27", "33", "38")
OMNI_MONO_RMS = {"cam0": 0.4390, "cam1": 0.4066}
OMNI_MONO_VIEWS = {"cam0": "37 of 39", "cam1": "36 of 39"}

_T0 = time.perf_counter()


def log(msg: str) -> None:
    """Progress line on standard error with the elapsed time."""
    print(f"[{time.perf_counter() - _T0:7.1f} s] {msg}", file=sys.stderr, flush=True)


def rms(residuals_px: np.ndarray) -> float:
    """``sqrt(mean(du^2 + dv^2))`` of residuals (N, 2) px over the finite rows."""
    r = np.asarray(residuals_px, float).reshape(-1, 2)
    r = r[np.all(np.isfinite(r), axis=1)]
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1)))) if len(r) else float("nan")


def views(dataset) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per image: pixels (N, 2) and target coordinates (N, 3), world frame."""
    out = []
    for i in range(len(dataset.image_ids)):
        m = dataset.obs_image == i
        out.append((dataset.uv_px[m], dataset.target_xyz[dataset.obs_target[m]]))
    return out


def raw_residuals(cal, dataset) -> np.ndarray:
    """Training residuals (N, 2) in raw pixels, ``uv - camera.project(R X + t)``.

    Computed here rather than read from ``statistics.rms_px``: for the Brown models
    that statistic is measured after the Brown correction (the ideal image), not in
    raw pixels, and differs from OpenCV's reprojection RMS.
    """
    index = {k: i for i, k in enumerate(cal.target_ids)}
    image = {k: i for i, k in enumerate(cal.image_ids)}
    rows = np.array([image[dataset.image_ids[i]] for i in dataset.obs_image])
    xyz = np.array([cal.target_xyz[index[dataset.target_ids[j]]] for j in dataset.obs_target])
    p = np.einsum("nij,nj->ni", cal.cam_from_world_R[rows], xyz) + cal.cam_from_world_t[rows]
    return dataset.uv_px - cal.camera.project(p)


def held_out_indices(n: int, max_views: int | None) -> list[int]:
    """Indices of the views to hold out: all, or ``max_views`` evenly spaced."""
    if max_views is None or max_views >= n:
        return list(range(n))
    return sorted(set(np.linspace(0, n - 1, max_views).round().astype(int).tolist()))


def options(model: str, seed: int, control_sigma="auto") -> CalibrationOptions:
    """Calibration options of the benchmark (no covariance: not needed here)."""
    return CalibrationOptions(
        model=Model(model), seed=seed, covariance=False, control_sigma=control_sigma
    )


def variant_label(model: str, control_sigma) -> str:
    """Row label of one of our variants."""
    if control_sigma is None:
        return f"ours {model}, board exact (--exact-targets)"
    if control_sigma == "auto":
        return f"ours {model}, defaults (board estimated, sigma 1e-3 of its size)"
    return f"ours {model}, board estimated (control sigma {control_sigma * 1000:g} mm)"


def adjusted_xyz(cal, dataset, rows: np.ndarray) -> np.ndarray:
    """Target coordinates (N, 3) of ``dataset``'s observations ``rows`` in ``cal``.

    The calibration's adjusted coordinates: the nominal ones for exact targets, the
    estimated board shape with ``control_sigma``. Targets ``cal`` never saw keep the
    dataset's coordinates.
    """
    index = {k: i for i, k in enumerate(cal.target_ids)}
    out = dataset.target_xyz[dataset.obs_target[rows]].copy()
    for n, j in enumerate(dataset.obs_target[rows]):
        i = index.get(dataset.target_ids[j])
        if i is not None:
            out[n] = cal.target_xyz[i]
    return out


def subset_init(init: Initialisation, keep: np.ndarray) -> Initialisation:
    """The initialisation of ``init.dataset`` restricted to the images where ``keep``."""
    return Initialisation(
        init.dataset.subset_images(keep, {i: "held out" for i in np.flatnonzero(~keep)}),
        init.cam_from_world_R[keep],
        init.cam_from_world_t[keep],
        int(keep.sum()),
        init.mapping,
        init.f_px,
        None if init.inlier_mask is None else init.inlier_mask[keep[init.dataset.obs_image]],
        init.principal_point_px,
    )


# --------------------------------------------------------------------------------------
# ours
# --------------------------------------------------------------------------------------


def ours_leave_one_out(
    init: Initialisation, model: str, held: list[int], seed: int, control_sigma=None
) -> dict:
    """Leave-one-view-out with one of our models.

    Returns ``{"residuals": list of (N_k, 2) px per held-out view, "ids": [...],
    "failed": [...]}``.
    """
    ds = init.dataset
    out = {"residuals": [], "ids": [], "failed": []}
    for n, k in enumerate(held):
        keep = np.ones(len(ds.image_ids), bool)
        keep[k] = False
        t0 = time.perf_counter()
        cal = calibrate(
            ds.subset_images(keep),
            options(model, seed, control_sigma),
            init=subset_init(init, keep),
        )
        rows = np.flatnonzero(ds.obs_image == k)
        uv, xyz = ds.uv_px[rows], adjusted_xyz(cal, ds, rows)
        res = resect(cal.camera, uv, xyz, np.random.default_rng(seed))
        if not res.success:
            out["failed"].append((ds.image_ids[k], res.status))
        out["residuals"].append(res.residuals_px)
        out["ids"].append(ds.image_ids[k])
        train = rms(raw_residuals(cal, ds.subset_images(keep)))
        log(
            f"  {variant_label(model, control_sigma)} without {ds.image_ids[k]} "
            f"({n + 1}/{len(held)}): train RMS "
            f"{train:.3f} px, held-out RMS {rms(res.residuals_px):.3f} px "
            f"({time.perf_counter() - t0:.1f} s)"
        )
    return out


# --------------------------------------------------------------------------------------
# OpenCV (Kannala-Brandt fisheye)
# --------------------------------------------------------------------------------------

_CV_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, np.finfo(float).eps)


def _cv_flag(name: str) -> int:
    """A ``cv2.fisheye`` calibration flag (OpenCV 4: ``cv2.fisheye.X``; 5: ``cv2.X``)."""
    return int(getattr(cv2.fisheye, name, None) or getattr(cv2, name))


_CV_FLAGS = (
    _cv_flag("CALIB_RECOMPUTE_EXTRINSIC")
    | _cv_flag("CALIB_CHECK_COND")
    | _cv_flag("CALIB_FIX_SKEW")
)


def cv_views(per_view, select=None) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """OpenCV's object (1,N,3) and image (1,N,2) float64 arrays, optionally row-selected.

    (OpenCV 5's ``cv2.fisheye.calibrate`` refuses the (N,1,3) layout.)
    """
    obj, img = [], []
    for k, (uv, xyz) in enumerate(per_view):
        m = np.ones(len(uv), bool) if select is None else select[k]
        obj.append(np.ascontiguousarray(xyz[m].reshape(1, -1, 3), dtype=np.float64))
        img.append(np.ascontiguousarray(uv[m].reshape(1, -1, 2), dtype=np.float64))
    return obj, img


def cv_calibrate(obj, img, size, flags=_CV_FLAGS, K0=None):
    """``cv2.fisheye.calibrate``; retried without CHECK_COND if that flag rejects a view.

    Returns ``(K (3,3), D (4,), rvecs, tvecs)`` or ``None`` when OpenCV fails.
    """
    for f in (flags, flags & ~_cv_flag("CALIB_CHECK_COND")):
        K = np.eye(3) if K0 is None else K0.copy()
        D = np.zeros((4, 1))
        try:
            _, K, D, rvecs, tvecs = cv2.fisheye.calibrate(
                obj, img, size, K, D, flags=f, criteria=_CV_CRITERIA
            )
            return K, D.ravel(), rvecs, tvecs
        except cv2.error:
            continue
    return None


def cv_residuals(obj, img, K, D, rvec, tvec) -> np.ndarray:
    """Raw-pixel residuals (N, 2), measured minus ``cv2.fisheye.projectPoints``."""
    proj, _ = cv2.fisheye.projectPoints(obj, rvec, tvec, K, D)
    return img.reshape(-1, 2) - proj.reshape(-1, 2)


def cv_resect(obj, img, K, D, rvec0=None, tvec0=None, residuals=None):
    """Held-out pose with OpenCV's calibration fixed: ``cv2.fisheye.solvePnP`` (or the
    given start), then Levenberg-Marquardt on the raw-pixel reprojection error (least
    squares, OpenCV's own calibration criterion). ``residuals(obj, img, rvec, tvec)``
    replaces the fisheye model's. Returns the residuals (N, 2) px (NaN on failure)."""
    if residuals is None:

        def residuals(o, i, rv, tv):
            return cv_residuals(o, i, K, D, rv, tv)

    if rvec0 is None:
        try:
            ok, rvec, tvec = cv2.fisheye.solvePnP(obj, img, K, D)
        except cv2.error:
            ok = False
        if not ok:
            return np.full((obj.shape[1], 2), np.nan)
    else:
        rvec, tvec = rvec0, tvec0
    x = np.concatenate([np.ravel(rvec), np.ravel(tvec)]).astype(float)
    lam = 1e-3

    def resid(p):
        return residuals(obj, img, p[:3].reshape(3, 1), p[3:].reshape(3, 1)).ravel()

    e = resid(x)
    cost = float(e @ e)
    for _ in range(50):
        # central differences (OpenCV's Jacobian column layout differs between versions)
        A = np.empty((len(e), 6))
        for j in range(6):
            d = np.zeros(6)
            d[j] = 1e-6
            A[:, j] = (resid(x - d) - resid(x + d)) / 2e-6  # d predicted / d x
        H, g = A.T @ A, A.T @ e  # e = measured - predicted: d e / d x = -A
        done = False
        for _try in range(8):
            step = np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), g)
            en = resid(x + step)
            cn = float(en @ en)
            if np.isfinite(cn) and cn <= cost:
                done = (cost - cn) <= 1e-12 * max(cost, 1e-300)
                x, e, cost, lam = x + step, en, cn, max(lam / 10, 1e-12)
                break
            lam *= 10
        else:
            break
        if done:
            break
    return e.reshape(-1, 2)


def cv_leave_one_out(per_view, held, size, flags=_CV_FLAGS, K0=None, select=None) -> dict:
    """Leave-one-view-out with ``cv2.fisheye`` (same output as :func:`ours_leave_one_out`)."""
    obj, img = cv_views(per_view, select)
    out = {"residuals": [], "ids": [], "failed": []}
    for k in held:
        others = [j for j in range(len(obj)) if j != k]
        fit = cv_calibrate([obj[j] for j in others], [img[j] for j in others], size, flags, K0)
        if fit is None:
            out["failed"].append((k, "cv2.fisheye.calibrate failed"))
            out["residuals"].append(np.full((obj[k].shape[1], 2), np.nan))
        else:
            out["residuals"].append(cv_resect(obj[k], img[k], fit[0], fit[1]))
        out["ids"].append(k)
    return out


# --------------------------------------------------------------------------------------
# OpenCV omnidir (Mei's unified model; opencv-contrib only)
# --------------------------------------------------------------------------------------

_OMNI_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-8)


def omni_calibrate(obj, img, size):
    """``cv2.omnidir.calibrate`` with the data README's settings (flags 0, 200 / 1e-8).

    Returns ``(K, xi, D, {view index: (rvec, tvec)})`` for the views OpenCV kept, or
    None when it fails.
    """
    try:
        _, K, xi, D, rvecs, tvecs, idx = cv2.omnidir.calibrate(
            obj, img, size, np.eye(3), np.zeros((1, 1)), np.zeros((1, 4)), 0, _OMNI_CRITERIA
        )
    except cv2.error:
        return None
    used = np.ravel(idx).astype(int).tolist()
    return K, float(np.ravel(xi)[0]), D, dict(zip(used, zip(rvecs, tvecs)))


def omni_residuals(obj, img, K, xi, D, rvec, tvec) -> np.ndarray:
    """Raw-pixel residuals (N, 2), measured minus ``cv2.omnidir.projectPoints``."""
    proj, _ = cv2.omnidir.projectPoints(obj, rvec, tvec, K, xi, D)
    return img.reshape(-1, 2) - proj.reshape(-1, 2)


def omni_resect(obj, img, K, xi, D):
    """Held-out pose with the omnidir calibration fixed: PnP on the undistorted
    (perspective) points, then LM on the raw-pixel error (:func:`cv_resect`)."""
    und = cv2.omnidir.undistortPoints(img, K, D, np.array([[xi]]), np.eye(3))
    ok, rvec, tvec = cv2.solvePnP(obj, und, np.eye(3), None)
    if not ok:
        return np.full((obj.shape[1], 2), np.nan)

    def residuals(o, i, rv, tv):
        return omni_residuals(o, i, K, xi, D, rv, tv)

    return cv_resect(obj, img, K, D, rvec, tvec, residuals)


def omni_rows(per_view, held, size) -> list[dict]:
    """OpenCV omnidir: all-view RMS (the views it keeps) and leave-one-view-out rows."""
    if not hasattr(cv2, "omnidir"):
        log("cv2.omnidir is absent (opencv-contrib-python-headless provides it): skipped")
        return [{"method": "OpenCV omnidir", "failed": ["cv2.omnidir absent"]}]
    obj, img = cv_views(per_view)
    fit = omni_calibrate(obj, img, size)
    if fit is None:
        return [{"method": "OpenCV omnidir", "failed": ["calibrate failed"]}]
    K, xi, D, poses = fit
    all_r = np.concatenate(
        [omni_residuals(obj[k], img[k], K, xi, D, *poses[k]) for k in sorted(poses)]
    )
    loo = {"residuals": [], "ids": [], "failed": []}
    for k in held:
        others = [j for j in range(len(obj)) if j != k]
        f = omni_calibrate([obj[j] for j in others], [img[j] for j in others], size)
        if f is None:
            loo["failed"].append((k, "cv2.omnidir.calibrate failed"))
            loo["residuals"].append(np.full((obj[k].shape[1], 2), np.nan))
        else:
            loo["residuals"].append(omni_resect(obj[k], img[k], f[0], f[1], f[2]))
        loo["ids"].append(k)
    label = f"OpenCV omnidir (Mei; all-view RMS over the {len(poses)} views it keeps)"
    return [_loo_row(label, rms(all_r), loo)]


# --------------------------------------------------------------------------------------
# the sections
# --------------------------------------------------------------------------------------


def section_ov_plane(variants, seed) -> dict:
    """Train on ov_plane_train, resect ov_plane_test; ours and OpenCV on the same corners."""
    train = load_dataset(DATA / "ov_plane_train.dataset.json")
    test = load_dataset(DATA / "ov_plane_test.dataset.json")
    log("ov_plane: initialising the training set")
    init = initialise(train, seed)
    test_rows = [np.flatnonzero(test.obs_image == k) for k in range(len(test.image_ids))]
    rows, first = [], None
    for model, control_sigma in variants:
        t0 = time.perf_counter()
        cal = calibrate(init.dataset, options(model, seed, control_sigma), init=init)
        res = [
            resect(
                cal.camera, test.uv_px[m], adjusted_xyz(cal, test, m), np.random.default_rng(seed)
            )
            for m in test_rows
        ]
        r = np.concatenate([x.residuals_px for x in res])
        inc = np.concatenate([x.incidence_deg for x in res])
        below = inc < MAX_INCIDENCE_OPENCV_DEG
        train_inc = np.asarray(cal.extra["observations"]["incidence_deg"])
        train_r = raw_residuals(cal, init.dataset)
        row = {
            "method": variant_label(model, control_sigma),
            "train_rms_all": rms(train_r),
            "train_rms_85": rms(train_r[train_inc < MAX_INCIDENCE_OPENCV_DEG]),
            "test_rms_85": rms(r[below]),
            "test_rms_all": rms(r),
            "n_test_85": int(below.sum()),
            "n_test": len(r),
            "n_test_beyond_90": int(np.sum(inc > 90)),
            "per_image_rms": [x.rms_px_all for x in res],
            "failed": [x.status for x in res if not x.success],
        }
        rows.append(row)
        log(
            f"ov_plane {row['method']}: train {row['train_rms_all']:.3f} px, test "
            f"{row['test_rms_all']:.3f} px (all), {row['test_rms_85']:.3f} px (<85 deg) "
            f"({time.perf_counter() - t0:.1f} s)"
        )
        if first is None:
            first = (cal, train_inc, [x.incidence_deg for x in res])
    test_views = views(test)
    # OpenCV on the corners under 85 deg (selected with our first model's poses)
    cal, train_inc, test_inc = first
    train_views = views(init.dataset)
    obs_image = init.dataset.obs_image
    sel = [train_inc[obs_image == k] < MAX_INCIDENCE_OPENCV_DEG for k in range(len(train_views))]
    obj, img = cv_views(train_views, sel)
    size = (train.width, train.height)
    f0 = init.f_px if init.mapping == "equidistant" else cal.camera.c
    K0 = np.array([[f0, 0, (size[0] - 1) / 2], [0, f0, (size[1] - 1) / 2], [0, 0, 1.0]])
    flags = _CV_FLAGS | _cv_flag("CALIB_USE_INTRINSIC_GUESS")
    fit = cv_calibrate(obj, img, size, flags, K0)
    if fit is None:
        rows.append({"method": "OpenCV fisheye (here)", "failed": ["calibrate failed"]})
    else:
        K, D, rvecs, tvecs = fit
        tr = np.concatenate(
            [cv_residuals(o, i, K, D, rv, tv) for o, i, rv, tv in zip(obj, img, rvecs, tvecs)]
        )
        tobj, timg = cv_views(test_views, [inc < MAX_INCIDENCE_OPENCV_DEG for inc in test_inc])
        te = [cv_resect(o, i, K, D) for o, i in zip(tobj, timg)]
        rows.append(
            {
                "method": "OpenCV fisheye (here)",
                "train_rms_85": rms(tr),
                "test_rms_85": rms(np.concatenate(te)),
                "n_test_85": int(sum(o.shape[1] for o in tobj)),
                "per_image_rms": [rms(x) for x in te],
                "K": K.tolist(),
                "D": D.tolist(),
            }
        )
    rows.append(
        {
            "method": "OpenCV fisheye (data README)",
            "train_rms_85": OPENCV_OV_PLANE_TRAIN_RMS,
            "test_rms_85": OPENCV_OV_PLANE_TEST_RMS,
        }
    )
    return {"rows": rows}


def section_leave_one_out(
    name, dataset, variants, max_views, seed, opencv="fisheye", held_ids=None
) -> dict:
    """All-view RMS and leave-one-view-out held-out RMS: ours and OpenCV's
    ``cv2.fisheye`` (or ``cv2.omnidir`` with ``opencv="omnidir"``). ``held_ids``: the
    image ids to hold out (default: ``max_views`` evenly spread, or all)."""
    log(f"{name}: initialising {len(dataset.image_ids)} images")
    init = initialise(dataset, seed)
    ds = init.dataset
    per_view = views(ds)
    held = held_out_indices(len(ds.image_ids), max_views)
    if held_ids is not None:
        held = [ds.image_ids.index(i) for i in held_ids if i in ds.image_ids]
    size = (ds.width, ds.height)
    rows = []
    t0 = time.perf_counter()
    if opencv == "omnidir":
        rows += omni_rows(per_view, held, size)
        log(f"{name} OpenCV omnidir: done ({time.perf_counter() - t0:.1f} s)")
        return _our_loo_rows(name, init, variants, held, seed, rows)
    obj, img = cv_views(per_view)
    # OpenCV's own initialisation first; where it fails or diverges (fish_1, fish_2), again
    # from a rough guess: f from our lens-unknown initialisation, principal point centred
    K0 = np.array([[init.f_px, 0, (size[0] - 1) / 2], [0, init.f_px, (size[1] - 1) / 2], [0, 0, 1]])
    for label, flags, guess in (
        ("OpenCV fisheye (KB)", _CV_FLAGS, None),
        (
            "OpenCV fisheye (KB, from a guess)",
            _CV_FLAGS | _cv_flag("CALIB_USE_INTRINSIC_GUESS"),
            K0,
        ),
    ):
        fit = cv_calibrate(obj, img, size, flags, guess)
        if fit is None:
            log(f"{name} {label}: cv2.fisheye.calibrate failed")
            continue
        K, D, rvecs, tvecs = fit
        all_r = np.concatenate(
            [cv_residuals(o, i, K, D, rv, tv) for o, i, rv, tv in zip(obj, img, rvecs, tvecs)]
        )
        if rms(all_r) > 5.0:
            log(f"{name} {label}: diverged (RMS {rms(all_r):.1f} px)")
            continue
        loo = cv_leave_one_out(per_view, held, size, flags, guess)
        rows.append(_loo_row(label, rms(all_r), loo))
        log(f"{name} {label}: done ({time.perf_counter() - t0:.1f} s)")
        break
    else:
        rows.append({"method": "OpenCV fisheye (KB)", "failed": ["calibrate failed/diverged"]})
    return _our_loo_rows(name, init, variants, held, seed, rows)


def _our_loo_rows(name, init, variants, held, seed, rows) -> dict:
    """Our variants' all-view and leave-one-view-out rows appended to ``rows``."""
    ds = init.dataset
    for model, control_sigma in variants:
        t0 = time.perf_counter()
        name_v = variant_label(model, control_sigma)
        cal = calibrate(ds, options(model, seed, control_sigma), init=init)
        all_rms = rms(raw_residuals(cal, ds))
        log(f"{name} {name_v}: all views RMS {all_rms:.3f} px; leave-one-out")
        loo = ours_leave_one_out(init, model, held, seed, control_sigma)
        rows.append(_loo_row(name_v, all_rms, loo))
        log(f"{name} {name_v}: done ({time.perf_counter() - t0:.1f} s)")
    return {
        "rows": rows,
        "n_views": len(ds.image_ids),
        "n_held": len(held),
        "n_obs": ds.n_observations,
    }


def _loo_row(method, all_rms, loo) -> dict:
    per = [rms(r) for r in loo["residuals"]]
    return {
        "method": method,
        "all_rms": all_rms,
        "loo_rms": rms(np.concatenate(loo["residuals"])),
        "loo_median_view": float(np.nanmedian(per)),
        "loo_worst_view": float(np.nanmax(per)),
        "per_view_rms": per,
        "failed": [str(f) for f in loo["failed"]],
    }


def fish_dataset(folder: str, square: float):
    """Detect the chessboard in one folder of real images (identical files dropped)."""
    from gtsam_sphere.apps.detect import BoardSpec, detect_images

    paths, seen, dropped = [], {}, []
    for p in sorted((DATA / "images" / folder).glob("*.jpg")):
        digest = hashlib.sha256(p.read_bytes()).hexdigest()
        if digest in seen:
            dropped.append(f"{p.name} (= {seen[digest]})")
            continue
        seen[digest] = p.name
        paths.append(str(p))
    if dropped:
        log(f"{folder}: identical image files dropped: {', '.join(dropped)}")
    board = BoardSpec.parse(FISH_BOARD.format(square=square))
    doc, report = detect_images(paths, board, progress=False)
    log(f"{folder}: {len(report.used)} of {len(paths)} images, {report.n_observations} corners")
    return parse_dataset(doc, folder), dropped


def section_recovery(folder: str, square: float, seed: int) -> dict:
    """Periphery recovery on real images: the real counts, and an occlusion check.

    1. ``recover_dataset`` on the detections (what ``gtsam-sphere detect --recover``
       adds). 2. Occlusion check: in each image the last column of corners is painted
       over (grey discs) so the full-board detection fails; the partial board must be
       rescued with the calibration (``rescue_partial_chessboard``), at the positions
       the full detection gave, with no corner invented.
    """
    from gtsam_sphere.apps.detect import (
        BoardSpec,
        _image_ids,
        detect_image,
        recover_dataset,
        rescue_partial_chessboard,
    )

    board = BoardSpec.parse(FISH_BOARD.format(square=square))
    paths = [str(p) for p in sorted((DATA / "images" / folder).glob("*.jpg"))]
    from gtsam_sphere.apps.detect import detect_images

    doc, _ = detect_images(paths, board, progress=False)
    _, rep = recover_dataset(doc, paths, board, model="radial", seed=seed)
    cal = calibrate(parse_dataset(doc, folder), options("radial", seed))
    path_of = dict(zip(_image_ids(paths), paths))
    n_images = n_visible = n_found = n_wrong = n_still = 0
    for im in doc["images"]:
        gray = cv2.imread(path_of[im["id"]], cv2.IMREAD_GRAYSCALE)
        det = {o["target"]: np.array(o["uv"]) for o in im["observations"]}
        grid = np.array([det[f"C{i:03d}"] for i in range(board.rows * board.cols)])
        grid = grid.reshape(board.rows, board.cols, 2)
        spacing = float(np.min(np.linalg.norm(np.diff(grid, axis=0), axis=2)))
        masked = gray.copy()
        for q in grid[:, -1]:
            centre = (int(round(q[0])), int(round(q[1])))
            cv2.circle(masked, centre, int(max(3, 0.45 * spacing)), int(np.median(gray)), -1)
        if detect_image(masked, board):
            n_still += 1
            continue
        visible = grid[:, :-1].reshape(-1, 2)
        found = rescue_partial_chessboard(masked, board, cal.camera)
        d = [float(np.min(np.linalg.norm(visible - q, axis=1))) for q in found.values()]
        n_images += 1
        n_visible += len(visible)
        n_found += sum(x < 0.5 for x in d)
        n_wrong += sum(x >= 0.5 for x in d)
    log(f"{folder}: recovery {rep.total} added; occlusion check {n_found}/{n_visible} rescued")
    return {
        "added": rep.total,
        "per_image": rep.added,
        "rms_before": rep.rounds[0]["rms_px"],
        "occluded_images": n_images,
        "occluded_still_detected": n_still,
        "occluded_visible": n_visible,
        "occluded_rescued": n_found,
        "occluded_wrong": n_wrong,
    }


# --------------------------------------------------------------------------------------
# printing
# --------------------------------------------------------------------------------------


def fmt(v, digits=3) -> str:
    """A number for a table cell ('-' when absent)."""
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "-"
    return f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def print_ov_plane(sec) -> None:
    print("\n### a. ov_plane: calibrate on train (18 images), resect test (7 images)\n")
    print(
        "| method | train RMS all (px) | train RMS <85 deg (px) | test RMS <85 deg (px) "
        "| test RMS all corners (px) | test corners (<85 / all / >90 deg) |"
    )
    print("|---|---|---|---|---|---|")
    for r in sec["rows"]:
        n = (
            f"{r.get('n_test_85', '-')} / {r.get('n_test', '-')} / {r.get('n_test_beyond_90', '-')}"
            if "n_test" in r or "n_test_85" in r
            else "-"
        )
        print(
            f"| {r['method']} | {fmt(r.get('train_rms_all'))} | {fmt(r.get('train_rms_85'))} "
            f"| {fmt(r.get('test_rms_85'))} | {fmt(r.get('test_rms_all'))} | {n} |"
        )
    for r in sec["rows"]:
        if r.get("failed"):
            print(f"  {r['method']}: failed: {r['failed']}")


def print_loo(title, sec, reference=None) -> None:
    print(
        f"\n### {title}: {sec['n_views']} views, {sec['n_obs']} corners; "
        f"leave-one-view-out over {sec['n_held']} views\n"
    )
    print(
        "| method | RMS all views (px) | held-out RMS (px) | median view (px) | worst view (px) |"
    )
    print("|---|---|---|---|---|")
    for r in sec["rows"]:
        print(
            f"| {r['method']} | {fmt(r.get('all_rms'))} | {fmt(r.get('loo_rms'))} "
            f"| {fmt(r.get('loo_median_view'))} | {fmt(r.get('loo_worst_view'))} |"
        )
    if reference:
        print(f"| {reference[0]} | {fmt(reference[1])} | - | - | - |")
    for r in sec["rows"]:
        if r.get("failed"):
            print(f"  {r['method']}: failed: {r['failed']}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--model",
        nargs="+",
        default=["radial+knn"],
        help="one or more models (space or comma separated), e.g. radial+knn brown+knn radial",
    )
    parser.add_argument(
        "--control-sigma",
        nargs="+",
        default=["exact", "auto"],
        help="board variants: 'exact' (or 'none': the board's nominal coordinates are "
        "exact, --exact-targets), 'auto' (the default of calibrate) and/or sigmas in metres "
        "with which the board corners are estimated (default: exact auto)",
    )
    parser.add_argument("--max-views", type=int, default=None, help="views held out per set")
    parser.add_argument("--quick", action="store_true", help="hold out 6 views per set")
    parser.add_argument(
        "--only",
        default="ov_plane,opencv,omnidir,fish,recovery",
        help="sections: ov_plane,opencv,omnidir,fish,recovery",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", default=None, help="also write the numbers to this file")
    args = parser.parse_args(argv)
    models = [m for text in args.model for m in text.split(",") if m]
    for m in models:
        Model(m)  # ValueError names a bad model
    sigmas = [
        None if t.lower() in ("none", "exact") else "auto" if t.lower() == "auto" else float(t)
        for text in args.control_sigma
        for t in text.split(",")
        if t
    ]
    variants = [(m, cs) for m in models for cs in sigmas]
    max_views = args.max_views if args.max_views is not None else (6 if args.quick else None)
    sections = set(args.only.split(","))
    if not DATA.exists():
        print(f"real data not available: {DATA} is absent (see ../shared/data/README.md)")
        return 0
    print(
        f"hold-out benchmark, models: {', '.join(models)}; control sigma (m): "
        f"{', '.join(str(x) for x in sigmas)}; seed {args.seed}"
    )
    results = {}
    if "ov_plane" in sections:
        results["ov_plane"] = section_ov_plane(variants, args.seed)
        print_ov_plane(results["ov_plane"])
    if "opencv" in sections:
        ds = load_dataset(DATA / "opencv_fisheye_left.dataset.json")
        sec = section_leave_one_out("opencv_fisheye_left", ds, variants, max_views, args.seed)
        results["opencv_fisheye_left"] = sec
        print_loo(
            "b. opencv_fisheye_left",
            sec,
            ("OpenCV fisheye (data README)", OPENCV_LEFT_RMS),
        )
    if "omnidir" in sections:
        from gtsam_sphere.io.dataset import load_rig_dataset, split_rig

        rig = split_rig(load_rig_dataset(DATA / "opencv_omnidir_stereo.dataset.json"))
        for cam, ds in rig.items():
            held_ids = [i for i in ds.image_ids if i.split("_")[-1] in OMNI_HELD_FRAMES]
            sec = section_leave_one_out(
                f"omnidir {cam}", ds, variants, None, args.seed, "omnidir", held_ids
            )
            results[f"omnidir_{cam}"] = sec
            print_loo(
                f"e. opencv_omnidir_stereo {cam} (one camera of the rig, alone)",
                sec,
                (f"OpenCV omnidir (data README, {OMNI_MONO_VIEWS[cam]} views)", OMNI_MONO_RMS[cam]),
            )
    if "fish" in sections:
        for folder, square in FISH.items():
            if not (DATA / "images" / folder).exists():
                print(f"\n{folder}: images absent, skipped")
                continue
            ds, dropped = fish_dataset(folder, square)
            sec = section_leave_one_out(folder, ds, variants, max_views, args.seed)
            sec["dropped_duplicates"] = dropped
            results[folder] = sec
            ref = ("py-OCamCalib (12 of 15 images)", OCAMCALIB_FISH1_RMS)
            print_loo(f"c. {folder}", sec, ref if folder == "fish_1" else None)
            if dropped:
                print(f"  identical files dropped: {', '.join(dropped)}")
    if "recovery" in sections:
        print("\n### d. periphery recovery on the real images (gtsam-sphere detect --recover)\n")
        print(
            "| set | corners added | occlusion check: images / visible corners / rescued "
            "/ wrong | full board still found |"
        )
        print("|---|---|---|---|")
        for folder, square in FISH.items():
            if not (DATA / "images" / folder).exists():
                continue
            r = section_recovery(folder, square, args.seed)
            results[f"recovery_{folder}"] = r
            print(
                f"| {folder} | {r['added']} | {r['occluded_images']} / {r['occluded_visible']} "
                f"/ {r['occluded_rescued']} / {r['occluded_wrong']} "
                f"| {r['occluded_still_detected']} |"
            )
    log("finished")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
