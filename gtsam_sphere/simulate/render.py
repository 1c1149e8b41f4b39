"""Rendering images of calibration targets seen through the simulator's lenses.

The renderer works backwards from the image: every output pixel is split into
``supersample x supersample`` sub-samples, each sub-sample is unprojected by the
lens (``lens.unproject``) to a ray, the ray is followed into the scene and the
target texture it hits is sampled (``cv2.remap``, bilinear); the sub-samples are
averaged (box filter over the pixel footprint). Any lens of
:mod:`gtsam_sphere.simulate.lenses` works, including fisheyes whose field of view
exceeds 180 degrees (rays with ``z < 0`` are followed like any other).

Scenes: a printed board (:func:`render_board_image`, chessboard or ChArUco, the
world frame is the board's), and an :class:`ArucoRoom`, a box room whose floor,
ceiling and walls carry ArUco markers (black code square with a white quiet zone) at
known 3-D positions and in-plane orientations. :func:`render_aruco_room` returns the image and the
true pixel of every visible marker corner and centre, keyed like
:func:`gtsam_sphere.apps.detect.detect_image` (``"M{id}"`` centre, ``"M{id}_{k}"``
corner ``k`` in OpenCV's order).

Conventions (``spec/dataset.md``): pixels ``(u, v)`` with ``(0, 0)`` the centre of
the top-left pixel; camera frame ``x`` right, ``y`` down, ``z`` forward; poses
``p_cam = R @ p_world + t``; world frame of the room: origin at a floor corner,
``X`` along the length, ``Y`` along the width, ``Z`` up, metres (as
:mod:`gtsam_sphere.simulate.room`).

Anti-aliasing: a point-sampled step edge averaged over ``S x S`` sub-samples is
quantised to ``1/S`` of a pixel (a systematic edge shift of up to ``1/(2S)`` px
for edges parallel to the pixel grid). Each marker texture is therefore pre-blurred
per image with a Gaussian of half the sub-sample spacing (measured at the marker),
which makes the sub-sample average a smooth estimate of the pixel's area integral at
the cost of a blur of about ``0.5 / S`` px: the edge shift left is below 0.007 px for
``S = 4`` and 0.03 px for ``S = 2`` (measured on pixel-aligned edges at 11 sub-pixel
phases, 8-bit output included; up to ``1 / (2 S)`` px without the pre-blur).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..apps.detect import BoardSpec

__all__ = [
    "ArucoMarker",
    "ArucoRoom",
    "make_aruco_room",
    "pixel_rays",
    "render_aruco_room",
    "render_board_image",
]


def _dictionary(name: str):
    key = str(name).upper()
    if not key.startswith("DICT_") or not hasattr(cv2.aruco, key):
        raise ValueError(f"unknown ArUco dictionary {name!r}")
    return cv2.aruco.getPredefinedDictionary(int(getattr(cv2.aruco, key)))


@dataclass(frozen=True)
class ArucoMarker:
    """One ArUco marker on a room face.

    Attributes
    ----------
    id : int
        Marker id in the room's dictionary.
    centre_m : ndarray, shape (3,)
        Centre of the black code square, world frame, metres.
    x_axis : ndarray, shape (3,)
        Unit vector (world frame) along the marker image's columns: from corner 0
        (top-left of the printed marker) to corner 1 (top-right).
    y_axis : ndarray, shape (3,)
        Unit vector (world frame) along the marker image's rows: from corner 0 to
        corner 3 (bottom-left). ``x_axis x y_axis`` points into the face (away from
        the viewer), so the marker reads the right way round from inside the room.
    size_m : float
        Side of the black code square (border bits included), metres.
    face : int
        Index of the room face the marker is printed on (see :meth:`ArucoRoom.faces`).
    """

    id: int
    centre_m: np.ndarray
    x_axis: np.ndarray
    y_axis: np.ndarray
    size_m: float
    face: int

    @property
    def normal(self) -> np.ndarray:
        """Unit normal on the printed side (towards the viewer), world frame, shape (3,)."""
        return -np.cross(self.x_axis, self.y_axis)

    def corners_m(self) -> np.ndarray:
        """Corners of the black square in OpenCV's order, world frame.

        Returns
        -------
        ndarray, shape (4, 3)
            Corner ``k`` (metres): 0 top-left, 1 top-right, 2 bottom-right,
            3 bottom-left of the printed marker, i.e. ``centre + h (sx x_axis +
            sy y_axis)`` with ``h = size / 2`` and ``(sx, sy) = (-1, -1), (1, -1),
            (1, 1), (-1, 1)``.
        """
        h = 0.5 * self.size_m
        signs = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
        return self.centre_m + h * (signs[:, :1] * self.x_axis + signs[:, 1:] * self.y_axis)


@dataclass(frozen=True)
class ArucoRoom:
    """A box room with ArUco markers on its floor, ceiling and walls.

    Attributes
    ----------
    size_m : tuple of float
        Room length ``X``, width ``Y`` and height ``Z`` (metres); the room is
        ``[0, X] x [0, Y] x [0, Z]`` in the world frame.
    markers : tuple of ArucoMarker
        The markers (unique ids, non-overlapping quiet zones).
    dictionary : str
        OpenCV dictionary name, e.g. ``"DICT_4X4_50"``.
    quiet_zone_bits : float
        Width of the white margin around each black square, in code cells.
    """

    size_m: tuple[float, float, float]
    markers: tuple[ArucoMarker, ...]
    dictionary: str = "DICT_4X4_50"
    quiet_zone_bits: float = 1.0

    def __post_init__(self) -> None:
        """Check the markers: unique valid ids, on their face, orthonormal axes, the
        printed side facing the room, inside the face (quiet zone included), no overlap.

        Raises
        ------
        ValueError
            Naming the offending marker.
        """
        size = np.asarray(self.size_m, dtype=float)
        if size.shape != (3,) or not np.all(size > 0):
            raise ValueError(f"size_m must be three positive lengths, got {self.size_m!r}")
        n_ids = int(_dictionary(self.dictionary).bytesList.shape[0])
        faces = self.faces(size)
        seen: set[int] = set()
        for m in self.markers:
            if not 0 <= m.id < n_ids or m.id in seen:
                raise ValueError(f"marker id {m.id}: duplicate or not in {self.dictionary}")
            seen.add(m.id)
            if not 0 <= m.face < 6:
                raise ValueError(f"marker {m.id}: face {m.face} is not 0..5")
            axis, coord, normal = faces[m.face]
            x, y = np.asarray(m.x_axis, float), np.asarray(m.y_axis, float)
            ok_axes = (
                abs(x @ x - 1) < 1e-9
                and abs(y @ y - 1) < 1e-9
                and abs(x @ y) < 1e-9
                and np.allclose(np.cross(x, y), -normal, atol=1e-9)
            )
            if not ok_axes:
                raise ValueError(
                    f"marker {m.id}: x_axis, y_axis must be orthonormal in face {m.face} with "
                    "x_axis x y_axis pointing into the face"
                )
            half = 0.5 * m.size_m * (1.0 + 2.0 * self.quiet_zone_bits / self.cells)
            corners = m.centre_m + half * np.array(
                [sx * x + sy * y for sx in (-1, 1) for sy in (-1, 1)]
            )
            if abs(m.centre_m[axis] - coord) > 1e-9 or not (
                np.all(corners >= -1e-9) and np.all(corners <= size + 1e-9)
            ):
                raise ValueError(f"marker {m.id}: not inside face {m.face} (quiet zone included)")
        _FaceLookup(self, list(self.markers))  # raises on overlapping markers

    @staticmethod
    def faces(size_m: Sequence[float]) -> list[tuple[int, float, np.ndarray]]:
        """The six faces as ``(axis, coordinate, inward unit normal)``.

        Face ``i`` is the plane ``X[axis] = coordinate`` (world frame, metres); the
        order is floor, ceiling, wall ``X = 0``, wall ``X = length``, wall ``Y = 0``,
        wall ``Y = width``.
        """
        lx, ly, lz = (float(s) for s in size_m)
        e = np.eye(3)
        return [
            (2, 0.0, e[2]),
            (2, lz, -e[2]),
            (0, 0.0, e[0]),
            (0, lx, -e[0]),
            (1, 0.0, e[1]),
            (1, ly, -e[1]),
        ]

    @property
    def cells(self) -> int:
        """Code cells along a marker side, border included (6 for 4x4 dictionaries)."""
        return int(_dictionary(self.dictionary).markerSize) + 2

    def target_points_m(self) -> dict[str, np.ndarray]:
        """World coordinates of every marker centre and corner.

        Returns
        -------
        dict of str to ndarray, shape (3,)
            ``"M{id}"`` -> centre, ``"M{id}_{k}"`` -> corner ``k`` (OpenCV order),
            metres, world frame.
        """
        out: dict[str, np.ndarray] = {}
        for m in self.markers:
            out[f"M{m.id}"] = np.asarray(m.centre_m, float).copy()
            for k, c in enumerate(m.corners_m()):
                out[f"M{m.id}_{k}"] = c
        return out


def make_aruco_room(
    size_m: Sequence[float] = (4.0, 3.5, 2.6),
    marker_m: float = 0.25,
    *,
    n_markers: int | None = None,
    dictionary: str = "DICT_4X4_50",
    quiet_zone_bits: float = 1.0,
    seed: int = 0,
) -> ArucoRoom:
    """Place ArUco markers over the faces of a box room.

    Markers are spread over the six faces in proportion to their area: each face is
    cut into a grid of cells, a random subset of cells receives one marker each, at
    a random position inside the cell and a random in-plane rotation (any angle),
    such that markers (with their quiet zones) never overlap each other or a face's
    edge.

    Parameters
    ----------
    size_m : sequence of 3 float
        Room length, width and height (metres).
    marker_m : float
        Side of each black code square (metres).
    n_markers : int, optional
        Number of markers (ids ``0 .. n_markers - 1``); default: every id of the
        dictionary.
    dictionary : str
        OpenCV ArUco dictionary name.
    quiet_zone_bits : float
        White margin around each marker, in code cells.
    seed : int
        Random seed of positions and rotations.

    Returns
    -------
    ArucoRoom

    Raises
    ------
    ValueError
        If the dictionary is unknown, has fewer than ``n_markers`` ids, or the
        markers do not fit on the faces.
    """
    d = _dictionary(dictionary)
    n_dict = int(d.bytesList.shape[0])
    n = n_dict if n_markers is None else int(n_markers)
    if not 1 <= n <= n_dict:
        raise ValueError(f"n_markers={n_markers}: {dictionary} has ids 0..{n_dict - 1}")
    size = tuple(float(s) for s in size_m)
    if len(size) != 3 or min(size) <= 0:
        raise ValueError(f"size_m must be three positive lengths, got {size_m!r}")
    cells = int(d.markerSize) + 2
    radius = (0.5 * marker_m + quiet_zone_bits * marker_m / cells) * math.sqrt(2.0)
    rng = np.random.default_rng(seed)
    faces = ArucoRoom.faces(size)
    spans = []  # (in-plane axes, extents) of each face
    for axis, _, _ in faces:
        a, b = [i for i in range(3) if i != axis]
        spans.append((a, b, size[a], size[b]))
    areas = np.array([s[2] * s[3] for s in spans])
    raw = n * areas / areas.sum()
    counts = np.floor(raw).astype(int)
    for i in np.argsort(-(raw - counts))[: n - counts.sum()]:
        counts[i] += 1
    ids = rng.permutation(n)
    markers: list[ArucoMarker] = []
    gap = 0.05  # metres between a quiet zone and a face edge / cell edge
    for f, ((axis, coord, normal), (a, b, la, lb), count) in enumerate(
        zip(faces, spans, counts, strict=True)
    ):
        if count == 0:
            continue
        na = max(1, int(round(math.sqrt(count * la / lb))))
        nb = int(math.ceil(count / na))
        ca, cb = la / na, lb / nb
        slack_a, slack_b = 0.5 * ca - radius - gap, 0.5 * cb - radius - gap
        if min(slack_a, slack_b) < 0:
            raise ValueError(
                f"{count} markers of {marker_m} m do not fit on face {f} ({la} x {lb} m)"
            )
        chosen = rng.permutation(na * nb)[:count]
        for cell in chosen:
            ia, ib = cell % na, cell // na
            centre = np.zeros(3)
            centre[axis] = coord
            centre[a] = (ia + 0.5) * ca + rng.uniform(-slack_a, slack_a)
            centre[b] = (ib + 0.5) * cb + rng.uniform(-slack_b, slack_b)
            psi = rng.uniform(0.0, 2.0 * math.pi)
            x_axis = np.zeros(3)
            x_axis[a], x_axis[b] = math.cos(psi), math.sin(psi)
            y_axis = np.cross(x_axis, normal)  # x_axis x y_axis = -normal (into the face)
            markers.append(
                ArucoMarker(int(ids[len(markers)]), centre, x_axis, y_axis, float(marker_m), f)
            )
    return ArucoRoom(size, tuple(markers), str(dictionary).upper(), float(quiet_zone_bits))


def pixel_rays(
    lens: Any, width: int, height: int, supersample: int = 4, *, exact: bool = False
) -> np.ndarray:
    """Camera-frame rays of every sub-sample of every pixel.

    Sub-sample ``(i, j)`` of pixel ``(u, v)`` sits at ``(u + o_j, v + o_i)`` with
    ``o = (k + 0.5) / S - 0.5``, ``k = 0 .. S - 1`` (a regular grid over the pixel's
    footprint). The rays depend only on the lens, so one array serves every pose.

    By default the lens is unprojected exactly at the integer pixel positions
    ``u = -1 .. width``, ``v = -1 .. height`` and the sub-sample rays are interpolated
    bilinearly between them and normalised: a lens with an iterative ``unproject``
    (Kannala-Brandt, decentering) then costs one unprojection per pixel instead of
    ``S * S``. The interpolation error is second order in the 1 px grid step: re-projected
    sub-samples land within ``0.15 / f`` px of their position (``f`` the lens scale in
    px; 4e-4 px for a 200 degree fisheye filling a 600 px circle; the test suite checks
    the bound). Sub-samples next to the lens's image-circle boundary (where a
    neighbouring grid ray is NaN) are NaN.

    Parameters
    ----------
    lens : lens object
        Anything with ``unproject(uv (N, 2)) -> rays (N, 3)`` (camera frame).
    width, height : int
        Image size in pixels.
    supersample : int
        Sub-samples ``S`` per pixel along each axis.
    exact : bool
        Unproject every sub-sample with the lens instead of interpolating.

    Returns
    -------
    ndarray, shape (S * S, height, width, 3), float32
        Unit rays (camera frame); NaN where the lens images nothing.
    """
    ss = int(supersample)
    if ss < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    offs = (np.arange(ss) + 0.5) / ss - 0.5

    def unproject(uv: np.ndarray) -> np.ndarray:
        with np.errstate(all="ignore"):
            r = np.asarray(lens.unproject(uv), dtype=np.float64).reshape(-1, 3)
            return r / np.linalg.norm(r, axis=1, keepdims=True)

    out = np.empty((ss * ss, height, width, 3), dtype=np.float32)
    if exact:
        vv, uu = np.mgrid[0:height, 0:width].astype(np.float64)
        for i, dv in enumerate(offs):
            for j, du in enumerate(offs):
                uv = np.stack([(uu + du).ravel(), (vv + dv).ravel()], axis=1)
                out[i * ss + j] = unproject(uv).reshape(height, width, 3)
        return out
    vv, uu = np.mgrid[-1 : height + 1, -1 : width + 1].astype(np.float64)
    grid = unproject(np.stack([uu.ravel(), vv.ravel()], axis=1)).reshape(height + 2, width + 2, 3)
    for i, dv in enumerate(offs):
        # node row v0 = v + floor(dv) (grid index +1 for the -1 border), weight fv on v0 + 1
        r0, fv = int(np.floor(dv)) + 1, dv - np.floor(dv)
        for j, du in enumerate(offs):
            c0, fu = int(np.floor(du)) + 1, du - np.floor(du)
            g00 = grid[r0 : r0 + height, c0 : c0 + width]
            g01 = grid[r0 : r0 + height, c0 + 1 : c0 + 1 + width]
            g10 = grid[r0 + 1 : r0 + 1 + height, c0 : c0 + width]
            g11 = grid[r0 + 1 : r0 + 1 + height, c0 + 1 : c0 + 1 + width]
            r = (1 - fv) * ((1 - fu) * g00 + fu * g01) + fv * ((1 - fu) * g10 + fu * g11)
            r /= np.linalg.norm(r, axis=2, keepdims=True)
            out[i * ss + j] = r
    return out


def _texture_atlas(
    room: ArucoRoom,
    markers: list[ArucoMarker],
    lens: Any,
    R: np.ndarray,
    t: np.ndarray,
    n_sub: int,
    tpb: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Marker textures (1 = white, 0 = black) side by side in one float32 image.

    Each tile holds a marker with its quiet zone (``cells + 2 * quiet_zone`` code cells
    of ``tpb`` texels), pre-blurred by half the sub-sample spacing at the marker's
    coarsest pixel scale in this view (see the module docstring). Returns the atlas
    and the texel origin ``(x, y)`` of every marker's tile, shape ``(len(markers), 2)``.
    """
    d = _dictionary(room.dictionary)
    cells = room.cells
    pad = int(round(room.quiet_zone_bits * tpb))
    side = cells * tpb + 2 * pad
    gap = 4  # white texels between tiles: bilinear samples never reach a neighbour
    n = max(1, len(markers))
    n_col = int(math.ceil(math.sqrt(n)))
    n_row = int(math.ceil(n / n_col))
    step = side + gap
    atlas = np.ones((n_row * step + gap, n_col * step + gap), dtype=np.float32)
    origin = np.zeros((len(markers), 2))
    sub_spacing_px = 1.0 / math.sqrt(n_sub)
    for i, m in enumerate(markers):
        img = cv2.aruco.generateImageMarker(d, int(m.id), cells * tpb, borderBits=1)
        img = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
        tex = (img > 127).astype(np.float32)
        # coarsest pixel scale over the marker: projected length of small steps
        pts = np.concatenate([m.corners_m(), m.centre_m[None]])
        h = 0.05 * m.size_m
        uv0 = np.asarray(lens.project(pts @ R.T + t), float)
        scale = [
            np.linalg.norm(np.asarray(lens.project((pts + h * a) @ R.T + t), float) - uv0, axis=1)
            / h
            for a in (m.x_axis, m.y_axis)
        ]
        px_per_m = np.concatenate(scale)
        px_per_m = px_per_m[np.isfinite(px_per_m) & (px_per_m > 0)]
        if px_per_m.size:
            texel_per_px = tpb * cells / (m.size_m * float(px_per_m.min()))
            tex = cv2.GaussianBlur(tex, (0, 0), max(0.5 * sub_spacing_px * texel_per_px, 0.7))
        r, c = divmod(i, n_col)
        y0, x0 = gap + r * step, gap + c * step
        atlas[y0 : y0 + side, x0 : x0 + side] = tex
        origin[i] = (x0, y0)
    return atlas, origin


