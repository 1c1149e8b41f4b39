"""Issue 4 item 3: a room of ArUco markers rendered through a 200 degree fisheye.

The room is rendered with :func:`gtsam_sphere.simulate.render.render_aruco_room` through
a circular Kannala-Brandt lens whose image circle holds a 200 degree field of view, so
markers are seen beyond 90 degrees off the axis. Checks: the detected marker corners
and centres against their true projections, and the whole pipeline (``gtsam-sphere
detect`` with a surveyed markers CSV, then ``gtsam-sphere calibrate``) against the
simulated lens.
"""

from __future__ import annotations

import json
import math
import time

import cv2
import numpy as np
import pytest

from gtsam_sphere.apps.detect import BoardSpec, detect_image
from gtsam_sphere.cli import main as cli_main
from gtsam_sphere.io.calibration import load_calibration
from gtsam_sphere.simulate.lenses import make_lens
from gtsam_sphere.simulate.render import make_aruco_room, pixel_rays, render_aruco_room

W, H = 800, 600
MARKER_M = 0.35
BOARD = f"aruco:DICT_4X4_50:{MARKER_M}"
# Circular fisheye: 200 deg across the image circle (radius 300 px), off-centre
# principal point, mild Kannala-Brandt distortion; the radial model represents it exactly
# (c = f, xp = cx, yp = cy, g3 = k1 (pi/2)^2, g5 = k2 (pi/2)^4).
LENS = make_lens(
    "kannala-brandt", 200.0, W, H, fill="circle", k1=-0.02, k2=0.002, cx=403.7, cy=296.2
)
# (camera centre in the room (m), yaw, pitch, roll (deg)); the room is 4 x 3.5 x 2.6 m
VIEWS = [
    ((2.0, 1.75, 1.3), 10, 5, 0),
    ((1.5, 1.5, 1.2), 40, 20, 90),
    ((2.5, 2.0, 1.4), 200, -25, 10),
    ((2.2, 1.4, 1.0), 120, 50, -30),
    ((1.8, 2.1, 1.5), -70, -50, 180),
    ((2.6, 1.6, 1.3), 300, 5, 45),
]
SURVEY_SIGMA_M = 0.003


def _cam_from_world(centre, yaw_deg, pitch_deg, roll_deg):
    """Pose looking along (yaw, pitch) from ``centre``, rolled about the view axis."""
    yaw, pitch, roll = (math.radians(a) for a in (yaw_deg, pitch_deg, roll_deg))
    fwd = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw)])
    fwd = np.append(fwd, math.sin(pitch))
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    c, s = math.cos(roll), math.sin(roll)
    world_from_cam = np.stack([c * right + s * down, -s * right + c * down, fwd], axis=1)
    R = world_from_cam.T
    return R, -R @ np.asarray(centre, float)


@pytest.fixture(scope="module")
def views(tmp_path_factory):
    """The room, the folder and six rendered views (PNG path, array, truth, R, t)."""
    t0 = time.perf_counter()
    folder = tmp_path_factory.mktemp("aruco_room")
    room = make_aruco_room(marker_m=MARKER_M, seed=1)
    rays = pixel_rays(LENS, W, H, supersample=4)
    out = []
    for i, view in enumerate(VIEWS):
        R, t = _cam_from_world(*view)
        img, truth = render_aruco_room(
            room, LENS, R, t, W, H, rays=rays, blur_sigma_px=0.6, noise_sigma=2.0, seed=i
        )
        path = folder / f"view{i}.png"
        cv2.imwrite(str(path), img)
        out.append((path, img, truth, R, t))
    print(f"rendered {len(out)} views of {W}x{H} in {time.perf_counter() - t0:.1f} s")
    return room, folder, out


