"""A wrong target description is caught (issue 15, item 4).

A chessboard described smaller than it is (``chessboard:4x6`` for a board with 6x8
inner corners) used to give 24-corner sub-grids at arbitrary offsets, i.e. mislabelled
corners. Detection now notices that the pattern continues beyond the described grid
(or that the grid jumps over squares) and stops with :class:`TargetMismatchError`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_detect import FISHEYE, FULL_VIEWS, H, W, rms_vs_truth

from gtsam_sphere.apps.detect import BoardSpec, add_cli_arguments, detect_image, run_cli
from gtsam_sphere.core.errors import InputError, TargetMismatchError
from gtsam_sphere.simulate.render import render_board_image

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def _render(view: str, spec: str = "chessboard:6x8:0.03"):
    R, t = FULL_VIEWS[view]
    board = BoardSpec.parse(spec)
    return render_board_image(
        board, FISHEYE.project, FISHEYE.unproject, R, t, W, H, blur_sigma_px=0.7, noise_sigma=1.0
    )


def test_error_is_an_input_error():
    assert issubclass(TargetMismatchError, InputError)


@pytest.mark.parametrize("view", ["a", "b"])
def test_rendered_6x8_board_described_as_4x6_is_refused(view):
    img, truth = _render(view)
    assert len(truth) == 48
    with pytest.raises(TargetMismatchError, match="continues beyond the described 4x6 grid"):
        detect_image(img, BoardSpec.parse("chessboard:4x6:0.03"))
    # described as it is: every corner, no complaint
    det = detect_image(img, BoardSpec.parse("chessboard:6x8:0.03"))
    assert set(det) == set(truth)
    assert rms_vs_truth(det, truth)[0] < 0.1


@pytest.mark.slow
def test_rendered_6x8_board_described_as_6x7_is_refused():
    # one row short: only one border continues (OpenCV finds no 5x8 grid at all here)
    img, _ = _render("a")
    with pytest.raises(TargetMismatchError, match="6x7 grid .*beyond the"):
        detect_image(img, BoardSpec.parse("chessboard:6x7:0.03"))


def test_cli_exits_2_naming_the_image(tmp_path, capsys):
    img, _ = _render("a")
    path = tmp_path / "view_a.png"
    cv2.imwrite(str(path), img)
    parser = argparse.ArgumentParser()
    add_cli_arguments(parser)
    out = tmp_path / "ds.json"
    args = parser.parse_args(
        [str(path), "--board", "chessboard:4x6:0.03", "-o", str(out), "--no-progress"]
    )
    assert run_cli(args) == 2
    err = capsys.readouterr().err
    assert "view_a.png" in err and "board is larger" in err and "full size" in err
    assert not out.exists()
    # --no-size-check: the user insists (a sub-grid of 24 corners is written)
    args = parser.parse_args(
        [str(path), "--board", "chessboard:4x6:0.03", "-o", str(out), "--no-progress"]
        + ["--no-size-check"]
    )
    assert run_cli(args) == 0 and out.exists()
    capsys.readouterr()


@pytest.mark.slow  # 9 s: detection over the real fish_1 images (CI runs it)
def test_real_fish_1_described_as_4x6_is_refused():
    paths = sorted((DATA / "images" / "fish_1").glob("*.jpg"))[:4]
    if not paths:
        pytest.skip(f"real images absent: {DATA / 'images' / 'fish_1'} (shared data not mounted)")
    small = BoardSpec.parse("chessboard:4x6:0.0325")
    full = BoardSpec.parse("chessboard:6x8:0.0325")
    for p in paths:
        gray = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        with pytest.raises(TargetMismatchError, match="4x6"):
            detect_image(gray, small)
        det = detect_image(gray, full)
        assert len(det) == 48, p.name
        assert np.all(np.isfinite(np.array(list(det.values()))))


def test_rendered_charuco_described_smaller_is_refused():
    from test_detect import POSES

    board = BoardSpec.parse("charuco:5x7:0.04:0.03:DICT_4X4_50")
    R, t = POSES["mild"]
    img, truth = render_board_image(
        board, FISHEYE.project, FISHEYE.unproject, R, t, W, H, blur_sigma_px=0.7
    )
    with pytest.raises(TargetMismatchError, match="ChArUco markers with ids"):
        detect_image(img, BoardSpec.parse("charuco:4x5:0.04:0.03:DICT_4X4_50"))
    det = detect_image(img, board)
    assert set(det) <= set(truth) and len(det) >= 0.7 * len(truth)
