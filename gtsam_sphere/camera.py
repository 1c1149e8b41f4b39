"""The spherical camera model of Chow et al. (2018), Eq. 1-5.

An image point lies on a virtual sphere of radius ``c`` (the principal
distance, px) centred on the perspective centre; its image coordinates
relative to the principal point ``(xp, yp)`` are the first two components of
that sphere point. Equating the object ray's incidence angle with the image
ray's refraction angle (Eq. 4) gives, in explicit form,

    x_ideal = c * X / |P|,   y_ideal = c * Y / |P|       (P = camera-frame point)

which is smooth everywhere except at ``P = 0``: the optical axis, 90 degrees
and rays behind the camera (Z < 0, the back half of the sphere) need no
special case. Measurement-side corrections (Brown Eq. 5 terms and the learned
kNN field) relate the raw pixel ``uv`` to the ideal point:

    uv - pp - brown(uv - pp) - learned(uv) = ideal(P)

See ``docs/conventions.md`` for frames and the unprojection ambiguity past
90 degrees (the sphere's front and back halves share the image disc).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

BROWN_TERMS: tuple[str, ...] = ("k1", "k2", "k3", "p1", "p2", "a1", "a2")
RADIAL_TERMS: tuple[str, ...] = ("g3", "g5", "g7", "g9", "g11", "g13")
#: normalising angle of the radial mapping's polynomial (rad)
ALPHA0_RAD = math.pi / 2


class Model(enum.StrEnum):
    """Camera models ``calibrate`` can estimate.

    ``sphere``: the paper's sphere mapping, ``xp, yp, c`` only.
    ``brown``: the sphere plus Brown (Eq. 5) terms.
    ``radial``: a generic radial mapping ``c * g(alpha)`` (:func:`radial_g`)
    plus optional decentering/affinity terms.
    ``+knn``: a kNN correction learned from the residuals on top (the grey-box loop).
    """

    SPHERE = "sphere"
    SPHERE_KNN = "sphere+knn"
    BROWN = "brown"
    BROWN_KNN = "brown+knn"
    RADIAL = "radial"
    RADIAL_KNN = "radial+knn"

    @property
    def uses_brown(self) -> bool:
        """The graph estimates Brown additional parameters."""
        return self in (Model.BROWN, Model.BROWN_KNN)

    @property
    def uses_radial(self) -> bool:
        """The graph estimates the radial mapping ``g`` (else the sphere mapping)."""
        return self in (Model.RADIAL, Model.RADIAL_KNN)

    @property
    def uses_knn(self) -> bool:
        """A kNN correction is learned from the residuals (the grey-box loop)."""
        return self in (Model.SPHERE_KNN, Model.BROWN_KNN, Model.RADIAL_KNN)


#: the model ``calibrate`` estimates unless told otherwise: a radial mapping in the
#: graph and a kNN correction for what remains (see README "Models")
DEFAULT_MODEL = Model.RADIAL_KNN


class Correction(Protocol):
    """A learned measurement correction: ``predict(uv_px (N,2)) -> (N,2)`` px."""

    def predict(self, uv_px: np.ndarray) -> np.ndarray: ...


def check_uv(uv_px: np.ndarray, name: str = "uv_px") -> np.ndarray:
    """Return pixels as a float (N, 2) array or raise ``ValueError`` with the shape."""
    arr = np.asarray(uv_px, dtype=float)
    if arr.ndim == 1 and arr.shape == (2,):
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2), got {arr.shape}")
    return arr


def check_points_cam(points_cam: np.ndarray) -> np.ndarray:
    """Return camera-frame points as a float (N, 3) array or raise ``ValueError``."""
    arr = np.asarray(points_cam, dtype=float)
    if arr.ndim == 1 and arr.shape == (3,):
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"points_cam must have shape (N, 3), got {arr.shape}")
    return arr


def parse_brown_terms(text: str | None) -> tuple[str, ...]:
    """Parse ``"k1,k2,p1"`` into an ordered tuple of Brown term names.

    Raises ``ValueError`` naming an unknown term. ``"all"`` selects all seven.
    """
    if text is None or text.strip() == "":
        return ()
    if text.strip().lower() == "all":
        return BROWN_TERMS
    names = [t.strip().lower() for t in text.split(",") if t.strip()]
    for n in names:
        if n not in BROWN_TERMS:
            raise ValueError(f"unknown additional parameter {n!r}; choose from {BROWN_TERMS}")
    return tuple(t for t in BROWN_TERMS if t in names)


def brown_distortion(
    xbar_px: np.ndarray, coeffs: dict[str, float], scale_px: float, jacobians: bool = False
):
    """Brown (1971) corrections of Chow et al. Eq. 5, on normalised coordinates.

    ``x^ = xbar / scale_px``; ``dx = scale_px * (x^ (K1 r^2 + K2 r^4 + K3 r^6)
    + P1 (r^2 + 2 x^2) + 2 P2 x^ y^ + A1 x^ + A2 y^)`` and likewise for ``dy``
    without the affinity terms.

    Parameters
    ----------
    xbar_px : ndarray, shape (N, 2)
        Measured pixels minus the principal point.
    coeffs : dict
        Term name (``BROWN_TERMS``) -> value (dimensionless); missing terms are 0.
    scale_px : float
        Normalisation radius in pixels.
    jacobians : bool
        Also return ``d(delta)/d(xbar)`` (N, 2, 2) and ``d(delta)/d(coeff)``
        (N, 2, len(coeffs)) in the order of ``coeffs``.

    Returns
    -------
    delta_px : ndarray, shape (N, 2)
    """
    x = xbar_px[:, 0] / scale_px
    y = xbar_px[:, 1] / scale_px
    g = {t: float(coeffs.get(t, 0.0)) for t in BROWN_TERMS}
    r2 = x * x + y * y
    radial = g["k1"] * r2 + g["k2"] * r2**2 + g["k3"] * r2**3
    dx = x * radial + g["p1"] * (r2 + 2 * x * x) + 2 * g["p2"] * x * y + g["a1"] * x + g["a2"] * y
    dy = y * radial + 2 * g["p1"] * x * y + g["p2"] * (r2 + 2 * y * y)
    delta = scale_px * np.stack([dx, dy], -1)
    if not jacobians:
        return delta
    dradial = 2 * g["k1"] + 4 * g["k2"] * r2 + 6 * g["k3"] * r2**2
    J = np.empty((len(x), 2, 2))
    J[:, 0, 0] = radial + dradial * x * x + 6 * g["p1"] * x + 2 * g["p2"] * y + g["a1"]
    J[:, 0, 1] = dradial * x * y + 2 * g["p1"] * y + 2 * g["p2"] * x + g["a2"]
    J[:, 1, 0] = dradial * x * y + 2 * g["p1"] * y + 2 * g["p2"] * x
    J[:, 1, 1] = radial + dradial * y * y + 2 * g["p1"] * x + 6 * g["p2"] * y
    columns = {
        "k1": (x * r2, y * r2),
        "k2": (x * r2**2, y * r2**2),
        "k3": (x * r2**3, y * r2**3),
        "p1": (r2 + 2 * x * x, 2 * x * y),
        "p2": (2 * x * y, r2 + 2 * y * y),
        "a1": (x, np.zeros_like(x)),
        "a2": (y, np.zeros_like(x)),
    }
    Jc = np.empty((len(x), 2, len(coeffs)))
    for k, name in enumerate(coeffs):
        Jc[:, 0, k], Jc[:, 1, k] = columns[name]
    return delta, J, scale_px * Jc


def radial_terms(n: int) -> tuple[str, ...]:
    """Names of the first ``n`` radial-mapping coefficients: ``("g3", "g5", ...)``."""
    if not 0 <= n <= len(RADIAL_TERMS):
        raise ValueError(f"the radial mapping has 0 to {len(RADIAL_TERMS)} terms, got {n}")
    return RADIAL_TERMS[:n]


def radial_g(alpha: np.ndarray, coeffs: np.ndarray, derivative: bool = False):
    """Radial mapping ``g(alpha) = alpha + A0 * sum_i g_i (alpha / A0)^(2i+3)``, ``A0 = pi/2``.

    ``c * g(alpha)`` is the geodesic distance (px) on the virtual sphere from
    the principal point to the image point; ``g = alpha`` is equidistant.

    Parameters
    ----------
    alpha : ndarray, shape (N,)
        Incidence angles (rad).
    coeffs : ndarray, shape (G,)
        ``g3, g5, ...`` (dimensionless).
    derivative : bool
        Also return ``dg/dalpha`` (N,) and ``dg/dcoeffs`` (N, G).
    """
    t = np.asarray(alpha, float) / ALPHA0_RAD
    g = np.array(alpha, float, copy=True)
    G = len(coeffs)
    powers = np.empty((len(t), G))
    for i in range(G):
        powers[:, i] = t ** (2 * i + 3)
    g += ALPHA0_RAD * powers @ np.asarray(coeffs, float)
    if not derivative:
        return g
    dg = np.ones_like(g)
    for i in range(G):
        dg += (2 * i + 3) * coeffs[i] * t ** (2 * i + 2)
    return g, dg, ALPHA0_RAD * powers


def ideal_projection(points_cam: np.ndarray, radial: np.ndarray | None, jacobians: bool = False):
    """Ideal image point on a unit sphere (c = 1), relative to the principal point.

    ``sphere`` mapping (``radial`` None, Eq. 1-4): ``m = P[:2] / |P|``.
    ``radial`` mapping: ``m = g(alpha) * P[:2] / |P[:2]|`` with
    :func:`radial_g`; smooth at the optical axis, injective up to 180 deg when
    ``g`` increases. Rays behind the camera need no special case; the
    antipode of the axis (alpha = 180 deg) is the one singular direction.

    Parameters
    ----------
    points_cam : ndarray, shape (N, 3)
        Camera frame (x right, y down, z forward), any direction, not 0.
    radial : ndarray, shape (G,), or None
    jacobians : bool
        Also return ``dm/dP`` (N, 2, 3) and ``dm/dradial`` (N, 2, G).

    Returns
    -------
    m : ndarray, shape (N, 2)
        Multiply by ``c`` for pixels.
    """
    # the mapping is scale invariant: work on P / max|P_i| so |P|^2 neither overflows
    # (1e300) nor underflows (1e-200); Jacobians are scaled back at the end
    big = np.max(np.abs(points_cam), axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = np.where(big > 0, 1.0 / big, np.nan)
        P = points_cam * inv[:, None]
        norm = np.linalg.norm(P, axis=1)
        u = P / norm[:, None]
    if radial is None:
        m = u[:, :2]
        if not jacobians:
            return m
        J_p = (np.eye(3)[None, :2, :] - u[:, :2, None] * u[:, None, :]) / norm[:, None, None]
        return m, J_p * inv[:, None, None], np.zeros((len(P), 2, 0))
    rho = np.hypot(P[:, 0], P[:, 1])
    alpha = np.arctan2(rho, P[:, 2])
    sin_a = rho / norm
    small = alpha < 1e-4
    safe_sin = np.where(small, 1.0, sin_a)
    out = radial_g(alpha, radial, derivative=jacobians)
    g = out[0] if jacobians else out
    kappa = (radial[0] / ALPHA0_RAD**2) if len(radial) else 0.0
    # s = g / sin(alpha), smooth and even in alpha: series at the axis
    s = np.where(small, 1.0 + (1.0 / 6.0 + kappa) * alpha**2, g / safe_sin)
    m = s[:, None] * u[:, :2]
    if not jacobians:
        return m
    _, dg, dg_dc = out
    cos_a = P[:, 2] / norm
    ds = np.where(
        small,
        2.0 * (1.0 / 6.0 + kappa) * alpha,
        (dg * safe_sin - g * cos_a) / safe_sin**2,
    )
    with np.errstate(invalid="ignore", divide="ignore"):
        direction = np.where(rho[:, None] > 0, P[:, :2] / rho[:, None], 0.0)
    dalpha = np.empty((len(P), 3))
    dalpha[:, :2] = direction * (P[:, 2] / norm**2)[:, None]
    dalpha[:, 2] = -rho / norm**2
    J_u = (np.eye(3)[None, :2, :] - u[:, :2, None] * u[:, None, :]) / norm[:, None, None]
    J_p = s[:, None, None] * J_u + (u[:, :2] * ds[:, None])[:, :, None] * dalpha[:, None, :]
    J_r = direction[:, :, None] * dg_dc[:, None, :]
    return m, J_p * inv[:, None, None], J_r


def sphere_residual(
    theta: np.ndarray,
    brown_names: tuple[str, ...],
    scale_px: float,
    uv_px: np.ndarray,
    points_cam: np.ndarray,
    jacobians: bool = False,
    radial_names: tuple[str, ...] | None = None,
):
    """Residual of the collinearity condition on the sphere, in pixels.

    ``e = (uv - pp - brown(uv - pp)) - c * m(P)`` with ``m`` from
    :func:`ideal_projection` and ``theta = [xp, yp, c, *radial, *brown]``.

    Parameters
    ----------
    theta : ndarray, shape (3 + G + B,)
    brown_names : tuple of str, length B
    scale_px : float
        Brown normalisation radius (px).
    uv_px : ndarray, shape (N, 2)
        Measured pixels, already corrected by any learned correction.
    points_cam : ndarray, shape (N, 3)
        Object points in the camera frame.
    jacobians : bool
        Also return ``de/dtheta`` (N, 2, 3 + G + B) and ``de/dpoints_cam`` (N, 2, 3).
    radial_names : tuple of str (length G) or None
        None: the paper's sphere mapping; a tuple: the radial mapping with
        these coefficients (``()`` is equidistant).

    Returns
    -------
    e_px : ndarray, shape (N, 2)
    """
    G = -1 if radial_names is None else len(radial_names)
    pp = theta[:2]
    c = theta[2]
    radial = None if G < 0 else np.asarray(theta[3 : 3 + G], float)
    b0 = 3 + max(G, 0)
    coeffs = dict(zip(brown_names, theta[b0:]))
    xbar = uv_px - pp
    if not jacobians:
        m = ideal_projection(points_cam, radial)
        if brown_names:
            return xbar - brown_distortion(xbar, coeffs, scale_px) - c * m
        return xbar - c * m
    m, J_m, J_r = ideal_projection(points_cam, radial, jacobians=True)
    n = len(m)
    if brown_names:
        delta, Jd, Jc = brown_distortion(xbar, coeffs, scale_px, jacobians=True)
        e = xbar - delta - c * m
    else:
        e = xbar - c * m
        Jd = np.zeros((n, 2, 2))
        Jc = np.zeros((n, 2, 0))
    J_theta = np.empty((n, 2, b0 + len(brown_names)))
    J_theta[:, :, :2] = Jd - np.eye(2)
    J_theta[:, :, 2] = -m
    J_theta[:, :, 3:b0] = -c * J_r
    J_theta[:, :, b0:] = -Jc
    return e, J_theta, -c * J_m


@dataclass
class SphereCamera:
    """A calibrated spherical camera: project and unproject over the whole sphere.

    Attributes
    ----------
    width, height : int
        Image size (px).
    xp, yp : float
        Principal point (px, OpenCV pixel convention).
    c : float
        Principal distance: radius of the virtual image sphere (px).
    brown : dict
        Brown additional parameters present in the model (dimensionless).
    brown_scale_px : float
        Normalisation radius of the Brown terms (px).
    correction : Correction or None
        Learned measurement correction (``predict(uv_px) -> (N, 2)`` px).
    radial : dict or None
        ``None``: the paper's sphere mapping (``c * P[:2] / |P|``). A dict
        ``{"g3": .., "g5": ..}``: the radial mapping ``c * g(alpha)`` of
        :func:`radial_g` (``{}`` is equidistant).
    """

    width: int
    height: int
    xp: float
    yp: float
    c: float
    brown: dict[str, float] = field(default_factory=dict)
    brown_scale_px: float = 0.0
    correction: Correction | None = None
    radial: dict[str, float] | None = None

    def __post_init__(self) -> None:
        for name in ("width", "height", "c"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"SphereCamera: {name} must be finite and > 0, got {value!r}")
        for name in ("xp", "yp", "brown_scale_px"):
            value = getattr(self, name)
            if not np.isfinite(value):
                raise ValueError(f"SphereCamera: {name} must be finite, got {value!r}")
        for kind, terms in (("brown", self.brown), ("radial", self.radial or {})):
            bad = {k: v for k, v in terms.items() if not np.isfinite(v)}
            if bad:
                raise ValueError(f"SphereCamera: {kind} terms must be finite, got {bad}")
        if self.brown_scale_px <= 0:
            self.brown_scale_px = 0.5 * max(self.width, self.height)

    @property
    def principal_point_px(self) -> np.ndarray:
        """``(xp, yp)`` as a (2,) array."""
        return np.array([self.xp, self.yp])

    @property
    def mapping(self) -> str:
        """``"sphere"`` or ``"radial"``."""
        return "sphere" if self.radial is None else "radial"

    def _radial_coeffs(self) -> np.ndarray | None:
        if self.radial is None:
            return None
        return np.array([float(self.radial.get(t, 0.0)) for t in RADIAL_TERMS], float)

    def distortion_px(self, uv_px: np.ndarray) -> np.ndarray:
        """Total measurement correction at raw pixels (N, 2): learned + Brown, px.

        As in the adjustment: the learned field at the raw pixel, then Brown
        at the pixel it corrected, ``uv - pp - ideal = learned(uv) + brown(uv -
        learned(uv) - pp)``.
        """
        uv = check_uv(uv_px)
        delta = np.zeros_like(uv)
        if self.correction is not None:
            delta += self.correction.predict(uv)
        if self.brown:
            delta += brown_distortion(
                uv - delta - self.principal_point_px, self.brown, self.brown_scale_px
            )
        return delta

    def ideal_from_pixels(self, uv_px: np.ndarray) -> np.ndarray:
        """Corrected image coordinates relative to the principal point, (N, 2) px."""
        uv = check_uv(uv_px)
        return uv - self.principal_point_px - self.distortion_px(uv)

    def pixel_residuals(self, uv_px: np.ndarray, ideal_residuals_px: np.ndarray) -> np.ndarray:
        """Residuals in raw pixels from residuals in corrected (ideal) coordinates.

        The adjustment's residual ``e = ideal_from_pixels(uv) - ideal(P)`` lives
        in corrected coordinates; OpenCV-style statistics need ``uv - project(P)``.
        To first order ``uv - project(P) = (I - d brown / d uv)^-1 e`` (the
        learned field's gradient, well below 1 px/px, is neglected), which is
        also what a strongly compressing Brown model at the rim amplifies.

        Parameters
        ----------
        uv_px : ndarray, shape (N, 2)
            Raw measurements.
        ideal_residuals_px : ndarray, shape (N, 2)

        Returns
        -------
        residuals_px : ndarray, shape (N, 2)
        """
        uv = check_uv(uv_px)
        e = check_uv(ideal_residuals_px, "ideal_residuals_px")
        if not self.brown:
            return e.copy()
        corrected = uv if self.correction is None else uv - self.correction.predict(uv)
        _, J, _ = brown_distortion(
            corrected - self.principal_point_px, self.brown, self.brown_scale_px, jacobians=True
        )
        A = np.eye(2)[None] - J
        ok = np.abs(np.linalg.det(A)) > 1e-12
        out = np.full_like(e, np.nan)
        out[ok] = np.linalg.solve(A[ok], e[ok][..., None])[..., 0]
        return out

    def ideal_from_points(self, points_cam: np.ndarray, jacobians: bool = False):
        """Ideal image coordinates (px, relative to the principal point) of camera-frame points.

        ``ideal_from_points(P) == ideal_from_pixels(project(P))``: the model
        without its measurement corrections, for factors with a frozen
        calibration (compare with :meth:`ideal_from_pixels` of the measurement).

        Parameters
        ----------
        points_cam : ndarray, shape (N, 3)
        jacobians : bool
            Also return ``d ideal / d points_cam``, shape (N, 2, 3) (px per unit).

        Returns
        -------
        ideal_px : ndarray, shape (N, 2)
        """
        p = check_points_cam(points_cam)
        out = ideal_projection(p, self._radial_coeffs(), jacobians=jacobians)
        if not jacobians:
            return self.c * out
        return self.c * out[0], self.c * out[1]

    def project(
        self, points_cam: np.ndarray, max_iterations: int = 50, tol_px: float = 1e-9
    ) -> np.ndarray:
        """Project camera-frame points to raw pixels.

        Parameters
        ----------
        points_cam : ndarray, shape (N, 3)
            Points in the camera frame (x right, y down, z forward); any
            direction, including behind the camera.
        max_iterations, tol_px
            Inversion of the measurement corrections: Newton steps on the
            Brown part (its exact Jacobian) with the learned correction held
            at the current estimate (a fixed-point step). This converges when
            the learned correction changes by less than 1 px per px
            (Lipschitz constant < 1) and the Brown map ``uv -> uv - brown`` is
            invertible over the image, true of every calibrated lens whose
            corrections do not fold the image.

        Returns
        -------
        uv_px : ndarray, shape (N, 2)
            NaN for the perspective centre itself (``|P| = 0``).
        """
        p = check_points_cam(points_cam)
        with np.errstate(invalid="ignore", divide="ignore"):
            ideal = self.c * ideal_projection(p, self._radial_coeffs())
        pp = self.principal_point_px
        uv = pp + ideal
        if not self.brown and self.correction is None:
            return uv
        # 1. the corrected pixel w: w - pp - brown(w - pp) = ideal (Newton, exact Jacobian)
        w = uv
        if self.brown:
            for _ in range(max_iterations):
                xbar = w - pp
                delta, J, _ = brown_distortion(
                    xbar, self.brown, self.brown_scale_px, jacobians=True
                )
                f = xbar - delta - ideal
                A = np.eye(2)[None] - J
                step = np.linalg.solve(A, f[..., None])[..., 0]
                w = w - step
                if np.all(~np.isfinite(step) | (np.abs(step) < tol_px)):
                    break
        if self.correction is None:
            return w
        # 2. the raw pixel: uv - learned(uv) = w (fixed point)
        uv = w.copy()
        for _ in range(max_iterations):
            new = w + self.correction.predict(np.nan_to_num(uv))
            step = new - uv
            uv = new
            if np.all(~np.isfinite(step) | (np.abs(step) < tol_px)):
                break
        return uv

    def max_alpha_rad(self) -> float:
        """Largest incidence angle (rad) up to which the radial mapping increases (<= pi)."""
        coeffs = self._radial_coeffs()
        if coeffs is None:
            return math.pi / 2
        grid = np.linspace(0.0, math.pi, 2049)
        _, dg, _ = radial_g(grid, coeffs, derivative=True)
        bad = np.flatnonzero(dg <= 0)
        return float(grid[bad[0] - 1]) if len(bad) else math.pi

    def unproject(self, uv_px: np.ndarray, hemisphere: float | np.ndarray = 1.0) -> np.ndarray:
        """Unit rays in the camera frame for raw pixels.

        Parameters
        ----------
        uv_px : ndarray, shape (N, 2)
        hemisphere : float or ndarray (N,)
            Sphere mapping only: ``+1`` front half of the image sphere
            (incidence below 90 deg), ``-1`` back half. The sphere's two
            halves share the image disc, so a pixel alone cannot tell them
            apart; see ``docs/conventions.md``. The radial mapping is
            one-to-one up to :meth:`max_alpha_rad` and ignores it.

        Returns
        -------
        rays : ndarray, shape (N, 3)
            NaN where the corrected point falls outside the model's image
            (the sphere's disc of radius ``c``; beyond ``g(max_alpha)`` for
            the radial mapping).
        """
        with np.errstate(invalid="ignore", over="ignore"):
            m = self.ideal_from_pixels(uv_px) / self.c
        bad = ~np.isfinite(m).all(axis=1)
        m[bad] = np.nan
        coeffs = self._radial_coeffs()
        if coeffs is None:
            with np.errstate(invalid="ignore", over="ignore"):
                rho2 = (m**2).sum(1)
                # the rim (90 deg) rounds to rho2 = 1 + eps: clip inside the tolerance
                z = np.sqrt(np.clip(1.0 - rho2, 0.0, None)) * np.sign(
                    np.asarray(hemisphere, float)
                )
            rays = np.column_stack([m, z * np.ones(len(m))])
            with np.errstate(invalid="ignore"):
                rays[~(rho2 <= 1.0 + 1e-12)] = np.nan
            return rays
        with np.errstate(over="ignore"):
            r = np.hypot(m[:, 0], m[:, 1])
        a_max = self.max_alpha_rad()
        g_max = float(radial_g(np.array([a_max]), coeffs)[0])
        lo = np.zeros_like(r)
        hi = np.full_like(r, a_max)
        alpha = np.clip(r, 0.0, a_max)
        for _ in range(60):  # safeguarded Newton on g(alpha) = r
            g, dg, _ = radial_g(alpha, coeffs, derivative=True)
            f = g - r
            lo = np.where(f < 0, alpha, lo)
            hi = np.where(f > 0, alpha, hi)
            with np.errstate(invalid="ignore", divide="ignore"):
                step = alpha - f / dg
            bisect = ~np.isfinite(step) | (step < lo) | (step > hi)
            done = np.abs(f) < 1e-15
            alpha = np.where(done, alpha, np.where(bisect, 0.5 * (lo + hi), step))
            if np.all(~np.isfinite(f) | (np.abs(f) < 1e-15)):
                break
        with np.errstate(invalid="ignore", divide="ignore"):
            direction = np.where(r[:, None] > 0, m / r[:, None], 0.0)
        rays = np.column_stack([np.sin(alpha)[:, None] * direction, np.cos(alpha)])
        rays[~(r <= g_max * (1 + 1e-12))] = np.nan
        return rays

    def to_dict(self) -> dict:
        """Model-specific ``camera`` entries of ``calibration@1``."""
        d = {
            "width": self.width,
            "height": self.height,
            "xp_px": self.xp,
            "yp_px": self.yp,
            "c_px": self.c,
            "mapping": self.mapping,
        }
        if self.radial is not None:
            d["radial"] = dict(self.radial)
            d["radial_alpha0_rad"] = ALPHA0_RAD
        if self.brown:
            d["brown"] = dict(self.brown)
            d["brown_scale_px"] = self.brown_scale_px
        return d