def test_pixel_rays_interpolation_is_exact_enough():
    w, h, ss = 320, 240, 3
    lens = make_lens("kannala-brandt", 200.0, w, h, fill="circle", k1=-0.02, k2=0.002)
    rays = pixel_rays(lens, w, h, ss)
    exact = pixel_rays(lens, w, h, ss, exact=True)
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    vv, uu = np.mgrid[0:h, 0:w].astype(float)
    worst = 0.0
    for i, dv in enumerate(offs):
        for j, du in enumerate(offs):
            r = rays[i * ss + j].reshape(-1, 3).astype(float)
            ok = np.all(np.isfinite(r), axis=1)
            uv = np.stack([(uu + du).ravel(), (vv + dv).ravel()], axis=1)[ok]
            worst = max(worst, float(np.max(np.linalg.norm(lens.project(r[ok]) - uv, axis=1))))
    print(f"f = {lens.f:.1f} px: interpolated rays re-project within {worst:.2e} px")
    assert worst < 0.15 / lens.f  # the documented bound (second order in the 1 px grid)
    # NaN only next to the image circle
    assert np.mean(np.isfinite(rays[..., 0])) > np.mean(np.isfinite(exact[..., 0])) - 0.01


@pytest.mark.slow  # end-to-end
def test_marker_corners_and_centres_match_the_truth(views):
    room, _, rendered = views
    board = BoardSpec.parse(BOARD)
    corner_err, centre_err, diag_err = [], [], []
    n_found = n_clear = n_clear_found = 0
    t0 = time.perf_counter()
    for _, img, truth, R, t in rendered:
        det = detect_image(img, board)
        assert set(det) <= set(truth), "a detection has no visible true counterpart"
        for m in room.markers:
            key = f"M{m.id}"
            if not all(f"{key}_{k}" in truth for k in range(4)):
                assert key not in det
                continue
            q = np.array([truth[f"{key}_{k}"] for k in range(4)])
            # Markers with >= 4 px per code cell whose white margin is imaged whole (inside
            # the image and the lens's 200 degree circle) must be found.
            half = 0.5 * m.size_m * (1 + 2 * room.quiet_zone_bits / room.cells)
            ring = np.array([[-1, -1], [0, -1], [1, -1], [1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0]])
            margin = m.centre_m + half * ring @ np.stack([m.x_axis, m.y_axis])
            uv = LENS.project(margin @ R.T + t)
            side = np.mean(np.linalg.norm(q - np.roll(q, 1, axis=0), axis=1))
            inside = np.all(np.isfinite(uv)) and np.all((uv >= 2) & (uv <= np.array([W, H]) - 3))
            clear = bool(inside and side >= 24.0)
            n_clear += clear
            if key not in det:
                continue
            n_found += 1
            n_clear_found += clear
            # ids "M{id}_{k}": corner k of cv2.aruco (0 top-left, clockwise on the printed
            # marker) = corner k of the renderer (ArucoMarker.corners_m)
            corner_err += [det[f"{key}_{k}"] - q[k] for k in range(4)]
            centre_err.append(det[key] - truth[key])
            # the straight-line answer: intersection of the diagonals of the true corners
            p, r, s, d = q[0], q[2] - q[0], q[1], q[3] - q[1]
            tt = ((s - p)[0] * d[1] - (s - p)[1] * d[0]) / (r[0] * d[1] - r[1] * d[0])
            diag_err.append(p + tt * r - truth[key])
    dt = time.perf_counter() - t0
    ce = np.linalg.norm(np.array(corner_err), axis=1)
    me = np.linalg.norm(np.array(centre_err), axis=1)
    de = np.linalg.norm(np.array(diag_err), axis=1)

    def rms(e):
        return float(np.sqrt(np.mean(e**2)))

    print(
        f"{n_found} markers ({n_clear_found}/{n_clear} clear ones) in {len(rendered)} views "
        f"({dt:.1f} s): corners RMS {rms(ce):.4f} px, "
        f"max {ce.max():.4f} px; centres RMS {rms(me):.4f} px, max {me.max():.4f} px; "
        f"diagonal intersection of the true corners: RMS {rms(de):.3f} px, max {de.max():.3f} px"
    )
    assert n_found >= 100 and n_clear_found >= 0.95 * n_clear
    # the lens bends the marker outlines enough that straight-line geometry is wrong...
    assert rms(de) > 0.2
    # ...while the detector's corners and centres follow the truth (issue 4: corners
    # within 0.1 px RMS; measured 0.03 px RMS, 0.07 px at worst, centres 0.009 / 0.024)
    assert rms(ce) < 0.05 and ce.max() < 0.2
    assert rms(me) < 0.02 and me.max() < 0.05


