"""Kalibr targets (issue 15, item 1): target.yaml, AprilGrid detection and numbering."""

from __future__ import annotations

import argparse
import json

import cv2
import numpy as np
import pytest
from test_detect import Equidistant, rot

from gtsam_sphere.apps.detect import (
    BoardSpec,
    add_cli_arguments,
    detect_image,
    read_kalibr_target,
    run_cli,
)
from gtsam_sphere.core.errors import DatasetError, OptionsError, TargetMismatchError
from gtsam_sphere.simulate.render import render_board_image

APRILGRID_YAML = """target_type: 'aprilgrid' #gridtype
tagCols: 6               #number of apriltags
tagRows: 6               #number of apriltags
tagSize: 0.088           #size of apriltag, edge to edge [m]
tagSpacing: 0.3          #ratio of space between tags to tagSize
"""
CHECKER_YAML = """target_type: 'checkerboard' #gridtype
targetCols: 6               #number of internal chessboard corners
targetRows: 8               #number of internal chessboard corners
rowSpacingMeters: 0.03      #size of one chessboard square [m]
colSpacingMeters: 0.03      #size of one chessboard square [m]
"""
# a 200 degree equidistant fisheye: 100 degrees off axis at 380 px from the centre
W = H = 800
LENS = Equidistant(380.0 / np.radians(100.0), W / 2 - 0.5 + 2.3, H / 2 - 0.5 - 1.4)
GRID = BoardSpec.aprilgrid(6, 6, 0.088, 0.3)


def _pose(rx, ry, rz, offset):
    """Camera from board: the board's centre at ``offset`` (camera frame, m), the printed
    side (Kalibr's +z) towards the camera, then rotated by (rx, ry, rz)."""
    size = GRID.cols * GRID.square_m - GRID.square_m + GRID.marker_m
    centre = np.array([size / 2, size / 2, 0.0])
    R = rot(rx, ry, rz) @ rot(np.pi, 0, 0)
    return R, np.asarray(offset, float) - R @ centre


VIEWS = {
    "front": _pose(0.1, 0.05, 0.1, [0.0, 0.0, 0.35]),
    "oblique": _pose(0.5, -0.4, 0.3, [0.05, 0.02, 0.3]),
    "side": _pose(0.2, 1.2, 0.1, [0.35, 0.0, 0.15]),
}


def _render(view, board=GRID):
    R, t = VIEWS[view]
    return render_board_image(
        board,
        LENS.project,
        LENS.unproject,
        R,
        t,
        W,
        H,
        px_per_square=100,
        supersample=3,
        blur_sigma_px=0.8,
        noise_sigma=2.0,
    )


def test_read_kalibr_aprilgrid_yaml(tmp_path):
    path = tmp_path / "target.yaml"
    path.write_text(APRILGRID_YAML)
    b = read_kalibr_target(str(path))
    assert (b.kind, b.cols, b.rows, b.marker_m, b.spacing) == ("aprilgrid", 6, 6, 0.088, 0.3)
    assert b.dictionary == "DICT_APRILTAG_36H11" and b.corner_count() == 144
    yaml = pytest.importorskip("yaml")  # the flat reader agrees with a YAML parser
    ref = yaml.safe_load(APRILGRID_YAML)
    assert (ref["tagCols"], ref["tagSize"], ref["tagSpacing"]) == (b.cols, b.marker_m, b.spacing)


def test_read_kalibr_checkerboard_yaml(tmp_path):
    path = tmp_path / "checker.yaml"
    path.write_text(CHECKER_YAML)
    b = read_kalibr_target(str(path))
    assert (b.kind, b.cols, b.rows, b.square_m) == ("chessboard", 6, 8, 0.03)


@pytest.mark.parametrize(
    "text, error, part",
    [
        (APRILGRID_YAML.replace("tagSize: 0.088", "tagSize: big"), DatasetError, "tagSize"),
        (APRILGRID_YAML.replace("tagCols: 6", ""), DatasetError, "tagCols"),
        (APRILGRID_YAML.replace("tagSpacing: 0.3", "tagSpacing: 3"), OptionsError, "spacing"),
        (
            CHECKER_YAML.replace("colSpacingMeters: 0.03", "colSpacingMeters: 0.04"),
            OptionsError,
            "colSpacingMeters",
        ),
        ("target_type: 'circlegrid'\n", OptionsError, "circlegrid"),
        ("tagCols:\n  - 6\n", DatasetError, "flat"),
    ],
)
def test_kalibr_yaml_errors_name_the_key(tmp_path, text, error, part):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(error, match=part):
        read_kalibr_target(str(path))