class _FaceLookup:
    """Which marker (index into ``markers``, -1 for none) may cover a point of a face.

    A 1 cm raster per face labels the raster cells within one cell diagonal of a
    marker's square (quiet zone included); the caller still tests the exact square.

    Raises
    ------
    ValueError
        If two markers claim the same raster cell (squares overlapping or closer than
        about 1.5 cm).
    """

    res = 0.01

    def __init__(self, room: ArucoRoom, markers: list[ArucoMarker]):
        self.faces = room.faces(room.size_m)
        self.axes = []
        self.shapes = []
        self.offsets = []
        total = 0
        for axis, _, _ in self.faces:
            a, b = [i for i in range(3) if i != axis]
            shape = (
                int(math.ceil(room.size_m[a] / self.res)),
                int(math.ceil(room.size_m[b] / self.res)),
            )
            self.axes.append((a, b))
            self.shapes.append(shape)
            self.offsets.append(total)
            total += shape[0] * shape[1]
        self.flat = np.full(total, -1, dtype=np.int32)
        cells = room.cells
        slack = self.res / math.sqrt(2.0) + 1e-9  # half a raster cell diagonal
        for k, m in enumerate(markers):
            a, b = self.axes[m.face]
            na, nb = self.shapes[m.face]
            half = 0.5 * m.size_m + room.quiet_zone_bits * m.size_m / cells
            reach = half * math.sqrt(2.0) + self.res
            ia = np.arange(
                max(0, int((m.centre_m[a] - reach) / self.res)),
                min(na, int((m.centre_m[a] + reach) / self.res) + 1),
            )
            ib = np.arange(
                max(0, int((m.centre_m[b] - reach) / self.res)),
                min(nb, int((m.centre_m[b] + reach) / self.res) + 1),
            )
            ga, gb = np.meshgrid(ia, ib, indexing="ij")
            rel = np.zeros((ga.size, 3))
            rel[:, a] = (ga.ravel() + 0.5) * self.res - m.centre_m[a]
            rel[:, b] = (gb.ravel() + 0.5) * self.res - m.centre_m[b]
            near = (np.abs(rel @ m.x_axis) <= half + slack) & (
                np.abs(rel @ m.y_axis) <= half + slack
            )
            flat = self.offsets[m.face] + ga.ravel()[near] * nb + gb.ravel()[near]
            taken = self.flat[flat]
            if np.any(taken >= 0):
                other = markers[int(taken[taken >= 0][0])].id
                raise ValueError(f"markers {other} and {m.id} overlap (quiet zones included)")
            self.flat[flat] = k

    def __call__(self, hit: np.ndarray, axis: np.ndarray, positive: np.ndarray) -> np.ndarray:
        """Marker labels (N,) of world points ``hit`` (N, 3) on the faces they lie on.

        Point ``i`` lies on the plane ``X[axis[i]] = size`` if ``positive[i]``, else on
        ``X[axis[i]] = 0``.
        """
        label = np.full(len(hit), -1, dtype=np.int32)
        for f, (fa, _, normal) in enumerate(self.faces):
            sel = np.flatnonzero((axis == fa) & (positive == (normal[fa] < 0)))
            if sel.size == 0:
                continue
            a, b = self.axes[f]
            na, nb = self.shapes[f]
            ia = np.clip((hit[sel, a] / self.res).astype(np.int64), 0, na - 1)
            ib = np.clip((hit[sel, b] / self.res).astype(np.int64), 0, nb - 1)
            label[sel] = self.flat[self.offsets[f] + ia * nb + ib]
        return label


