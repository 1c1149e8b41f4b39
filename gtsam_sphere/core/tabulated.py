"""Tabulated measurement corrections: a learned field sampled once on a dense pixel grid.

A kNN correction (:class:`gtsam_sphere.estimation.correct.KNNCorrection`) answers
each query with a neighbour search, about 100 us per point in scikit-learn. A
camera used inside a loop (projection of a map every frame, remap tables) needs
the same field at a fraction of that: :class:`CorrectionTable` evaluates the
field once at the nodes of a regular grid over the image (every
``spacing_px``, :data:`DEFAULT_SPACING_PX`) and interpolates bilinearly in
between, with no per-point Python. The kNN field is piecewise constant (it
jumps where the set of nearest neighbours changes), so no smoother
interpolation is closer to it than the bilinear one; how close the table is
is measured by :meth:`CorrectionTable.agreement` (on ``opencv_fisheye_left``,
see ``benchmarks/bench_camera.py``).

The table is built lazily by :meth:`gtsam_sphere.core.camera.SphereCamera.correction_table`
and cached on the camera (not written to calibration files: it is a function of
the correction, rebuilt in well under a second).
"""

from __future__ import annotations

import math

import numpy as np

#: node spacing of the default correction table (px): agrees with the kNN field within
#: 0.01 px RMS over the observed region of opencv_fisheye_left (bench_camera.py)
DEFAULT_SPACING_PX = 2.0
#: the table extends this far beyond the image on each side (px); farther out the
#: values of its edge are held (a kNN field is constant far from its data too)
DEFAULT_PAD_PX = 16.0
#: nodes evaluated per call of the correction while the table is built (memory)
BUILD_CHUNK = 65536


