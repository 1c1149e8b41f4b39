"""mrcal's splined stereographic lens model (``LENSMODEL_SPLINED_STEREOGRAPHIC_...``).

The model as mrcal documents it (https://mrcal.secretsauce.net/splined-models.html,
"Projection function" and "Field-of-view selection"; the model string's grammar on
https://mrcal.secretsauce.net/lensmodels.html): a ray ``p`` (camera frame, x right,
y down, z forward) has the normalized stereographic projection

    ``theta = atan2(|p_xy|, p_z)``, ``u = p_xy / |p_xy| * 2 tan(theta / 2)``
    (equivalently ``u = 2 p_xy / (|p| + p_z)``),

two B-spline surfaces over the ``u`` plane give a correction ``du = (dux(u),
duy(u))``, and the pixel is ``q = (fx (ux + dux) + cx, fy (uy + duy) + cy)``.

The control points ("knots") form a regular ``Nx`` by ``Ny`` grid on the ``u`` plane,
centred on ``u = 0``, with one spacing ``h`` in both directions. ``fov_x_deg`` is the
horizontal field the spline's valid region spans: its edge is at ``|ux| = 2 tan(fov_x /
4)``, and ``Nx - order`` spline intervals span ``[-u_edge, u_edge]``, so ``h = 2 u_edge
/ (Nx - order)``; the vertical valid region is ``(Ny - order) h / 2`` either side of
the axis. This package writes ``order=3`` (cubic, uniform B-splines): in an interval
``[k_i, k_i + h)`` with ``s = (x - k_i) / h`` the surface is ``sum_j b_j(s) c_{i-1+j}``
with ``b = ((1 - s)^3, 3 s^3 - 6 s^2 + 4, -3 s^3 + 3 s^2 + 3 s + 1, s^3) / 6``, a tensor
product in ``x`` and ``y``; outside the valid region the edge intervals' polynomials
are continued. The intrinsics vector is ``fx, fy, cx, cy`` then, per control point in
row-major order (``y`` slow, ``x`` fast), ``dux`` and ``duy``: ``4 + 2 Nx Ny`` numbers.

This implementation is written from that description; ``tests/test_export_formats.py``
checks it against mrcal itself when Debian's ``python3-mrcal`` is installed.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

__all__ = [
    "SplineConfig",
    "stereographic_u",
    "splined_project",
]

_NAME = re.compile(
    r"^LENSMODEL_SPLINED_STEREOGRAPHIC_order=(\d+)_Nx=(\d+)_Ny=(\d+)_fov_x_deg=(\d+(?:\.\d*)?)$"
)


@dataclass(frozen=True)
class SplineConfig:
    """The configuration of a splined stereographic model (not optimised).

    Attributes
    ----------
    Nx, Ny : int
        Control points across and down (each at least ``order + 1``).
    fov_x_deg : int
        Horizontal field (deg) the valid region spans.
    order : int
        B-spline order; only 3 (cubic) is implemented.
    """

    Nx: int
    Ny: int
    fov_x_deg: int
    order: int = 3

    def __post_init__(self):
        if self.order != 3:
            raise ValueError(f"splined model order={self.order}: only order=3 is implemented")
        if self.Nx < 4 or self.Ny < 4:
            raise ValueError(f"splined model needs Nx, Ny >= 4, got {self.Nx}, {self.Ny}")
        if not 0 < self.fov_x_deg < 360:
            raise ValueError(f"splined model fov_x_deg={self.fov_x_deg} is not in (0, 360)")

    @property
    def lensmodel(self) -> str:
        """mrcal's model string (``fov_x_deg`` in whole degrees):
        ``LENSMODEL_SPLINED_STEREOGRAPHIC_order=.._Nx=.._Ny=.._fov_x_deg=..``."""
        return (
            f"LENSMODEL_SPLINED_STEREOGRAPHIC_order={self.order}_Nx={self.Nx}_Ny={self.Ny}"
            f"_fov_x_deg={int(self.fov_x_deg)}"
        )

    @classmethod
    def parse(cls, lensmodel: str) -> SplineConfig:
        """The configuration of a model string; ``ValueError`` naming it when malformed."""
        m = _NAME.match(str(lensmodel).strip())
        if not m:
            raise ValueError(
                f"{lensmodel!r} is not LENSMODEL_SPLINED_STEREOGRAPHIC_order=.._Nx=.._Ny=.."
                "_fov_x_deg=.."
            )
        order, nx, ny, fov = int(m[1]), int(m[2]), int(m[3]), float(m[4])
        return cls(nx, ny, int(fov) if fov == int(fov) else fov, order)

    @property
    def n_params(self) -> int:
        """Length of the intrinsics vector, ``4 + 2 Nx Ny``."""
        return 4 + 2 * self.Nx * self.Ny

    @property
    def u_edge_x(self) -> float:
        """``|ux|`` at the valid region's horizontal edge, ``2 tan(fov_x / 4)``."""
        return 2.0 * math.tan(math.radians(self.fov_x_deg) / 4.0)

    @property
    def spacing(self) -> float:
        """Control-point spacing ``h`` on the ``u`` plane."""
        return 2.0 * self.u_edge_x / (self.Nx - self.order)

    @property
    def u_edge_y(self) -> float:
        """``|uy|`` at the valid region's vertical edge, ``(Ny - order) h / 2``."""
        return (self.Ny - self.order) * self.spacing / 2.0

    def knots(self) -> tuple[np.ndarray, np.ndarray]:
        """Control-point positions on the ``u`` plane: ``(x (Nx,), y (Ny,))``."""
        h = self.spacing
        return (
            (np.arange(self.Nx) - (self.Nx - 1) / 2.0) * h,
            (np.arange(self.Ny) - (self.Ny - 1) / 2.0) * h,
        )

    def in_valid_region(self, u: np.ndarray) -> np.ndarray:
        """``u`` (N, 2) inside the spline's valid region, (N,) bool."""
        u = np.asarray(u, float).reshape(-1, 2)
        with np.errstate(invalid="ignore"):
            return (np.abs(u[:, 0]) <= self.u_edge_x * (1 + 1e-12)) & (
                np.abs(u[:, 1]) <= self.u_edge_y * (1 + 1e-12)
            )