@pytest.mark.slow  # end-to-end
def test_detect_cli_and_calibrate_recover_the_lens(views, tmp_path):
    room, folder, rendered = views
    # survey: every marker centre with 3 mm noise per axis, and that sigma
    rng = np.random.default_rng(7)
    csv_path = tmp_path / "markers.csv"
    lines = ["id,X,Y,Z,sigma"]
    for m in room.markers:
        xyz = m.centre_m + rng.normal(0.0, SURVEY_SIGMA_M, 3)
        lines.append(f"{m.id},{xyz[0]:.4f},{xyz[1]:.4f},{xyz[2]:.4f},{SURVEY_SIGMA_M}")
    csv_path.write_text("\n".join(lines) + "\n")
    paths = [str(v[0]) for v in rendered]
    dataset, calib_path = tmp_path / "ds.json", tmp_path / "calib.json"
    t0 = time.perf_counter()
    args = ["detect", *paths, "--board", BOARD, "--markers-csv", str(csv_path)]
    assert cli_main([*args, "-o", str(dataset), "--no-progress"]) == 0
    t1 = time.perf_counter()
    doc = json.loads(dataset.read_text())
    assert len(doc["images"]) == len(VIEWS)
    n_obs = sum(len(i["observations"]) for i in doc["images"])
    # honest noise level of these observations: the centre error against the truth
    truth_of = {v[0].stem: v[2] for v in rendered}  # image id = file stem
    err = [
        np.asarray(o["uv"]) - truth_of[image["id"]][o["target"]]
        for image in doc["images"]
        for o in image["observations"]
    ]
    centre_rms = float(np.sqrt(np.mean(np.sum(np.array(err) ** 2, axis=1))))
    # the default model (radial+knn): the radial part represents the lens exactly
    assert cli_main(["calibrate", str(dataset), "-o", str(calib_path), "--quiet"]) == 0
    t2 = time.perf_counter()
    calib = load_calibration(str(calib_path))
    cam, stats = calib.camera, calib.statistics
    sig = stats["intrinsics_sigma"]
    # The formal sigmas scale with the adjustment's sigma_px, estimated from residuals that
    # the adjusted targets (3 mm priors, 3-4 views each) partly absorb: 2-3x below the true
    # detection error here. Rescale them to the measured per-axis noise of the centres
    # (centre_rms / sqrt 2) for an honest n-sigma test.
    scale = centre_rms / math.sqrt(2.0) / stats["sigma_px"]
    print(
        f"detect {t1 - t0:.1f} s ({n_obs} centres, RMS error {centre_rms:.4f} px), calibrate "
        f"{t2 - t1:.1f} s: model {calib.model}, rms {stats['rms_px']:.4f} px, sigma_px "
        f"{stats['sigma_px']:.4f}, max incidence {stats['max_incidence_deg']:.1f} deg"
    )
    for name, est, true in (("xp", cam.xp, LENS.cx), ("yp", cam.yp, LENS.cy), ("c", cam.c, LENS.f)):
        s = sig[f"{name}_px"]
        print(
            f"  {name}: {est:.4f} px, truth {true:.4f} px, error {est - true:+.4f} px, formal "
            f"sigma {s:.4f} px ({(est - true) / s:+.1f}), rescaled sigma {s * scale:.4f} px "
            f"({(est - true) / (s * scale):+.1f})"
        )
        assert abs(est - true) < 0.05  # a twentieth of a pixel
        assert abs(est - true) < 3.0 * s * scale
    assert stats["max_incidence_deg"] > 90.0  # the field past 180 degrees is used
    assert stats["n_images"] == len(VIEWS)