class CorrectionTable:
    """A correction field ``uv (N, 2) -> (N, 2)`` px tabulated on a regular grid.

    Parameters
    ----------
    correction : object with ``predict(uv_px (N, 2)) -> (N, 2)``
        The field to tabulate (evaluated once per node here, never afterwards).
    width, height : int
        Image size (px); the grid covers ``[-0.5 - pad, width - 0.5 + pad]`` by
        ``[-0.5 - pad, height - 0.5 + pad]``.
    spacing_px : float
        Node spacing (px).
    pad_px : float
        Margin of the grid beyond the image (px).

    Attributes
    ----------
    spacing_px : float
    origin_px : ndarray, shape (2,)
        Pixel of node ``(0, 0)``.
    shape : (int, int)
        Nodes ``(rows, columns)``.
    values : ndarray, shape (rows, columns, 2)
        The field at the nodes (px).
    """

    def __init__(
        self,
        correction,
        width: int,
        height: int,
        spacing_px: float = DEFAULT_SPACING_PX,
        pad_px: float = DEFAULT_PAD_PX,
    ):
        if not (math.isfinite(spacing_px) and spacing_px > 0):
            raise ValueError(f"spacing_px must be finite and > 0, got {spacing_px!r}")
        if not (math.isfinite(pad_px) and pad_px >= 0):
            raise ValueError(f"pad_px must be finite and >= 0, got {pad_px!r}")
        self.spacing_px = float(spacing_px)
        self.origin_px = np.array([-0.5 - pad_px, -0.5 - pad_px])
        n_cols = int(math.ceil((width + 2 * pad_px) / spacing_px)) + 1
        n_rows = int(math.ceil((height + 2 * pad_px) / spacing_px)) + 1
        self.shape = (n_rows, n_cols)
        nodes = self.nodes()
        values = np.empty_like(nodes)
        for s in range(0, len(nodes), BUILD_CHUNK):
            values[s : s + BUILD_CHUNK] = correction.predict(nodes[s : s + BUILD_CHUNK])
        self._set_values(values.reshape(n_rows, n_cols, 2))

    def nodes(self) -> np.ndarray:
        """Pixels (rows * columns, 2) of the nodes, row by row."""
        n_rows, n_cols = self.shape
        gu = self.origin_px[0] + self.spacing_px * np.arange(n_cols)
        gv = self.origin_px[1] + self.spacing_px * np.arange(n_rows)
        return np.stack(np.meshgrid(gu, gv), -1).reshape(-1, 2)

    def with_values(self, values: np.ndarray) -> CorrectionTable:
        """A table on the same nodes holding other ``values`` (rows, columns, 2)."""
        out = object.__new__(CorrectionTable)
        out.spacing_px = self.spacing_px
        out.origin_px = self.origin_px.copy()
        out.shape = self.shape
        out._set_values(np.asarray(values, float).reshape(*self.shape, 2))
        return out

    def _set_values(self, values: np.ndarray) -> None:
        self.values = values
        # per cell, the bilinear form a + b fx + c fy + d fx fy (fx, fy in [0, 1]) as one
        # contiguous row of 8 numbers: a lookup is one gather
        v = self.values
        f00, f01, f10, f11 = v[:-1, :-1], v[:-1, 1:], v[1:, :-1], v[1:, 1:]
        cells = np.stack([f00, f01 - f00, f10 - f00, f11 - f10 - f01 + f00], axis=2)
        cells = cells.reshape(-1, 8)
        # one contiguous array per coefficient: eight 1-D gathers beat one of rows
        self._coef = [np.ascontiguousarray(cells[:, i]) for i in range(8)]
        self._inv_h = 1.0 / self.spacing_px
        self.check = getattr(self, "check", None)

    def _locate(self, uv: np.ndarray):
        """Cell index (N,) and the position in the cell ``fx, fy`` (N,) of pixels (N, 2)."""
        n_rows, n_cols = self.shape
        with np.errstate(invalid="ignore"):
            # beyond the grid: its edge; NaN stays NaN in fx, fy (and so in the output)
            # and its cell index, whatever the cast makes of it, is clipped into the table
            x = np.clip((uv[:, 0] - self.origin_px[0]) * self._inv_h, 0.0, n_cols - 1.0)
            y = np.clip((uv[:, 1] - self.origin_px[1]) * self._inv_h, 0.0, n_rows - 1.0)
            ix = np.clip(x.astype(np.intp), 0, n_cols - 2)
            iy = np.clip(y.astype(np.intp), 0, n_rows - 2)
        return iy * (n_cols - 1) + ix, x - ix, y - iy

    def predict(self, uv_px: np.ndarray) -> np.ndarray:
        """Interpolated correction (N, 2) px at pixels (N, 2); NaN where a pixel is NaN."""
        uv = np.asarray(uv_px, float).reshape(-1, 2)
        cell, fx, fy = self._locate(uv)
        a_u, a_v, b_u, b_v, c_u, c_v, d_u, d_v = (c.take(cell) for c in self._coef)
        out = np.empty((len(uv), 2))
        out[:, 0] = a_u + fx * b_u + fy * (c_u + fx * d_u)
        out[:, 1] = a_v + fx * b_v + fy * (c_v + fx * d_v)
        nan = np.isnan(out[:, 0]) | np.isnan(out[:, 1])  # a NaN coordinate: both NaN
        if nan.any():
            out[nan] = np.nan
        return out

    def predict_with_jacobian(self, uv_px: np.ndarray):
        """Correction (N, 2) px and its derivative ``d corr / d uv`` (N, 2, 2) px/px.

        The derivative of the bilinear interpolant inside each cell (on a
        cell edge, that of the cell to its lower right).
        """
        uv = np.asarray(uv_px, float).reshape(-1, 2)
        cell, fx, fy = self._locate(uv)
        a_u, a_v, b_u, b_v, c_u, c_v, d_u, d_v = (c.take(cell) for c in self._coef)
        out = np.empty((len(uv), 2))
        out[:, 0] = a_u + fx * b_u + fy * (c_u + fx * d_u)
        out[:, 1] = a_v + fx * b_v + fy * (c_v + fx * d_v)
        J = np.empty((len(uv), 2, 2))
        J[:, 0, 0] = (b_u + fy * d_u) * self._inv_h
        J[:, 1, 0] = (b_v + fy * d_v) * self._inv_h
        J[:, 0, 1] = (c_u + fx * d_u) * self._inv_h
        J[:, 1, 1] = (c_v + fx * d_v) * self._inv_h
        bad = ~np.isfinite(uv).all(axis=1)
        if bad.any():
            out[bad] = np.nan
            J[bad] = np.nan
        return out, J

    def invert(self, w_px: np.ndarray, max_iterations: int = 50, tol_px: float = 1e-9):
        """Pixels ``uv`` (N, 2) with ``uv - table(uv) = w``, the raw pixel of a corrected one.

        One fixed-point step from ``w``, then Newton steps with the cell's own
        Jacobian on the points not yet done (no per-point Python). Inside a
        cell the table is bilinear, so a Newton step that stays in its cell
        leaves the residual ``d * sx * sy / h^2`` exactly (``d`` the cell's
        cross term, ``s`` the step): a point is done when that, or the step
        itself, is below ``tol_px``. Converges while the table changes by less
        than 1 px per px. NaN rows stay NaN.
        """
        w = np.asarray(w_px, float).reshape(-1, 2)
        first = self.predict(w)
        u = w[:, 0] + first[:, 0]
        v = w[:, 1] + first[:, 1]
        active = np.flatnonzero(np.isfinite(u) & np.isfinite(v))
        inv_h, inv_h2 = self._inv_h, self._inv_h**2
        for _ in range(max_iterations):
            if len(active) == 0:
                break
            us, vs = u[active], v[active]
            cell, fx, fy = self._locate(np.column_stack([us, vs]))
            a_u, a_v, b_u, b_v, c_u, c_v, d_u, d_v = (c.take(cell) for c in self._coef)
            # residual of uv - table(uv) - w and its Jacobian I - d table / d uv
            ru = us - (a_u + fx * b_u + fy * (c_u + fx * d_u)) - w[active, 0]
            rv = vs - (a_v + fx * b_v + fy * (c_v + fx * d_v)) - w[active, 1]
            j11 = 1.0 - (b_u + fy * d_u) * inv_h
            j12 = -(c_u + fx * d_u) * inv_h
            j21 = -(b_v + fy * d_v) * inv_h
            j22 = 1.0 - (c_v + fx * d_v) * inv_h
            det = j11 * j22 - j12 * j21
            su = (j22 * ru - j12 * rv) / det
            sv = (j11 * rv - j21 * ru) / det
            u[active] = us - su
            v[active] = vs - sv
            # done: a step below tol, or one inside its cell whose exact leftover is
            nx, ny = fx - su * inv_h, fy - sv * inv_h
            inside = (nx >= 0) & (nx <= 1) & (ny >= 0) & (ny <= 1)
            left = np.maximum(np.abs(d_u), np.abs(d_v)) * inv_h2 * np.abs(su * sv)
            small = (np.abs(su) < tol_px) & (np.abs(sv) < tol_px)
            active = active[~(small | (inside & (left < 0.5 * tol_px)))]
        return np.column_stack([u, v])

    def agreement(self, correction, uv_px: np.ndarray) -> dict[str, float]:
        """How well the table follows ``correction`` at pixels ``uv_px`` (N, 2).

        Returns
        -------
        dict
            ``rms_px`` (over both coordinates together: ``sqrt(mean |d|^2)``),
            ``max_px`` (largest ``|d|``) and ``n`` (pixels compared), where
            ``d`` is the table minus the exact prediction.
        """
        uv = np.asarray(uv_px, float).reshape(-1, 2)
        d = np.linalg.norm(self.predict(uv) - correction.predict(uv), axis=1)
        return {
            "rms_px": float(np.sqrt(np.mean(d**2))) if len(d) else math.nan,
            "max_px": float(np.max(d)) if len(d) else math.nan,
            "n": len(d),
        }

    @property
    def nbytes(self) -> int:
        """Memory held by the table (bytes)."""
        return int(self.values.nbytes + sum(c.nbytes for c in self._coef))


