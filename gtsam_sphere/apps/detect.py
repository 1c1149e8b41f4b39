"""Automatic calibration-target detection producing ``gtsam-sphere/dataset@1`` files.

Supported targets
-----------------
``chessboard:COLSxROWS:SQUARE``
    A plain chessboard with ``COLS x ROWS`` *inner* corners (OpenCV's ``patternSize``)
    and squares of ``SQUARE`` metres. Target ids are ``"C000"``, ``"C001"``, ... in
    row-major order; corner ``C{r*COLS+c:03d}`` sits at board coordinates
    ``(c*SQUARE, r*SQUARE, 0)``.
``charuco:SXxSY:SQUARE:MARKER:DICT``
    An OpenCV ChArUco board of ``SX x SY`` squares. Target ids are ``"C{id:03d}"`` with
    OpenCV's ChArUco corner ids and OpenCV's board coordinates.
``aprilgrid:COLSxROWS:TAG:SPACING`` (or ``--target target.yaml``, Kalibr's file)
    Kalibr's AprilGrid: ``COLS x ROWS`` tag36h11 tags of side ``TAG`` metres with a
    2-cell black border, gaps of ``SPACING`` times the tag side and a small black
    square at every tag corner. Target ids ``"C{k:03d}"`` are Kalibr's grid points
    (:meth:`BoardSpec.aprilgrid_corner_ids`), board frame as Kalibr's (x right, y up
    the print, origin at the lower left corner of tag 0). :func:`read_kalibr_target`
    also reads Kalibr's ``checkerboard`` files.
``aruco:DICT:MARKER``
    Individual ArUco markers of side ``MARKER`` metres spread over a scene. Each marker
    gives the target ``"M{id}"`` (the image of its centre) and ``"M{id}_{k}"`` (its
    corners ``k = 0..3`` in OpenCV order), both from a fit of the marker's cell pattern
    to the pixels that follows the lens distortion across the marker (under a fisheye
    the intersection of the image diagonals is not the centre's image); markers too
    small to fit (below about 2.5 px per code cell) are left out. Only the centres can
    become dataset targets: their approximate coordinates come from a survey CSV
    (``id,X,Y,Z[,sigma]``).

Conventions (see ``spec/dataset.md``): pixels ``(u, v)`` with ``(0, 0)`` the centre of
the top-left pixel, ``u`` right, ``v`` down; board frame in metres with the board in
the plane ``z = 0``; camera frame ``x`` right, ``y`` down, ``z`` forward.

Chessboard ordering
-------------------
A chessboard whose inner-corner counts ``COLS + ROWS`` is even (e.g. 4x6, 8x6) looks
identical after a 180 degree rotation, and a square one (``COLS == ROWS``) also after
90 degrees, so the detector's corner order is ambiguous. Ids are made consistent as
follows: (1) the order is made right-handed in the image (board ``x`` cross board
``y`` points away from the camera, i.e. the board is seen from its printed side);
(2) if the colour pattern breaks the symmetry (``COLS + ROWS`` odd), the rotation
that puts a *dark* square between ``C000`` and its neighbours is chosen; (3)
otherwise the rotation whose ``C000`` is nearest to the image's top-left corner
(smallest ``u + v``) is chosen.

Limitation: for symmetric boards rule (3) depends on the view, so if the camera
rolls by more than about 90 degrees relative to the board between images, the same
physical corner can receive different ids in different images. This is harmless for
an intrinsic calibration with one free pose per image (the relabelled corners are
the board seen with a pose rotated by 180 degrees about its normal), but it breaks
any method that assumes one board pose shared by several images (e.g. a static
board seen by a moving rig). Use a ChArUco board or an asymmetric chessboard then.

A board larger than described
-----------------------------
``cv2.findChessboardCornersSB`` asked for a 4x6 grid on a board with 6x8 inner corners
returns a 4x6 sub-grid, at an arbitrary offset and, under strong fisheye distortion,
often jumping over whole rows or columns: every corner mislabelled. After detection the
grid is therefore checked (:func:`_grid_continuation`): chessboard saddles one square
beyond a border (predicted by local homographies), saddles between neighbouring grid
corners, or grid cells holding more than one square mean the pattern continues, and
detection stops with :class:`~gtsam_sphere.core.errors.TargetMismatchError` (exit code
2) naming the image and what was seen. On the fish_1 / fish_2 images of the shared data
every one of the 31 images described as 4x6 is refused and none described as 6x8 is.

Periphery recovery (``gtsam-sphere detect ... --recover`` or ``--recover-with CALIB``)
----------------------------------------------------------------------------------------
The detector misses what a fisheye shows worst: ChArUco corners whose markers are too
distorted to decode, and whole chessboards (``findChessboardCornersSB`` is
all-or-nothing) that are partly out of view or strongly foreshortened.
:func:`recover_dataset` closes the loop: calibrate the detections (``--recover``,
model ``--recover-model``, default ``radial``) or take a calibration
(``--recover-with``); resect each image with the calibration fixed
(:mod:`gtsam_sphere.estimation.resect`) and project every board corner; refine each prediction
locally (``cv2.cornerSubPix`` in a window scaled to the predicted square, then the
saddle fit) and keep it only if it is a chessboard saddle within
``min(3 px, 0.3 square)`` of its prediction; for a chessboard image with no detection,
place the largest partial grid found (``CALIB_CB_LARGER``) on the board, refusing grids
whose corners are not all saddles or do not fit the calibration within 1.5 px, and
complete it the same way; recalibrate and predict again (``--recover-rounds``); drop
recovered corners the final recalibration puts past 5 sigma. Recovered observations
carry ``"recovered": true`` and the summary lists the corners added per image. A partial
grid's ids may be off by whole squares or a board symmetry when the image cannot tell
(the limitation above: harmless for intrinsic calibration).
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..core.errors import DatasetError, InputError, OptionsError, TargetMismatchError
from ..core.least_squares import Damping, levenberg_marquardt
from ..core.robust import Loss, mad_sigma, robust_weight

__all__ = [
    "BoardSpec",
    "DetectionReport",
    "RecoveryReport",
    "add_cli_arguments",
    "detect_image",
    "detect_images",
    "predict_and_refine",
    "read_kalibr_target",
    "read_markers_csv",
    "recover_dataset",
    "refine_predicted_corners",
    "rescue_partial_chessboard",
    "run_cli",
]

DATASET_FORMAT = "gtsam-sphere/dataset@1"


# --------------------------------------------------------------------------------------
# Board specification
# --------------------------------------------------------------------------------------


def _parse_dims(text: str, what: str) -> tuple[int, int]:
    parts = text.lower().split("x")
    if len(parts) != 2:
        raise OptionsError(f"bad {what} {text!r}: expected 'NxM', e.g. '4x6'")
    try:
        a, b = int(parts[0]), int(parts[1])
    except ValueError:
        raise OptionsError(f"bad {what} {text!r}: expected two integers 'NxM'") from None
    if a < 1 or b < 1:
        raise OptionsError(f"bad {what} {text!r}: both counts must be >= 1")
    return a, b


def _parse_length(text: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise OptionsError(f"bad {what} {text!r}: expected a length in metres") from None
    if not np.isfinite(value) or value <= 0:
        raise OptionsError(f"bad {what} {text!r}: must be a positive length in metres")
    return value


def _parse_dictionary(text: str) -> int:
    name = text.upper()
    if not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
        known = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))
        raise OptionsError(f"bad ArUco dictionary {text!r}: expected one of {', '.join(known)}")
    return int(getattr(cv2.aruco, name))


@dataclass
class BoardSpec:
    """Description of a calibration target.

    Attributes
    ----------
    kind : str
        ``"chessboard"``, ``"charuco"`` or ``"aruco"``.
    cols, rows : int
        Chessboard: inner corners per row / number of rows (OpenCV ``patternSize``).
        ChArUco: squares along x / y. ArUco: unused (0).
    square_m : float
        Side of a square in metres (chessboard, ChArUco); 0 for ArUco.
    marker_m : float
        Side of an ArUco marker in metres (ChArUco, ArUco); 0 for chessboards.
    dictionary : str
        ArUco dictionary name, e.g. ``"DICT_4X4_50"`` (ChArUco, ArUco,
        ``"DICT_APRILTAG_36H11"`` for AprilGrids); ``""`` otherwise.
    text : str
        The specification string the board was parsed from.
    spacing : float
        AprilGrid: gap between neighbouring tags as a fraction of the tag side
        (Kalibr's ``tagSpacing``); 0 otherwise.

    AprilGrids (``kind == "aprilgrid"``, Kalibr's target) use ``cols`` / ``rows`` for
    the tags along x / y (``tagCols``, ``tagRows``), ``marker_m`` for the tag side
    (``tagSize``, edge to edge of the black border) and ``square_m`` for the tag pitch
    ``tagSize * (1 + tagSpacing)``.
    """

    kind: str
    cols: int = 0
    rows: int = 0
    square_m: float = 0.0
    marker_m: float = 0.0
    dictionary: str = ""
    text: str = ""
    spacing: float = 0.0
    _charuco: object = field(default=None, repr=False, compare=False)

    @classmethod
    def parse(cls, text: str) -> BoardSpec:
        """Parse a board specification string.

        Parameters
        ----------
        text : str
            ``"chessboard:COLSxROWS:SQUARE_M"`` (inner corners),
            ``"charuco:SXxSY:SQUARE_M:MARKER_M:DICT"`` (squares) or
            ``"aruco:DICT:MARKER_M"``.

        Returns
        -------
        BoardSpec

        Raises
        ------
        ValueError
            With a message naming the offending part of ``text``.
        """
        parts = [p.strip() for p in str(text).strip().split(":")]
        kind = parts[0].lower()
        if kind == "chessboard":
            if len(parts) != 3:
                raise OptionsError(
                    f"bad board {text!r}: expected 'chessboard:COLSxROWS:SQUARE_M' "
                    "(inner corners, square side in metres)"
                )
            cols, rows = _parse_dims(parts[1], "chessboard size")
            if cols < 2 or rows < 2:
                raise OptionsError(f"bad chessboard size {parts[1]!r}: need >= 2x2 inner corners")
            square = _parse_length(parts[2], "square size")
            return cls("chessboard", cols, rows, square, text=str(text))
        if kind == "charuco":
            if len(parts) != 5:
                raise OptionsError(
                    f"bad board {text!r}: expected 'charuco:SXxSY:SQUARE_M:MARKER_M:DICT' "
                    "(squares, lengths in metres)"
                )
            sx, sy = _parse_dims(parts[1], "ChArUco size")
            if sx < 2 or sy < 2:
                raise OptionsError(f"bad ChArUco size {parts[1]!r}: need >= 2x2 squares")
            square = _parse_length(parts[2], "square size")
            marker = _parse_length(parts[3], "marker size")
            if marker >= square:
                raise OptionsError(
                    f"bad marker size {parts[3]!r}: must be smaller than the square ({parts[2]})"
                )
            _parse_dictionary(parts[4])
            return cls("charuco", sx, sy, square, marker, parts[4].upper(), text=str(text))
        if kind == "aprilgrid":
            if len(parts) != 4:
                raise OptionsError(
                    f"bad board {text!r}: expected 'aprilgrid:COLSxROWS:TAG_M:SPACING' "
                    "(tags, tag side in metres, gap / tag side as Kalibr's tagSpacing)"
                )
            cols, rows = _parse_dims(parts[1], "AprilGrid size")
            return cls.aprilgrid(cols, rows, _parse_length(parts[2], "tag size"), parts[3], text)
        if kind == "aruco":
            if len(parts) != 3:
                raise OptionsError(f"bad board {text!r}: expected 'aruco:DICT:MARKER_M'")
            _parse_dictionary(parts[1])
            marker = _parse_length(parts[2], "marker size")
            return cls("aruco", marker_m=marker, dictionary=parts[1].upper(), text=str(text))
        raise OptionsError(
            f"bad board kind {parts[0]!r} in {text!r}: expected 'chessboard', 'charuco', "
            "'aprilgrid' or 'aruco'"
        )

    @classmethod
    def aprilgrid(
        cls, cols: int, rows: int, tag_m: float, spacing: float | str, text: str = ""
    ) -> BoardSpec:
        """Kalibr's AprilGrid: ``cols x rows`` tag36h11 tags of side ``tag_m`` metres.

        Parameters
        ----------
        cols, rows : int
            Tags along the board's x / y axes (Kalibr ``tagCols``, ``tagRows``).
        tag_m : float
            Tag side in metres, edge to edge of the black border (``tagSize``).
        spacing : float or str
            Gap between tags over the tag side (``tagSpacing``, e.g. 0.3), in (0, 1].
        text : str
            Specification text to keep (default: ``"aprilgrid:COLSxROWS:TAG_M:SPACING"``).
        """
        try:
            ratio = float(spacing)
        except ValueError:
            raise OptionsError(
                f"bad tag spacing {spacing!r}: expected the gap over the tag side, e.g. 0.3"
            ) from None
        if not (np.isfinite(ratio) and 0.0 < ratio <= 1.0):
            raise OptionsError(
                f"bad tag spacing {spacing!r}: the gap over the tag side must be in (0, 1]"
            )
        if int(cols) < 1 or int(rows) < 1 or int(cols) * int(rows) > 587:
            raise OptionsError(
                f"bad AprilGrid size {cols}x{rows}: need 1 to 587 tags (tag36h11 has 587 ids)"
            )
        if not (np.isfinite(tag_m) and tag_m > 0):
            raise OptionsError(f"bad tag size {tag_m!r}: must be a positive length in metres")
        return cls(
            "aprilgrid",
            int(cols),
            int(rows),
            float(tag_m) * (1.0 + ratio),
            float(tag_m),
            "DICT_APRILTAG_36H11",
            text=text or f"aprilgrid:{int(cols)}x{int(rows)}:{float(tag_m):g}:{ratio:g}",
            spacing=ratio,
        )

    def aprilgrid_corner_ids(self, tag_id: int) -> list[str]:
        """Target ids of an AprilGrid tag's corners, in OpenCV's corner order.

        Kalibr numbers the corners of a ``tagCols x tagRows`` grid row by row on a
        ``2 tagRows x 2 tagCols`` lattice, from the board's origin at the lower left
        corner of tag 0 (x to the right, y up the printed target); tag ``t`` sits in
        tag row ``t // tagCols``, column ``t % tagCols``, and its lower left, lower
        right, upper right, upper left corners are points ``b, b + 1, b + 2 tagCols + 1,
        b + 2 tagCols`` with ``b = (t // tagCols) 4 tagCols + (t % tagCols) 2`` (the
        comments of ``GridCalibrationTargetAprilgrid.cpp`` in ethz-asl/kalibr draw this
        ordering). Kalibr prints each tag's code matrix rotated by 180 degrees
        (``createTargetPDF.py``: ``rotation=2``): read row by row from its upper left
        cell as printed, white = 1, most significant bit first, a tag shows its tag36h11
        code, whereas OpenCV's marker image shows it rotated by 180 degrees. OpenCV's
        corners (clockwise from the upper left one of its upright marker) therefore
        lie at the printed tag's lower right, lower left, upper left and upper right
        corners: points ``b + 1, b, b + 2 tagCols, b + 2 tagCols + 1``.

        Returns
        -------
        list of 4 str
            ``"C{point:03d}"`` for OpenCV's corners 0, 1, 2, 3.
        """
        n = 2 * self.cols
        base = (tag_id // self.cols) * 2 * n + (tag_id % self.cols) * 2
        return [f"C{k:03d}" for k in (base + 1, base, base + n, base + n + 1)]

    # -- helpers -------------------------------------------------------------------

    def aruco_dictionary(self):
        """Return the ``cv2.aruco.Dictionary`` of a ChArUco/ArUco target."""
        return cv2.aruco.getPredefinedDictionary(_parse_dictionary(self.dictionary))

    def charuco_board(self):
        """Return (and cache) the ``cv2.aruco.CharucoBoard`` of a ChArUco target."""
        if self.kind != "charuco":
            raise ValueError(f"board {self.text!r} is not a ChArUco board")
        if self._charuco is None:
            self._charuco = cv2.aruco.CharucoBoard(
                (self.cols, self.rows), self.square_m, self.marker_m, self.aruco_dictionary()
            )
        return self._charuco

    def object_points_m(self) -> dict[str, np.ndarray]:
        """Board-frame coordinates of every target of a printed board.

        Returns
        -------
        dict of str to ndarray, shape (3,)
            Target id -> ``(x, y, 0)`` in metres, board frame (``x`` along a row of
            corners, ``y`` down the rows, board plane ``z = 0``; AprilGrids: Kalibr's
            frame and point numbering, see :meth:`aprilgrid_corner_ids`). Empty for ``"aruco"``
            (markers spread over a scene have no board frame; use a markers CSV).
        """
        if self.kind == "chessboard":
            out = {}
            for r in range(self.rows):
                for c in range(self.cols):
                    xyz = np.array([c * self.square_m, r * self.square_m, 0.0])
                    out[f"C{r * self.cols + c:03d}"] = xyz
            return out
        if self.kind == "aprilgrid":
            out = {}
            for r in range(2 * self.rows):
                for c in range(2 * self.cols):
                    x = (c // 2) * self.square_m + (c % 2) * self.marker_m
                    y = (r // 2) * self.square_m + (r % 2) * self.marker_m
                    out[f"C{r * 2 * self.cols + c:03d}"] = np.array([x, y, 0.0])
            return out
        if self.kind == "charuco":
            pts = np.asarray(self.charuco_board().getChessboardCorners(), dtype=float)
            # OpenCV stores float32: snap to the exact multiples of the square size.
            grid = np.round(pts[:, :2] / self.square_m) * self.square_m
            return {f"C{i:03d}": np.array([g[0], g[1], 0.0]) for i, g in enumerate(grid)}
        return {}

    def corner_count(self) -> int:
        """Number of corner targets on the board (0 for ``"aruco"``)."""
        if self.kind == "chessboard":
            return self.cols * self.rows
        if self.kind == "charuco":
            return (self.cols - 1) * (self.rows - 1)
        if self.kind == "aprilgrid":
            return 4 * self.cols * self.rows
        return 0


# --------------------------------------------------------------------------------------
# Kalibr target files
# --------------------------------------------------------------------------------------


def _flat_yaml(path: str) -> dict[str, str]:
    """The ``key: value`` lines of a flat YAML mapping (Kalibr's target files).

    Comments (``#`` to the end of the line) and blank lines are skipped; values keep
    their text with surrounding quotes removed. Nested mappings and lists are refused.
    """
    out: dict[str, str] = {}
    with open(path, encoding="utf-8") as fh:
        for lineno, raw in enumerate(fh, start=1):
            line = raw.split("#", 1)[0].rstrip()
            if not line.strip() or line.strip() in ("---", "..."):
                continue
            if line[0].isspace() or ":" not in line or line.lstrip().startswith("-"):
                raise DatasetError(
                    f"{path}:{lineno}: expected a flat 'key: value' line as in Kalibr's "
                    f"target files, got {raw.strip()!r}"
                )
            key, value = (x.strip() for x in line.split(":", 1))
            if len(value) >= 2 and value[0] == value[-1] and value[0] in "'\"":
                value = value[1:-1]
            if key in out:
                raise DatasetError(f"{path}:{lineno}: key {key!r} given twice")
            out[key] = value
    return out


def read_kalibr_target(path: str) -> BoardSpec:
    """Read a Kalibr target description (``target.yaml``).

    Supported (Kalibr wiki, "Calibration targets"):

    ``target_type: aprilgrid``
        ``tagCols``, ``tagRows`` (tags), ``tagSize`` (tag side in metres, edge to edge
        of the black border), ``tagSpacing`` (gap between tags over ``tagSize``).
        Tags of the tag36h11 family with Kalibr's 2-cell black border; target ids and
        board coordinates as Kalibr numbers them (:meth:`BoardSpec.aprilgrid_corner_ids`:
        ``"C{k:03d}"`` for Kalibr's grid point ``k``; board frame x right, y up the
        printed target, origin at the lower left corner of tag 0, metres).
    ``target_type: checkerboard``
        ``targetCols``, ``targetRows`` (inner corners along x / y), ``rowSpacingMeters``,
        ``colSpacingMeters`` (square sides, which must be equal here): the chessboard
        ``chessboard:COLSxROWS:SQUARE`` (ids ``C{r * COLS + c:03d}``, as Kalibr's
        ``r * cols + c``).

    Parameters
    ----------
    path : str
        The YAML file.

    Returns
    -------
    BoardSpec

    Raises
    ------
    DatasetError
        When the file is not a flat mapping, a key is missing or a value is malformed;
        the message names the file and the key.
    OptionsError
        For target types this package does not detect (``circlegrid``) and rectangular
        checkerboard squares.
    """
    keys = _flat_yaml(path)

    def get(name: str, kind: type):
        if name not in keys:
            raise DatasetError(f"{path}: Kalibr target file without {name!r}")
        try:
            value = kind(keys[name])
        except ValueError:
            what = "an integer" if kind is int else "a number"
            raise DatasetError(f"{path}: {name}: {keys[name]!r} is not {what}") from None
        if not (np.isfinite(value) and value > 0):
            raise DatasetError(f"{path}: {name}: {keys[name]!r} must be positive")
        return value

    kind = keys.get("target_type", "").strip().lower()
    if kind == "aprilgrid":
        return BoardSpec.aprilgrid(
            get("tagCols", int),
            get("tagRows", int),
            get("tagSize", float),
            get("tagSpacing", float),
            text=f"{path} (aprilgrid {keys['tagCols']}x{keys['tagRows']}, tagSize "
            f"{keys['tagSize']} m, tagSpacing {keys['tagSpacing']})",
        )
    if kind == "checkerboard":
        cols, rows = get("targetCols", int), get("targetRows", int)
        dx, dy = get("colSpacingMeters", float), get("rowSpacingMeters", float)
        if abs(dx - dy) > 1e-9 * max(dx, dy):
            raise OptionsError(
                f"{path}: colSpacingMeters {dx} and rowSpacingMeters {dy} differ: only square "
                "chessboard squares are supported"
            )
        return BoardSpec.parse(f"chessboard:{cols}x{rows}:{dx!r}")
    if "target_type" not in keys:
        raise DatasetError(f"{path}: Kalibr target file without 'target_type'")
    raise OptionsError(
        f"{path}: target_type {keys['target_type']!r} is not supported: expected "
        "'aprilgrid' or 'checkerboard'"
    )


# --------------------------------------------------------------------------------------
# Single-image detection
# --------------------------------------------------------------------------------------


def _to_gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if img.dtype != np.uint8:
        lo, hi = float(np.nanmin(img)), float(np.nanmax(img))
        scale = 255.0 / (hi - lo) if hi > lo else 1.0
        img = np.clip((img.astype(np.float64) - lo) * scale, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img)


def _min_spacing(grid: np.ndarray) -> float:
    """Smallest distance between neighbouring corners of a (rows, cols, 2) grid."""
    d = []
    if grid.shape[1] > 1:
        d.append(np.linalg.norm(np.diff(grid, axis=1), axis=2).ravel())
    if grid.shape[0] > 1:
        d.append(np.linalg.norm(np.diff(grid, axis=0), axis=2).ravel())
    return float(np.min(np.concatenate(d))) if d else 10.0


def _subpix(gray: np.ndarray, pts: np.ndarray, half_win: int) -> np.ndarray:
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    p = np.ascontiguousarray(pts.reshape(-1, 1, 2).astype(np.float32))
    p = cv2.cornerSubPix(gray, p, (half_win, half_win), (-1, -1), crit)
    return p.reshape(-1, 2).astype(np.float64)


def _saddle_refine(
    gray: np.ndarray,
    pts: np.ndarray,
    radius: int = 2,
    sigma: float = 1.0,
    max_move: float = 3.0,
    return_mask: bool = False,
):
    """Polish X-corner positions by fitting a quadratic saddle to the smoothed image.

    The image is smoothed with a Gaussian (``sigma`` pixels); around each estimate a
    quadratic ``f = a x^2 + b xy + c y^2 + d x + e y + g`` is fitted (Gaussian-weighted
    least squares over a ``(2 radius + 1)^2`` grid resampled at the estimate) and the
    estimate moves to its stationary point; repeated until the step is below 1e-4 px.
    Unlike ``cornerSubPix`` this needs only a few pixels around the corner, so curved
    fisheye edges and nearby ChArUco markers do not bias it. Points that are not saddles
    (``4ac - b^2 >= 0``) or that would move more than ``max_move`` pixels keep their input
    position.

    Parameters
    ----------
    gray : ndarray, shape (H, W)
        Grey image.
    pts : ndarray, shape (N, 2)
        Initial positions ``(u, v)`` in pixels.

    Returns
    -------
    ndarray, shape (N, 2)
        Refined positions in pixels.
    ndarray of bool, shape (N,)
        Only with ``return_mask``: True where the saddle fit succeeded.
    """
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return (pts.copy(), np.zeros(0, dtype=bool)) if return_mask else pts.copy()
    g = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), sigma)
    off = np.arange(-radius, radius + 1, dtype=np.float64)
    xx, yy = (a.ravel() for a in np.meshgrid(off, off))
    design = np.stack([xx * xx, xx * yy, yy * yy, xx, yy, np.ones_like(xx)], axis=1)
    w = np.exp(-(xx**2 + yy**2) / (2.0 * radius**2))
    solver = np.linalg.pinv(design * w[:, None])  # (6, K)
    grid = np.stack([xx, yy], axis=1)
    out = pts.copy()
    good = np.ones(len(pts), dtype=bool)
    for _ in range(20):
        m = (out[:, None, :] + grid[None]).reshape(-1, 1, 2).astype(np.float32)
        vals = cv2.remap(g, m[..., 0], m[..., 1], cv2.INTER_CUBIC, None, cv2.BORDER_REPLICATE)
        vals = vals.reshape(len(out), -1).astype(np.float64)
        a, b, c, d, e, _ = solver @ (vals * w[None]).T
        det = 4.0 * a * c - b * b
        good &= det < 0
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.stack([(b * e - 2.0 * c * d) / det, (b * d - 2.0 * a * e) / det], axis=1)
        step = np.where(np.isfinite(step) & good[:, None], np.clip(step, -0.5, 0.5), 0.0)
        out += step
        if np.max(np.abs(step)) < 1e-4:
            break
    bad = ~good | (np.linalg.norm(out - pts, axis=1) > max_move)
    out[bad] = pts[bad]
    if return_mask:
        return out, ~bad
    return out


def _sample(gray: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``gray`` at pixel positions ``uv`` (N, 2)."""
    m = np.ascontiguousarray(uv.reshape(-1, 1, 2).astype(np.float32))
    vals = cv2.remap(
        gray.astype(np.float32), m[..., 0], m[..., 1], cv2.INTER_LINEAR, cv2.BORDER_REPLICATE
    )
    return vals.ravel().astype(np.float64)


def _orient_chessboard(gray: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Apply the consistent-ordering rule (module docstring) to a (rows, cols, 2) grid."""
    rows, cols = grid.shape[:2]
    # (1) right-handed: image of board x cross image of board y > 0 (u right, v down).
    ex = grid[:, -1].mean(axis=0) - grid[:, 0].mean(axis=0)
    ey = grid[-1].mean(axis=0) - grid[0].mean(axis=0)
    if ex[0] * ey[1] - ex[1] * ey[0] < 0:
        grid = grid[:, ::-1]
    candidates = [grid, grid[::-1, ::-1]]
    if rows == cols:  # 90 degree rotations keep the handedness
        rot = np.transpose(grid, (1, 0, 2))[:, ::-1]
        candidates += [rot, rot[::-1, ::-1]]
    if (rows + cols) % 2 == 1:
        # (2) colour breaks the symmetry: C000-C001-C010-C011 must enclose a dark square.
        def dark_first(g: np.ndarray) -> float:
            c_in = g[:2, :2].reshape(-1, 2).mean(axis=0)  # square (1,1): dark
            c_nb = g[:2, 1:3].reshape(-1, 2).mean(axis=0)  # square (1,2): light
            return float(np.diff(_sample(gray, np.array([c_in, c_nb])))[0])

        return max(candidates, key=dark_first)
    # (3) symmetric: C000 nearest the image's top-left corner.
    return min(candidates, key=lambda g: float(g[0, 0].sum()))


def _detect_chessboard(
    gray: np.ndarray, board: BoardSpec, attempts: int, check_size: bool = True
) -> dict[str, np.ndarray]:
    size = (board.cols, board.rows)
    corners = None
    flags_sb = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
    # findChessboardCornersSB draws random numbers: seed it for reproducible results and
    # retry with other seeds and with image normalisation (on the real fisheye test
    # images single calls fail on some images that later attempts find).
    for attempt in range(max(1, int(attempts))):
        for extra in (0, cv2.CALIB_CB_NORMALIZE_IMAGE):
            cv2.setRNGSeed(attempt)
            ok, c = cv2.findChessboardCornersSB(gray, size, flags=flags_sb | extra)
            if ok and c is not None:
                corners = np.asarray(c, dtype=np.float64).reshape(-1, 2)
                break
        if corners is not None:
            break
    else:
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        ok, c = cv2.findChessboardCorners(gray, size, flags=flags)
        if ok and c is not None:
            c = np.asarray(c, dtype=np.float64).reshape(board.rows, board.cols, 2)
            half = int(np.clip(0.3 * _min_spacing(c), 2, 11))
            corners = _subpix(gray, c.reshape(-1, 2), half)
    if corners is None or len(corners) != board.cols * board.rows:
        return {}
    corners, good = _refine_grid_corners(gray, corners.reshape(board.rows, board.cols, 2))
    if check_size:
        beyond = _grid_continuation(gray, corners)
        if beyond:
            raise TargetMismatchError(
                f"the chessboard pattern continues beyond the described {board.cols}x"
                f"{board.rows} grid ({'; '.join(beyond)}): the board is larger than "
                f"{board.text!r} says; give its full size (inner corners, COLSxROWS), "
                "otherwise the corners would be labelled wrongly"
            )
    # orient with every corner (the grid must be complete), then leave out the failed ones
    order = np.arange(board.rows * board.cols, dtype=float).reshape(board.rows, board.cols)
    both = np.concatenate([corners, order[..., None]], axis=2)
    grid = _orient_chessboard(gray, both[..., :2])
    if not np.array_equal(grid, both[..., :2]):
        for cand in _grid_symmetries(both):
            if np.array_equal(cand[..., :2], grid):
                both = cand
                break
    flat = both.reshape(-1, 3)
    good_flat = good.ravel()[flat[:, 2].astype(int)]
    return {f"C{i:03d}": flat[i, :2].copy() for i in range(len(flat)) if good_flat[i]}


def _grid_symmetries(grid: np.ndarray) -> list[np.ndarray]:
    """The reorderings of a (rows, cols, k) grid that :func:`_orient_chessboard` can pick."""
    out = []
    for g in (grid, grid[:, ::-1]):
        rot = np.transpose(g, (1, 0, 2))[:, ::-1]
        out += [g, g[::-1, ::-1], rot, rot[::-1, ::-1]]
    return out


def _refine_grid_corners(gray: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Refine a detected (rows, cols, 2) corner grid; flag the corners that are not saddles.

    Every corner is polished by the saddle fit (:func:`_saddle_refine`). Where that fit
    fails (the detector's estimate is not at a saddle: seen 3-4 px off on real fisheye
    images), the corner is searched again with ``cv2.cornerSubPix`` in a window of 0.3
    times its distance to the nearest neighbouring corner, then polished; it is flagged
    when that fails too or :func:`saddle_score` stays below 0.5.

    Returns
    -------
    grid : ndarray, shape (rows, cols, 2)
        Refined positions (px).
    good : ndarray of bool, shape (rows, cols)
    """
    rows, cols = grid.shape[:2]
    pts = grid.reshape(-1, 2)
    refined, ok = _saddle_refine(gray, pts, return_mask=True)
    if not np.all(ok):
        spacing = np.full((rows, cols), np.inf)
        for axis in (0, 1):
            d = np.linalg.norm(np.diff(grid, axis=axis), axis=2)
            lo = [slice(None)] * 2
            hi = [slice(None)] * 2
            lo[axis], hi[axis] = slice(0, -1), slice(1, None)
            spacing[tuple(lo)] = np.minimum(spacing[tuple(lo)], d)
            spacing[tuple(hi)] = np.minimum(spacing[tuple(hi)], d)
        spacing = spacing.ravel()
        for i in np.flatnonzero(~ok):
            half = int(np.clip(0.3 * spacing[i], 2, 11)) if np.isfinite(spacing[i]) else 3
            start = _subpix(gray, pts[i : i + 1], half)
            q, ok_i = _saddle_refine(gray, start, return_mask=True)
            score, _ = saddle_score(gray, q, radius=max(2.0, 0.25 * spacing[i]))
            if ok_i[0] and score[0] >= 0.5:
                refined[i], ok[i] = q[0], True
    return refined.reshape(rows, cols, 2), ok.reshape(rows, cols)


def _grid_continuation(gray: np.ndarray, grid: np.ndarray) -> list[str]:
    """Where a detected chessboard grid is part of a larger pattern.

    A grid of the described size found on a larger board is a sub-grid: either the
    pattern continues beyond one of its borders, or (under strong distortion, seen on
    real fisheye images) the detector skipped whole rows or columns, so that a board
    corner lies between two "neighbouring" grid corners. Both are tested with the
    saddle test: candidates are (1) the points one square beyond each border,
    predicted by a homography fitted to the nearest block of up to 3x3 grid corners
    (exact under perspective, close under local lens distortion) and (2) the
    midpoints between neighbouring grid corners. Each candidate is searched with
    ``cv2.cornerSubPix`` (half window 0.25 local spacing) from it and from four starts
    0.2 spacing around it, each polished by the saddle fit; it counts as a board
    corner when one of them succeeds, stays within 0.4 local spacing of the
    candidate and 0.35 spacing away from every grid corner, and
    :func:`saddle_score` (ring radius 0.25 spacing) is at least 0.5 with 8 grey levels
    of contrast. On a printed board the points beyond a border lie on the board's
    outer edge (a square's corner against the white margin, score about 0) and the
    midpoints on square edges (score about 0). (3) The grid's cells must each be one
    square: the ring around a cell's centre (radius 0.2 of its shortest side) must be
    uniform; a ring contrast over 0.35 times the grid corners' median marks a cell that
    holds edges or corners of several squares (the detector jumped over squares).

    Parameters
    ----------
    gray : ndarray, shape (H, W), uint8
        Grey image.
    grid : ndarray, shape (rows, cols, 2)
        Detected corners ``(u, v)`` in pixels, in grid order.

    Returns
    -------
    list of str
        One description per group of candidates (a border, or the gap between two grid
        rows / columns) where at least 2 candidates and at least half of those inside
        the image are board corners, e.g. ``"beyond the last row (5 of 6 points)"``,
        and a line when at least 2 and a quarter of the cells hold several squares.
        Empty when the grid looks complete.
    """
    rows, cols = grid.shape[:2]
    h, w = gray.shape[:2]

    def beyond(r_out: int | None, c_out: int | None) -> np.ndarray:
        """Predicted corners of the grid line one square beyond a border.

        ``r_out`` (-1 or rows) for a row beyond the first/last row, else ``c_out``.
        Each point from a homography fitted to the nearest block of up to 3x3 grid
        corners next to it: exact under perspective, close under local distortion.
        """
        n = cols if r_out is not None else rows
        out = np.empty((n, 2))
        for k in range(n):
            lo_k = int(np.clip(k - 1, 0, max(n - 3, 0)))
            ks = np.arange(lo_k, min(lo_k + 3, n))
            if r_out is not None:
                rs = np.arange(0, min(3, rows)) if r_out < 0 else np.arange(max(rows - 3, 0), rows)
                rr, cc = np.meshgrid(rs, ks, indexing="ij")
                target = (k, r_out)
            else:
                cs = np.arange(0, min(3, cols)) if c_out < 0 else np.arange(max(cols - 3, 0), cols)
                rr, cc = np.meshgrid(ks, cs, indexing="ij")
                target = (c_out, k)
            src = np.stack([cc.ravel(), rr.ravel()], axis=1).astype(np.float64)
            dst = grid[rr.ravel(), cc.ravel()]
            hom, _ = cv2.findHomography(src, dst, 0)
            if hom is None:
                out[k] = np.nan
                continue
            q = hom @ np.array([target[0], target[1], 1.0])
            out[k] = q[:2] / q[2] if abs(q[2]) > 1e-12 else np.nan
        return out

    groups: list[tuple[str, np.ndarray, np.ndarray]] = []
    sp_col = np.linalg.norm(np.diff(grid, axis=0), axis=2)  # (rows-1, cols): along a column
    sp_row = np.linalg.norm(np.diff(grid, axis=1), axis=2)  # (rows, cols-1): along a row
    groups.append(("beyond the first row", beyond(-1, None), sp_col[0]))
    groups.append(("beyond the last row", beyond(rows, None), sp_col[-1]))
    groups.append(("beyond the first column", beyond(None, -1), sp_row[:, 0]))
    groups.append(("beyond the last column", beyond(None, cols), sp_row[:, -1]))
    for i in range(rows - 1):
        groups.append(
            (f"between grid rows {i} and {i + 1}", 0.5 * (grid[i] + grid[i + 1]), sp_col[i])
        )
    for j in range(cols - 1):
        groups.append(
            (
                f"between grid columns {j} and {j + 1}",
                0.5 * (grid[:, j] + grid[:, j + 1]),
                sp_row[:, j],
            )
        )
    corners = grid.reshape(-1, 2)
    found = []
    for name, cand, spacing in groups:
        spacing = np.asarray(spacing, dtype=np.float64)
        margin = np.maximum(0.3 * spacing, 4.0)
        inside = (
            np.all(np.isfinite(cand), axis=1)
            & (spacing >= 8.0)
            & (cand[:, 0] >= margin)
            & (cand[:, 0] <= w - 1 - margin)
            & (cand[:, 1] >= margin)
            & (cand[:, 1] <= h - 1 - margin)
        )
        n_in = int(np.count_nonzero(inside))
        if n_in < 2:
            continue
        hits = 0
        for p, s in zip(cand[inside], spacing[inside]):
            # several starts around the prediction (the distortion bends the lines)
            offs = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]], float) * 0.2 * s
            starts = _subpix(gray, p[None] + offs, int(np.clip(0.25 * s, 2, 15)))
            q, ok = _saddle_refine(gray, starts, return_mask=True, max_move=0.4 * s)
            near = (
                ok
                & (np.linalg.norm(q - p, axis=1) <= 0.4 * s)
                & (np.min(np.linalg.norm(q[:, None] - corners[None], axis=2), axis=1) >= 0.35 * s)
            )
            if not np.any(near):
                continue
            score, contrast = saddle_score(gray, q[near], radius=max(2.0, 0.25 * s))
            if np.any((score >= 0.5) & (contrast >= 8.0)):
                hits += 1
        if hits >= 2 and 2 * hits >= n_in:
            found.append(f"{name} ({hits} of {n_in} points)")
    if rows >= 2 and cols >= 2:
        # (3) every cell one square: uniform around its centre (ring contrast well below
        # the grid corners')
        _, corner_contrast = saddle_score(gray, corners, radius=3.0)
        ref = float(np.median(corner_contrast))
        cells = 0.25 * (grid[:-1, :-1] + grid[1:, :-1] + grid[:-1, 1:] + grid[1:, 1:])
        side = np.minimum(
            np.minimum(sp_row[:-1], sp_row[1:]), np.minimum(sp_col[:, :-1], sp_col[:, 1:])
        )
        ok = (side >= 8.0).ravel()
        if np.count_nonzero(ok) >= 2 and ref >= 8.0:
            centres = cells.reshape(-1, 2)[ok]
            radius = np.maximum(0.2 * side.ravel()[ok], 2.0)
            contrast = np.array(
                [saddle_score(gray, c[None], radius=r)[1][0] for c, r in zip(centres, radius)]
            )
            busy = int(np.count_nonzero(contrast > 0.35 * ref))
            if busy >= 2 and 4 * busy >= len(centres):
                found.append(f"{busy} of {len(centres)} grid cells hold more than one square")
    return found


def _aruco_parameters():
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.cornerRefinementWinSize = 5
    params.cornerRefinementMaxIterations = 100
    params.cornerRefinementMinAccuracy = 0.001
    return params


def _detect_charuco(gray: np.ndarray, board: BoardSpec) -> dict[str, np.ndarray]:
    cb = board.charuco_board()
    cparams = cv2.aruco.CharucoParameters()
    cparams.minMarkers = 1
    detector = cv2.aruco.CharucoDetector(cb, cparams, _aruco_parameters())
    ch_corners, ch_ids, _, marker_ids = detector.detectBoard(gray)
    if marker_ids is not None:
        known = set(np.asarray(cb.getIds()).ravel().tolist())
        foreign = sorted({int(i) for i in np.asarray(marker_ids).ravel()} - known)
        if len(foreign) >= 2:
            raise TargetMismatchError(
                f"ChArUco markers with ids {foreign} seen, but the described board "
                f"{board.text!r} has ids {min(known)}..{max(known)}: the board is larger "
                "(or another board is in view); give its full size in squares"
            )
    if ch_ids is None or ch_corners is None or len(ch_ids) == 0:
        return {}
    pts = np.asarray(ch_corners, dtype=np.float64).reshape(-1, 2)
    ids = np.asarray(ch_ids).ravel().astype(int)
    # OpenCV refines with a fixed cornerSubPix window that the markers and curved
    # fisheye edges bias (0.1-0.5 px on rendered boards): polish with a local saddle fit.
    # Corners whose fit fails are retried from a small-window cornerSubPix estimate and
    # dropped if they still fail (OpenCV's estimate is then often ~1 px off).
    refined, ok = _saddle_refine(gray, pts, return_mask=True)
    if not np.all(ok):
        retry, ok2 = _saddle_refine(gray, _subpix(gray, pts[~ok], 2), return_mask=True)
        refined[~ok] = retry
        ok[~ok] = ok2
        refined, ids = refined[ok], ids[ok]
    return {f"C{i:03d}": refined[k] for k, i in enumerate(ids)}


def _detect_aprilgrid(
    gray: np.ndarray, board: BoardSpec, grow: bool = True
) -> dict[str, np.ndarray]:
    """Kalibr AprilGrid: tag36h11 tags by ``cv2.aruco``, corners polished as saddles.

    The tags are found and decoded by ``cv2.aruco.ArucoDetector`` with the
    ``DICT_APRILTAG_36h11`` dictionary and a 2-cell black border (Kalibr prints its tags
    with ``blackTagBorder = 2``); each tag gives its 4 corners under Kalibr's point ids
    (:meth:`BoardSpec.aprilgrid_corner_ids`). On an AprilGrid every tag corner touches
    one of the small black squares in the gaps, so it is an X-corner: it is polished by
    the saddle fit (:func:`_saddle_refine`, a few pixels around the corner, unbiased by
    curved fisheye edges), retried from a small-window ``cv2.cornerSubPix`` estimate,
    and dropped if it still is not a saddle (as for ChArUco corners) or scores below
    0.75 on a 3 px ring (:func:`saddle_score`: a small square so narrow that the fit
    also sees its other corners). With ``grow`` the
    tags the decoder missed are then predicted from the layout and kept when their
    code is seen (:func:`_grow_aprilgrid`).

    Raises
    ------
    TargetMismatchError
        When the tags contradict the layout: two or more tags with ids the grid does not
        have (a larger grid), the same id twice (tags that are not the target's), or
        most neighbouring tags not where the layout puts them (:func:`_aprilgrid_layout_check`).
    """
    params = _aruco_parameters()
    params.markerBorderBits = 2
    params.perspectiveRemovePixelPerCell = 8
    detector = cv2.aruco.ArucoDetector(board.aruco_dictionary(), params)
    corners, ids, _ = detector.detectMarkers(gray)
    if ids is None or len(ids) == 0:
        return {}
    n_tags = board.cols * board.rows
    ids = np.asarray(ids).ravel().astype(int)
    quads = [np.asarray(q, dtype=np.float64).reshape(4, 2) for q in corners]
    foreign = sorted(int(i) for i in ids if i >= n_tags)
    if len(foreign) >= 2:
        raise TargetMismatchError(
            f"AprilGrid tags with ids {foreign} seen, but the described {board.cols}x"
            f"{board.rows} grid has ids 0..{n_tags - 1}: the grid is larger than "
            f"{board.text!r} says (or other tag36h11 tags are in view); give its full size"
        )
    keep = [k for k, i in enumerate(ids) if i < n_tags]
    ids = ids[keep]
    quads = [quads[k] for k in keep]
    uniq, counts = np.unique(ids, return_counts=True)
    if np.any(counts > 1):
        raise TargetMismatchError(
            f"AprilGrid tag ids {uniq[counts > 1].tolist()} seen twice: tags that are not "
            "part of the target are in view (hide them), or two targets are"
        )
    drop = _aprilgrid_layout_check(board, ids, quads)
    keep = [k for k, i in enumerate(ids) if int(i) not in drop]
    ids, quads = ids[keep], [quads[k] for k in keep]
    if not len(ids):
        return {}
    keys = [k for i in ids for k in board.aprilgrid_corner_ids(int(i))]
    pts = np.concatenate(quads, axis=0)
    refined, ok = _saddle_refine(gray, pts, return_mask=True)
    if not np.all(ok):
        retry, ok2 = _saddle_refine(gray, _subpix(gray, pts[~ok], 2), return_mask=True)
        refined[~ok] = retry
        ok[~ok] = ok2
    out = {k: refined[j] for j, k in enumerate(keys) if ok[j]}
    whole = {
        int(i): refined[4 * n : 4 * n + 4]
        for n, i in enumerate(ids)
        if np.all(ok[4 * n : 4 * n + 4])
    }
    if grow:
        for i, q in _grow_aprilgrid(gray, board, whole).items():
            out.update(zip(board.aprilgrid_corner_ids(i), q))
            whole[i] = q
    # on strongly foreshortened tags the small squares are 2-3 px wide and the saddle
    # fit also sees their other corners (0.2-0.5 px bias): such corners are no clean
    # saddle on a 3 px ring (score below 0.75; clean ones score 0.9 and more)
    if out:
        keys = list(out)
        score, _ = saddle_score(gray, np.array([out[k] for k in keys]), radius=3.0)
        out = {k: out[k] for k, sc in zip(keys, score) if sc >= 0.75}
    return out


def _grow_aprilgrid(
    gray: np.ndarray, board: BoardSpec, tags: dict[int, np.ndarray], rounds: int = 12
) -> dict[int, np.ndarray]:
    """Tags the decoder missed, predicted from the layout and verified by their code.

    Under a fisheye the decoder misses most tags away from the centre (bent borders,
    cells of 2-4 px). The layout says where they are. For a missing tag next to a found
    one (same row or column of tags), its two corners facing the found tag (one small
    square away) are predicted by the homography of the found tag's corners; its two
    far corners by a quadratic along each lattice line through the found tag's two
    corners and the refined near corner (the bend of the lens to second order: a
    homography from one tag misses them by 6-15 px on the rendered 200 degree views,
    more than the distance to the next saddle). Each prediction is polished by
    ``cv2.cornerSubPix`` (half window 0.2 gap) and the saddle fit and must stay within
    0.35 gap of it (the next saddle, across the small square, is one gap away). The tag
    is kept only if its 10 x 10 cells, sampled through the homography of its refined
    corners, show the expected code: correlation with the tag's pattern at least 0.8
    and at most 2 of its 100 cells on the wrong side of the mid grey. Repeated while
    tags are added (``rounds`` at most).

    Parameters
    ----------
    gray : ndarray, shape (H, W), uint8
    board : BoardSpec
        AprilGrid.
    tags : dict of int to ndarray, shape (4, 2)
        Found tags: id -> refined corners in OpenCV's order (pixels).

    Returns
    -------
    dict of int to ndarray, shape (4, 2)
        The added tags, same form.
    """
    points = board.object_points_m()
    dictionary = board.aruco_dictionary()
    h, w = gray.shape
    n2 = 2 * board.cols  # lattice columns
    found = dict(tags)
    added: dict[int, np.ndarray] = {}
    cells = 10
    centres = (np.arange(cells) + 0.5) / cells
    cu, cv_ = np.meshgrid(centres, centres)
    unit = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], np.float32)

    def lattice(key: str) -> tuple[int, int]:
        return divmod(int(key[1:]), n2)

    def polish(pred: np.ndarray, gap: float) -> np.ndarray | None:
        if np.any(~np.isfinite(pred)) or np.any((pred < 3) | (pred > np.array([w - 4, h - 4]))):
            return None
        q = _subpix(gray, pred, int(np.clip(0.2 * gap, 2, 11)))
        q, ok = _saddle_refine(gray, q, return_mask=True)
        if not np.all(ok) or np.max(np.linalg.norm(q - pred, axis=1)) > 0.35 * gap:
            return None
        return q

    def attempt(m: int, n: int) -> np.ndarray | None:
        ids_m, ids_n = board.aprilgrid_corner_ids(m), board.aprilgrid_corner_ids(n)
        where_n = dict(zip(ids_n, found[n]))
        hom, _ = cv2.findHomography(np.array([points[k][:2] for k in ids_n]), found[n], 0)
        if hom is None:
            return None
        horizontal = m // board.cols == n // board.cols
        # near corners: on the lattice line next to n
        lm = [lattice(k) for k in ids_m]
        axis = 1 if horizontal else 0
        n_lines = {lattice(k)[axis] for k in ids_n}
        near_line = min({p[axis] for p in lm}, key=lambda x: min(abs(x - y) for y in n_lines))
        near = [i for i, p in enumerate(lm) if p[axis] == near_line]
        far = [i for i in range(4) if i not in near]
        xy_m = np.array([points[k][:2] for k in ids_m])
        pred = cv2.perspectiveTransform(xy_m[None], hom)[0]
        side = float(np.mean(np.linalg.norm(pred - np.roll(pred, 1, axis=0), axis=1)))
        gap = board.spacing * side
        if gap < 3.0:
            return None
        q_near = polish(pred[near], gap)
        if q_near is None:
            return None
        out = np.empty((4, 2))
        out[near] = q_near
        for i in far:
            # the lattice line through corner i: n's two corners on it, m's near corner
            other = 1 - axis
            line = lm[i][other]
            on_n = [k for k in ids_n if lattice(k)[other] == line]
            on_m = [near[j] for j in range(2) if lm[near[j]][other] == line]
            if len(on_n) != 2 or len(on_m) != 1:
                return None
            s = np.array([points[k][0 if horizontal else 1] for k in on_n])
            s = np.append(s, xy_m[on_m[0]][0 if horizontal else 1])
            uv = np.array([where_n[k] for k in on_n] + [out[on_m[0]]])
            coef = np.polyfit(s, uv, 2)
            s_far = xy_m[i][0 if horizontal else 1]
            out[i] = coef[0] * s_far**2 + coef[1] * s_far + coef[2]
        q_far = polish(out[far], gap)
        if q_far is None:
            return None
        out[far] = q_far
        # the code, sampled through the refined corners' homography
        h_tag = cv2.getPerspectiveTransform(unit, out.astype(np.float32))
        uv = cv2.perspectiveTransform(
            np.stack([cu.ravel(), cv_.ravel()], axis=1)[None].astype(np.float64), h_tag
        )[0]
        vals = _sample(gray, uv)
        bits = cv2.aruco.generateImageMarker(dictionary, m, cells, borderBits=2)
        expect = (np.asarray(bits).ravel() > 127).astype(np.float64)
        if vals.std() == 0:
            return None
        corr = float(np.corrcoef(vals, expect)[0, 1])
        mid = 0.5 * (vals[expect > 0].mean() + vals[expect == 0].mean())
        wrong = int(np.count_nonzero((vals > mid) != (expect > 0)))
        return out if corr >= 0.8 and wrong <= 2 else None

    for _ in range(rounds):
        new = {}
        for m in range(board.cols * board.rows):
            if m in found:
                continue
            r, c = divmod(m, board.cols)
            for rr, cc in ((r, c - 1), (r, c + 1), (r - 1, c), (r + 1, c)):
                n = rr * board.cols + cc
                if 0 <= rr < board.rows and 0 <= cc < board.cols and n in found:
                    q = attempt(m, n)
                    if q is not None:
                        new[m] = q
                        break
        if not new:
            break
        found.update(new)
        added.update(new)
    return added