def test_aprilgrid_numbering_is_kalibrs():
    # Kalibr (GridCalibrationTargetAprilgrid.cpp): points on a 2 tagRows x 2 tagCols
    # lattice, row by row from the lower left corner of tag 0, x right, y up the print
    pts = GRID.object_points_m()
    assert len(pts) == 144
    np.testing.assert_allclose(pts["C000"], [0, 0, 0])
    np.testing.assert_allclose(pts["C001"], [0.088, 0, 0])
    np.testing.assert_allclose(pts["C002"], [0.088 * 1.3, 0, 0])
    np.testing.assert_allclose(pts["C012"], [0, 0.088, 0])
    np.testing.assert_allclose(pts["C024"], [0, 0.088 * 1.3, 0])
    np.testing.assert_allclose(pts["C143"], [5 * 0.1144 + 0.088, 5 * 0.1144 + 0.088, 0])
    # OpenCV's corners 0..3 (of its upright marker, which Kalibr prints turned by 180
    # degrees): lower right, lower left, upper left, upper right of the printed tag
    assert GRID.aprilgrid_corner_ids(0) == ["C001", "C000", "C012", "C013"]
    assert GRID.aprilgrid_corner_ids(7) == ["C027", "C026", "C038", "C039"]
    assert BoardSpec.parse("aprilgrid:6x6:0.088:0.3") == GRID


