"""Benchmark: the calibrated camera in a loop, ``project`` / ``unproject`` throughput.

Not a test: prints a table. A real calibration (default: ``opencv_fisheye_left``
calibrated with the default model, ``radial+knn``) is loaded and its camera
timed on N points (rays in the valid field at random depths, and their pixels):

- ``project`` / ``unproject`` with the exact kNN correction (``exact=True``, the
  behaviour before the correction table; timed on fewer points, it is slow);
- ``project`` / ``unproject`` with the tabulated correction (the default; the
  table is built before timing, its build time is its own row);
- ``cv2.fisheye.projectPoints`` / ``cv2.fisheye.undistortPoints`` on the same
  points, with a Kannala-Brandt lens fitted to the camera's radial mapping
  (``fx = fy``, ``k1..k4`` by linear least squares on ``r(alpha)``; its fit
  error is printed: it is there for the speed, not as an export);
- ``radial`` alone (the camera without its correction), for scale.

Throughput is points per second of CPU time of this process (``time.process_time``,
less sensitive than wall clock to other processes on a shared machine), the best
of ``--repeats``. Then the table's agreement with the exact kNN over the observed
region (random pixels within 8 px of the training pixels; RMS and max, px), and
``gtsam-sphere undistort`` of a ~1 MP image (``remap_tables`` + ``apply_remap``)
with the exact and the tabulated correction.

When the calibration file holds no kNN correction (on ``opencv_fisheye_left`` the
grey-box loop may keep round 0, whose RMS the correction did not lower), one is
fitted the way the loop's first round does: :class:`KNNCorrection` (k and weights
by cross-validation) on the file's observations and their residuals.

Usage::

    python benchmarks/bench_camera.py                  # calibrates opencv_fisheye_left first
    python benchmarks/bench_camera.py CALIB.json       # an existing calibration
    python benchmarks/bench_camera.py --quick          # fewer points, one repeat
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from gtsam_sphere.apps.undistort import apply_remap, remap_tables
from gtsam_sphere.core.camera import radial_g
from gtsam_sphere.core.tabulated import check_pixels
from gtsam_sphere.estimation.correct import KNNCorrection
from gtsam_sphere.io.calibration import load_calibration

DATA = Path("/work/shared/data/opencv_fisheye_left.dataset.json")


def best_time(fn, repeats: int) -> float:
    """Least CPU seconds of ``repeats`` calls of ``fn``."""
    out = math.inf
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        out = min(out, time.process_time() - t0)
    return out


def calibration(path: str | None):
    if path is not None:
        return load_calibration(path), path
    out = Path(tempfile.mkdtemp()) / "calib.json"
    cmd = [sys.executable, "-m", "gtsam_sphere", "calibrate", str(DATA), "-o", str(out)]
    subprocess.run(cmd, check=True, capture_output=True)
    return load_calibration(out), f"{DATA.name} (calibrated now)"


def ensure_knn(calib) -> str:
    """Give the camera a kNN correction if the file has none; say where it came from."""
    cam = calib.camera
    if cam.correction is not None:
        return "the calibration's own kNN"
    obs = calib.extra["observations"]
    uv = np.asarray(obs["uv_px"], float)
    res = np.asarray(obs["residual_px"], float)
    cam.correction = KNNCorrection(degree=0).fit(uv, res)
    return "fitted here on the file's residuals (the file kept none)"


def kb_fit(cam, alpha_max: float):
    """``K, D`` of a Kannala-Brandt lens following the camera's radial mapping."""
    alpha = np.linspace(1e-3, alpha_max, 400)
    coeffs = cam._radial_coeffs()
    r = cam.c * radial_g(alpha, coeffs, warp=cam._radial_warp())
    A = np.column_stack([alpha ** (2 * i + 1) for i in range(5)])
    sol, *_ = np.linalg.lstsq(A, r, rcond=None)
    f = sol[0]
    K = np.array([[f, 0, cam.xp], [0, f, cam.yp], [0, 0, 1.0]])
    D = (sol[1:] / f).reshape(4, 1)
    return K, D, float(np.max(np.abs(A @ sol - r)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("calibration", nargs="?")
    parser.add_argument("--n", type=int, default=1_000_000, help="points (table, cv2)")
    parser.add_argument("--n-exact", type=int, default=20_000, help="points (exact kNN)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    if args.quick:
        args.n, args.n_exact, args.repeats = 200_000, 5_000, 1
    import cv2

    calib, source = calibration(args.calibration)
    cam = calib.camera
    knn_source = ensure_knn(calib)
    knn = cam.correction
    print(f"calibration: {source}, model {calib.model}, {cam.width}x{cam.height} px")
    print(
        f"kNN correction: {knn_source}, k = {knn.n_neighbors_} ({knn.weights_}), "
        f"{len(knn.uv_px_)} training pixels"
    )
    print(
        f"valid field: observed {math.degrees(cam.observed_alpha_rad or math.nan):.2f} deg, "
        f"valid_alpha {math.degrees(cam.valid_alpha_rad()):.2f} deg, "
        f"max_alpha (one-to-one) {math.degrees(cam.max_alpha_rad()):.2f} deg"
    )
    t0 = time.perf_counter()
    table = cam.correction_table()
    build_s = time.perf_counter() - t0
    rng = np.random.default_rng(1)
    # points: random pixels in the valid field, their rays (exact), random depths
    uv = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], (int(1.3 * args.n), 2))
    uv = uv[cam.valid_pixel_mask(uv)][: args.n]
    rays = cam.unproject(uv, exact=True)
    pts = rays * rng.uniform(0.5, 5.0, (len(rays), 1))
    n = len(pts)
    ne = min(args.n_exact, n)
    K, D, kb_err = kb_fit(cam, cam.valid_alpha_rad())
    obj = pts.reshape(1, -1, 3)
    zero = np.zeros(3)
    radial_only = dataclasses.replace(cam, correction=None)  # the same lens without its kNN
    rows = []

    def row(name, fn, count):
        sec = best_time(fn, args.repeats)
        rows.append((name, count, sec, count / sec))

    row("project, exact kNN (before)", lambda: cam.project(pts[:ne], exact=True), ne)
    row("project, table (default)", lambda: cam.project(pts), n)
    row("project, radial alone", lambda: radial_only.project(pts), n)
    row("cv2.fisheye.projectPoints", lambda: cv2.fisheye.projectPoints(obj, zero, zero, K, D), n)
    row("unproject, exact kNN (before)", lambda: cam.unproject(uv[:ne], exact=True), ne)
    row("unproject, table (default)", lambda: cam.unproject(uv), n)
    row("unproject, radial alone", lambda: radial_only.unproject(uv), n)
    uv_cv = uv.reshape(1, -1, 2)
    row("cv2.fisheye.undistortPoints", lambda: cv2.fisheye.undistortPoints(uv_cv, K, D), n)
    print(
        f"\nthroughput (CPU time, best of {args.repeats}), {n} points; table built in "
        f"{build_s:.2f} s wall ({table.spacing_px:g} px nodes, {table.nbytes / 1e6:.1f} MB)"
    )
    print(f"{'':34s}{'points':>10s}{'seconds':>10s}{'points/s':>12s}")
    for name, count, sec, rate in rows:
        print(f"{name:34s}{count:10d}{sec:10.4f}{rate:12.3g}")
    by = {r[0]: r[3] for r in rows}
    fast_p, fast_u = by["project, table (default)"], by["unproject, table (default)"]
    print(
        f"table vs cv2.fisheye: project {by['cv2.fisheye.projectPoints'] / fast_p:.2f}x "
        f"slower, unproject {by['cv2.fisheye.undistortPoints'] / fast_u:.2f}x slower; "
        f"speed-up over exact kNN: project {fast_p / by['project, exact kNN (before)']:.0f}x, "
        f"unproject {fast_u / by['unproject, exact kNN (before)']:.0f}x"
    )
    print(f"(KB lens fitted to r(alpha) within {kb_err:.3f} px up to the valid field)")
    # agreement of the table with the exact kNN, and of the two projections
    check = check_pixels(knn, cam.width, cam.height, n=50_000, seed=2)
    agree = table.agreement(knn, check)
    uv_t = cam.project(pts[:ne])
    uv_e = cam.project(pts[:ne], exact=True)
    dproj = np.linalg.norm(uv_t - uv_e, axis=1)
    round_trip = np.linalg.norm(cam.project(cam.unproject(uv[:ne])) - uv[:ne], axis=1)
    print(
        f"\ntable vs exact kNN, {agree['n']} pixels of the observed region: RMS "
        f"{agree['rms_px']:.5f} px, max {agree['max_px']:.5f} px; project table vs exact on "
        f"{ne} points: RMS {np.sqrt(np.mean(dproj**2)):.5f} px, max {dproj.max():.5f} px; "
        f"table round trip project(unproject(uv)) - uv: max {round_trip.max():.2e} px"
    )
    # undistort of a ~1 MP output image
    img = (rng.random((cam.height, cam.width)) * 255).astype(np.uint8)
    size = (1280, 800)
    timings = {}
    for label, exact in (("exact kNN (before)", True), ("table (default)", False)):
        target = cam if not exact else _ExactCamera(cam)
        t0 = time.perf_counter()
        tables = remap_tables(target, "perspective", fov_deg=120.0, size=size)
        t1 = time.perf_counter()
        apply_remap(img, tables)
        t2 = time.perf_counter()
        timings[label] = (t1 - t0, t2 - t1)
    print(f"\nundistort to a {size[0]}x{size[1]} perspective image (120 deg), wall seconds:")
    for label, (tt, ta) in timings.items():
        print(f"  {label:20s} remap tables {tt:7.2f}   remap {ta:6.3f}   total {tt + ta:7.2f}")


class _ExactCamera:
    """The camera as before the table: ``exact=True`` everywhere, no valid-field limit."""

    def __init__(self, cam):
        self._cam = cam

    def __getattr__(self, name):
        return getattr(self._cam, name)

    def project(self, p, *a, **k):
        return self._cam.project(p, *a, exact=True, valid_only=False, **k)

    def unproject(self, uv, *a, **k):
        return self._cam.unproject(uv, *a, exact=True, **k)

    def pixel_hemisphere(self, uv, *a, **k):
        return self._cam.pixel_hemisphere(uv, *a, exact=True, **k)

    def ideal_from_pixels(self, uv, *a, **k):
        return self._cam.ideal_from_pixels(uv, *a, exact=True, **k)


if __name__ == "__main__":
    main()