def _aprilgrid_layout_check(board: BoardSpec, ids: np.ndarray, quads: list[np.ndarray]) -> set[int]:
    """Tags whose corners contradict their neighbours; raise when most tags do.

    For every pair of detected tags that are neighbours in the layout (same tag row,
    next column; or next row), the homography from the board coordinates of one tag's
    corners to their image positions predicts the other tag's corners; a pair is
    inconsistent when the prediction misses by more than 0.3 of the tag's image side
    (under perspective it is exact, and the lens distortion over one tag pitch stays
    well below that). With at least 2 pairs and more than half inconsistent the layout
    (tag columns, rows or spacing) does not describe the board: raise. Otherwise a tag
    whose every checked pair is inconsistent has a corner off (seen on rendered fisheye
    views: a quadrilateral corner on the neighbouring small square, 20 px away) and is
    returned for dropping.

    Returns
    -------
    set of int
        Ids of the tags to leave out.
    """
    points = board.object_points_m()
    where = {int(i): q for i, q in zip(ids, quads)}
    bad = total = 0
    pairs: dict[int, list[bool]] = {}
    for i, q in where.items():
        src = np.array([points[k][:2] for k in board.aprilgrid_corner_ids(i)])
        hom, _ = cv2.findHomography(src, q, 0)
        if hom is None:
            continue
        side = float(np.mean(np.linalg.norm(q - np.roll(q, 1, axis=0), axis=1)))
        for j in (i + 1, i + board.cols):
            if j not in where or (j == i + 1 and j % board.cols == 0):
                continue
            other = np.array([points[k][:2] for k in board.aprilgrid_corner_ids(j)])
            pred = cv2.perspectiveTransform(other[None], hom)[0]
            total += 1
            off = bool(np.max(np.linalg.norm(pred - where[j], axis=1)) > 0.3 * side)
            bad += off
            pairs.setdefault(i, []).append(off)
            pairs.setdefault(j, []).append(off)
    if total >= 2 and 2 * bad > total:
        raise TargetMismatchError(
            f"AprilGrid tags are not where the {board.cols}x{board.rows} layout of "
            f"{board.text!r} puts them ({bad} of {total} neighbouring tag pairs off by more "
            "than 0.3 tag): check tagCols, tagRows and tagSpacing"
        )
    return {i for i, offs in pairs.items() if all(offs)}


