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
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

BROWN_TERMS: tuple[str, ...] = ("k1", "k2", "k3", "p1", "p2", "a1", "a2")


class Model(enum.StrEnum):
    """Camera models ``calibrate`` can estimate."""

    SPHERE = "sphere"
    SPHERE_KNN = "sphere+knn"
    BROWN = "brown"
    BROWN_KNN = "brown+knn"

    @property
    def uses_brown(self) -> bool:
        """The graph estimates Brown additional parameters."""
        return self in (Model.BROWN, Model.BROWN_KNN)

    @property
    def uses_knn(self) -> bool:
        """A kNN correction is learned from the residuals (the grey-box loop)."""
        return self in (Model.SPHERE_KNN, Model.BROWN_KNN)


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


def sphere_residual(
    theta: np.ndarray,
    brown_names: tuple[str, ...],
    scale_px: float,
    uv_px: np.ndarray,
    points_cam: np.ndarray,
    jacobians: bool = False,
):
    """Residual of the collinearity condition on the sphere, in pixels.

    ``e = (uv - pp - brown(uv - pp)) - c * P[:2] / |P|`` with
    ``theta = [xp, yp, c, *brown coefficients in brown_names order]``.

    Parameters
    ----------
    theta : ndarray, shape (3 + B,)
    brown_names : tuple of str, length B
    scale_px : float
        Brown normalisation radius (px).
    uv_px : ndarray, shape (N, 2)
        Measured pixels, already corrected by any learned correction.
    points_cam : ndarray, shape (N, 3)
        Object points in the camera frame.
    jacobians : bool
        Also return ``de/dtheta`` (N, 2, 3 + B) and ``de/dpoints_cam`` (N, 2, 3).

    Returns
    -------
    e_px : ndarray, shape (N, 2)
    """
    pp = theta[:2]
    c = theta[2]
    coeffs = dict(zip(brown_names, theta[3:]))
    xbar = uv_px - pp
    norm = np.linalg.norm(points_cam, axis=1)
    s = points_cam[:, :2] / norm[:, None]
    if not brown_names:
        e = xbar - c * s
        if not jacobians:
            return e
        Jd = np.zeros((len(e), 2, 2))
        Jc = np.zeros((len(e), 2, 0))
    elif not jacobians:
        return xbar - brown_distortion(xbar, coeffs, scale_px) - c * s
    else:
        delta, Jd, Jc = brown_distortion(xbar, coeffs, scale_px, jacobians=True)
        e = xbar - delta - c * s
    n = len(e)
    J_theta = np.empty((n, 2, 3 + len(brown_names)))
    J_theta[:, :, :2] = Jd - np.eye(2)
    J_theta[:, :, 2] = -s
    J_theta[:, :, 3:] = -Jc
    u = points_cam / norm[:, None]
    J_p = -(c / norm)[:, None, None] * (np.eye(3)[None, :2, :] - u[:, :2, None] * u[:, None, :])
    return e, J_theta, J_p


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
    """

    width: int
    height: int
    xp: float
    yp: float
    c: float
    brown: dict[str, float] = field(default_factory=dict)
    brown_scale_px: float = 0.0
    correction: Correction | None = None

    def __post_init__(self) -> None:
        if self.brown_scale_px <= 0:
            self.brown_scale_px = 0.5 * max(self.width, self.height)

    @property
    def principal_point_px(self) -> np.ndarray:
        """``(xp, yp)`` as a (2,) array."""
        return np.array([self.xp, self.yp])

    def distortion_px(self, uv_px: np.ndarray) -> np.ndarray:
        """Total measurement correction at raw pixels (N, 2): Brown + learned, px."""
        uv = check_uv(uv_px)
        delta = np.zeros_like(uv)
        if self.brown:
            delta += brown_distortion(uv - self.principal_point_px, self.brown, self.brown_scale_px)
        if self.correction is not None:
            delta += self.correction.predict(uv)
        return delta

    def ideal_from_pixels(self, uv_px: np.ndarray) -> np.ndarray:
        """Corrected image coordinates relative to the principal point, (N, 2) px."""
        uv = check_uv(uv_px)
        return uv - self.principal_point_px - self.distortion_px(uv)

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
        norm = np.linalg.norm(p, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            ideal = self.c * p[:, :2] / norm[:, None]
        pp = self.principal_point_px
        uv = pp + ideal
        if not self.brown and self.correction is None:
            return uv
        for _ in range(max_iterations):
            target = ideal.copy()
            if self.correction is not None:
                target += self.correction.predict(np.nan_to_num(uv))
            xbar = uv - pp
            if self.brown:
                delta, J, _ = brown_distortion(
                    xbar, self.brown, self.brown_scale_px, jacobians=True
                )
                f = xbar - delta - target
                A = np.eye(2)[None] - J
                step = np.linalg.solve(A, f[..., None])[..., 0]
            else:
                step = xbar - target
            uv = uv - step
            if np.all(~np.isfinite(step) | (np.abs(step) < tol_px)):
                break
        return uv

    def unproject(self, uv_px: np.ndarray, hemisphere: float | np.ndarray = 1.0) -> np.ndarray:
        """Unit rays in the camera frame for raw pixels.

        Parameters
        ----------
        uv_px : ndarray, shape (N, 2)
        hemisphere : float or ndarray (N,)
            ``+1`` front half of the image sphere (incidence below 90 deg),
            ``-1`` back half. The sphere's two halves share the image disc,
            so a pixel alone cannot tell them apart; see
            ``docs/conventions.md``.

        Returns
        -------
        rays : ndarray, shape (N, 3)
            NaN where the corrected point falls outside the sphere's disc
            (radius ``c``).
        """
        m = self.ideal_from_pixels(uv_px) / self.c
        rho2 = (m**2).sum(1)
        with np.errstate(invalid="ignore"):
            z = np.sqrt(1.0 - rho2) * np.sign(np.asarray(hemisphere, float))
        rays = np.column_stack([m, z * np.ones(len(m))])
        rays[rho2 > 1.0 + 1e-12] = np.nan
        return rays

    def to_dict(self) -> dict:
        """Model-specific ``camera`` entries of ``calibration@1``."""
        d = {
            "width": self.width,
            "height": self.height,
            "xp_px": self.xp,
            "yp_px": self.yp,
            "c_px": self.c,
        }
        if self.brown:
            d["brown"] = dict(self.brown)
            d["brown_scale_px"] = self.brown_scale_px
        return d