def choose_config(u: np.ndarray, nx: int = 16) -> SplineConfig:
    """A configuration whose valid region holds the stereographic points ``u`` (N, 2).

    ``fov_x_deg`` is the smallest whole degree whose ``u_edge_x`` reaches past ``max
    |ux|`` (plus 2 %), ``Ny`` the fewest control points reaching ``max |uy|``.
    """
    u = np.asarray(u, float).reshape(-1, 2)
    u = u[np.all(np.isfinite(u), axis=1)]
    if not len(u):
        raise ValueError("no finite stereographic point to lay the spline over")
    ux = 1.02 * float(np.max(np.abs(u[:, 0])))
    uy = 1.02 * float(np.max(np.abs(u[:, 1])))
    fov = min(359, int(math.ceil(math.degrees(4.0 * math.atan(max(ux, 1e-3) / 2.0)))))
    probe = SplineConfig(nx, 4, fov)
    ny = 3 + max(1, int(math.ceil(2.0 * uy / probe.spacing)))
    return SplineConfig(nx, max(ny, 4), fov)


def stereographic_u(rays: np.ndarray) -> np.ndarray:
    """Normalized stereographic projection ``u = 2 p_xy / (|p| + p_z)`` of rays (N, 3), (N, 2).

    Infinite for rays pointing straight back (``theta = 180 deg``).
    """
    rays = np.asarray(rays, float).reshape(-1, 3)
    d = np.linalg.norm(rays, axis=1) + rays[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        return 2.0 * rays[:, :2] / d[:, None]


def _basis(t: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Cubic uniform B-spline weights at control-point coordinates ``t`` (N,).

    Returns the first control point index (N,) and the four weights (N, 4); the
    interval is clamped to the valid ones (``1 .. n - 3``), continuing the edge
    polynomials outside.
    """
    i = np.clip(np.floor(t), 1, n - 3).astype(int)
    s = t - i
    s2, s3 = s * s, s * s * s
    w = np.column_stack([(1 - s) ** 3, 3 * s3 - 6 * s2 + 4, -3 * s3 + 3 * s2 + 3 * s + 1, s3]) / 6.0
    return i - 1, w


def spline_weights(config: SplineConfig, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 16 control points and weights of the correction at each ``u`` (N, 2).

    Returns
    -------
    index : ndarray, shape (N, 16)
        Control-point index ``iy * Nx + ix``.
    weight : ndarray, shape (N, 16)
        Tensor-product weights (sum 1).
    """
    u = np.asarray(u, float).reshape(-1, 2)
    h = config.spacing
    tx = u[:, 0] / h + (config.Nx - 1) / 2.0
    ty = u[:, 1] / h + (config.Ny - 1) / 2.0
    ix, wx = _basis(np.nan_to_num(tx), config.Nx)
    iy, wy = _basis(np.nan_to_num(ty), config.Ny)
    rows = (iy[:, None, None] + np.arange(4)[None, :, None]) * config.Nx
    index = (rows + ix[:, None, None] + np.arange(4)[None, None, :]).reshape(-1, 16)
    weight = (wy[:, :, None] * wx[:, None, :]).reshape(-1, 16)
    return index, weight


def splined_project(
    params: np.ndarray, rays: np.ndarray, config: SplineConfig, jacobians: bool = False
):
    """Project rays with a splined stereographic model (see the module docstring).

    Parameters
    ----------
    params : ndarray, shape (4 + 2 Nx Ny,)
        mrcal's intrinsics: ``fx, fy, cx, cy`` (px), then ``dux, duy`` per control
        point (dimensionless, on the stereographic plane).
    rays : ndarray, shape (N, 3)
        Camera frame (x right, y down, z forward).
    config : SplineConfig
    jacobians : bool
        Also return ``d uv / d params``, shape (N, 2, 4 + 2 Nx Ny) (dense).

    Returns
    -------
    uv_px : ndarray, shape (N, 2)
        NaN for rays pointing straight back.
    """
    params = np.asarray(params, float)
    if len(params) != config.n_params:
        raise ValueError(f"{config.lensmodel} has {config.n_params} intrinsics, got {len(params)}")
    fx, fy, cx, cy = params[:4]
    coef = params[4:].reshape(-1, 2)
    u = stereographic_u(rays)
    index, weight = spline_weights(config, u)
    du = np.einsum("nk,nkc->nc", weight, coef[index])
    ud = u + du
    uv = np.column_stack([fx * ud[:, 0] + cx, fy * ud[:, 1] + cy])
    bad = ~np.all(np.isfinite(u), axis=1)
    uv[bad] = np.nan
    if not jacobians:
        return uv
    n = len(u)
    J = np.zeros((n, 2, config.n_params))
    J[:, 0, 0] = ud[:, 0]
    J[:, 1, 1] = ud[:, 1]
    J[:, 0, 2] = 1.0
    J[:, 1, 3] = 1.0
    rows = np.repeat(np.arange(n), 16)
    J[rows, 0, 4 + 2 * index.ravel()] = fx * weight.ravel()
    J[rows, 1, 5 + 2 * index.ravel()] = fy * weight.ravel()
    J[bad] = np.nan
    return uv, J