def _detect_aruco(gray: np.ndarray, board: BoardSpec) -> dict[str, np.ndarray]:
    """ArUco markers: ``cv2.aruco`` detection, then a photometric fit of each marker.

    ``cv2.aruco`` finds and decodes the markers; its corners (``CORNER_REFINE_SUBPIX``)
    are off by 0.5 px RMS and up to 3 px on blurred, fisheye-curved outlines, and the
    centre of a marker is not the intersection of its image diagonals under lens
    distortion (even with the true corners: 1.0 px RMS, 3.5 px at worst on the rendered
    200 degree fisheye views of ``tests/test_aruco_room.py``). Each marker is
    therefore refined by :func:`_fit_aruco_marker`, which fits the marker's known
    black/white cell pattern to the pixels and maps the corners and the centre through
    the fitted (distortion-aware) mapping. A marker whose fit fails (in practice:
    markers below about 2.5 px per code cell) is left out, like ChArUco corners whose
    saddle fit fails.
    """
    dictionary = board.aruco_dictionary()
    params = _aruco_parameters()
    # Read the bits from 8 px per cell instead of 4 after perspective removal: decodes
    # markers whose cells the fisheye bends (on rendered 200 degree views, 10 more of
    # 175 markers seen near 90 degrees).
    params.perspectiveRemovePixelPerCell = 8
    detector = cv2.aruco.ArucoDetector(dictionary, params)
    corners, ids, _ = detector.detectMarkers(gray)
    out: dict[str, np.ndarray] = {}
    if ids is None:
        return out
    image = np.asarray(gray, dtype=np.float64)
    cells = int(dictionary.markerSize) + 2
    for quad, mid in zip(corners, np.asarray(ids).ravel(), strict=True):
        q = np.asarray(quad, dtype=np.float64).reshape(4, 2)
        key = f"M{int(mid)}"
        if key in out:  # the same id twice in one image is ambiguous: drop both
            out[key] = np.array([np.nan, np.nan])
            continue
        bits = cv2.aruco.generateImageMarker(dictionary, int(mid), cells, borderBits=1)
        fit = _fit_aruco_marker(image, q, (np.asarray(bits) > 127).astype(np.float64))
        if fit is None:
            continue  # OpenCV's corners alone are 0.3-3 px off: leave the marker out
        out[key] = fit[1]
        for k in range(4):
            out[f"{key}_{k}"] = fit[0][k].copy()
    bad = {k.split("_")[0] for k, v in out.items() if not np.all(np.isfinite(v))}
    return {k: v for k, v in out.items() if k.split("_")[0] not in bad}


