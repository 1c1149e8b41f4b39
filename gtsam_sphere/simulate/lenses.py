"""Ground-truth lens models for the simulator, vectorised over N points.

Every lens maps points in the camera frame (``x`` right, ``y`` down, ``z``
forward, metres) to pixels ``uv_px`` with ``(0, 0)`` at the centre of the
top-left pixel, ``u`` right and ``v`` down, and back to unit rays.

The central lenses share one pipeline::

    alpha = atan2(hypot(x, y), z)                 # incidence angle, [0, pi]
    phi   = atan2(y, x)                           # azimuth
    q     = rho0(alpha) * (cos phi, sin phi)      # ideal normalised coords
    m     = q * (1 + k1 s + k2 s^2 + ...) + T(q)  # s = |q|^2, T = decentering
    u     = cx + f * ((1 + a1) * m_x + a2 * m_y)  # affinity (Brown/Chow Eq. 5)
    v     = cy + f * m_y

``rho0`` is the family's radial mapping (``tan`` for the pinhole, ``alpha``
for the equidistant fisheye, ...), the polynomial holds the family's radial
coefficients (Brown ``k1..k3`` for the pinhole, which reproduces OpenCV's
``projectPoints`` model, ``k1..k4`` for Kannala-Brandt, which reproduces
OpenCV's fisheye model, ``k1, k2`` for the unified model) and ``T`` is the
OpenCV/Brown decentering term with ``p1, p2``::

    T_x = 2 p1 q_x q_y + p2 (s + 2 q_x^2)
    T_y = p1 (s + 2 q_y^2) + 2 p2 q_x q_y

``unproject`` undoes the affinity in closed form, the polynomial and the
decentering with a Newton iteration started from a bisection on the radial
part, and ``rho0`` in closed form or by bisection.

Two wrappers add imperfections no such model holds: :class:`NonCentral`
(moving entrance pupil) and :class:`ErrorField` (smooth non-parametric
pixel displacement field).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from functools import cached_property
from typing import Any, ClassVar

import numpy as np

__all__ = [
    "PinholeBrown",
    "Equidistant",
    "Equisolid",
    "Stereographic",
    "SphereLens",
    "KannalaBrandt",
    "Unified",
    "DoubleSphere",
    "FieldOfView",
    "NonCentral",
    "ErrorField",
    "LENS_KINDS",
    "make_lens",
    "lens_from_dict",
    "incidence_angle",
]

_HALF_PI = 0.5 * math.pi
_GRID = 20001  # samples used to find where a radial mapping stops increasing


def _as_points(points_cam: Any) -> np.ndarray:
    p = np.asarray(points_cam, dtype=float)
    if p.ndim == 1:
        p = p[None, :]
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points_cam must have shape (N, 3), got {p.shape}")
    return p


def _as_uv(uv_px: Any) -> np.ndarray:
    uv = np.asarray(uv_px, dtype=float)
    if uv.ndim == 1:
        uv = uv[None, :]
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"uv_px must have shape (N, 2), got {uv.shape}")
    return uv


def _field_names(cls: type) -> tuple[str, ...]:
    return tuple(fl.name for fl in fields(cls))


def incidence_angle(points_cam: Any) -> np.ndarray:
    """Incidence angle of camera-frame points to the optical axis.

    Parameters
    ----------
    points_cam : array_like, shape (N, 3)
        Points (or directions) in the camera frame (x right, y down, z forward).

    Returns
    -------
    alpha_rad : ndarray, shape (N,)
        ``atan2(hypot(x, y), z)`` in radians, in ``[0, pi]``.
    """
    p = _as_points(points_cam)
    return np.arctan2(np.hypot(p[:, 0], p[:, 1]), p[:, 2])


def _bisect_increasing(func, target: np.ndarray, lo: float, hi: float, n_iter: int = 80):
    """Solve ``func(x) = target`` for an increasing ``func`` on ``[lo, hi]``."""
    a = np.full(target.shape, lo, dtype=float)
    b = np.full(target.shape, hi, dtype=float)
    for _ in range(n_iter):
        mid = 0.5 * (a + b)
        below = func(mid) < target
        a = np.where(below, mid, a)
        b = np.where(below, b, mid)
    return 0.5 * (a + b)


def _monotonic_limit(func, hi: float) -> float:
    """Largest angle in ``[0, hi]`` (rad) up to which ``func`` is finite and increasing."""
    alpha = np.linspace(0.0, hi, _GRID)
    with np.errstate(all="ignore"):
        values = func(alpha)
    ok = np.isfinite(values[1:]) & (np.diff(values) > 0.0)
    bad = np.flatnonzero(~ok)
    return hi if bad.size == 0 else float(alpha[max(bad[0] - 1, 1)])


@dataclass(frozen=True)
class _CentralLens:
    """Common machinery of the central lens families (see the module docstring).

    Parameters
    ----------
    cx, cy : float
        Principal point in pixels.
    f : float
        Scale (principal distance) in pixels.
    a1, a2 : float
        Affinity and shear (Brown/Chow Eq. 5): ``du += a1 * xbar + a2 * ybar``.
    p1, p2 : float
        Decentering distortion on the normalised coordinates (OpenCV form).
    max_angle_deg : float
        User cap on the incidence angle (degrees); points beyond it project to
        NaN. :attr:`max_incidence_deg` is the smaller of this cap and the
        family's own validity/monotonicity limit.
    """

    cx: float
    cy: float
    f: float
    a1: float = 0.0
    a2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    max_angle_deg: float = 180.0

    kind: ClassVar[str] = "central"

    # -- family specifics ---------------------------------------------------
    def _rho0(self, alpha: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _alpha0(self, rho: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`_rho0` on ``[0, _base_max_rad]`` (bisection fallback)."""
        hi = self._base_max_rad
        r = np.clip(rho, 0.0, None)
        return _bisect_increasing(self._rho0, r, 0.0, hi)

    @property
    def _base_max_rad(self) -> float:
        """Largest incidence angle (rad) where ``rho0`` is finite and increasing."""
        return math.pi

    @property
    def _radial_coeffs(self) -> tuple[float, ...]:
        return ()

    # -- shared -------------------------------------------------------------
    def _radial_factor(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Radial polynomial ``R(s)`` and ``dR/ds`` with ``s = |q|^2``."""
        r = np.ones_like(s)
        dr = np.zeros_like(s)
        for i, k in enumerate(self._radial_coeffs, start=1):
            if k != 0.0:
                r = r + k * s**i
                dr = dr + i * k * s ** (i - 1)
        return r, dr

    def _radial_total(self, alpha: np.ndarray) -> np.ndarray:
        """Normalised image radius (before decentering) as a function of alpha."""
        rho = self._rho0(alpha)
        r, _ = self._radial_factor(rho * rho)
        return rho * r

    @cached_property
    def _max_rad(self) -> float:
        limit = min(self._base_max_rad, math.radians(self.max_angle_deg))
        if any(k != 0.0 for k in self._radial_coeffs):
            limit = min(limit, _monotonic_limit(self._radial_total, self._base_max_rad))
        return limit

    @property
    def max_incidence_deg(self) -> float:
        """Largest incidence angle (degrees) the mapping is valid and monotonic for."""
        return math.degrees(self._max_rad)

    @property
    def has_decentering(self) -> bool:
        """True when ``p1`` or ``p2`` is non-zero."""
        return self.p1 != 0.0 or self.p2 != 0.0

    def _distort(self, q: np.ndarray) -> np.ndarray:
        s = np.sum(q * q, axis=1)
        r, _ = self._radial_factor(s)
        m = q * r[:, None]
        if self.has_decentering:
            x, y = q[:, 0], q[:, 1]
            m[:, 0] += 2.0 * self.p1 * x * y + self.p2 * (s + 2.0 * x * x)
            m[:, 1] += self.p1 * (s + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return m

    def _distort_jacobian(self, q: np.ndarray) -> np.ndarray:
        x, y = q[:, 0], q[:, 1]
        s = x * x + y * y
        r, dr = self._radial_factor(s)
        jac = np.empty((q.shape[0], 2, 2))
        jac[:, 0, 0] = r + 2.0 * dr * x * x + 2.0 * self.p1 * y + 6.0 * self.p2 * x
        jac[:, 0, 1] = 2.0 * dr * x * y + 2.0 * self.p1 * x + 2.0 * self.p2 * y
        jac[:, 1, 0] = 2.0 * dr * x * y + 2.0 * self.p1 * x + 2.0 * self.p2 * y
        jac[:, 1, 1] = r + 2.0 * dr * y * y + 6.0 * self.p1 * y + 2.0 * self.p2 * x
        return jac

    def _undistort(self, m: np.ndarray) -> np.ndarray:
        """Invert :meth:`_distort`: normalised distorted -> ideal coordinates."""
        q = m.copy()
        if self._radial_coeffs and any(k != 0.0 for k in self._radial_coeffs):
            rd = np.hypot(m[:, 0], m[:, 1])
            rho_max = float(self._rho0(np.array([self._max_rad]))[0])

            def total(rho):
                return rho * self._radial_factor(rho * rho)[0]

            rho = _bisect_increasing(total, rd, 0.0, rho_max, n_iter=60)
            scale = np.divide(rho, rd, out=np.ones_like(rd), where=rd > 0)
            q = m * scale[:, None]
        elif not self.has_decentering:
            return q
        for _ in range(30):
            res = self._distort(q) - m
            if not np.any(np.abs(res) > 1e-15):
                break
            jac = self._distort_jacobian(q)
            det = jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0]
            det = np.where(np.abs(det) < 1e-300, 1e-300, det)
            dx = (jac[:, 1, 1] * res[:, 0] - jac[:, 0, 1] * res[:, 1]) / det
            dy = (-jac[:, 1, 0] * res[:, 0] + jac[:, 0, 0] * res[:, 1]) / det
            q = q - np.stack([dx, dy], axis=1)
        return q

    def _normalised_to_px(self, m: np.ndarray) -> np.ndarray:
        u = self.cx + self.f * ((1.0 + self.a1) * m[:, 0] + self.a2 * m[:, 1])
        v = self.cy + self.f * m[:, 1]
        return np.stack([u, v], axis=1)

    def _px_to_normalised(self, uv: np.ndarray) -> np.ndarray:
        my = (uv[:, 1] - self.cy) / self.f
        mx = ((uv[:, 0] - self.cx) / self.f - self.a2 * my) / (1.0 + self.a1)
        return np.stack([mx, my], axis=1)

    def ideal_pixels(self, uv_px: Any) -> np.ndarray:
        """Pixels with the image-plane distortion undone: ``(cx, cy) + f * q``.

        ``q`` are the normalised coordinates before the radial polynomial,
        decentering and affinity (:meth:`unproject`'s first steps), so for a lens
        without radial coefficients (the sphere lens) these are the pixels of the
        same lens without sensor defects.

        Parameters
        ----------
        uv_px : array_like, shape (N, 2)
            Pixel coordinates (OpenCV convention).

        Returns
        -------
        uv_ideal_px : ndarray, shape (N, 2)
        """
        q = self._undistort(self._px_to_normalised(_as_uv(uv_px)))
        return np.array([self.cx, self.cy]) + self.f * q

    def project(self, points_cam: Any) -> np.ndarray:
        """Project camera-frame points to pixels.

        Parameters
        ----------
        points_cam : array_like, shape (N, 3)
            Points in the camera frame (x right, y down, z forward), any units
            (only the direction matters).

        Returns
        -------
        uv_px : ndarray, shape (N, 2)
            Pixel coordinates (``(0, 0)`` = centre of the top-left pixel).
            Rows are NaN where the incidence angle exceeds
            :attr:`max_incidence_deg` or the point is the camera centre.
        """
        p = _as_points(points_cam)
        rxy = np.hypot(p[:, 0], p[:, 1])
        alpha = np.arctan2(rxy, p[:, 2])
        phi = np.arctan2(p[:, 1], p[:, 0])
        bad = ~np.isfinite(alpha) | (alpha > self._max_rad + 1e-12) | ((rxy == 0) & (p[:, 2] == 0))
        alpha = np.where(bad, 0.0, alpha)
        with np.errstate(all="ignore"):
            rho = self._rho0(alpha)
        q = np.stack([rho * np.cos(phi), rho * np.sin(phi)], axis=1)
        uv = self._normalised_to_px(self._distort(q))
        uv[bad] = np.nan
        return uv

    def _rays_from_ideal(self, q: np.ndarray, alpha: np.ndarray) -> np.ndarray:
        phi = np.arctan2(q[:, 1], q[:, 0])
        sa = np.sin(alpha)
        return np.stack([sa * np.cos(phi), sa * np.sin(phi), np.cos(alpha)], axis=1)

    def unproject(self, uv_px: Any) -> np.ndarray:
        """Back-project pixels to unit rays in the camera frame.

        Parameters
        ----------
        uv_px : array_like, shape (N, 2)
            Pixel coordinates (``(0, 0)`` = centre of the top-left pixel).

        Returns
        -------
        rays : ndarray, shape (N, 3)
            Unit direction vectors in the camera frame. Rows are NaN for pixels
            beyond the image of :attr:`max_incidence_deg`.
        """
        uv = _as_uv(uv_px)
        q = self._undistort(self._px_to_normalised(uv))
        rho = np.hypot(q[:, 0], q[:, 1])
        rho_max = float(self._rho0(np.array([self._max_rad]))[0])
        with np.errstate(all="ignore"):
            alpha = self._alpha0(np.minimum(rho, rho_max))
        rays = self._rays_from_ideal(q, alpha)
        bad = ~np.isfinite(rho) | (rho > rho_max * (1.0 + 1e-9) + 1e-12)
        rays[bad] = np.nan
        return rays

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description: ``{"kind": ..., <every parameter>: float}``."""
        out: dict[str, Any] = {"kind": self.kind}
        for name in _field_names(type(self)):
            out[name] = float(getattr(self, name))
        out["max_incidence_deg"] = self.max_incidence_deg
        return out


@dataclass(frozen=True)
class PinholeBrown(_CentralLens):
    """Perspective lens with Brown radial and decentering distortion (OpenCV model).

    ``r = f * tan(alpha)`` before distortion; ``k1, k2, k3`` act on the
    normalised coordinates ``q = (x/z, y/z)`` exactly as in OpenCV's
    ``projectPoints`` (with ``p1, p2`` its tangential terms). Valid up to
    ``max_angle_deg`` (default 85 degrees) or where the distortion stops the
    radius from increasing, whichever comes first.
    """

    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    max_angle_deg: float = 85.0

    kind: ClassVar[str] = "pinhole"

    def _rho0(self, alpha):
        return np.tan(alpha)

    def _alpha0(self, rho):
        return np.arctan(rho)

    @property
    def _base_max_rad(self):
        return _HALF_PI - 1e-6

    @property
    def _radial_coeffs(self):
        return (self.k1, self.k2, self.k3)


@dataclass(frozen=True)
class Equidistant(_CentralLens):
    """Equidistant fisheye, ``r = f * alpha``; valid up to 180 degrees."""

    kind: ClassVar[str] = "equidistant"

    def _rho0(self, alpha):
        return alpha

    def _alpha0(self, rho):
        return np.asarray(rho, dtype=float)


@dataclass(frozen=True)
class Equisolid(_CentralLens):
    """Equisolid-angle fisheye, ``r = 2 f sin(alpha / 2)``; valid up to 180 degrees."""

    kind: ClassVar[str] = "equisolid"

    def _rho0(self, alpha):
        return 2.0 * np.sin(0.5 * alpha)

    def _alpha0(self, rho):
        return 2.0 * np.arcsin(np.clip(0.5 * rho, 0.0, 1.0))


@dataclass(frozen=True)
class Stereographic(_CentralLens):
    """Stereographic fisheye, ``r = 2 f tan(alpha / 2)``; valid below 180 degrees."""

    kind: ClassVar[str] = "stereographic"

    def _rho0(self, alpha):
        return 2.0 * np.tan(0.5 * alpha)

    def _alpha0(self, rho):
        return 2.0 * np.arctan(0.5 * rho)

    @property
    def _base_max_rad(self):
        return math.pi - 1e-6


@dataclass(frozen=True)
class KannalaBrandt(_CentralLens):
    """Kannala-Brandt / OpenCV fisheye lens.

    ``r = f * (theta + k1 theta^3 + k2 theta^5 + k3 theta^7 + k4 theta^9)``
    with ``theta = alpha``; valid up to where ``r`` stops increasing (may
    exceed 90 degrees) and at most 180 degrees.
    """

    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0

    kind: ClassVar[str] = "kannala-brandt"

    def _rho0(self, alpha):
        return alpha

    def _alpha0(self, rho):
        return np.asarray(rho, dtype=float)

    @property
    def _radial_coeffs(self):
        return (self.k1, self.k2, self.k3, self.k4)


@dataclass(frozen=True)
class Unified(_CentralLens):
    """Unified (Mei) catadioptric / fisheye model with parameter ``xi``.

    The point is lifted to the unit sphere ``s = p / |p|``, then
    ``q = (s_x, s_y) / (s_z + xi)`` (i.e. ``rho0 = sin a / (cos a + xi)``),
    followed by Mei's radial ``k1, k2`` and decentering ``p1, p2`` on ``q``.
    Valid while ``s_z + xi > 0`` and the mapping increases:
    ``alpha < acos(-min(xi, 1/xi))`` (180 degrees for ``xi = 1``).
    """

    xi: float = 1.0
    k1: float = 0.0
    k2: float = 0.0

    kind: ClassVar[str] = "unified"

    def _rho0(self, alpha):
        return np.sin(alpha) / (np.cos(alpha) + self.xi)

    @property
    def _base_max_rad(self):
        if self.xi <= 0.0:
            return _HALF_PI - 1e-6
        return math.acos(-min(self.xi, 1.0 / self.xi)) - 1e-6

    @property
    def _radial_coeffs(self):
        return (self.k1, self.k2)


@dataclass(frozen=True)
class SphereLens(_CentralLens):
    """The project's spherical model: ``uv = (cx, cy) + f * (x, y) / |p|``.

    ``f`` is the principal distance ``c`` of the spherical model (Chow et al.
    2018), ``cx, cy`` its principal point ``(x_p, y_p)``. The image radius is
    ``r = f sin(alpha)``: a point behind the camera (``alpha > 90`` degrees)
    lands on the same disc as its mirror image in front, so the mapping is
    not injective past 90 degrees; :meth:`unproject` therefore takes the
    hemisphere to return. Decentering ``p1, p2`` and affinity ``a1, a2`` apply
    as for the other families. Valid up to ``max_angle_deg`` (default 180).
    """

    kind: ClassVar[str] = "sphere"

    def _rho0(self, alpha):
        return np.sin(alpha)

    def _alpha0(self, rho):
        return np.arcsin(np.clip(rho, 0.0, 1.0))

    def unproject(self, uv_px: Any, hemisphere: int = 1) -> np.ndarray:
        """Back-project pixels to unit rays on the chosen hemisphere.

        Parameters
        ----------
        uv_px : array_like, shape (N, 2)
            Pixel coordinates (``(0, 0)`` = centre of the top-left pixel).
        hemisphere : {+1, -1} or array_like of shape (N,)
            ``+1`` returns the ray in front of the camera (``z >= 0``), ``-1``
            the ray behind it (``z <= 0``).

        Returns
        -------
        rays : ndarray, shape (N, 3)
            Unit direction vectors in the camera frame; NaN outside the disc of
            radius ``f`` or beyond :attr:`max_incidence_deg`.
        """
        uv = _as_uv(uv_px)
        q = self._undistort(self._px_to_normalised(uv))
        rho = np.hypot(q[:, 0], q[:, 1])
        front = self._alpha0(rho)
        hemi = np.broadcast_to(np.asarray(hemisphere), rho.shape)
        alpha = np.where(hemi < 0, math.pi - front, front)
        rays = self._rays_from_ideal(q, alpha)
        bad = ~np.isfinite(rho) | (rho > 1.0 + 1e-12) | (alpha > self._max_rad + 1e-9)
        rays[bad] = np.nan
        return rays


@dataclass(frozen=True)
class DoubleSphere(_CentralLens):
    """Double sphere camera model (Usenko, Demmel and Cremers 2018).

    The point ``p`` (distance ``d1 = |p|``) is projected onto a first unit
    sphere, shifted by ``xi`` along the optical axis onto a second one
    (``d2 = |(x, y, xi d1 + z)|``) and projected by a pinhole displaced by
    ``alpha / (1 - alpha)``::

        q = (x, y) / (alpha d2 + (1 - alpha) (xi d1 + z))

    For a unit direction at incidence ``a`` this is the radial mapping
    ``rho0(a) = sin a / (alpha sqrt(sin^2 a + (xi + cos a)^2) + (1 - alpha)(xi + cos a))``.
    The paper's validity condition ``z > -w2 d1`` with
    ``w1 = alpha / (1 - alpha)`` (``alpha <= 1/2``) or ``(1 - alpha) / alpha``,
    ``w2 = (w1 + xi) / sqrt(2 w1 xi + xi^2 + 1)`` gives the largest incidence
    ``acos(-w2)``: past 180 degrees of field of view when ``w2 > 0`` (e.g.
    ``xi = -0.2, alpha = 0.6`` reaches 244 degrees, ``alpha = 0.5`` 360).
    :meth:`unproject` uses the paper's closed-form inverse.

    Parameters
    ----------
    xi : float
        Shift between the two spheres (dimensionless, typically ``-0.3 .. 0.3``).
    alpha : float
        Pinhole displacement parameter in ``[0, 1)`` (dimensionless).
    """

    xi: float = -0.2
    alpha: float = 0.6

    kind: ClassVar[str] = "double-sphere"

    def __post_init__(self) -> None:
        if not 0.0 <= self.alpha < 1.0:
            raise ValueError(f"double-sphere alpha must be in [0, 1), got {self.alpha}")

    def _rho0(self, alpha):
        s, c = np.sin(alpha), np.cos(alpha)
        shifted = self.xi + c
        d2 = np.sqrt(s * s + shifted * shifted)
        return s / (self.alpha * d2 + (1.0 - self.alpha) * shifted)

    def _alpha0(self, rho):
        r2 = np.asarray(rho, dtype=float) ** 2
        a, xi = self.alpha, self.xi
        with np.errstate(invalid="ignore", divide="ignore"):
            mz = (1.0 - a * a * r2) / (a * np.sqrt(1.0 - (2.0 * a - 1.0) * r2) + 1.0 - a)
            k = (mz * xi + np.sqrt(mz * mz + (1.0 - xi * xi) * r2)) / (mz * mz + r2)
        return np.arctan2(k * np.sqrt(r2), k * mz - xi)

    @cached_property
    def _base_max_rad(self):
        a, xi = self.alpha, self.xi
        w1 = a / (1.0 - a) if a <= 0.5 else (1.0 - a) / a
        w2 = (w1 + xi) / math.sqrt(2.0 * w1 * xi + xi * xi + 1.0)
        limit = math.acos(min(max(-w2, -1.0), 1.0))
        return _monotonic_limit(self._rho0, min(limit, math.pi - 1e-6))


@dataclass(frozen=True)
class FieldOfView(_CentralLens):
    """Field-of-view (FOV) model of Devernay and Faugeras (2001), parameter ``omega``.

    The paper maps the pinhole radius ``r_u = tan a`` to
    ``r_d = arctan(2 r_u tan(omega / 2)) / omega``. Written with the incidence
    angle ``a`` this is ``rho0(a) = atan2(2 tan(omega / 2) sin a, cos a) / omega``,
    identical below 90 degrees and its continuous, increasing extension past
    them (``rho0(90 deg) = pi / (2 omega)``, ``rho0 -> pi / omega`` at 180
    degrees), so the model is valid over the whole sphere bar the antipode of
    the axis. Its inverse is ``a = atan2(sin(omega rho), 2 tan(omega / 2) cos(omega rho))``.

    Parameters
    ----------
    omega : float
        The model's parameter (radians, in ``(0, pi)``); the scale ``f`` is
        chosen by :func:`make_lens`, so ``omega`` only sets the shape.
    """

    omega: float = 1.0

    kind: ClassVar[str] = "fov"

    def __post_init__(self) -> None:
        if not 0.0 < self.omega < math.pi:
            raise ValueError(f"fov omega must be in (0, pi) radians, got {self.omega}")

    def _rho0(self, alpha):
        k = 2.0 * math.tan(0.5 * self.omega)
        return np.arctan2(k * np.sin(alpha), np.cos(alpha)) / self.omega

    def _alpha0(self, rho):
        k = 2.0 * math.tan(0.5 * self.omega)
        w = self.omega * np.asarray(rho, dtype=float)
        return np.arctan2(np.sin(w), k * np.cos(w))

    @property
    def _base_max_rad(self):
        return math.pi - 1e-6


# -- imperfection wrappers ------------------------------------------------------


@dataclass(frozen=True)
class NonCentral:
    """A lens whose entrance pupil slides along the optical axis.

    The ray imaged at incidence angle ``alpha`` passes through the pupil centre
    ``c(alpha) = (0, 0, pupil_shift_m * (alpha / (pi/2))^2)`` (camera frame,
    metres). :meth:`project` solves ``alpha = angle(p - c(alpha))`` by
    fixed-point iteration started at the central angle and projects the
    direction ``p - c(alpha)`` with the wrapped lens, so unlike a central lens
    the result depends on the distance of the point.

    Parameters
    ----------
    lens : lens object
        Any central lens of this module.
    pupil_shift_m : float
        Pupil displacement (metres) at 90 degrees incidence.
    """

    lens: Any
    pupil_shift_m: float

    kind: ClassVar[str] = "non-central"

    @property
    def cx(self) -> float:
        """Principal point u (px) of the wrapped lens."""
        return self.lens.cx

    @property
    def cy(self) -> float:
        """Principal point v (px) of the wrapped lens."""
        return self.lens.cy

    @property
    def f(self) -> float:
        """Scale (px) of the wrapped lens."""
        return self.lens.f

    @property
    def max_incidence_deg(self) -> float:
        """Largest incidence angle (degrees), that of the wrapped lens."""
        return self.lens.max_incidence_deg

    def pupil_centre(self, alpha_rad: Any) -> np.ndarray:
        """Entrance pupil centre for incidence angles.

        Parameters
        ----------
        alpha_rad : array_like, shape (N,)
            Incidence angles (radians).

        Returns
        -------
        centres_cam : ndarray, shape (N, 3)
            Pupil centres in the camera frame (metres).
        """
        a = np.asarray(alpha_rad, dtype=float)
        z = self.pupil_shift_m * (a / _HALF_PI) ** 2
        return np.stack([np.zeros_like(z), np.zeros_like(z), z], axis=-1)

    def project(self, points_cam: Any) -> np.ndarray:
        """Project camera-frame points (metres) to pixels.

        Parameters
        ----------
        points_cam : array_like, shape (N, 3)
            Points in the camera frame, metres (distance matters here).

        Returns
        -------
        uv_px : ndarray, shape (N, 2)
            Pixel coordinates; NaN where the wrapped lens cannot image the ray.
        """
        p = _as_points(points_cam)
        alpha = incidence_angle(p)
        for _ in range(50):
            d = p - self.pupil_centre(alpha)
            new = incidence_angle(d)
            done = not np.any(np.abs(new - alpha) > 1e-14)
            alpha = new
            if done:
                break
        return self.lens.project(p - self.pupil_centre(alpha))

    def unproject_with_origin(self, uv_px: Any, **kwargs: Any) -> tuple[np.ndarray, np.ndarray]:
        """Back-project pixels to rays with their (angle-dependent) origins.

        Parameters
        ----------
        uv_px : array_like, shape (N, 2)
            Pixel coordinates.
        **kwargs
            Passed to the wrapped lens' ``unproject`` (e.g. ``hemisphere``).

        Returns
        -------
        origins_cam : ndarray, shape (N, 3)
            Pupil centres the rays pass through (camera frame, metres).
        rays : ndarray, shape (N, 3)
            Unit ray directions in the camera frame.
        """
        rays = self.lens.unproject(uv_px, **kwargs)
        return self.pupil_centre(incidence_angle(rays)), rays

    def unproject(self, uv_px: Any, **kwargs: Any) -> np.ndarray:
        """Unit ray directions (camera frame), shape (N, 3); see :meth:`unproject_with_origin`.

        Parameters
        ----------
        uv_px : array_like, shape (N, 2)
            Pixel coordinates.
        **kwargs
            Passed to the wrapped lens' ``unproject``.

        Returns
        -------
        rays : ndarray, shape (N, 3)
            Unit directions; they start at the pupil centre, not the origin.
        """
        return self.lens.unproject(uv_px, **kwargs)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description including the wrapped lens."""
        return {
            "kind": self.kind,
            "pupil_shift_m": float(self.pupil_shift_m),
            "lens": self.lens.to_dict(),
        }


@dataclass(frozen=True)
class ErrorField:
    """A lens plus a smooth, non-parametric pixel displacement field.

    ``uv = lens.project(p) + d(uv_lens)`` with
    ``d(w) = sum_k c_k e_k sin(2 pi <w_k, (w - centre)> / scale_px + phase_k)``
    where the unit displacement directions ``e_k``, wave vectors ``w_k``
    (0.3 to 1.5 cycles per ``scale_px``), phases and weights are drawn from
    ``seed`` and the weights ``c_k >= 0`` sum to ``amplitude_px``, so
    ``|d| <= amplitude_px``. :meth:`unproject` inverts the field by fixed-point
    iteration (the field is a contraction for any sensible amplitude).

    Parameters
    ----------
    lens : lens object
        The wrapped lens.
    amplitude_px : float
        Bound on the displacement magnitude (pixels).
    n_terms : int
        Number of sinusoids.
    seed : int
        Seed of the field (deterministic).
    scale_px : float or None
        Length (pixels) the frequencies refer to; default ``2 * lens.f``.
    """

    lens: Any
    amplitude_px: float
    n_terms: int = 6
    seed: int = 0
    scale_px: float | None = None
    _terms: np.ndarray = field(init=False, repr=False, compare=False, hash=False)

    kind: ClassVar[str] = "error-field"

    def __post_init__(self) -> None:
        rng = np.random.default_rng(self.seed)
        n = max(int(self.n_terms), 1)
        ang_e = rng.uniform(0.0, 2.0 * math.pi, n)
        ang_w = rng.uniform(0.0, 2.0 * math.pi, n)
        freq = rng.uniform(0.3, 1.5, n)
        phase = rng.uniform(0.0, 2.0 * math.pi, n)
        weight = rng.uniform(0.5, 1.0, n)
        weight = weight / weight.sum() * float(self.amplitude_px)
        terms = np.stack(
            [
                weight * np.cos(ang_e),
                weight * np.sin(ang_e),
                freq * np.cos(ang_w),
                freq * np.sin(ang_w),
                phase,
            ],
            axis=1,
        )
        object.__setattr__(self, "_terms", terms)

    @property
    def cx(self) -> float:
        """Principal point u (px) of the wrapped lens."""
        return self.lens.cx

    @property
    def cy(self) -> float:
        """Principal point v (px) of the wrapped lens."""
        return self.lens.cy

    @property
    def f(self) -> float:
        """Scale (px) of the wrapped lens."""
        return self.lens.f

    @property
    def max_incidence_deg(self) -> float:
        """Largest incidence angle (degrees), that of the wrapped lens."""
        return self.lens.max_incidence_deg

    def displacement(self, uv_px: Any) -> np.ndarray:
        """Displacement field at lens pixels.

        Parameters
        ----------
        uv_px : array_like, shape (N, 2)
            Pixels of the wrapped lens.

        Returns
        -------
        duv_px : ndarray, shape (N, 2)
            Displacement (pixels) added by the field.
        """
        uv = _as_uv(uv_px)
        scale = float(self.scale_px) if self.scale_px else 2.0 * float(self.lens.f)
        w = (uv - np.array([self.lens.cx, self.lens.cy])) / scale
        t = self._terms
        arg = 2.0 * math.pi * (w @ t[:, 2:4].T) + t[:, 4][None, :]
        s = np.sin(arg)
        return np.stack([s @ t[:, 0], s @ t[:, 1]], axis=1)

    def project(self, points_cam: Any) -> np.ndarray:
        """Project camera-frame points to pixels, field included.

        Parameters
        ----------
        points_cam : array_like, shape (N, 3)
            Points in the camera frame (metres).

        Returns
        -------
        uv_px : ndarray, shape (N, 2)
            Pixel coordinates; NaN where the wrapped lens is NaN.
        """
        uv = self.lens.project(points_cam)
        return uv + self.displacement(uv)

    def remove_field(self, uv_px: Any) -> np.ndarray:
        """Invert the field: observed pixels -> pixels of the wrapped lens.

        Parameters
        ----------
        uv_px : array_like, shape (N, 2)
            Observed pixel coordinates.

        Returns
        -------
        uv_lens_px : ndarray, shape (N, 2)
            ``w`` with ``w + d(w) = uv_px`` (fixed-point iteration).
        """
        uv = _as_uv(uv_px)
        w = uv.copy()
        for _ in range(100):
            new = uv - self.displacement(w)
            done = not np.any(np.abs(new - w) > 1e-12)
            w = new
            if done:
                break
        return w

    def unproject(self, uv_px: Any, **kwargs: Any) -> np.ndarray:
        """Back-project pixels to unit rays (camera frame), shape (N, 3).

        Parameters
        ----------
        uv_px : array_like, shape (N, 2)
            Pixel coordinates.
        **kwargs
            Passed to the wrapped lens' ``unproject`` (e.g. ``hemisphere``).

        Returns
        -------
        rays : ndarray, shape (N, 3)
            Unit direction vectors in the camera frame.
        """
        return self.lens.unproject(self.remove_field(uv_px), **kwargs)

    def unproject_with_origin(self, uv_px: Any, **kwargs: Any) -> tuple[np.ndarray, np.ndarray]:
        """Back-project pixels to rays with their origins.

        Parameters
        ----------
        uv_px : array_like, shape (N, 2)
            Observed pixel coordinates.
        **kwargs
            Passed to the wrapped lens (e.g. ``hemisphere``).

        Returns
        -------
        origins_cam : ndarray, shape (N, 3)
            Ray origins in the camera frame (metres; zeros for a central lens).
        rays : ndarray, shape (N, 3)
            Unit ray directions in the camera frame.
        """
        w = self.remove_field(uv_px)
        if hasattr(self.lens, "unproject_with_origin"):
            return self.lens.unproject_with_origin(w, **kwargs)
        rays = self.lens.unproject(w, **kwargs)
        return np.zeros_like(rays), rays

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description including the wrapped lens."""
        return {
            "kind": self.kind,
            "amplitude_px": float(self.amplitude_px),
            "n_terms": int(self.n_terms),
            "seed": int(self.seed),
            "scale_px": None if self.scale_px is None else float(self.scale_px),
            "lens": self.lens.to_dict(),
        }


# -- factory -------------------------------------------------------------------

LENS_KINDS: dict[str, type] = {
    "pinhole": PinholeBrown,
    "equidistant": Equidistant,
    "equisolid": Equisolid,
    "stereographic": Stereographic,
    "sphere": SphereLens,
    "kannala-brandt": KannalaBrandt,
    "unified": Unified,
    "double-sphere": DoubleSphere,
    "fov": FieldOfView,
}


def lens_from_dict(desc: dict[str, Any]) -> Any:
    """Rebuild a lens from :meth:`to_dict` output (e.g. ``truth.json["lens"]``).

    Parameters
    ----------
    desc : dict
        Lens description with a ``"kind"`` key.

    Returns
    -------
    lens : lens object
        Equal (``==``) to the lens that wrote ``desc``.
    """
    kind = desc["kind"]
    if kind == NonCentral.kind:
        return NonCentral(lens_from_dict(desc["lens"]), desc["pupil_shift_m"])
    if kind == ErrorField.kind:
        return ErrorField(
            lens_from_dict(desc["lens"]),
            desc["amplitude_px"],
            n_terms=desc["n_terms"],
            seed=desc["seed"],
            scale_px=desc.get("scale_px"),
        )
    if kind not in LENS_KINDS:
        raise ValueError(f"unknown lens kind {kind!r}; expected one of {sorted(LENS_KINDS)}")
    cls = LENS_KINDS[kind]
    params = {k: v for k, v in desc.items() if k in _field_names(cls)}
    return cls(**params)


def make_lens(
    kind: str,
    fov_deg: float,
    width: int,
    height: int,
    fill: str | None = None,
    circle_radius_px: float | None = None,
    **options: Any,
) -> Any:
    """Build a lens whose half field of view lands on the image border or a given circle.

    Parameters
    ----------
    kind : str
        One of :data:`LENS_KINDS`: ``"pinhole"``, ``"equidistant"``,
        ``"equisolid"``, ``"stereographic"``, ``"sphere"``,
        ``"kannala-brandt"``, ``"unified"``, ``"double-sphere"``, ``"fov"``.
    fov_deg : float
        Full field of view (degrees) across the circle or the diagonal.
    width, height : int
        Image size in pixels; the principal point defaults to the image
        centre ``((width - 1) / 2, (height - 1) / 2)``.
    fill : {"circle", "diagonal"} or None
        ``"circle"``: ``fov_deg / 2`` lands at ``min(width, height) / 2`` from
        the principal point (circular fisheye; default for ``fov_deg >= 180``)
        and incidence is capped at ``fov_deg / 2`` (black outside the circle);
        ``"diagonal"``: at the half diagonal (default below 180 degrees).
        For the sphere lens above 180 degrees the disc radius is ``f``, so
        ``f = 0.98 * min(width, height) / 2`` whatever ``fill`` says.
    circle_radius_px : float or None
        Overrides ``fill``: ``fov_deg / 2`` lands at this distance (pixels)
        from the principal point and incidence is capped at ``fov_deg / 2``.
        Smaller than the image (e.g. ``0.25 * min(width, height)``: a small
        circular fisheye on a large sensor) or larger than the half diagonal
        (a full-frame fisheye whose circle the sensor crops: the image border
        then limits the incidence). For the sphere lens above 180 degrees it
        is the disc radius ``f``.
    **options
        Other lens parameters (``cx``, ``cy``, ``k1``, ``p1``, ``a1``, ``xi``,
        ``alpha``, ``omega``, ``max_angle_deg``, ...).

    Returns
    -------
    lens : lens object
        An instance of the class for ``kind`` with ``f`` (pixels) chosen.

    Raises
    ------
    ValueError
        For an unknown ``kind``, ``fill``, option, a non-positive
        ``circle_radius_px`` or a field of view the family cannot reach.
    """
    if kind not in LENS_KINDS:
        raise ValueError(f"unknown lens kind {kind!r}; expected one of {sorted(LENS_KINDS)}")
    if not (0.0 < fov_deg <= 360.0):
        raise ValueError(f"fov_deg must be in (0, 360], got {fov_deg}")
    if circle_radius_px is not None:
        if not (math.isfinite(circle_radius_px) and circle_radius_px > 0.0):
            raise ValueError(f"circle_radius_px must be positive, got {circle_radius_px}")
        fill = "circle"
    if fill is None:
        fill = "circle" if fov_deg >= 180.0 else "diagonal"
    if fill not in ("circle", "diagonal"):
        raise ValueError(f"fill must be 'circle' or 'diagonal', got {fill!r}")
    cls = LENS_KINDS[kind]
    if "f" in options:
        raise ValueError("make_lens chooses f from fov_deg; build the lens class directly instead")
    unknown = set(options) - set(_field_names(cls))
    if unknown:
        raise ValueError(f"unknown option(s) {sorted(unknown)} for lens kind {kind!r}")
    params = dict(options)
    params.setdefault("cx", (width - 1) / 2.0)
    params.setdefault("cy", (height - 1) / 2.0)
    half = math.radians(fov_deg / 2.0)
    # A lens sees no further than fov/2. The sphere lens folds rays past 90 deg back onto
    # the image disc, so without this cap a "120 deg" sphere lens would also image the
    # targets behind it.
    if (fill == "circle" or kind == "sphere") and "max_angle_deg" not in options:
        default_cap = {fl.name: fl.default for fl in fields(cls)}["max_angle_deg"]
        params["max_angle_deg"] = min(default_cap, fov_deg / 2.0)
    if circle_radius_px is not None:
        radius_px = float(circle_radius_px)
    elif fill == "circle":
        radius_px = min(width, height) / 2.0
    else:
        radius_px = math.hypot(width, height) / 2.0
    if kind == "sphere" and fov_deg > 180.0:
        params["max_angle_deg"] = min(params.get("max_angle_deg", 180.0), fov_deg / 2.0)
        disc_px = radius_px if circle_radius_px is not None else 0.98 * min(width, height) / 2.0
        return cls(f=disc_px, **params)
    unit = cls(f=1.0, **params)
    if half > unit._max_rad + 1e-9:
        raise ValueError(
            f"lens kind {kind!r} cannot reach fov_deg={fov_deg}: its mapping is valid only up "
            f"to {2 * unit.max_incidence_deg:.3f} degrees of field of view"
        )
    rho = float(unit._radial_total(np.array([half]))[0])
    if not (np.isfinite(rho) and rho > 0.0):
        raise ValueError(f"lens kind {kind!r} cannot reach fov_deg={fov_deg}")
    return cls(f=radius_px / rho, **params)