#: coarsest and finest node spacing :func:`choose_table` tries (px)
START_SPACING_PX = 4.0
MIN_SPACING_PX = 1.0
#: agreement :func:`choose_table` asks of the table (px RMS)
TABLE_TOL_RMS_PX = 0.01


def check_pixels(correction, width: int, height: int, n: int = 2000, seed: int = 0) -> np.ndarray:
    """Pixels (n, 2) at which to compare a table with its correction: the observed region.

    A correction that keeps its training pixels (``uv_px_``, as the kNN) is checked
    around them (a random training pixel plus a uniform offset of up to 8 px in
    each coordinate); any other over the whole image.
    """
    rng = np.random.default_rng(seed)
    train = getattr(correction, "uv_px_", None)
    if train is not None and len(train):
        train = np.asarray(train, float).reshape(-1, 2)
        pick = train[rng.integers(0, len(train), n)]
        uv = pick + rng.uniform(-8.0, 8.0, (n, 2))
    else:
        uv = rng.uniform([-0.5, -0.5], [width - 0.5, height - 0.5], (n, 2))
    return np.clip(uv, [-0.5, -0.5], [width - 0.5, height - 0.5])


def choose_table(
    correction,
    width: int,
    height: int,
    spacing_px: float | None = None,
    tol_rms_px: float = TABLE_TOL_RMS_PX,
) -> CorrectionTable:
    """A :class:`CorrectionTable` of ``correction``, fine enough to follow it.

    With ``spacing_px`` None: :data:`START_SPACING_PX`, halved (down to
    :data:`MIN_SPACING_PX`) while the RMS difference at :func:`check_pixels` exceeds
    ``tol_rms_px``. The table's ``check`` attribute holds the last
    :meth:`CorrectionTable.agreement` (``None`` when ``spacing_px`` was given).
    """
    if spacing_px is not None:
        table = CorrectionTable(correction, width, height, spacing_px)
        table.check = None
        return table
    uv = check_pixels(correction, width, height)
    spacing = START_SPACING_PX
    while True:
        table = CorrectionTable(correction, width, height, spacing)
        table.check = table.agreement(correction, uv)
        if table.check["rms_px"] <= tol_rms_px or spacing / 2 < MIN_SPACING_PX:
            return table
        spacing /= 2