def _normal_cdf(z: np.ndarray, gauss: np.ndarray) -> np.ndarray:
    """Standard normal CDF at ``z`` given ``gauss = exp(-z^2 / 2)``.

    Abramowitz & Stegun 7.1.26 for ``erf`` (absolute error below 1e-7).
    """
    t = 1.0 / (1.0 + 0.3275911 / np.sqrt(2.0) * np.abs(z))
    poly = t * (
        0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429)))
    )
    return 0.5 + np.sign(z) * (0.5 - 0.5 * poly * gauss)


def _cell_occupancy(
    x: np.ndarray, sigma: np.ndarray, lo: float, n: int, orders: int
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Blurred indicators of the cells ``[lo + i, lo + i + 1)``, ``i = 0 .. n - 1``.

    Terms of Mehler's expansion of the bivariate normal CDF,
    ``Phi2(a, b; rho) = sum_k rho^k / k! g_k(a) g_k(b)`` with ``g_0 = Phi`` and
    ``g_k = He_{k-1} phi`` (``He`` the probabilists' Hermite polynomials): the
    probability that a point blurred by a correlated Gaussian falls in cell ``(i, j)``
    is ``sum_k rho^k / k! occ_k[i](x) occ_k[j](y)``, each term separable.

    Parameters
    ----------
    x : ndarray, shape (N,)
        Positions along one marker axis (code cells).
    sigma : ndarray, shape (N,)
        Blur at each position along that axis (code cells).
    lo : float
        Left edge of the first cell.
    n : int
        Number of cells.
    orders : int
        Highest order ``k`` of the expansion.

    Returns
    -------
    list of (occ, d_x, d_log_sigma), one per order ``k = 0 .. orders``
        Each an ndarray of shape (N, n): ``g_k`` differenced over each cell's edges
        (order 0: the cell's occupancy in [0, 1]), and its derivatives with respect to
        ``x`` and ``log(sigma)``.
    """
    sig = np.asarray(sigma, dtype=np.float64)[:, None]
    z = (lo + np.arange(n + 1, dtype=np.float64)[None, :] - x[:, None]) / sig
    gauss = np.exp(-0.5 * z * z)
    phi = gauss / np.sqrt(2.0 * np.pi)
    he = [np.ones_like(z), z]  # He_0, He_1, ...
    for k in range(2, orders + 2):
        he.append(z * he[-1] - (k - 1) * he[-2])
    g = [_normal_cdf(z, gauss)] + [he[k - 1] * phi for k in range(1, orders + 2)]
    out = []
    for k in range(orders + 1):
        dg = g[1] if k == 0 else -g[k + 1]  # d g_k / dz
        out.append(
            (
                g[k][:, 1:] - g[k][:, :-1],
                -(dg[:, 1:] - dg[:, :-1]) / sig,  # dz/dx = -1/sigma
                -((z * dg)[:, 1:] - (z * dg)[:, :-1]),  # dz/dlog(sigma) = -z
            )
        )
    return out


#: damping of the marker fit: x4 on a worse step, /3 on a better one, up to 1e8
_MARKER_DAMPING = Damping(
    initial=1e-3,
    increase=4.0,
    increase_singular=10.0,
    decrease=3.0,
    floor=1e-9,
    ceiling=1e8,
    accept_equal=True,
)


def _fit_marker_stage(model, p, obs, wts, free, theta, pred, jac, max_iterations):
    """One weighted Levenberg-Marquardt stage of :func:`_fit_aruco_marker`.

    Minimises ``sum(wts * (obs - model(p, theta))^2)`` over the ``free`` parameters
    from ``theta`` (``pred, jac = model(p, theta)`` given), by
    :func:`gtsam_sphere.core.least_squares.levenberg_marquardt`. Stops when a step's
    predicted decrease is below 1e-6 of the cost, an accepted one lowers the cost by
    at most 1e-8 of it, or moves no geometric parameter by 1e-6 or more.

    Returns ``(theta, pred)``: the parameters reached and the model's values there.
    """
    # the model gives values and Jacobian together: the trial's are the next linearisation's
    last = {"x": theta, "pred": pred, "jac": jac}
    here = dict(last)

    def full(delta):
        step = np.zeros(len(theta))
        step[free] = delta
        return step

    def cost(x):
        pred_x, jac_x = model(p, x)
        last.update(x=x, pred=pred_x, jac=jac_x)
        res = obs - pred_x
        return float(np.sum(wts * res * res))

    def linearize(x):
        if last["x"] is not x:
            cost(x)
        here.update(last)
        jw = last["jac"][:, free] * wts[:, None]
        res = obs - last["pred"]
        return np.einsum("ni,nj->ij", jw, last["jac"][:, free]), -np.einsum("ni,n->i", jw, res)

    def small(c_old, c_new, delta):
        return not (c_old - c_new > 1e-8 * c_old) or np.max(np.abs(full(delta)[:20])) < 1e-6

    res0 = obs - pred
    fit = levenberg_marquardt(
        theta,
        cost,
        linearize,
        retract=lambda x, delta: x + full(delta),
        converged=small,
        negligible=lambda delta, g, c: delta @ -g < 1e-6 * c,
        damping=_MARKER_DAMPING,
        max_iterations=max_iterations,
        cost0=float(np.sum(wts * res0 * res0)),
    )
    return fit.x, (last["pred"] if last["x"] is fit.x else here["pred"])


def _fit_aruco_marker(
    image: np.ndarray,
    quad: np.ndarray,
    bits: np.ndarray,
    *,
    quiet_zone: float = 0.5,
    max_iterations: int = 30,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Fit a marker's cell pattern to the image; return its corners and centre.

    Model of the pixels around the marker (its black border plus ``quiet_zone``
    cells of the white margin)::

        I(u) = a0 + a1 pu + a2 pv + b * T(G(u)),   p = (pu, pv) = (u - c0) / s0
        G(u) = H(p + Q(p) + C(p))

    ``G`` maps pixels to marker coordinates (code cells, corner 0 at ``(0, 0)``, ``x``
    towards corner 1, ``y`` towards corner 3): a homography ``H`` (exact for a square
    seen by a distortion-free camera) after a quadratic warp ``Q`` and a cubic warp
    ``C``, the local lens distortion to third order (``Q`` leaves out the two
    components that ``H``'s perspective terms also produce to second order; ``C`` is
    only fitted from 5 px per cell on, where it matters and is determined). ``c0`` and
    ``s0`` are the centre and half side (pixels) of OpenCV's quadrilateral.

    ``T`` is the marker's known cell pattern (1 white, 0 black, white outside) seen
    through an isotropic Gaussian blur of ``sigma`` pixels (fitted): mapped to marker
    coordinates by the local Jacobian of ``G``, the blur is a correlated Gaussian
    whose marginals blur the cell edges (exact for straight edges) and whose
    correlation, large where the lens or the perspective shears the marker, rounds the
    cell corners asymmetrically (Mehler's expansion to second order in the
    correlation, :func:`_cell_occupancy`). Leaving the correlation out biased corners
    by 0.15 px RMS on sheared markers blurred by 2 px; leaving out ``C`` by 0.08 px RMS
    on fisheye markers of 40-100 px.

    The 25 parameters are found by Levenberg-Marquardt (analytic Jacobian, except for
    the blur's dependence on the warp) from OpenCV's corners without ``C``, then again
    with ``C`` and Huber weights (2.5 robust sigma) on the pixels of the updated region.
    Corners and centre are the pixels that ``G`` maps to ``(0, 0), (n, 0), (n, n),
    (0, n)`` and ``(n / 2, n / 2)`` (Newton), ``n`` cells a side. On rendered 200 degree
    fisheye views (markers of 20-100 px, blur 0.6-2 px, noise 2 grey levels) corners are
    within 0.02-0.05 px RMS of the truth and centres within 0.01-0.02 px RMS
    (``tests/test_aruco_room.py``).

    Parameters
    ----------
    image : ndarray, shape (H, W), float
        Grey image.
    quad : ndarray, shape (4, 2)
        OpenCV's corners ``(u, v)`` in pixels, OpenCV's order.
    bits : ndarray, shape (n, n)
        Cell pattern of the marker in that order (1 white, 0 black), border included.
    quiet_zone : float
        Width of the white margin used by the fit (code cells).
    max_iterations : int
        Levenberg-Marquardt iterations per stage.

    Returns
    -------
    (corners (4, 2), centre (2,)) in pixels, or None
        None when the fit fails: a side below 2.5 px per cell, too few pixels,
        contrast below 10 grey levels, blur over half a cell, residual RMS over 20 %
        of the contrast, over 2 % of the white margin's pixels darker than mid-grey
        (e.g. cut by a fisheye's image circle: 0.4 px corner errors), or a corner more
        than ``max(4 px, 0.75 cell)`` from OpenCV's (whose corners are up to 3.2 px off
        on small sharp-angled markers of rendered fisheye views).
    """
    n = int(bits.shape[0])
    pad = 2  # white cells around the pattern (the quiet zone and beyond)
    grid = np.pad(np.asarray(bits, dtype=np.float64), pad, constant_values=1.0)
    n_ext, lo = n + 2 * pad, -float(pad)
    quad = np.asarray(quad, dtype=np.float64).reshape(4, 2)
    c0 = quad.mean(axis=0)
    side = float(np.mean(np.linalg.norm(quad - np.roll(quad, 1, axis=0), axis=1)))
    if not np.all(np.isfinite(quad)) or side < 2.5 * n:
        return None  # below 2.5 px per cell the fit is unreliable (errors up to 1.4 px)
    s0 = 0.5 * side
    px_per_cell = side / n
    target = np.array([[0.0, 0.0], [n, 0.0], [n, n], [0.0, n]])
    hom = cv2.getPerspectiveTransform(
        ((quad - c0) / s0).astype(np.float32), target.astype(np.float32)
    ).astype(np.float64)
    if not np.all(np.isfinite(hom)) or abs(hom[2, 2]) < 1e-12:
        return None
    hom /= hom[2, 2]
    h_img, w_img = image.shape
    margin = (quiet_zone + 1.0) * px_per_cell + 3.0
    u0, v0 = np.maximum(np.floor(quad.min(axis=0) - margin), 0).astype(int)
    u1 = int(min(w_img - 1, np.ceil(quad[:, 0].max() + margin)))
    v1 = int(min(h_img - 1, np.ceil(quad[:, 1].max() + margin)))
    if u1 <= u0 or v1 <= v0:
        return None
    # large markers: every k-th pixel along each axis (at least 6 per cell) bounds the cost
    stride = max(1, int(px_per_cell // 6))
    vv, uu = np.mgrid[v0 : v1 + 1 : stride, u0 : u1 + 1 : stride]
    p_all = (np.stack([uu.ravel(), vv.ravel()], axis=1) - c0) / s0
    i_all = image[vv.ravel(), uu.ravel()]

    # parameters: homography h (8), quadratic warp q (4), cubic warp k (8), log of the
    # blur in pixels (1), photometry a0, a1, a2, b (4)
    n_par = 25
    blur_orders = 2  # Mehler terms of the blur's correlation (4 terms: no gain)

    def warp(p, th):
        """Marker coordinates of normalised pixels p (N, 2), with the intermediates."""
        h, q, k = th[:8], th[8:12], th[12:20]
        px, py = p[:, 0], p[:, 1]
        mono = (px**3, px * px * py, px * py * py, py**3)
        x = px + q[2] * px * px + q[3] * px * py + q[0] * py * py
        y = py + q[1] * px * px - q[2] * px * py - q[3] * py * py
        x = x + k[0] * mono[0] + k[1] * mono[1] + k[2] * mono[2] + k[3] * mono[3]
        y = y + k[4] * mono[0] + k[5] * mono[1] + k[6] * mono[2] + k[7] * mono[3]
        w = h[6] * x + h[7] * y + 1.0
        mx = (h[0] * x + h[1] * y + h[2]) / w
        my = (h[3] * x + h[4] * y + h[5]) / w
        # d(mx, my)/d(x, y)
        a = (
            (h[0] - mx * h[6]) / w,
            (h[1] - mx * h[7]) / w,
            (h[3] - my * h[6]) / w,
            (h[4] - my * h[7]) / w,
        )
        # d(x, y)/d(px, py)
        xx, xy, yy = px * px, px * py, py * py
        d = (
            1.0 + 2 * q[2] * px + q[3] * py + 3 * k[0] * xx + 2 * k[1] * xy + k[2] * yy,
            q[3] * px + 2 * q[0] * py + k[1] * xx + 2 * k[2] * xy + 3 * k[3] * yy,
            2 * q[1] * px - q[2] * py + 3 * k[4] * xx + 2 * k[5] * xy + k[6] * yy,
            1.0 - q[2] * px - 2 * q[3] * py + k[5] * xx + 2 * k[6] * xy + 3 * k[7] * yy,
        )
        # d(mx, my)/d(u, v) = a d / s0
        jg = (
            (a[0] * d[0] + a[1] * d[2]) / s0,
            (a[0] * d[1] + a[1] * d[3]) / s0,
            (a[2] * d[0] + a[3] * d[2]) / s0,
            (a[2] * d[1] + a[3] * d[3]) / s0,
        )
        return x, y, w, mx, my, mono, a, jg

    def model(p, th):
        """Predicted grey values (N,) and their Jacobian (N, n_par).

        The blur is isotropic in the image (``sigma_px``): along the marker axes it is
        ``sigma_px`` times the norm of the rows of dG/du, with the correlation of the
        rows' directions, so edges seen obliquely or compressed by the lens are blurred
        as much as in the image. (Its dependence on the warp is left out of the
        Jacobian: Levenberg-Marquardt only needs descent directions.)
        """
        a0, a1, a2, b = th[21:25]
        px, py = p[:, 0], p[:, 1]
        x, y, w, mx, my, mono, a, jg = warp(p, th)
        sigma_px = np.exp(th[20])
        nx = np.maximum(np.hypot(jg[0], jg[1]), 1e-12)
        ny = np.maximum(np.hypot(jg[2], jg[3]), 1e-12)
        rho = (jg[0] * jg[2] + jg[1] * jg[3]) / (nx * ny)  # correlation of the blur
        terms_x = _cell_occupancy(mx, sigma_px * nx, lo, n_ext, blur_orders)
        terms_y = _cell_occupancy(my, sigma_px * ny, lo, n_ext, blur_orders)
        t, t_x, t_y, t_s = (np.zeros(len(px)) for _ in range(4))
        weight = np.ones(len(px))
        for k, ((ox, dox, lox), (oy, doy, loy)) in enumerate(zip(terms_x, terms_y)):
            if k:
                weight = weight * rho / k  # rho^k / k!
            # einsum (no BLAS): threaded BLAS on these small products is 5-10x slower on
            # a busy machine
            row = np.einsum("nj,ji->ni", oy, grid)  # pattern rows weighted by the y terms
            col = np.einsum("ni,ji->nj", ox, grid)  # pattern columns weighted by the x terms
            t += weight * np.sum(row * ox, axis=1)
            t_x += weight * np.sum(row * dox, axis=1)
            t_y += weight * np.sum(col * doy, axis=1)
            t_s += weight * (np.sum(row * lox, axis=1) + np.sum(col * loy, axis=1))
        jac = np.empty((len(px), n_par))
        bx, by = b * t_x / w, b * t_y / w
        jac[:, 0], jac[:, 1], jac[:, 2] = bx * x, bx * y, bx
        jac[:, 3], jac[:, 4], jac[:, 5] = by * x, by * y, by
        persp = bx * mx + by * my
        jac[:, 6], jac[:, 7] = -persp * x, -persp * y
        gx = b * (t_x * a[0] + t_y * a[2])  # b dT/dx
        gy = b * (t_x * a[1] + t_y * a[3])  # b dT/dy
        jac[:, 8] = gx * py * py
        jac[:, 9] = gy * px * px
        jac[:, 10] = (gx * px - gy * py) * px
        jac[:, 11] = (gx * px - gy * py) * py
        for i, m in enumerate(mono):
            jac[:, 12 + i] = gx * m
            jac[:, 16 + i] = gy * m
        jac[:, 20] = b * t_s
        jac[:, 21], jac[:, 22], jac[:, 23], jac[:, 24] = 1.0, px, py, t
        return a0 + a1 * px + a2 * py + b * t, jac

    def region(th):
        _, _, w, mx, my, _, _, _ = warp(p_all, th)
        lim = n + quiet_zone
        return (w > 0) & (mx >= -quiet_zone) & (mx <= lim) & (my >= -quiet_zone) & (my <= lim)

    theta = np.zeros(n_par)
    theta[:8] = hom.ravel()[:8]
    theta[20] = np.log(0.8)
    sel = region(theta)
    if np.count_nonzero(sel) < 4 * (n + 1) ** 2 / stride**2:
        return None
    dark, light = np.percentile(i_all[sel], [5, 95])
    theta[21], theta[24] = dark, light - dark
    free = np.ones(n_par, dtype=bool)
    free[12:20] = False  # stage 0: no cubic warp (converges faster from OpenCV's corners)
    # the cubic warp from 5 px per cell on: on smaller markers it fits the noise
    cubic = side >= 5.0 * n
    for stage in range(2):
        if stage == 1 and cubic:
            free[12:20] = True
        sel = region(theta)
        p, obs = p_all[sel], i_all[sel]
        if len(obs) < 4 * (n + 1) ** 2 / stride**2:
            return None
        pred, jac = model(p, theta)
        res = obs - pred
        if stage == 0:
            wts = np.ones_like(res)
        else:  # Huber weights at 2.5 robust sigma of the first stage's residuals
            scale = max(mad_sigma(res), 0.5)
            wts, _ = robust_weight(np.abs(res), Loss.HUBER, 2.5 * scale)
        theta, pred = _fit_marker_stage(model, p, obs, wts, free, theta, pred, jac, max_iterations)
        res = obs - pred
    if not np.all(np.isfinite(theta)):
        return None
    contrast = theta[24]
    rms = float(np.sqrt(np.sum(wts * res * res) / np.sum(wts)))
    if contrast < 10.0 or np.exp(theta[20]) > 0.5 * px_per_cell or rms > 0.2 * contrast:
        return None
    # a white margin partly dark (the marker touches the edge of a fisheye's image
    # circle, an occluder, a dark surround) biases the fit: refuse the marker
    _, _, _, mx, my, _, _, _ = warp(p, theta)
    margin_px = (mx < 0) | (mx > n) | (my < 0) | (my > n)
    if np.mean(res[margin_px] < -0.5 * contrast) > 0.02:
        return None

    def to_pixel(m_target, guess):
        u = np.asarray(guess, dtype=np.float64).copy()
        for _ in range(30):
            _, _, _, mx, my, _, _, jg = warp(((u - c0) / s0)[None], theta)
            jac_g = np.array([[jg[0][0], jg[1][0]], [jg[2][0], jg[3][0]]])
            du = np.linalg.solve(jac_g, np.array([mx[0], my[0]]) - m_target)
            u -= du
            if not np.all(np.isfinite(u)):
                return u
            if np.max(np.abs(du)) < 1e-9:
                break
        return u

    try:
        corners = np.array([to_pixel(target[k], quad[k]) for k in range(4)])
        centre = to_pixel(np.array([0.5 * n, 0.5 * n]), corners.mean(axis=0))
    except np.linalg.LinAlgError:
        return None
    moved = np.linalg.norm(corners - quad, axis=1)
    if not (np.all(np.isfinite(corners)) and np.all(np.isfinite(centre))):
        return None
    if np.max(moved) > max(4.0, 0.75 * px_per_cell):
        return None
    return corners, centre


def detect_image(
    gray: np.ndarray, board: BoardSpec, *, attempts: int = 3, check_size: bool = True
) -> dict[str, np.ndarray]:
    """Detect the targets of ``board`` in one image.

    Parameters
    ----------
    gray : ndarray, shape (H, W) or (H, W, 3)
        Image (BGR images are converted to grey; non-uint8 images are rescaled).
    board : BoardSpec
        Target description.
    attempts : int, optional
        Chessboards: number of seeds tried with ``cv2.findChessboardCornersSB`` (each
        with and without ``CALIB_CB_NORMALIZE_IMAGE``) before falling back to
        ``cv2.findChessboardCorners``. The detector is seeded (``cv2.setRNGSeed``), so
        results are reproducible; this resets OpenCV's global RNG.
    check_size : bool, optional
        Chessboards: test that the detected grid is the whole pattern
        (:func:`_grid_continuation`: no board corner one square beyond a border or
        between two neighbouring grid corners) and raise otherwise.

    Returns
    -------
    dict of str to ndarray, shape (2,)
        Target id -> sub-pixel position ``(u, v)`` in pixels ((0, 0) = centre of the
        top-left pixel). Empty when nothing is found. Chessboards are all-or-nothing
        (every inner corner or none); ChArUco boards may be partial; ArUco markers give
        ``"M{id}"`` (centre) and ``"M{id}_{k}"`` (corners).

    Raises
    ------
    TargetMismatchError
        When the image shows a larger board than ``board`` describes (see
        ``check_size``); the message says where the pattern continues.
    """
    g = _to_gray(gray)
    if board.kind == "chessboard":
        return _detect_chessboard(g, board, attempts, check_size)
    if board.kind == "charuco":
        return _detect_charuco(g, board)
    if board.kind == "aprilgrid":
        return _detect_aprilgrid(g, board)
    if board.kind == "aruco":
        return _detect_aruco(g, board)
    raise ValueError(f"unknown board kind {board.kind!r}")


# --------------------------------------------------------------------------------------
# Peripheral recovery helper
# --------------------------------------------------------------------------------------


def saddle_score(gray: np.ndarray, uv: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Chessboard X-corner score from intensities on a ring around each point.

    Around an X-corner the ring profile ``f(theta)`` satisfies ``f(theta + pi) = f(theta)``
    and ``f(theta + pi/2) = -f(theta)`` (after removing its mean); the score is
    ``(corr(f, f_180) - corr(f, f_90)) / 2``: about 1 at a saddle, about -1 or 0 on an
    edge, a blob or noise.

    Parameters
    ----------
    gray : ndarray, shape (H, W)
        Grey image.
    uv : ndarray, shape (N, 2)
        Positions in pixels.
    radius : float
        Ring radius in pixels.

    Returns
    -------
    score : ndarray, shape (N,)
        Saddle score in [-1, 1].
    contrast : ndarray, shape (N,)
        Standard deviation of the ring intensities (grey levels).
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    n_ring = 32
    theta = 2 * np.pi * np.arange(n_ring) / n_ring
    radii = np.array([0.6 * radius, radius])
    offs = np.concatenate([np.stack([r * np.cos(theta), r * np.sin(theta)], 1) for r in radii])
    pts = uv[:, None, :] + offs[None]
    f = _sample(np.asarray(gray), pts.reshape(-1, 2)).reshape(len(uv), len(radii), n_ring)
    f = f - f.mean(axis=2, keepdims=True)
    contrast = f.std(axis=2).mean(axis=1)

    def corr(shift: int) -> np.ndarray:
        g = np.roll(f, shift, axis=2)
        num = (f * g).sum(axis=(1, 2))
        den = np.sqrt((f * f).sum(axis=(1, 2)) * (g * g).sum(axis=(1, 2)))
        return num / np.maximum(den, 1e-12)

    score = 0.5 * (corr(n_ring // 2) - corr(n_ring // 4))
    return score, contrast


def refine_predicted_corners(
    gray: np.ndarray,
    predicted_uv_px: dict[str, np.ndarray],
    window_px: int = 7,
    *,
    min_score: float = 0.5,
    min_contrast: float = 8.0,
) -> dict[str, np.ndarray]:
    """Refine predicted chessboard-corner positions locally and keep the credible ones.

    Meant for recovering corners the detector missed (e.g. at the fisheye periphery)
    once a calibration predicts where they are. Each prediction is refined with
    ``cv2.cornerSubPix`` in a window of about ``window_px`` pixels; it is rejected if the
    refinement moved it by more than ``window_px / 2``, or if the refined point is not a
    chessboard saddle (:func:`saddle_score` below ``min_score``, or ring contrast below
    ``min_contrast`` grey levels), or if it falls outside the image.

    Parameters
    ----------
    gray : ndarray, shape (H, W) or (H, W, 3)
        Image.
    predicted_uv_px : dict of str to array_like, shape (2,)
        Target id -> predicted ``(u, v)`` in pixels.
    window_px : int, optional
        Full side of the refinement window in pixels (>= 5); ``cornerSubPix`` uses the
        half-size ``window_px // 2``.
    min_score : float, optional
        Minimum saddle score in [-1, 1].
    min_contrast : float, optional
        Minimum ring intensity standard deviation (grey levels, 0..255 image).

    Returns
    -------
    dict of str to ndarray, shape (2,)
        Accepted target id -> refined ``(u, v)`` in pixels.
    """
    if window_px < 5:
        raise ValueError(f"window_px={window_px} too small: need >= 5")
    if not predicted_uv_px:
        return {}
    g = _to_gray(gray)
    h, w = g.shape
    keys = list(predicted_uv_px)
    pred = np.array([np.asarray(predicted_uv_px[k], dtype=np.float64) for k in keys])
    half = int(window_px // 2)
    margin = half + 1
    inside = (
        np.all(np.isfinite(pred), axis=1)
        & (pred[:, 0] >= margin)
        & (pred[:, 0] <= w - 1 - margin)
        & (pred[:, 1] >= margin)
        & (pred[:, 1] <= h - 1 - margin)
    )
    out: dict[str, np.ndarray] = {}
    if not np.any(inside):
        return out
    idx = np.flatnonzero(inside)
    refined = _subpix(g, pred[idx], half)
    moved = np.linalg.norm(refined - pred[idx], axis=1)
    score, contrast = saddle_score(g, refined, radius=max(2.0, 0.5 * window_px))
    ok = (moved <= 0.5 * window_px) & (score >= min_score) & (contrast >= min_contrast)
    for j, i in enumerate(idx):
        if ok[j]:
            out[keys[i]] = refined[j]
    return out


# --------------------------------------------------------------------------------------
# Many images -> dataset@1
# --------------------------------------------------------------------------------------


@dataclass
class DetectionReport:
    """What :func:`detect_images` found.

    Attributes
    ----------
    used : list of (str, int)
        ``(image id, number of observations)`` for every image written to the dataset.
    skipped : list of (str, str)
        ``(image path, reason)`` for every image left out.
    unknown_markers : dict of str to int
        ArUco target id -> number of detections dropped because the marker is not in the
        markers CSV.
    """

    used: list[tuple[str, int]] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)
    unknown_markers: dict[str, int] = field(default_factory=dict)

    @property
    def n_observations(self) -> int:
        """Total number of observations written."""
        return sum(n for _, n in self.used)

    def summary(self) -> str:
        """Human-readable multi-line summary."""
        lines = [
            f"images used: {len(self.used)}, skipped: {len(self.skipped)}, "
            f"observations: {self.n_observations}"
        ]
        for name, n in self.used:
            lines.append(f"  {name}: {n} corners")
        for path, reason in self.skipped:
            lines.append(f"  skipped {path}: {reason}")
        if self.unknown_markers:
            total = sum(self.unknown_markers.values())
            ids = ", ".join(sorted(self.unknown_markers))
            lines.append(f"  {total} marker detections not in the markers CSV: {ids}")
        return "\n".join(lines)


def read_markers_csv(path: str) -> dict[str, tuple[np.ndarray, float | None]]:
    """Read surveyed marker centres.

    Parameters
    ----------
    path : str
        CSV file with rows ``id,X,Y,Z[,sigma]`` (object units, usually metres); a header
        row and ``#`` comment lines are allowed.

    Returns
    -------
    dict of str to (ndarray (3,), float or None)
        ``"M{id}"`` -> (approximate centre coordinates, sigma or None when absent).

    Raises
    ------
    ValueError
        Naming the file and line of a malformed or duplicate row.
    """
    out: dict[str, tuple[np.ndarray, float | None]] = {}
    with open(path, newline="") as fh:
        for lineno, row in enumerate(csv.reader(fh), start=1):
            cells = [c.strip() for c in row]
            if not cells or not cells[0] or cells[0].startswith("#"):
                continue
            try:
                mid = int(cells[0])
            except ValueError:
                if lineno == 1:  # header
                    continue
                raise DatasetError(f"{path}:{lineno}: bad marker id {cells[0]!r}") from None
            if len(cells) not in (4, 5):
                raise DatasetError(f"{path}:{lineno}: expected 'id,X,Y,Z[,sigma]', got {row!r}")
            try:
                xyz = np.array([float(c) for c in cells[1:4]])
                sigma = float(cells[4]) if len(cells) == 5 and cells[4] else None
            except ValueError:
                raise DatasetError(f"{path}:{lineno}: non-numeric value in {row!r}") from None
            if not np.all(np.isfinite(xyz)) or (sigma is not None and not sigma >= 0):
                raise DatasetError(f"{path}:{lineno}: non-finite coordinate or bad sigma {row!r}")
            key = f"M{mid}"
            if key in out:
                raise DatasetError(f"{path}:{lineno}: duplicate marker id {mid}")
            out[key] = (xyz, sigma)
    return out


def _progress(i: int, n: int, name: str) -> None:
    width = 30
    done = int(width * i / max(n, 1))
    bar = "#" * done + "." * (width - done)
    sys.stderr.write(f"\r[{bar}] {i}/{n} {name[:40]:<40}")
    if i == n:
        sys.stderr.write("\n")
    sys.stderr.flush()


def _image_ids(paths: list[str]) -> list[str]:
    """Image ids: file stems, disambiguated by parent folders when needed."""
    ids = [Path(p).stem for p in paths]
    depth = 1
    while len(set(ids)) < len(ids) and depth < 8:
        ids = ["/".join(Path(p).with_suffix("").parts[-depth - 1 :]) for p in paths]
        depth += 1
    if len(set(ids)) < len(ids):
        ids = [f"{i:04d}_{s}" for i, s in enumerate(ids)]
    return ids


def detect_images(
    paths: list[str],
    board: BoardSpec,
    *,
    progress: bool = True,
    markers_csv: str | None = None,
    min_points: int = 1,
    check_size: bool = True,
) -> tuple[dict, DetectionReport]:
    """Detect ``board`` in many images and build a ``gtsam-sphere/dataset@1`` dataset.

    Parameters
    ----------
    paths : list of str
        Image files (all of the same size: one physical camera per dataset).
    board : BoardSpec
        Target description.
    progress : bool, optional
        Draw a text progress bar on stderr.
    markers_csv : str, optional
        For ``"aruco"`` targets: surveyed marker centres (see :func:`read_markers_csv`),
        written as targets ``"M{id}"`` with their sigma (absent = approximate only).
        Detections of markers not in the CSV are counted in
        ``report.unknown_markers``. Required for ``"aruco"``.
    min_points : int, optional
        Images with fewer usable observations are skipped (and reported).
    check_size : bool, optional
        Chessboards: refuse a grid that is part of a larger pattern (see
        :func:`detect_image`); ``--no-size-check`` turns it off.

    Returns
    -------
    dataset : dict
        ``{"format": "gtsam-sphere/dataset@1", "units": "m", "camera": {"width",
        "height"}, "targets": [...], "images": [...]}``; board targets carry
        ``"sigma": 0`` and board-frame coordinates in metres, observations are pixel
        positions ``(u, v)``.
    report : DetectionReport
        Per-image counts, skipped images with reasons, unknown markers.

    Raises
    ------
    ValueError
        If ``board`` is ``"aruco"`` without ``markers_csv``, or no image is usable.
    TargetMismatchError
        If an image shows a larger target than ``board`` describes; the message names
        the image.
    """
    report = DetectionReport()
    survey = None
    if board.kind == "aruco":
        if markers_csv is None:
            raise OptionsError(
                "ArUco marker detection needs --markers-csv (surveyed marker centres): "
                "markers have no board frame"
            )
        survey = read_markers_csv(markers_csv)
    elif markers_csv is not None:
        raise OptionsError(f"markers_csv is only used with 'aruco' targets, not {board.kind!r}")
    board_points = board.object_points_m()
    paths = [str(p) for p in paths]
    ids = _image_ids(paths)
    size: tuple[int, int] | None = None
    images = []
    used_targets: set[str] = set()
    for i, (path, image_id) in enumerate(zip(paths, ids, strict=True)):
        if progress:
            _progress(i, len(paths), Path(path).name)
        img = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
        if img is None:
            report.skipped.append((path, "cannot read image"))
            continue
        hw = (img.shape[1], img.shape[0])
        if size is None:
            size = hw
        elif hw != size:
            report.skipped.append((path, f"size {hw[0]}x{hw[1]} differs from {size[0]}x{size[1]}"))
            continue
        try:
            found = detect_image(img, board, check_size=check_size)
        except TargetMismatchError as exc:
            raise TargetMismatchError(f"image {path}: {exc}") from None
        obs = []
        for key in sorted(found):
            uv = found[key]
            if survey is not None:
                if "_" in key:
                    continue  # marker corners have no surveyed coordinates
                if key not in survey:
                    report.unknown_markers[key] = report.unknown_markers.get(key, 0) + 1
                    continue
            elif key not in board_points:
                continue
            obs.append({"target": key, "uv": [float(uv[0]), float(uv[1])]})
        if not found:
            report.skipped.append((path, "no target found"))
            continue
        if len(obs) < max(1, min_points):
            why = "no known target" if not obs else f"only {len(obs)} observations"
            report.skipped.append((path, f"{why} (need >= {max(1, min_points)})"))
            continue
        used_targets.update(o["target"] for o in obs)
        images.append({"id": image_id, "observations": obs})
        report.used.append((image_id, len(obs)))
    if progress and paths:
        _progress(len(paths), len(paths), "done")
    if not images:
        raise InputError(
            f"no usable image among {len(paths)}: "
            + "; ".join(f"{p}: {r}" for p, r in report.skipped[:5])
        )
    targets = []
    for key in sorted(used_targets):
        if survey is not None:
            xyz, sigma = survey[key]
            t = {"id": key, "xyz": [float(x) for x in xyz]}
            if sigma is not None:
                t["sigma"] = float(sigma)
        else:
            t = {"id": key, "xyz": [float(x) for x in board_points[key]], "sigma": 0}
        targets.append(t)
    assert size is not None
    dataset = {
        "format": DATASET_FORMAT,
        "units": "m",
        "camera": {"width": int(size[0]), "height": int(size[1])},
        "targets": targets,
        "images": images,
        "source": {"detector": "gtsam_sphere.apps.detect", "board": board.text},
    }
    return dataset, report


def write_json_atomic(obj: dict, path: str) -> None:
    """Write ``obj`` as JSON to ``path`` atomically (``dataset.write_json_atomic``)."""
    from ..io.dataset import write_json_atomic as _write

    _write(path, obj)


# --------------------------------------------------------------------------------------
# Periphery recovery: detect -> calibrate -> predict the missed corners -> refine -> recalibrate
# --------------------------------------------------------------------------------------


@dataclass
class RecoveryReport:
    """What :func:`recover_dataset` added.

    Attributes
    ----------
    added : dict of str to int
        Image id -> corners added to that image (all rounds, after the final check).
    rescued : list of str
        Images the detector had skipped (no full chessboard) that now have observations:
        a partial grid found by ``cv2.findChessboardCornersSB`` (``CALIB_CB_LARGER``),
        placed on the board with the calibration, plus the recovered corners.
    dropped : int
        Recovered corners removed again because the recalibration found them past
        5 sigma.
    rounds : list of dict
        Per round: ``{"round", "model", "rms_px", "n_observations", "added"}`` of the
        calibration that made the predictions (round 0 with the input detections), and
        a last entry ``"final"`` for the recalibration with every recovered corner.
    failures : dict of str to str
        Image id -> why no corner could be predicted (resection failed, ...).
    """

    added: dict[str, int] = field(default_factory=dict)
    rescued: list[str] = field(default_factory=list)
    dropped: int = 0
    rounds: list[dict] = field(default_factory=list)
    failures: dict[str, str] = field(default_factory=dict)

    @property
    def total(self) -> int:
        """Corners added over all images."""
        return sum(self.added.values())

    def summary(self) -> str:
        """Human-readable multi-line summary."""
        lines = [
            f"periphery recovery: {self.total} corners added in "
            f"{sum(1 for n in self.added.values() if n)} images "
            f"({len(self.rescued)} images rescued from a partial board), "
            f"{self.dropped} dropped by the recalibration"
        ]
        for r in self.rounds:
            lines.append(
                f"  calibration {r['round']}: {r['model']}, {r['n_observations']} corners, "
                f"RMS {r['rms_px']:.4f} px, max incidence {r['max_incidence_deg']:.1f} deg"
            )
        for image_id, n in self.added.items():
            if n:
                tag = " (rescued)" if image_id in self.rescued else ""
                lines.append(f"  {image_id}: +{n} corners{tag}")
        for image_id, why in self.failures.items():
            lines.append(f"  {image_id}: no prediction ({why})")
        return "\n".join(lines)


def _board_neighbour_spacing(
    camera, R: np.ndarray, t: np.ndarray, xyz: np.ndarray, step_m: float
) -> np.ndarray:
    """Predicted distance (px) from each board point (N, 3) to its nearest grid neighbour."""
    offsets = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], float) * step_m
    # recovery predicts corners past the field the detected ones cover: extrapolate
    centre = camera.project(xyz @ R.T + t, valid_only=False)
    dist = np.full(len(xyz), np.inf)
    for d in offsets:
        q = camera.project((xyz + d) @ R.T + t, valid_only=False)
        dist = np.minimum(dist, np.linalg.norm(q - centre, axis=1))
    return dist


def predict_and_refine(
    gray: np.ndarray,
    detected: dict[str, np.ndarray],
    board: BoardSpec,
    camera,
    *,
    rng: np.random.Generator | None = None,
    max_incidence_deg: float = 180.0,
    max_offset_px: float = 3.0,
    min_score: float = 0.5,
    min_contrast: float = 8.0,
    strict: bool = False,
) -> tuple[dict[str, np.ndarray], str]:
    """Recover the board corners of one image that the detector missed.

    The pose is resected from the detected corners with the calibration fixed
    (:func:`gtsam_sphere.estimation.resect.resect`); every other corner of the board is projected
    with ``camera.project`` and refined locally: ``cv2.cornerSubPix`` in a window scaled to
    the predicted local square size, then the detector's saddle fit. A corner is kept
    when the refined point is a chessboard saddle (:func:`saddle_score`, ring contrast),
    lies within ``min(max_offset_px, 0.3 * local spacing)`` of the prediction, and is not
    within half a spacing of another corner.

    Parameters
    ----------
    gray : ndarray, shape (H, W)
        Grey image.
    detected : dict of str to ndarray, shape (2,)
        Target id -> detected ``(u, v)`` px (at least 4).
    board : BoardSpec
        Chessboard or ChArUco board (its corners are the candidates).
    camera : SphereCamera
        Calibrated camera (``project``, ``unproject``, ``ideal_from_points``).
    rng : numpy.random.Generator, optional
        RANSAC samples of the resection.
    max_incidence_deg : float
        Corners predicted past this incidence angle (camera frame, degrees) are not
        tried: the calibration does not extrapolate far beyond the angles it saw.
    max_offset_px : float
        Largest distance (px) between a prediction and its refined corner.
    min_score, min_contrast : float
        Saddle test of :func:`refine_predicted_corners`.
    strict : bool
        Refuse (status not ``"ok"``) when any detected corner is more than
        ``max_offset_px / 2`` from its reprojection with the resected pose: used for
        partial grids, whose placement on the board is a hypothesis.

    Returns
    -------
    added : dict of str to ndarray, shape (2,)
        Recovered target id -> refined ``(u, v)`` px.
    status : str
        ``"ok"`` or why nothing could be predicted.
    """
    from ..estimation.resect import resect

    points = board.object_points_m()
    ids = [k for k in detected if k in points]
    if len(ids) < 4:
        return {}, f"only {len(ids)} detected board corners"
    uv = np.array([detected[k] for k in ids], float)
    xyz = np.array([points[k] for k in ids], float)
    res = resect(camera, uv, xyz, rng if rng is not None else np.random.default_rng(0))
    if not res.success:
        return {}, f"resection failed: {res.status}"
    worst = float(np.nanmax(np.linalg.norm(res.residuals_px, axis=1)))
    if strict and not worst <= 0.5 * max_offset_px:
        return {}, f"detected corners do not fit the calibration ({worst:.1f} px)"
    missing = [k for k in points if k not in detected]
    if not missing:
        return {}, "ok"
    g = _to_gray(gray)
    h, w = g.shape
    mxyz = np.array([points[k] for k in missing], float)
    p = mxyz @ res.R.T + res.t
    inc = np.degrees(np.arctan2(np.hypot(p[:, 0], p[:, 1]), p[:, 2]))
    pred = camera.project(p, valid_only=False)  # missed corners may lie past the field
    spacing = _board_neighbour_spacing(camera, res.R, res.t, mxyz, board.square_m)
    ok = (
        np.all(np.isfinite(pred), axis=1)
        & (inc <= max_incidence_deg)
        & (spacing >= 6.0)  # squares below ~6 px cannot be refined reliably
        & (pred[:, 0] >= 0)
        & (pred[:, 0] <= w - 1)
        & (pred[:, 1] >= 0)
        & (pred[:, 1] <= h - 1)
    )
    added: dict[str, np.ndarray] = {}
    windows = np.clip(2 * np.round(0.35 * np.nan_to_num(spacing)).astype(int) + 1, 5, 21)
    for win in np.unique(windows[ok]):
        sel = np.flatnonzero(ok & (windows == win))
        found = refine_predicted_corners(
            g,
            {missing[i]: pred[i] for i in sel},
            window_px=int(win),
            min_score=min_score,
            min_contrast=min_contrast,
        )
        if not found:
            continue
        keys = list(found)
        pts, good = _saddle_refine(g, np.array([found[k] for k in keys]), return_mask=True)
        index = {missing[i]: i for i in sel}
        for k, q, gd in zip(keys, pts, good):
            i = index[k]
            if gd and np.linalg.norm(q - pred[i]) <= min(max_offset_px, 0.3 * spacing[i]):
                added[k] = q
    if added:
        # two corners snapping to one image point: keep neither
        keys = list(added)
        allpts = np.array([added[k] for k in keys] + [detected[k] for k in ids])
        sp = spacing[[missing.index(k) for k in keys]]
        d = np.linalg.norm(allpts[: len(keys), None] - allpts[None], axis=2)
        d[np.arange(len(keys)), np.arange(len(keys))] = np.inf
        clash = np.min(d, axis=1) < 0.5 * sp
        added = {k: added[k] for k, c in zip(keys, clash) if not c}
    return added, "ok"


def _partial_chessboard_candidates(gray: np.ndarray, board: BoardSpec) -> list[dict]:
    """Partial chessboard grids, placed on the board in every admissible way.

    ``cv2.findChessboardCornersSB`` with ``CALIB_CB_LARGER`` finds the largest regular
    grid of at least 3x3 inner corners. Its position on the board is ambiguous (a shift
    by whole squares or a rotation is the same image content): every placement that fits
    the board and agrees with the square colours is returned, as target id -> ``(u, v)``.
    """
    flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_LARGER
    g = _to_gray(gray)
    try:
        cv2.setRNGSeed(0)
        ok, corners, meta = cv2.findChessboardCornersSBWithMeta(g, (3, 3), flags=flags)
    except cv2.error:
        return []
    if not ok or corners is None or meta is None:
        return []
    rows, cols = meta.shape[:2]
    if rows * cols != len(corners):
        return []
    grid = np.asarray(corners, dtype=np.float64).reshape(rows, cols, 2)
    grid, good = _refine_grid_corners(g, grid)
    if not np.all(good):  # a grid with corners off any saddle is not trusted
        return []
    ex = grid[:, -1].mean(axis=0) - grid[:, 0].mean(axis=0)
    ey = grid[-1].mean(axis=0) - grid[0].mean(axis=0)
    if ex[0] * ey[1] - ex[1] * ey[0] < 0:  # right-handed, as _orient_chessboard
        grid = grid[:, ::-1]
    rot = np.transpose(grid, (1, 0, 2))[:, ::-1]
    candidates = []
    for o in (grid, grid[::-1, ::-1], rot, rot[::-1, ::-1]):
        a, b = o.shape[:2]
        if a > board.rows or b > board.cols or a < 2 or b < 3:
            continue
        # is the square enclosed by o[0,0], o[0,1], o[1,0], o[1,1] dark?
        c_in = o[:2, :2].reshape(-1, 2).mean(axis=0)
        c_nb = o[:2, 1:3].reshape(-1, 2).mean(axis=0)
        first_dark = float(np.diff(_sample(g, np.array([c_in, c_nb])))[0]) > 0
        for dr in range(board.rows - a + 1):
            for dc in range(board.cols - b + 1):
                # the square right-below inner corner (r, c) is dark when r + c is even
                if ((dr + dc) % 2 == 0) != first_dark:
                    continue
                cand = {}
                for i in range(a):
                    for j in range(b):
                        cand[f"C{(dr + i) * board.cols + dc + j:03d}"] = o[i, j].copy()
                candidates.append(cand)
    return candidates


def rescue_partial_chessboard(
    gray: np.ndarray, board: BoardSpec, camera, **kwargs
) -> dict[str, np.ndarray]:
    """Corners of a chessboard only partly in view, with ids from the calibration.

    Each placement of the partial grid (:func:`_partial_chessboard_candidates`) is
    completed by :func:`predict_and_refine`; the placement that explains most corners wins
    (ties: the first). A placement that differs from the truth by whole squares or a
    board symmetry gives the same image content: with one pose per image, as in an
    intrinsic calibration, that is harmless (see the module docstring on symmetric
    boards). Returns target id -> ``(u, v)`` px, empty when no grid is found.
    """
    best: dict[str, np.ndarray] = {}
    for cand in _partial_chessboard_candidates(gray, board):
        added, status = predict_and_refine(gray, cand, board, camera, strict=True, **kwargs)
        if status != "ok":
            continue
        if len(cand) + len(added) > len(best):
            best = {**cand, **added}
    n = board.rows * board.cols
    if len(best) == n:  # the whole board: ids by the detector's ordering rule
        grid = np.array([best[f"C{i:03d}"] for i in range(n)]).reshape(board.rows, board.cols, 2)
        flat = _orient_chessboard(_to_gray(gray), grid).reshape(-1, 2)
        best = {f"C{i:03d}": flat[i].copy() for i in range(n)}
    return best


def recover_dataset(
    dataset: dict,
    paths: list[str],
    board: BoardSpec,
    *,
    model: str = "radial",
    calibration=None,
    rounds: int = 2,
    max_extrapolation_deg: float = 10.0,
    max_offset_px: float = 3.0,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> tuple[dict, RecoveryReport]:
    """Add the board corners the detector missed, predicted by a calibration.

    The loop: calibrate the detections (or start from ``calibration``) -> for every
    image, resect its pose with the calibration fixed and predict the board's other
    corners (:func:`predict_and_refine`); for a chessboard image the detector skipped,
    place a partial grid (:func:`rescue_partial_chessboard`) -> recalibrate with the
    added corners and predict again (``rounds`` times) -> a final recalibration drops
    recovered corners past 5 sigma. Added observations carry ``"recovered": true``.

    Parameters
    ----------
    dataset : dict
        ``dataset@1`` from :func:`detect_images` of ``paths`` (board targets, board frame).
    paths : list of str
        The image files, in the order given to :func:`detect_images`.
    board : BoardSpec
        Chessboard or ChArUco board.
    model : str
        Model of the internal calibrations (``gtsam_sphere.core.camera.Model``); the
        default ``radial`` extrapolates smoothly towards the periphery.
    calibration : Calibration, optional
        Use its camera for the first predictions instead of calibrating the detections.
    rounds : int
        Prediction rounds (each after a recalibration).
    max_extrapolation_deg : float
        Corners are predicted up to this many degrees past the largest incidence angle
        the calibration was estimated from.
    max_offset_px : float
        Largest distance between a prediction and the refined corner (px).
    seed : int
        Seed of the calibrations and resections.
    progress : callable(str), optional
        Receives progress lines.

    Returns
    -------
    dataset : dict
        A new ``dataset@1`` document with the recovered observations and targets.
    report : RecoveryReport
    """
    from ..estimation.calibrate import CalibrationOptions, calibrate
    from ..io.dataset import parse_dataset

    if board.kind not in ("chessboard", "charuco"):
        raise OptionsError(
            f"corner recovery needs a chessboard or ChArUco board, not {board.kind!r}"
        )
    say = progress or (lambda _line: None)
    points = board.object_points_m()
    size = (int(dataset["camera"]["width"]), int(dataset["camera"]["height"]))
    ids = _image_ids([str(p) for p in paths])
    path_of = dict(zip(ids, [str(p) for p in paths]))
    obs = {
        im["id"]: {o["target"]: np.asarray(o["uv"], float) for o in im["observations"]}
        for im in dataset["images"]
    }
    recovered: dict[str, set[str]] = {i: set() for i in ids}
    report = RecoveryReport()
    opts = CalibrationOptions(model=model, seed=seed, covariance=False)
    rng = np.random.default_rng(seed)

    def document() -> dict:
        images, used = [], set()
        for image_id in ids:
            if image_id not in obs or not obs[image_id]:
                continue
            rows = []
            for key in sorted(obs[image_id]):
                row = {"target": key, "uv": [float(x) for x in obs[image_id][key]]}
                if key in recovered[image_id]:
                    row["recovered"] = True
                rows.append(row)
            used.update(obs[image_id])
            images.append({"id": image_id, "observations": rows})
        doc = dict(dataset)
        doc["images"] = images
        doc["targets"] = [
            {"id": k, "xyz": [float(x) for x in points[k]], "sigma": 0}
            for k in sorted(used)
            if k in points
        ]
        return doc

    def run_calibration(label):
        calib = calibrate(parse_dataset(document(), "<recovery>"), opts)
        s = calib.statistics
        report.rounds.append(
            {
                "round": label,
                "model": str(model),
                "rms_px": float(s["rms_px"]),
                "n_observations": int(s["n_observations"]),
                "max_incidence_deg": float(s["max_incidence_deg"]),
            }
        )
        say(
            f"calibration {label}: {s['n_observations']} corners, RMS {s['rms_px']:.4f} px, "
            f"max incidence {s['max_incidence_deg']:.1f} deg"
        )
        return calib

    calib = calibration
    if calib is None:
        calib = run_calibration(0)
    else:
        report.rounds.append(
            {
                "round": "given",
                "model": str(calib.model),
                "rms_px": float(calib.statistics.get("rms_px", float("nan"))),
                "n_observations": int(calib.statistics.get("n_observations", 0)),
                "max_incidence_deg": float(calib.statistics.get("max_incidence_deg", 180.0)),
            }
        )
    for rnd in range(1, max(1, int(rounds)) + 1):
        max_inc = float(calib.statistics.get("max_incidence_deg", 170.0)) + max_extrapolation_deg
        kwargs = {
            "rng": rng,
            "max_incidence_deg": min(max_inc, 180.0),
            "max_offset_px": max_offset_px,
        }
        n_round = 0
        for image_id in ids:
            gray = cv2.imread(path_of[image_id], cv2.IMREAD_GRAYSCALE)
            if gray is None or gray.shape != (size[1], size[0]):
                continue  # unreadable, or another camera (detect_images skipped it)
            have = obs.get(image_id, {})
            if len(have) >= 4:
                added, status = predict_and_refine(gray, have, board, calib.camera, **kwargs)
            elif board.kind == "chessboard":
                added = rescue_partial_chessboard(gray, board, calib.camera, **kwargs)
                status = "ok" if added else "no partial chessboard found"
                if added:
                    report.rescued.append(image_id)
            else:
                added, status = {}, f"only {len(have)} detected corners"
            if status != "ok":
                report.failures[image_id] = status
                continue
            report.failures.pop(image_id, None)
            obs.setdefault(image_id, {}).update(added)
            recovered[image_id].update(added)
            n_round += len(added)
        say(f"round {rnd}: {n_round} corners added")
        if n_round == 0:
            break
        calib = run_calibration(rnd)
    # final check: recovered corners the recalibration finds past 5 sigma are dropped
    if any(recovered.values()):
        o = calib.extra.get("observations", {})
        res = np.linalg.norm(np.asarray(o.get("residual_px", []), float).reshape(-1, 2), axis=1)
        sigma = float(calib.statistics["sigma_px"])
        drop = 0
        for image_id, key, r in zip(o.get("image", []), o.get("target", []), res):
            if key in recovered.get(image_id, set()) and r > 5.0 * sigma:
                del obs[image_id][key]
                recovered[image_id].discard(key)
                drop += 1
        report.dropped = drop
        if drop:
            say(f"{drop} recovered corners past 5 sigma dropped")
            run_calibration("final")
        else:
            report.rounds[-1] = dict(report.rounds[-1], round="final")
    report.added = {i: len(recovered[i]) for i in ids}
    report.rescued = [i for i in dict.fromkeys(report.rescued) if recovered[i]]
    out = document()
    out["source"] = dict(
        dataset.get("source", {}),
        recovery={
            "model": str(model),
            "rounds": report.rounds,
            "added": report.total,
            "dropped": report.dropped,
        },
    )
    return out, report


# --------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``detect`` sub-command's arguments to ``parser``."""
    parser.add_argument(
        "images", nargs="*", metavar="IMAGES", help="image files (one camera; rigs: --camera)"
    )
    rig = parser.add_argument_group(
        "rigs",
        "one folder or glob per camera, images paired into frames, written as dataset@2",
    )
    rig.add_argument(
        "--camera",
        action="append",
        default=None,
        metavar="ID=DIR_OR_GLOB",
        help="a camera of the rig and its images (repeat per camera; the first is the rig frame)",
    )
    rig.add_argument(
        "--sync",
        choices=("stem", "timestamp"),
        default="stem",
        help="pair images by file-name stem (default) or by the time stamp in the name",
    )
    rig.add_argument(
        "--sync-tolerance",
        type=float,
        default=0.01,
        metavar="S",
        help="--sync timestamp: largest time difference (s) within a frame (default 0.01)",
    )
    rig.add_argument(
        "--timestamp-unit",
        choices=("auto", "s", "ms", "us", "ns"),
        default="auto",
        help="--sync timestamp: unit of the numbers in the names (default: from their digits)",
    )
    bag = parser.add_argument_group(
        "ROS bags",
        "images from a ROS1 .bag or ROS2 bag (needs the rosbags package: gtsam-sphere[ros]); "
        "one topic: dataset@1, several: a rig (dataset@2) paired by header stamp",
    )
    bag.add_argument(
        "--bag", metavar="FILE", default=None, help="ROS1 .bag file or ROS2 bag folder"
    )
    bag.add_argument(
        "--topics",
        nargs="+",
        metavar="TOPIC",
        default=None,
        help="image topics (Image or CompressedImage)",
    )
    bag.add_argument(
        "--bag-freq",
        type=float,
        default=None,
        metavar="HZ",
        help="keep at most one image per topic every 1/HZ seconds (as Kalibr's --bag-freq)",
    )
    bag.add_argument(
        "--approx-sync",
        type=float,
        default=0.02,
        metavar="S",
        help="several topics: largest stamp difference (s) in a frame (default 0.02, as Kalibr)",
    )
    target = parser.add_mutually_exclusive_group(required=True)
    target.add_argument(
        "--board",
        metavar="SPEC",
        help="target: 'chessboard:COLSxROWS:SQUARE_M' (inner corners), "
        "'charuco:SXxSY:SQUARE_M:MARKER_M:DICT', 'aprilgrid:COLSxROWS:TAG_M:SPACING' "
        "(Kalibr's) or 'aruco:DICT:MARKER_M'",
    )
    target.add_argument(
        "--target",
        metavar="TARGET.yaml",
        help="Kalibr target file (target_type aprilgrid or checkerboard) instead of --board",
    )
    parser.add_argument(
        "--markers-csv",
        metavar="CSV",
        default=None,
        help="surveyed ArUco marker centres 'id,X,Y,Z[,sigma]' (aruco targets)",
    )
    parser.add_argument(
        "-o", "--output", required=True, metavar="DATASET.json", help="output dataset file"
    )
    parser.add_argument(
        "--min-points", type=int, default=1, help="skip images with fewer observations"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--no-size-check",
        action="store_true",
        help="chessboards: accept a grid although the pattern seems to continue beyond it "
        "(by default detection stops: a board larger than described mislabels corners)",
    )
    rec = parser.add_argument_group(
        "periphery recovery",
        "calibrate the detections, predict the board corners the detector missed (and "
        "partial chessboards it skipped) with the calibration, refine them locally, keep the "
        "real saddles near their prediction, recalibrate; added observations are marked "
        '"recovered": true',
    )
    rec.add_argument(
        "--recover", action="store_true", help="recover missed corners (calibrates internally)"
    )
    rec.add_argument(
        "--recover-with",
        metavar="CALIB.json",
        default=None,
        help="recover missed corners, first predictions from this calibration@1 file",
    )
    rec.add_argument(
        "--recover-model",
        default="radial",
        help="model of the internal calibrations (default radial: smooth extrapolation)",
    )
    rec.add_argument("--recover-rounds", type=int, default=2, help="prediction rounds")
    rec.add_argument(
        "--recover-max-offset-px",
        type=float,
        default=3.0,
        help="largest distance between a prediction and its refined corner (px)",
    )


def board_from_args(args: argparse.Namespace) -> BoardSpec:
    """The target of ``--board SPEC`` or ``--target TARGET.yaml`` (Kalibr)."""
    if getattr(args, "target", None):
        return read_kalibr_target(args.target)
    if not getattr(args, "board", None):
        raise OptionsError("no target: give --board SPEC or --target TARGET.yaml")
    return BoardSpec.parse(args.board)


def run_cli(args: argparse.Namespace) -> int:
    """Run the ``detect`` sub-command; return the process exit code (0 = success)."""
    if getattr(args, "camera", None):  # a rig: detect_rig.run_cli (the command line routes it)
        raise OptionsError("--camera ID=DIR_OR_GLOB is a rig: run it with detect_rig.run_cli")
    if not args.images:
        raise OptionsError("no images: give IMAGES (one camera) or --camera ID=DIR_OR_GLOB (rig)")
    try:
        board = board_from_args(args)
        dataset, report = detect_images(
            list(args.images),
            board,
            progress=not getattr(args, "no_progress", False),
            markers_csv=args.markers_csv,
            min_points=getattr(args, "min_points", 1),
            check_size=not getattr(args, "no_size_check", False),
        )
    except (InputError, OSError) as exc:  # bad options or input files; a bug keeps its traceback
        print(f"gtsam-sphere detect: error: {exc}", file=sys.stderr)
        return 2
    recovery = None
    if getattr(args, "recover", False) or getattr(args, "recover_with", None):
        from ..core.camera import Model
        from ..io.calibration import load_calibration

        def say(line: str) -> None:
            if not getattr(args, "no_progress", False):
                print(f"recovery: {line}", file=sys.stderr, flush=True)

        if args.recover_model not in {m.value for m in Model}:
            print(
                f"gtsam-sphere detect: error: recovery: unknown --recover-model "
                f"{args.recover_model!r}; choose from {', '.join(m.value for m in Model)}",
                file=sys.stderr,
            )
            return 2
        try:
            calib = load_calibration(args.recover_with) if args.recover_with else None
            dataset, recovery = recover_dataset(
                dataset,
                list(args.images),
                board,
                model=args.recover_model,
                calibration=calib,
                rounds=args.recover_rounds,
                max_offset_px=args.recover_max_offset_px,
                progress=say,
            )
        except (InputError, OSError) as exc:
            print(f"gtsam-sphere detect: error: recovery: {exc}", file=sys.stderr)
            return 2
    write_json_atomic(dataset, args.output)
    print(report.summary())
    if recovery is not None:
        print(recovery.summary())
    print(
        f"wrote {args.output}: {len(dataset['images'])} images, {len(dataset['targets'])} targets"
    )
    return 0