def _remap_points(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` at texel positions ``(x, y)`` (N,) with ``cv2.remap``.

    The points are laid out as rows of 1024 (``cv2.remap`` refuses maps whose sides
    exceed 32767).
    """
    n = len(x)
    cols = 1024
    rows = -(-n // cols)
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(
        image,
        mx.reshape(rows, cols),
        my.reshape(rows, cols),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return out.ravel()[:n]


def render_aruco_room(
    room: ArucoRoom,
    lens: Any,
    cam_from_world_R: np.ndarray,
    cam_from_world_t: np.ndarray,
    width: int,
    height: int,
    *,
    supersample: int = 4,
    rays: np.ndarray | None = None,
    texels_per_bit: int = 48,
    black: float = 25.0,
    white: float = 230.0,
    wall: float = 140.0,
    outside: float = 0.0,
    blur_sigma_px: float = 0.0,
    noise_sigma: float = 0.0,
    seed: int = 0,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Render a room of ArUco markers as seen through a simulated lens.

    Each sub-sample ray (:func:`pixel_rays`) is moved to the world frame, intersected
    with the room's six planes (the camera is inside the box, so the nearest hit in
    front of the ray is the face it sees), and the texture of the marker covering the
    hit (if any) is sampled bilinearly with ``cv2.remap``; faces are a uniform grey
    elsewhere. Sub-samples are averaged, then optional optical blur and noise are
    added.

    Parameters
    ----------
    room : ArucoRoom
        The scene (world frame, metres).
    lens : lens object
        ``project(points_cam (N, 3)) -> uv (N, 2)`` px and
        ``unproject(uv (N, 2)) -> rays (N, 3)``, e.g. from
        :func:`gtsam_sphere.simulate.lenses.make_lens`.
    cam_from_world_R : ndarray, shape (3, 3)
        Rotation world -> camera, ``p_cam = R @ p_world + t``.
    cam_from_world_t : ndarray, shape (3,)
        Translation (metres); the camera centre ``-R.T @ t`` must be inside the room.
    width, height : int
        Image size in pixels.
    supersample : int
        Sub-samples per pixel along each axis (ignored when ``rays`` is given).
    rays : ndarray, shape (S * S, height, width, 3), optional
        Precomputed :func:`pixel_rays` of ``lens`` (saves the unprojection when
        rendering several poses).
    texels_per_bit : int
        Texture resolution of a code cell.
    black, white, wall, outside : float
        Grey levels of the marker's dark cells, of its light cells and quiet zone,
        of the bare faces, and of pixels the lens images nothing into.
    blur_sigma_px : float
        Gaussian blur (pixels) of the rendered image (optics); 0 = none.
    noise_sigma : float
        Additive Gaussian noise (grey levels).
    seed : int
        Noise seed.

    Returns
    -------
    image : ndarray, shape (height, width), uint8
        Rendered grey image.
    truth : dict of str to ndarray, shape (2,)
        ``"M{id}"`` (centre) and ``"M{id}_{k}"`` (corner ``k``, OpenCV order) ->
        true ``(u, v)`` pixels of every such point the lens images inside the image
        (``-0.5 <= u <= width - 0.5``, same for ``v``), for markers whose printed side
        faces the camera.

    Raises
    ------
    ValueError
        If the camera is not inside the room or ``rays`` has the wrong shape.
    """
    R = np.asarray(cam_from_world_R, dtype=np.float64).reshape(3, 3)
    t = np.asarray(cam_from_world_t, dtype=np.float64).reshape(3)
    centre = -R.T @ t
    size = np.asarray(room.size_m, float)
    if not (np.all(centre > 0) and np.all(centre < size)):
        raise ValueError(f"camera centre {centre.tolist()} is not inside the room {size.tolist()}")
    if rays is None:
        rays = pixel_rays(lens, width, height, supersample)
    rays = np.asarray(rays)
    if rays.ndim != 4 or rays.shape[1:] != (height, width, 3):
        raise ValueError(f"rays must have shape (S*S, {height}, {width}, 3), got {rays.shape}")
    markers = [m for m in room.markers if float(m.normal @ (centre - m.centre_m)) > 0]
    atlas, tile_origin = _texture_atlas(room, markers, lens, R, t, rays.shape[0], texels_per_bit)
    atlas = black + (white - black) * atlas
    lookup = _FaceLookup(room, markers)
    cells, qz, tpb = room.cells, room.quiet_zone_bits, int(texels_per_bit)
    m_centre = np.array([m.centre_m for m in markers]).reshape(-1, 3)
    m_x = np.array([m.x_axis for m in markers]).reshape(-1, 3)
    m_y = np.array([m.y_axis for m in markers]).reshape(-1, 3)
    m_bit = np.array([m.size_m / cells for m in markers])
    lo, hi = np.zeros(3), size

    def trace(r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Grey values, marker labels and validity of camera-frame rays (N, 3)."""
        r = r.astype(np.float64)
        # world-frame directions R^T r, written out (faster than a BLAS call on (N, 3))
        d = r[:, :1] * R[0] + r[:, 1:2] * R[1] + r[:, 2:] * R[2]
        valid = np.all(np.isfinite(d), axis=1)
        d[~valid] = (0.0, 0.0, 1.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            lam_axes = (np.where(d > 0, hi, lo) - centre) / d
        lam_axes[~np.isfinite(lam_axes) | (lam_axes <= 0)] = np.inf
        axis = np.argmin(lam_axes, axis=1)  # the ray leaves the box through this axis' plane
        rows = np.arange(len(d))
        hit = centre + lam_axes[rows, axis][:, None] * d
        label = lookup(hit, axis, d[rows, axis] > 0)
        label[~valid] = -1
        value = np.where(valid, float(wall), float(outside))
        idx = np.flatnonzero(label >= 0)
        if idx.size:
            k = label[idx]
            rel = hit[idx] - m_centre[k]
            x = np.einsum("ij,ij->i", rel, m_x[k]) / m_bit[k] + 0.5 * cells  # cells from corner 0
            y = np.einsum("ij,ij->i", rel, m_y[k]) / m_bit[k] + 0.5 * cells
            inside = (x >= -qz) & (x <= cells + qz) & (y >= -qz) & (y <= cells + qz)
            idx, k, x, y = idx[inside], k[inside], x[inside], y[inside]
            mx = tile_origin[k, 0] + (x + qz) * tpb - 0.5
            my = tile_origin[k, 1] + (y + qz) * tpb - 0.5
            value[idx] = _remap_points(atlas, mx, my)
        return value, label, valid

    n_sub = rays.shape[0]
    flat = rays.reshape(n_sub, height * width, 3)
    # Pixels away from every marker see bare wall (or nothing): only the pixels within
    # 2 px of a marker's lookup region (which exceeds the marker by >= 1 cm) get every
    # sub-sample traced; the others get the wall / outside grey by their valid fraction.
    value0, label0, _ = trace(flat[0])
    near = (label0 >= 0).reshape(height, width).astype(np.uint8)
    near = cv2.dilate(near, np.ones((5, 5), np.uint8)).ravel() > 0
    frac = np.mean(np.all(np.isfinite(flat), axis=2), axis=0)
    acc = float(wall) * frac + float(outside) * (1.0 - frac)
    idx = np.flatnonzero(near)
    if idx.size:
        total = np.zeros(idx.size)
        for s in range(n_sub):
            total += value0[idx] if s == 0 else trace(flat[s, idx])[0]
        acc[idx] = total / n_sub
    image = _finish_image(acc.reshape(height, width), blur_sigma_px, noise_sigma, seed)

    truth: dict[str, np.ndarray] = {}
    points = room.target_points_m()
    facing = {m.id: float(m.normal @ (centre - m.centre_m)) > 0 for m in room.markers}
    keys = [k for k in points if facing[int(k[1:].split("_")[0])]]
    if keys:
        xyz = np.array([points[k] for k in keys])
        uv = np.asarray(lens.project(xyz @ R.T + t), dtype=np.float64).reshape(-1, 2)
        for k, q in zip(keys, uv, strict=True):
            if _inside_image(q, width, height):
                truth[k] = q
    return image, truth


def _finish_image(img: np.ndarray, blur_sigma_px: float, noise_sigma: float, seed: int):
    """Optics blur (Gaussian, px), additive noise (grey levels, seeded), 8-bit quantisation
    of a float image (H, W); returns uint8 (H, W)."""
    if blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
    if noise_sigma > 0:
        img = img + np.random.default_rng(seed).normal(0.0, noise_sigma, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def _inside_image(q: np.ndarray, width: int, height: int) -> bool:
    """A finite pixel ``(u, v)`` on the image (pixel centres at integers)."""
    return bool(
        np.all(np.isfinite(q)) and -0.5 <= q[0] <= width - 0.5 and -0.5 <= q[1] <= height - 0.5
    )


# --------------------------------------------------------------------------------------
# Printed boards (chessboard, ChArUco)
# --------------------------------------------------------------------------------------


def _aprilgrid_texture(board: BoardSpec, px_per_tag: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Texture of Kalibr's AprilGrid (see :func:`_board_texture`), rows along board ``+y``.

    Tags of 10 x 10 cells (the 6 x 6 tag36h11 code inside a 2-cell black border, as
    Kalibr prints them: OpenCV's marker image turned by 180 degrees), tag 0 at the
    board origin, tag ``t`` in tag row ``t // cols``
    (board ``y`` up the printed target), column ``t % cols``; a black square of the gap's
    side at every tag corner (inner and outer), one tag pitch of white margin around.
    ``px_per_tag`` is rounded up to a multiple of 10 that makes the gap a whole number of
    texels.
    """
    cells = 10
    ppc = max(1, int(np.ceil(px_per_tag / cells)))
    for _ in range(1000):
        gap = board.spacing * cells * ppc
        if abs(gap - round(gap)) < 1e-6:
            break
        ppc += 1
    else:
        raise ValueError(
            f"tag spacing {board.spacing} is not a multiple of 1/{cells * ppc} of the tag: "
            "cannot render it on a texel grid"
        )
    tag, gap = cells * ppc, int(round(board.spacing * cells * ppc))
    pitch = tag + gap
    margin = pitch
    width = board.cols * pitch - gap + 2 * margin
    height = board.rows * pitch - gap + 2 * margin
    tex = np.full((height, width), 255, dtype=np.uint8)
    dictionary = board.aruco_dictionary()
    for t in range(board.cols * board.rows):
        y0 = margin + (t // board.cols) * pitch
        x0 = margin + (t % board.cols) * pitch
        img = cv2.aruco.generateImageMarker(dictionary, t, tag, borderBits=2)
        # Kalibr prints OpenCV's marker image rotated by 180 degrees (BoardSpec.
        # aprilgrid_corner_ids); texture rows go up the page: flipud(rot180) = fliplr
        tex[y0 : y0 + tag, x0 : x0 + tag] = np.fliplr(img)
    for i in range(board.rows + 1):
        for j in range(board.cols + 1):
            y0, x0 = margin + i * pitch - gap, margin + j * pitch - gap
            tex[y0 : y0 + gap, x0 : x0 + gap] = 0
    texel_m = board.marker_m / tag
    return tex, -np.array([1.0, 1.0]) * margin * texel_m, texel_m


def _board_texture(board: BoardSpec, px_per_square: int) -> tuple[np.ndarray, np.ndarray, float]:
    """High-resolution board texture and the board coordinates of its texel origin.

    Returns ``(texture uint8 (H, W), origin_m (2,), texel_m)``: texel ``(i, j)`` covers
    board ``x`` in ``origin + [j, j+1) * texel_m`` (likewise ``y`` with ``i``);
    ``texel_m = square / px_per_square`` (AprilGrids: ``px_per_square`` texels per tag,
    see :func:`_aprilgrid_texture`).
    """
    if board.kind == "aprilgrid":
        return _aprilgrid_texture(board, px_per_square)
    pps = int(px_per_square)
    if board.kind == "chessboard":
        nx, ny = board.cols + 1, board.rows + 1  # squares
        margin = pps  # one square of white border
        j = (np.arange(nx * pps + 2 * margin) - margin) // pps
        i = (np.arange(ny * pps + 2 * margin) - margin) // pps
        inside = (i[:, None] >= 0) & (i[:, None] < ny) & (j[None] >= 0) & (j[None] < nx)
        dark = ((i[:, None] + j[None]) % 2 == 0) & inside
        tex = np.where(dark, 0, 255).astype(np.uint8)
        # Board frame origin is the first inner corner, one square inside the board.
        origin = -np.array([1.0, 1.0]) * board.square_m - margin / pps * board.square_m
        return tex, origin, board.square_m / pps
    if board.kind == "charuco":
        margin = pps
        size = (board.cols * pps + 2 * margin, board.rows * pps + 2 * margin)
        tex = board.charuco_board().generateImage(size, marginSize=margin, borderBits=1)
        origin = -np.array([1.0, 1.0]) * margin / pps * board.square_m
        return np.asarray(tex, dtype=np.uint8), origin, board.square_m / pps
    raise ValueError(
        f"rendering supports chessboard, charuco and aprilgrid boards, not {board.kind!r}"
    )


def render_board_image(
    board: BoardSpec,
    lens_project: Callable[[np.ndarray], np.ndarray],
    lens_unproject: Callable[[np.ndarray], np.ndarray],
    cam_from_world_R: np.ndarray,
    cam_from_world_t: np.ndarray,
    width: int,
    height: int,
    px_per_square: int = 48,
    *,
    supersample: int = 4,
    background: int = 128,
    blur_sigma_px: float = 0.0,
    noise_sigma: float = 0.0,
    seed: int = 0,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Render a printed board as seen through an arbitrary camera.

    Every output pixel is split into ``supersample x supersample`` sub-samples; each is
    unprojected to a ray, intersected with the board plane, and the board texture
    (``px_per_square`` texels per square) is sampled bilinearly (``cv2.remap``); the
    sub-samples are averaged (box anti-aliasing over the pixel footprint).

    Parameters
    ----------
    board : BoardSpec
        ``"chessboard"``, ``"charuco"`` or ``"aprilgrid"`` board (Kalibr's frame: x
        right, y up the printed target, z towards its viewer); the world frame is the
        board frame.
    lens_project : callable
        ``project(points_cam (N, 3)) -> uv (N, 2)`` pixels.
    lens_unproject : callable
        ``unproject(uv (N, 2)) -> rays (N, 3)`` in the camera frame (any length).
    cam_from_world_R : ndarray, shape (3, 3)
        Rotation board -> camera, ``p_cam = R @ p_board + t``.
    cam_from_world_t : ndarray, shape (3,)
        Translation in metres.
    width, height : int
        Image size in pixels.
    px_per_square : int, optional
        Texture resolution (texels per board square; AprilGrids: per tag, rounded up
        to a multiple of 10).
    supersample : int, optional
        Sub-samples per pixel along each axis.
    background : int, optional
        Grey level where rays miss the board (or hit it from behind).
    blur_sigma_px : float, optional
        Gaussian blur (pixels) applied to the rendered image (optics), 0 = none.
    noise_sigma : float, optional
        Additive Gaussian noise (grey levels).
    seed : int, optional
        Noise seed.

    Returns
    -------
    image : ndarray, shape (height, width), uint8
        Rendered grey image.
    truth : dict of str to ndarray, shape (2,)
        Target id -> projected ``(u, v)`` pixels of every board corner in front of the
        camera and inside the image.
    """
    R = np.asarray(cam_from_world_R, dtype=np.float64).reshape(3, 3)
    t = np.asarray(cam_from_world_t, dtype=np.float64).reshape(3)
    tex, origin, texel_m = _board_texture(board, px_per_square)
    ss = int(supersample)
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    acc = np.zeros((height, width), dtype=np.float64)
    normal = R[:, 2]  # board z axis in the camera frame
    d0 = float(normal @ t)  # plane: normal . p = d0
    vv, uu = np.mgrid[0:height, 0:width].astype(np.float64)
    for dv in offs:
        for du in offs:
            uv = np.stack([(uu + du).ravel(), (vv + dv).ravel()], axis=1)
            rays = np.asarray(lens_unproject(uv), dtype=np.float64).reshape(-1, 3)
            denom = rays @ normal
            with np.errstate(divide="ignore", invalid="ignore"):
                lam = d0 / denom
            valid = np.isfinite(lam) & (lam > 0) & np.all(np.isfinite(rays), axis=1)
            p_cam = rays * np.where(valid, lam, 0.0)[:, None]
            p_board = (p_cam - t) @ R  # R^T (p - t)
            mx = (p_board[:, 0] - origin[0]) / texel_m - 0.5
            my = (p_board[:, 1] - origin[1]) / texel_m - 0.5
            mx = np.where(valid, mx, -10.0).astype(np.float32).reshape(height, width)
            my = np.where(valid, my, -10.0).astype(np.float32).reshape(height, width)
            sample = cv2.remap(
                tex.astype(np.float32),
                mx,
                my,
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=float(background),
            )
            acc += sample
    image = _finish_image(acc / (ss * ss), blur_sigma_px, noise_sigma, seed)

    truth: dict[str, np.ndarray] = {}
    obj = board.object_points_m()
    if obj:
        keys = list(obj)
        pts = np.array([obj[k] for k in keys]) @ R.T + t
        uv = np.asarray(lens_project(pts), dtype=np.float64).reshape(-1, 2)
        for k, p, q in zip(keys, pts, uv, strict=True):
            # Corners seen from behind the board are not visible. The camera is on the
            # printed side when normal . p_cam > 0 (board y down the print), < 0 for
            # AprilGrids (Kalibr's frame: y up the print, z towards the viewer).
            facing = float(normal @ p) * (-1.0 if board.kind == "aprilgrid" else 1.0) > 0
            if facing and _inside_image(q, width, height):
                truth[k] = q
    return image, truth