def test_rendered_tags_read_as_kalibr_prints_them():
    # Kalibr's printed tag, read row by row from the upper left data cell as printed
    # (white = 1, most significant bit first), is the tag36h11 code: tag 0 is 0xd5d628584
    # and tag 1 0xd97f18b49 in the AprilTag code tables (Kaess's, which Kalibr uses)
    from gtsam_sphere.simulate.render import _board_texture

    tex, origin, texel = _board_texture(GRID, 100)
    page = np.flipud(tex)  # texture rows go up the page
    tag_px = int(round(GRID.marker_m / texel))
    cell = tag_px // 10
    pitch = int(round(GRID.square_m / texel))
    for tag_id, code in ((0, 0xD5D628584), (1, 0xD97F18B49)):
        x0 = int(round(-origin[0] / texel)) + tag_id * pitch
        y1 = page.shape[0] - int(round(-origin[1] / texel))  # bottom of tag row 0, as printed
        block = page[y1 - tag_px : y1, x0 : x0 + tag_px]
        bits = block[2 * cell + cell // 2 : 8 * cell : cell, 2 * cell + cell // 2 : 8 * cell : cell]
        value = int("".join("1" if b > 127 else "0" for b in bits.ravel()), 2)
        assert value == code, (tag_id, hex(value))


@pytest.mark.parametrize("view", ["front", "oblique", "side"])
def test_rendered_aprilgrid_through_a_200_degree_fisheye(view):
    img, truth = _render(view)
    det = detect_image(img, GRID)
    assert set(det) <= set(truth)  # every id is Kalibr's id of that corner
    err = np.linalg.norm(np.array([det[k] - truth[k] for k in det]), axis=1)
    R, t = VIEWS[view]
    p = np.array([GRID.object_points_m()[k] for k in det]) @ R.T + t
    inc = np.degrees(np.arctan2(np.hypot(p[:, 0], p[:, 1]), p[:, 2]))
    rms = float(np.sqrt(np.mean(err**2)))
    print(
        f"aprilgrid {view}: {len(det)}/{len(truth)} corners, RMS {rms:.4f} px, "
        f"max {err.max():.3f} px, incidence up to {inc.max():.1f} deg"
    )
    # the decoder finds the central tags; the layout-guided growth finds the rest
    assert len(det) >= (len(truth) if view == "front" else 0.55 * len(truth))
    assert rms < 0.08 and err.max() < 0.25  # right ids: every corner where its id says


def test_growth_adds_only_verified_tags():
    from gtsam_sphere.apps.detect import _detect_aprilgrid

    img, truth = _render("oblique")
    seeds = _detect_aprilgrid(img, GRID, grow=False)
    grown = _detect_aprilgrid(img, GRID)
    print(f"oblique view: {len(seeds)} corners decoded, {len(grown)} with the growth")
    assert len(grown) > 1.5 * len(seeds)
    # every added tag's corners are where its id puts them (its code was checked)
    assert all(np.linalg.norm(grown[k] - truth[k]) < 0.25 for k in grown)


def test_aprilgrid_described_smaller_is_refused():
    img, _ = _render("front")
    with pytest.raises(TargetMismatchError, match="larger"):
        detect_image(img, BoardSpec.aprilgrid(5, 5, 0.088, 0.3))


@pytest.mark.slow
def test_cli_detect_with_kalibr_target(tmp_path, capsys):
    paths = []
    for view in ("front", "side"):
        img, _ = _render(view)
        paths.append(tmp_path / f"{view}.png")
        cv2.imwrite(str(paths[-1]), img)
    target = tmp_path / "target.yaml"
    target.write_text(APRILGRID_YAML)
    parser = argparse.ArgumentParser()
    add_cli_arguments(parser)
    out = tmp_path / "ds.json"
    args = parser.parse_args(
        [*map(str, paths), "--target", str(target), "-o", str(out), "--no-progress"]
    )
    assert run_cli(args) == 0
    ds = json.loads(out.read_text())
    assert [im["id"] for im in ds["images"]] == ["front", "side"]
    pts = GRID.object_points_m()
    for t in ds["targets"]:
        np.testing.assert_allclose(t["xyz"], pts[t["id"]])
    with pytest.raises(SystemExit):  # --board and --target exclude each other
        parser.parse_args([str(paths[0]), "--target", str(target), "--board", "x", "-o", "o"])
    capsys.readouterr()


CALIBRATION_VIEWS = {
    **VIEWS,
    "left": _pose(-0.2, -1.0, -0.2, [-0.3, 0.05, 0.2]),
    "up": _pose(0.9, 0.1, 0.5, [0.0, -0.25, 0.25]),
    "down": _pose(-0.8, 0.2, -0.4, [0.05, 0.25, 0.25]),
    "far": _pose(0.2, -0.3, 1.2, [0.0, 0.0, 0.5]),
}


@pytest.mark.slow  # end-to-end: 7 renders, detection, calibration
def test_aprilgrid_renders_to_calibration_recover_the_lens(tmp_path):
    from gtsam_sphere.estimation.calibrate import CalibrationOptions, calibrate
    from gtsam_sphere.io.dataset import load_dataset

    paths = []
    for name, (R, t) in CALIBRATION_VIEWS.items():
        img, _ = render_board_image(
            GRID,
            LENS.project,
            LENS.unproject,
            R,
            t,
            W,
            H,
            px_per_square=100,
            supersample=3,
            blur_sigma_px=0.8,
            noise_sigma=2.0,
            seed=len(paths),
        )
        paths.append(str(tmp_path / f"{name}.png"))
        cv2.imwrite(paths[-1], img)
    target = tmp_path / "target.yaml"
    target.write_text(APRILGRID_YAML)
    parser = argparse.ArgumentParser()
    add_cli_arguments(parser)
    out = tmp_path / "ds.json"
    args = parser.parse_args([*paths, "--target", str(target), "-o", str(out), "--no-progress"])
    assert run_cli(args) == 0
    # the lens is equidistant: the radial mapping with no terms is exact
    options = CalibrationOptions(model="radial", radial_terms=0, brown_terms=(), covariance=True)
    calib = calibrate(load_dataset(out), options)
    cam, sig = calib.camera, calib.statistics["intrinsics_sigma"]
    print(
        f"{calib.statistics['n_observations']} corners, RMS {calib.statistics['rms_px']:.4f} px; "
        f"xp {cam.xp - LENS.cx:+.4f} ({sig['xp_px']:.4f}), yp {cam.yp - LENS.cy:+.4f} "
        f"({sig['yp_px']:.4f}), c {cam.c - LENS.f:+.4f} ({sig['c_px']:.4f}) px"
    )
    for est, true, s in (
        (cam.xp, LENS.cx, sig["xp_px"]),
        (cam.yp, LENS.cy, sig["yp_px"]),
        (cam.c, LENS.f, sig["c_px"]),
    ):
        assert abs(est - true) < 3 * s, (est, true, s)
    assert calib.statistics["rms_px"] < 0.1


@pytest.mark.slow
def test_cli_rig_detect_with_kalibr_target(tmp_path, capsys):
    from gtsam_sphere.cli import main

    front, _ = _render("front")
    side, _ = _render("side")
    for cam, images in (("cam0", (front, side)), ("cam1", (side, front))):
        (tmp_path / cam).mkdir()
        for stem, img in zip(("000", "001"), images):
            cv2.imwrite(str(tmp_path / cam / f"{stem}.png"), img)
    target = tmp_path / "target.yaml"
    target.write_text(APRILGRID_YAML)
    out = tmp_path / "rig.json"
    argv = ["detect", "--target", str(target), "-o", str(out), "--no-progress"]
    cams = ["--camera", f"cam0={tmp_path / 'cam0'}", "--camera", f"cam1={tmp_path / 'cam1'}"]
    assert main([*argv, *cams]) == 0
    doc = json.loads(out.read_text())
    assert doc["format"] == "gtsam-sphere/dataset@2"
    n = {im["id"]: len(im["observations"]) for im in doc["images"]}
    assert n["cam0/000"] == n["cam1/001"] == 144  # the front view: every corner
    wrong = tmp_path / "small.yaml"
    wrong.write_text(
        APRILGRID_YAML.replace("tagCols: 6", "tagCols: 5").replace("tagRows: 6", "tagRows: 5")
    )
    assert main(["detect", "--target", str(wrong), "-o", str(out), "--no-progress", *cams]) == 2
    assert "larger" in capsys.readouterr().err


def test_detect_bag_without_rosbags_says_what_to_install(tmp_path, monkeypatch, capsys):
    import sys

    from gtsam_sphere.cli import main

    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)  # as if absent
    target = tmp_path / "target.yaml"
    target.write_text(APRILGRID_YAML)
    argv = ["detect", "--bag", str(tmp_path / "x.bag"), "--topics", "/cam0/image_raw"]
    assert main([*argv, "--target", str(target), "-o", str(tmp_path / "o.json")]) == 2
    assert "gtsam-sphere[ros]" in capsys.readouterr().err
