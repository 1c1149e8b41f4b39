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

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ._compat import StrEnum
from .errors import OptionsError
from .tabulated import CorrectionTable, choose_table

BROWN_TERMS: tuple[str, ...] = ("k1", "k2", "k3", "p1", "p2", "a1", "a2")
RADIAL_TERMS: tuple[str, ...] = ("g3", "g5", "g7", "g9", "g11", "g13")
#: key of the radial mapping's warp (:func:`radial_warp`, a fixed shape constant) in
#: ``SphereCamera.radial`` when the lens needs one (a field that saturates its rim)
WARP_TERM = "w"
#: normalising angle of the radial mapping's polynomial (rad)
ALPHA0_RAD = math.pi / 2
#: a fold of the Brown map farther than this many ``brown_scale_px`` from the principal
#: point counts as none (tiny terms fold only astronomically far out)
FOLD_HORIZON = 1e6
#: margin (rad, 2 deg) beyond the largest observed incidence angle up to which
#: :meth:`SphereCamera.project` still answers: a calibration extrapolates this little
#: reliably (the radial polynomial and the nearest-neighbour field hold their shape),
#: and points on the edge of the observed field stay projectable
VALID_MARGIN_RAD = math.radians(2.0)


class Model(StrEnum):
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


def check_region(alpha_by_azimuth_rad) -> tuple[float, ...]:
    """Validate a valid region's table of incidence limits, as a tuple of float.

    Parameters
    ----------
    alpha_by_azimuth_rad : array_like, shape (A,)
        Largest valid incidence angle (rad, in ``[0, pi]``) at the ``A >= 4``
        evenly spaced azimuths ``2 pi i / A``.

    Raises
    ------
    OptionsError
        Not a 1-D list of at least 4 finite angles in ``[0, pi]``.
    """
    try:
        a = np.asarray(alpha_by_azimuth_rad, float)
    except (TypeError, ValueError) as exc:
        raise OptionsError(f"valid region: not a list of angles ({exc})") from None
    if a.ndim != 1 or len(a) < 4:
        raise OptionsError(f"valid region: need a 1-D list of >= 4 angles, got shape {a.shape}")
    if not np.all(np.isfinite(a)) or np.any(a < 0) or np.any(a > math.pi):
        raise OptionsError("valid region: angles must be finite and in [0, pi] rad")
    return tuple(float(x) for x in a)


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

    Raises :class:`~gtsam_sphere.core.errors.OptionsError` (a ``ValueError``) naming an
    unknown term. ``"all"`` selects all seven.
    """
    if text is None or text.strip() == "":
        return ()
    if text.strip().lower() == "all":
        return BROWN_TERMS
    names = [t.strip().lower() for t in text.split(",") if t.strip()]
    for n in names:
        if n not in BROWN_TERMS:
            raise OptionsError(f"unknown additional parameter {n!r}; choose from {BROWN_TERMS}")
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
        raise OptionsError(f"the radial mapping has 0 to {len(RADIAL_TERMS)} terms, got {n}")
    return RADIAL_TERMS[:n]


def _warped_angle(alpha: np.ndarray, warp: float | None):
    """``(phi, k, dphi/dalpha)`` of the warp: ``phi = atan2(k sin(alpha), cos(alpha))``,
    ``k = exp(warp)``; ``(alpha, 1, 1)`` without a warp (``warp`` None)."""
    a = np.asarray(alpha, float)
    if warp is None:
        return a, 1.0, 1.0
    k = math.exp(warp)
    sin_a, cos_a = np.sin(a), np.cos(a)
    return np.arctan2(k * sin_a, cos_a), k, k / (cos_a**2 + (k * sin_a) ** 2)


def radial_warp(alpha: np.ndarray, w: float) -> np.ndarray:
    """Warped incidence ``beta(alpha) = atan2(k sin(alpha), cos(alpha)) / k``, ``k = exp(w)``.

    The field-of-view model's shape (Devernay and Faugeras 2001) normalised to slope 1
    on the axis: ``w = 0`` is ``beta = alpha``; ``w < 0`` bends towards ``tan(alpha)``
    (a perspective lens), ``w > 0`` saturates (a lens that squeezes its rim).
    Increasing on ``[0, pi]`` for every ``w``; ``beta(pi) = pi / k``.

    Parameters
    ----------
    alpha : ndarray, shape (N,)
        Incidence angles (rad).
    w : float
        Log of the warp ``k`` (dimensionless).

    Returns
    -------
    beta : ndarray, shape (N,)
    """
    phi, k, _ = _warped_angle(alpha, w)
    return phi / k


def radial_g(
    alpha: np.ndarray, coeffs: np.ndarray, derivative: bool = False, warp: float | None = None
):
    """Radial mapping ``g(alpha) = h(alpha) = alpha + A0 * sum_i g_i (alpha / A0)^(2i+3)``.

    ``A0 = pi/2``. ``c * g(alpha)`` is the geodesic distance (px) on the virtual sphere
    from the principal point to the image point; ``g = alpha`` is equidistant. With a
    ``warp`` ``w`` (``k = exp(w)``): ``g(alpha) = h(phi) / k`` with ``phi = atan2(k
    sin(alpha), cos(alpha))`` (so ``g = beta`` of :func:`radial_warp` when every ``g_i``
    is 0); ``phi / A0`` spans ``[0, 2]`` like ``alpha / A0``, which keeps the
    polynomial's coefficients of order one for any ``k``.

    Parameters
    ----------
    alpha : ndarray, shape (N,)
        Incidence angles (rad).
    coeffs : ndarray, shape (G,)
        ``g3, g5, ...`` (dimensionless).
    derivative : bool
        Also return ``dg/dalpha`` (N,) and ``dg/dcoeffs`` (N, G).
    warp : float or None
        ``w`` (None: no warp). A shape constant chosen by the initialisation, not
        estimated: a free ``w`` is nearly redundant with the polynomial.
    """
    x, k, dx_da = _warped_angle(alpha, warp)
    t = x / ALPHA0_RAD
    h = np.array(x, float, copy=True)
    G = len(coeffs)
    powers = np.empty((len(t), G))
    for i in range(G):
        powers[:, i] = t ** (2 * i + 3)
    h += ALPHA0_RAD * powers @ np.asarray(coeffs, float)
    g = h / k
    if not derivative:
        return g
    dh = np.ones_like(h)
    for i in range(G):
        dh += (2 * i + 3) * coeffs[i] * t ** (2 * i + 2)
    return g, dh * dx_da / k, ALPHA0_RAD * powers / k


def radial_g_horner(
    alpha: np.ndarray, coeffs: np.ndarray, warp: float | None = None, derivative: bool = False
):
    """:func:`radial_g` (and ``dg/dalpha``) by Horner's rule in ``(x / A0)^2``: no powers.

    The same function as :func:`radial_g` to rounding (about 1e-16 relative),
    without the coefficient Jacobian; used by the fast paths of
    :meth:`SphereCamera.project` and :meth:`SphereCamera.unproject`.
    """
    x, k, dx_da = _warped_angle(alpha, warp)
    c = np.asarray(coeffs, float)
    while len(c) and c[-1] == 0.0:
        c = c[:-1]
    t = x * (1.0 / ALPHA0_RAD)
    t2 = t * t
    if len(c):
        poly = np.full_like(t, c[-1])
        for ci in c[-2::-1]:
            poly *= t2
            poly += ci
        h = x + ALPHA0_RAD * t * t2 * poly
    else:
        h = x.copy()
    g = h / k
    if not derivative:
        return g
    if len(c):
        n = np.arange(len(c))
        dc = (2 * n + 3) * c
        dpoly = np.full_like(t, dc[-1])
        for ci in dc[-2::-1]:
            dpoly *= t2
            dpoly += ci
        dh = 1.0 + t2 * dpoly
    else:
        dh = np.ones_like(t)
    return g, dh * dx_da / k


def ideal_projection(
    points_cam: np.ndarray,
    radial: np.ndarray | None,
    jacobians: bool = False,
    warp: float | None = None,
):
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
    warp : float or None
        ``w`` of :func:`radial_warp` for the radial mapping (None: no warp).

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
    out = radial_g(alpha, radial, derivative=jacobians, warp=warp)
    g = out[0] if jacobians else out
    kappa = (radial[0] / ALPHA0_RAD**2) if len(radial) else 0.0
    if warp is not None:  # g = alpha + ((1 - k^2) / 3 + g3 k^2 / A0^2) alpha^3 + O(alpha^5)
        k2 = math.exp(2.0 * warp)
        kappa = kappa * k2 + (1.0 - k2) / 3.0
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
    warp: float | None = None,
):
    """Residual of the collinearity condition on the sphere, in pixels.

    ``e = A^-1 ((uv - pp - brown(uv - pp)) - c * m(P))`` with ``m`` from
    :func:`ideal_projection`, ``theta = [xp, yp, c, *radial, *brown]`` and ``A = I -
    d brown_pa / d uv`` the decentering and affinity part of ``I - d brown / d uv``
    (:func:`decentering_affinity_matrix`; ``I`` without ``p1, p2, a1, a2``).

    The corrections act on the measurement, so the bracket is a residual in corrected
    coordinates, whose metric the corrections change: an affinity scales x by ``1 -
    a1``, a decentering term far from the principal point scales y by ``1 - 6 p2 y``
    (Brown-normalised units). A least-squares cost there can fall by inflating them
    (a 119 deg equisolid object with 5 % blunders slid to ``a1 = 0.56``, the principal
    point 650 px off, sigma 0.61 px for 1 px noise, and ended untrusted at 33x the
    oracle's 3D error). ``A^-1`` maps the residual back to raw pixels to first order;
    the radial Brown terms ``k1-k3`` stay in corrected coordinates (past 90 deg their
    fold makes ``I - d brown / d uv`` singular: a pixel does not pin the ray down).

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
    warp : float or None
        The radial mapping's fixed warp ``w`` (:func:`radial_g`); None: none.

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
        m = ideal_projection(points_cam, radial, warp=warp)
        if brown_names:
            if not _has_pa(coeffs):
                return xbar - brown_distortion(xbar, coeffs, scale_px) - c * m
            # as in the Jacobian branch, to the last bit
            delta, Jd, _ = brown_distortion(xbar, coeffs, scale_px, jacobians=True)
            A_inv = np.linalg.inv(_pa_matrix(xbar, coeffs, scale_px, Jd))
            return np.einsum("nij,nj->ni", A_inv, xbar - delta - c * m)
        return xbar - c * m
    m, J_m, J_r = ideal_projection(points_cam, radial, jacobians=True, warp=warp)
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
    J_pc = -c * J_m
    if not _has_pa(coeffs):
        return e, J_theta, J_pc
    # e' = A^-1 e, A = I - J_pa: de' = A^-1 (de + dJ_pa e')
    A_inv = np.linalg.inv(_pa_matrix(xbar, coeffs, scale_px, Jd))
    e_out = np.einsum("nij,nj->ni", A_inv, e)
    dJ = _pa_matrix_derivatives(xbar, coeffs, scale_px)
    names = list(brown_names)
    J_theta[:, :, 0] += np.einsum("nij,nj->ni", dJ["xp"], e_out)
    J_theta[:, :, 1] += np.einsum("nij,nj->ni", dJ["yp"], e_out)
    for t in PA_TERMS:
        if t in coeffs:
            J_theta[:, :, b0 + names.index(t)] += np.einsum("nij,nj->ni", dJ[t], e_out)
    J_theta = np.einsum("nij,njk->nik", A_inv, J_theta)
    J_pc = np.einsum("nij,njk->nik", A_inv, J_pc)
    return e_out, J_theta, J_pc


#: the decentering and affinity terms, whose part of ``I - d brown / d uv`` is undone in
#: :func:`sphere_residual`
PA_TERMS = ("p1", "p2", "a1", "a2")
#: the radial Brown terms, which stay in corrected coordinates (:func:`sphere_residual`)
RADIAL_BROWN_TERMS = ("k1", "k2", "k3")


def has_radial_brown(terms) -> bool:
    """Whether ``terms`` (names, or a dict of coefficients) hold a radial Brown term."""
    return any(t in terms for t in RADIAL_BROWN_TERMS)


def _has_pa(coeffs: dict) -> bool:
    return any(t in coeffs for t in PA_TERMS)


def decentering_affinity_matrix(
    xbar_px: np.ndarray, brown: dict[str, float], scale_px: float
) -> np.ndarray:
    """``A = I - d brown_pa / d xbar`` (N, 2, 2): the decentering (``p1, p2``) and
    affinity (``a1, a2``) part of the Brown map's ``I - d brown / d uv``.

    Parameters
    ----------
    xbar_px : ndarray, shape (N, 2)
        Measured (corrected) pixels minus the principal point.
    brown : dict
        Brown coefficients (missing terms are 0; the radial ``k1-k3`` are ignored).
    scale_px : float
        Brown normalisation radius.

    Returns
    -------
    ndarray, shape (N, 2, 2)
    """
    return _pa_matrix(np.asarray(xbar_px, float), brown, scale_px)


def _pa_matrix(xbar_px, brown, scale_px, J_brown=None) -> np.ndarray:
    """:func:`decentering_affinity_matrix`, from ``J_brown = d brown / d xbar`` (N, 2, 2)
    of the same coefficients when they hold no radial term (then it is all of it)."""
    if J_brown is None or has_radial_brown(brown):
        pa = {t: brown[t] for t in PA_TERMS if t in brown}
        J_brown = brown_distortion(xbar_px, pa, scale_px, jacobians=True)[1]
    return np.eye(2)[None] - J_brown


def _pa_matrix_derivatives(xbar_px, brown, scale_px) -> dict[str, np.ndarray]:
    """Derivatives (N, 2, 2) of ``J_pa = I - A`` (:func:`decentering_affinity_matrix`) by
    ``xp, yp`` (px; ``xbar = uv - pp``) and by ``p1, p2, a1, a2``."""
    n = len(xbar_px)
    x = xbar_px[:, 0] / scale_px
    y = xbar_px[:, 1] / scale_px
    p1, p2 = float(brown.get("p1", 0.0)), float(brown.get("p2", 0.0))
    out = {
        "p1": np.stack([np.stack([6 * x, 2 * y], -1), np.stack([2 * y, 2 * x], -1)], 1),
        "p2": np.stack([np.stack([2 * y, 2 * x], -1), np.stack([2 * x, 6 * y], -1)], 1),
        "a1": np.broadcast_to(np.array([[1.0, 0.0], [0.0, 0.0]]), (n, 2, 2)),
        "a2": np.broadcast_to(np.array([[0.0, 1.0], [0.0, 0.0]]), (n, 2, 2)),
    }
    d_dx = np.array([[6 * p1, 2 * p2], [2 * p2, 2 * p1]]) / scale_px
    d_dy = np.array([[2 * p2, 2 * p1], [2 * p1, 6 * p2]]) / scale_px
    out["xp"] = np.broadcast_to(-d_dx, (n, 2, 2))
    out["yp"] = np.broadcast_to(-d_dy, (n, 2, 2))
    return out


# -- the Brown map along a line of pixels through the principal point --------------------------
#
# Along ``xbar = u * s * d`` (``d`` a unit direction, ``s`` the Brown scale) the radial
# component of the corrected coordinates ``xbar - brown(xbar)`` is a polynomial in ``u``:
#
#     d . (xbar - brown(xbar)) / s = b1 u + b2 u^2 - k1 u^3 - k2 u^5 - k3 u^7
#     b1 = 1 - a1 dx^2 - a2 dx dy,   b2 = -3 (p1 dx + p2 dy)
#
# (the tangential component holds only p1, p2, a2). A lens seeing past 90 deg is
# represented by this polynomial rising to a maximum (the fold, incidence 90 deg) and
# falling beyond it (the back half of the image sphere, whose ideal radius c sin(alpha)
# shrinks while the image radius keeps growing).


def _brown_line_coeffs(brown: dict[str, float], d: np.ndarray) -> np.ndarray:
    """Ascending coefficients (N, 8) of ``d . (xbar - brown(xbar)) / s`` in ``u = |xbar| / s``."""
    g = {t: float(brown.get(t, 0.0)) for t in BROWN_TERMS}
    dx, dy = d[:, 0], d[:, 1]
    out = np.zeros((len(d), 8))
    out[:, 1] = 1.0 - g["a1"] * dx * dx - g["a2"] * dx * dy
    out[:, 2] = -3.0 * (g["p1"] * dx + g["p2"] * dy)
    out[:, 3] = -g["k1"]
    out[:, 5] = -g["k2"]
    out[:, 7] = -g["k3"]
    return out


def _poly_eval(coeffs: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Polynomials with ascending coefficients (N, K) at ``u`` (N,) (Horner)."""
    out = np.zeros(len(coeffs))
    for k in range(coeffs.shape[1] - 1, -1, -1):
        out = out * u + coeffs[:, k]
    return out


def _poly_derivative(coeffs: np.ndarray) -> np.ndarray:
    """Ascending coefficients (N, K - 1) of the derivatives of polynomials (N, K)."""
    return coeffs[:, 1:] * np.arange(1, coeffs.shape[1])


def _positive_real_roots(coeffs: np.ndarray) -> np.ndarray:
    """Positive real roots of polynomials (N, K), ascending and padded with ``inf``, (N, K - 1).

    Companion-matrix eigenvalues; a near-double root (which rounding splits
    into a complex pair) counts as real, so callers check the sign changes.
    """
    n_rows, k = coeffs.shape
    out = np.full((n_rows, max(k - 1, 0)), np.inf)
    if k < 2 or n_rows == 0:
        return out
    # a leading term negligible up to FOLD_HORIZON is dropped (it would only add roots beyond
    # it, and its companion matrix would overflow)
    reach = FOLD_HORIZON ** np.arange(k)
    with np.errstate(over="ignore"):
        lower = np.abs(coeffs[:, -1]) * reach[-1] <= 1e-18 * np.max(
            np.abs(coeffs[:, :-1]) * reach[:-1], axis=1
        )
    if lower.any():
        sub = _positive_real_roots(coeffs[lower, :-1])
        out[np.flatnonzero(lower)[:, None], np.arange(sub.shape[1])[None]] = sub
    full = ~lower
    if not full.any():
        return out
    c = coeffs[full]
    deg = k - 1
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        if deg == 1:
            roots = (-c[:, 0] / c[:, 1])[:, None]
            ok = np.isfinite(roots) & (roots > 0)
        else:
            comp = np.zeros((len(c), deg, deg))
            comp[:, 1:, :-1] = np.eye(deg - 1)
            comp[:, :, -1] = -c[:, :-1] / c[:, -1:]
            z = np.linalg.eigvals(comp)
            roots = z.real
            ok = (np.abs(z.imag) <= 1e-6 * (1.0 + np.abs(z))) & (roots > 0)
    out[full] = np.sort(np.where(ok, roots, np.inf), axis=1)
    return out


def _turning_points(coeffs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First maximum ``u_f`` and the following minimum ``u_m`` (``inf`` if none) on ``u > 0``.

    For polynomials (N, K) increasing at ``u = 0``: the polynomial increases on
    ``[0, u_f]`` and decreases on ``[u_f, u_m]``. A maximum beyond
    ``FOLD_HORIZON`` counts as none.
    """
    dg = _poly_derivative(coeffs)
    cand = _positive_real_roots(dg)
    n_rows, m = cand.shape
    inf = np.full(n_rows, np.inf)
    if m == 0:
        return inf, inf.copy()
    # refine the roots (companion eigenvalues lose digits near a double root)
    ddg = _poly_derivative(dg)
    for _ in range(2):
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            fin = np.where(np.isfinite(cand), cand, 0.0)
            new = np.stack(
                [
                    fin[:, j] - _poly_eval(dg, fin[:, j]) / _poly_eval(ddg, fin[:, j])
                    for j in range(m)
                ],
                1,
            )
            close = np.isfinite(new) & (np.abs(new - cand) <= 1e-3 * cand)
        cand = np.where(close, new, cand)
    nxt = np.concatenate([cand[:, 1:], np.full((n_rows, 1), np.inf)], 1)
    with np.errstate(invalid="ignore", over="ignore"):
        probe = np.where(np.isfinite(nxt), 0.5 * (cand + nxt), 2.0 * cand + 1.0)
    finite = np.isfinite(probe)
    slope = np.zeros((n_rows, m))
    for j in range(m):
        slope[finite[:, j], j] = _poly_eval(dg[finite[:, j]], probe[finite[:, j], j])
    rows = np.arange(n_rows)
    down = finite & (slope < 0)
    has = down.any(1)
    kf = np.argmax(down, 1)
    u_f = np.where(has, cand[rows, kf], np.inf)
    u_f[u_f > FOLD_HORIZON] = np.inf
    up = finite & (slope > 0) & (np.arange(m)[None] > kf[:, None]) & has[:, None]
    u_m = np.where(up.any(1), cand[rows, np.argmax(up, 1)], np.inf)
    return u_f, u_m


def _solve_monotone(
    coeffs: np.ndarray, target: np.ndarray, lo: np.ndarray, hi: np.ndarray, sign: np.ndarray
) -> np.ndarray:
    """Root of ``poly(u) = target`` on ``[lo, hi]`` where ``sign * poly`` increases; NaN if none.

    ``hi`` may be ``inf`` (the polynomial is then monotone up to infinity).
    Safeguarded Newton (bisection when a step leaves the bracket).
    """
    lo = np.array(lo, float)
    hi = np.array(hi, float)
    dg = _poly_derivative(coeffs)

    def h(u):
        with np.errstate(invalid="ignore", over="ignore"):
            return sign * (_poly_eval(coeffs, u) - target)

    open_hi = ~np.isfinite(hi)
    trial = np.where(open_hi, np.maximum(2.0 * lo, lo + 1.0), hi)
    for _ in range(64):
        grow = open_hi & ~(h(trial) >= 0)
        if not grow.any():
            break
        trial[grow] *= 2.0
    hi = np.where(open_hi, trial, hi)
    with np.errstate(invalid="ignore"):
        has = np.isfinite(lo) & np.isfinite(hi) & (h(lo) <= 0) & (h(hi) >= 0)
    u = np.where(has, 0.5 * (lo + hi), np.nan)
    lo, hi = np.where(has, lo, np.nan), np.where(has, hi, np.nan)
    for _ in range(200):
        f = h(u)
        with np.errstate(invalid="ignore"):
            lo = np.where(f <= 0, u, lo)
            hi = np.where(f >= 0, u, hi)
            with np.errstate(divide="ignore", over="ignore"):
                step = u - f / (sign * _poly_eval(dg, u))
            inside = np.isfinite(step) & (step > lo) & (step < hi)
            new = np.where(inside, step, 0.5 * (lo + hi))
            moving = np.abs(new - u) > 4e-16 * np.abs(new)
        u = new
        if not np.any(moving & has):
            break
    return u


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
        :func:`radial_g` (``{}`` is equidistant); a key ``"w"`` (:data:`WARP_TERM`)
        warps its variable (:func:`radial_warp`).
    observed_alpha_rad : float or None
        Largest incidence angle (rad) of the observations the calibration used:
        the field its data support. :meth:`project` answers up to it plus
        :data:`VALID_MARGIN_RAD` (:meth:`valid_alpha_rad`) and gives NaN beyond;
        ``None`` (a camera not from data): no limit beyond the model's own.
    valid_region_alpha_rad : tuple of float or None
        The valid region where the projection uncertainty is small (built by
        :func:`gtsam_sphere.analysis.uncertainty.with_valid_region`): the
        largest incidence angle (rad) at ``A`` evenly spaced ray azimuths
        ``2 pi i / A`` (``atan2(y, x)`` of the camera-frame ray, x right,
        y down), linearly interpolated between them (:meth:`region_alpha_rad`).
        When set, :meth:`project` (``valid_only``), :meth:`valid_mask` and
        :meth:`valid_pixel_mask` also give NaN / ``False`` outside it.
        ``None`` (default): no such region.

    The learned correction is evaluated through a table
    (:meth:`correction_table`, built on first use and cached; ``exact=True``
    on the methods that use the correction asks the correction itself).
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
    observed_alpha_rad: float | None = None
    valid_region_alpha_rad: tuple[float, ...] | None = None
    # lazily built caches (not compared, not printed, not written to files)
    _table: CorrectionTable | None = field(default=None, init=False, repr=False, compare=False)
    _table_key: tuple | None = field(default=None, init=False, repr=False, compare=False)
    _max_alpha_key: tuple | None = field(default=None, init=False, repr=False, compare=False)
    _max_alpha: float = field(default=math.pi, init=False, repr=False, compare=False)

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
        if self.observed_alpha_rad is not None:
            a = float(self.observed_alpha_rad)
            if not (np.isfinite(a) and 0 < a <= math.pi):
                raise ValueError(f"SphereCamera: observed_alpha_rad must be in (0, pi], got {a!r}")
            self.observed_alpha_rad = a
        if self.valid_region_alpha_rad is not None:
            self.valid_region_alpha_rad = check_region(self.valid_region_alpha_rad)

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

    def _radial_warp(self) -> float | None:
        if self.radial is None or WARP_TERM not in self.radial:
            return None
        return float(self.radial[WARP_TERM])

    # -- the tabulated correction and the valid field -------------------------------------------

    def correction_table(self, spacing_px: float | None = None) -> CorrectionTable | None:
        """The learned correction tabulated on a pixel grid (None without a correction).

        Built on first use (:func:`~gtsam_sphere.core.tabulated.choose_table`:
        4 px nodes, finer while it differs from the correction by more than
        0.01 px RMS around the training pixels) and cached on the camera until
        :attr:`correction` is replaced or another ``spacing_px`` is asked for
        (a correction changed in place needs :meth:`clear_cache`). Not written to
        calibration files.
        """
        if self.correction is None:
            return None
        key = self._table_key
        fresh = key is not None and key[0] is self.correction
        if not fresh or (spacing_px is not None and key[1] != spacing_px):
            self._table = choose_table(self.correction, self.width, self.height, spacing_px)
            self._table_key = (self.correction, spacing_px)
        return self._table

    def clear_cache(self) -> None:
        """Forget the cached correction table and field limit (after changing them in place)."""
        self._table = None
        self._table_key = None
        self._max_alpha_key = None
        self._dist_cache = None
        self._g_cache = None

    def _tabulable(self) -> bool:
        """Brown terms that cannot fold inside the table: tabulated with the correction.

        The radial mapping (``k1-k3`` refused: decentering and affinity only) or
        no Brown terms, and the Brown map one-to-one over the image and its margin.
        """
        if not self.brown:
            return True
        if self.radial is None or any(self.brown.get(t, 0.0) for t in RADIAL_BROWN_TERMS):
            return False
        reach = math.hypot(self.width, self.height) + 64.0
        return self._fold_free_radius() * self.brown_scale_px > reach

    def distortion_table(self) -> CorrectionTable | None:
        """The whole measurement correction ``distortion_px`` tabulated (fast paths).

        The learned table's nodes with the Brown terms added at each node
        (``learned + brown(node - learned - pp)``), so that one lookup gives the
        corrected pixel and :meth:`project` needs one fixed point. None without a
        learned correction or when the Brown map may fold (:meth:`_tabulable`).
        """
        learned = self.correction_table()
        if learned is None or not self._tabulable():
            return None
        if not self.brown:
            return learned
        key = (learned, self.xp, self.yp, tuple(sorted(self.brown.items())), self.brown_scale_px)
        cached = getattr(self, "_dist_cache", None)
        if cached is not None and cached[0][0] is learned and cached[0][1:] == key[1:]:
            return cached[1]
        nodes = learned.nodes()
        lv = learned.values.reshape(-1, 2)
        total = lv + brown_distortion(
            nodes - lv - self.principal_point_px, self.brown, self.brown_scale_px
        )
        table = learned.with_values(total.reshape(learned.values.shape))
        self._dist_cache = (key, table)
        return table

    def _ideal_radial_fast(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ideal points (N, 2) px of the radial mapping and the incidence angles (N,)."""
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        rho = np.hypot(x, y)
        alpha = np.arctan2(rho, z)
        g = radial_g_horner(alpha, self._radial_coeffs(), self._radial_warp())
        with np.errstate(invalid="ignore", divide="ignore"):
            scale = self.c * g / rho
        # on the axis the ideal point is the principal point; P = 0 and the antipode: NaN
        scale = np.where(rho > 0, scale, np.where(z > 0, 0.0, np.nan))
        ideal = np.empty((len(p), 2))
        ideal[:, 0] = scale * x
        ideal[:, 1] = scale * y
        return ideal, alpha

    def _g_tables(self):
        """Cached tables of the radial mapping up to :meth:`max_alpha_rad`.

        ``grid, g_grid``: ``g`` at 4097 angles (a bracket for any radius);
        ``cells``: per cell of a uniform grid of 4097 radii on ``[0, g(a_top)]``
        (``a_top`` 10 deg past :meth:`valid_alpha_rad`, at most ``max_alpha``: a
        polynomial ``g`` can grow by orders of magnitude past the data), the cubic
        Hermite polynomial in the cell's local coordinate of the inverse
        ``alpha(r)`` (four arrays), for a start within about 1e-13 rad.
        """
        coeffs, warp = self._radial_coeffs(), self._radial_warp()
        a_max = self.max_alpha_rad()
        a_top = min(a_max, self.valid_alpha_rad() + math.radians(10.0))
        key = (tuple(coeffs), warp, a_max, a_top)
        cached = getattr(self, "_g_cache", None)
        if cached is not None and cached[0] == key:
            return cached[1]
        grid = np.linspace(0.0, a_max, 4097)
        g_grid = radial_g(grid, coeffs, warp=warp)
        g_top = float(radial_g(np.array([a_top]), coeffs, warp=warp)[0])
        r_nodes = np.linspace(0.0, g_top, 4097)
        h = r_nodes[1] - r_nodes[0]
        a_nodes = self._alpha_bracketed(r_nodes, grid, g_grid)
        _, dg = radial_g_horner(a_nodes, coeffs, warp, derivative=True)
        with np.errstate(divide="ignore"):
            m = np.where(dg > 0, h / dg, 0.0)  # slope in the cell's unit (0 at a fold: safe)
        m = np.minimum(m, 4.0 * (a_max / 4096.0))
        a0, a1, m0, m1 = a_nodes[:-1], a_nodes[1:], m[:-1], m[1:]
        cells = (a0, m0, 3.0 * (a1 - a0) - 2.0 * m0 - m1, 2.0 * (a0 - a1) + m0 + m1)
        tables = {"grid": grid, "g_grid": g_grid, "inv_h": 1.0 / h, "cells": cells}
        self._g_cache = (key, tables)
        return tables

    def _alpha_bracketed(self, r: np.ndarray, grid: np.ndarray, g_grid: np.ndarray) -> np.ndarray:
        """``alpha`` (N,) with ``g(alpha) = r``: a start and bracket from the table of ``g``,
        then safeguarded Newton (bisection when a step leaves the bracket)."""
        coeffs, warp = self._radial_coeffs(), self._radial_warp()
        a_max = grid[-1]
        alpha = np.interp(r, g_grid, grid)
        # the grid is uniform in alpha: the cell of the interpolated start brackets the root
        # (g increases on it), one cell more on each side against rounding
        with np.errstate(invalid="ignore"):
            j = np.clip(np.nan_to_num(alpha * ((len(grid) - 1) / a_max)), 0, len(grid) - 1)
        j = j.astype(np.intp)
        lo = grid[np.maximum(j - 1, 0)]
        hi = grid[np.minimum(j + 2, len(grid) - 1)]
        beyond = r > g_grid[-1]
        lo = np.where(beyond, a_max, lo)
        active = np.flatnonzero(np.isfinite(r) & ~beyond)
        for _ in range(60):
            if len(active) == 0:
                break
            a = alpha[active]
            g, dg = radial_g_horner(a, coeffs, warp, derivative=True)
            f = g - r[active]
            lo_a = np.where(f < 0, a, lo[active])
            hi_a = np.where(f > 0, a, hi[active])
            with np.errstate(invalid="ignore", divide="ignore"):
                step = a - f / dg
            bisect = ~np.isfinite(step) | (step < lo_a) | (step > hi_a)
            new = np.where(bisect, 0.5 * (lo_a + hi_a), step)
            moving = (np.abs(new - a) > 4e-16 * np.maximum(a, 1e-300)) & (np.abs(f) > 1e-16)
            alpha[active] = np.where(np.abs(f) > 0, new, a)
            lo[active], hi[active] = lo_a, hi_a
            active = active[moving]
        return alpha

    def _alpha_of_radius(self, r: np.ndarray) -> tuple[np.ndarray, float]:
        """Incidence ``alpha`` (N,) with ``g(alpha) = r`` (radial mapping) and ``g(max_alpha)``.

        The cubic Hermite table of the inverse (:meth:`_g_tables`) and one Newton
        step (:func:`radial_g_horner`); the few points where that step is not
        clearly final (near the fold of ``g``, where the inverse is steep) are
        solved by :meth:`_alpha_bracketed`. ``r`` beyond the table: ``max_alpha``.
        """
        tables = self._g_tables()
        coeffs, warp = self._radial_coeffs(), self._radial_warp()
        n_cells = len(tables["cells"][0])
        with np.errstate(invalid="ignore"):
            x = r * tables["inv_h"]
            past = ~(x <= n_cells)  # beyond the Hermite table (or NaN): the bracketed solve
            x = np.clip(np.nan_to_num(x), 0.0, float(n_cells))
        j = np.minimum(x.astype(np.intp), n_cells - 1)
        t = x - j
        c0, c1, c2, c3 = (c.take(j) for c in tables["cells"])
        alpha = c0 + t * (c1 + t * (c2 + t * c3))
        g, dg = radial_g_horner(alpha, coeffs, warp, derivative=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            step = (g - r) / dg
            alpha = alpha - step
            doubt = past | ~(np.abs(step) < 1e-7) | ~(dg > 1e-3)
        g_max = float(tables["g_grid"][-1])
        doubt &= np.isfinite(r) & (r <= g_max)
        if doubt.any():
            alpha[doubt] = self._alpha_bracketed(r[doubt], tables["grid"], tables["g_grid"])
        return alpha, g_max

    def _unproject_radial_fast(self, uv_px: np.ndarray) -> np.ndarray | None:
        """:meth:`unproject` of the radial mapping on the tables; None if they do not apply."""
        uv = check_uv(uv_px)
        if self.correction is not None:
            table = self.distortion_table()
            if table is None:
                return None
            dist = table.predict(uv)
        elif self.brown:
            dist = brown_distortion(uv - self.principal_point_px, self.brown, self.brown_scale_px)
        else:
            dist = np.zeros_like(uv)
        inv_c = 1.0 / self.c
        with np.errstate(invalid="ignore", over="ignore"):
            mx = (uv[:, 0] - self.xp - dist[:, 0]) * inv_c
            my = (uv[:, 1] - self.yp - dist[:, 1]) * inv_c
            r = np.hypot(mx, my)
        alpha, g_max = self._alpha_of_radius(r)
        with np.errstate(invalid="ignore", divide="ignore"):
            scale = np.where(r > 0, np.sin(alpha) / r, 0.0)
        rays = np.empty((len(uv), 3))
        rays[:, 0] = scale * mx
        rays[:, 1] = scale * my
        rays[:, 2] = np.cos(alpha)
        with np.errstate(invalid="ignore"):
            rays[~(r <= g_max * (1 + 1e-12))] = np.nan
        return rays

    def _learned(self, uv: np.ndarray, exact: bool = False) -> np.ndarray:
        """The learned correction at raw pixels (N, 2): the table, or ``exact`` the model."""
        if exact:
            return self.correction.predict(uv)
        return self.correction_table().predict(uv)

    def valid_alpha_rad(self) -> float:
        """Largest incidence angle (rad) :meth:`project` answers for by default.

        The smaller of the lens's one-to-one field (:meth:`max_alpha_rad` for the
        radial mapping; pi for the sphere mapping, whose Brown fold
        :meth:`project` handles) and the observed field plus the margin
        (``observed_alpha_rad + VALID_MARGIN_RAD``, when known).
        """
        limit = math.pi if self.radial is None else self.max_alpha_rad()
        if self.observed_alpha_rad is not None:
            limit = min(limit, self.observed_alpha_rad + VALID_MARGIN_RAD)
        return float(limit)

    def region_alpha_rad(self, azimuth_rad: np.ndarray) -> np.ndarray:
        """Largest valid incidence angle (rad) at ray azimuths (N,), shape (N,).

        :attr:`valid_region_alpha_rad` linearly interpolated (periodically) at
        ``azimuth_rad`` (``atan2(y, x)`` of camera-frame rays, rad), capped
        at :meth:`valid_alpha_rad`; without a region, :meth:`valid_alpha_rad`
        everywhere. NaN azimuths give NaN.
        """
        az = np.asarray(azimuth_rad, float).reshape(-1)
        limit = self.valid_alpha_rad()
        if self.valid_region_alpha_rad is None:
            return np.where(np.isfinite(az), limit, np.nan)
        table = np.asarray(self.valid_region_alpha_rad, float)
        n = len(table)
        with np.errstate(invalid="ignore"):
            x = np.mod(az, 2 * math.pi) * (n / (2 * math.pi))
            i = np.clip(np.floor(x), 0, n - 1)
            f = x - i
            i = np.nan_to_num(i).astype(int)
            out = (1 - f) * table[i] + f * table[(i + 1) % n]
        return np.minimum(out, limit)

    def valid_mask(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) whose ray lies in the valid field, (N,) bool.

        ``incidence <= valid_alpha_rad()``, and with a valid region
        (:attr:`valid_region_alpha_rad`) ``incidence <=
        region_alpha_rad(azimuth)`` (and the point is finite and not the
        perspective centre): the rays :meth:`project` answers for.
        """
        p = check_points_cam(points_cam)
        with np.errstate(invalid="ignore"):
            alpha = np.arctan2(np.hypot(p[:, 0], p[:, 1]), p[:, 2])
            ok = np.isfinite(p).all(axis=1) & np.any(p != 0, axis=1)
            ok &= alpha <= self.valid_alpha_rad()
            if self.valid_region_alpha_rad is not None:
                ok &= alpha <= self.region_alpha_rad(np.arctan2(p[:, 1], p[:, 0]))
            return ok

    def inside_image(self, uv_px: np.ndarray) -> np.ndarray:
        """Raw pixels (N, 2) in ``[-0.5, width - 0.5] x [-0.5, height - 0.5]``, (N,) bool.

        ``(0, 0)`` is the centre of the top-left pixel, so these are the sensor's
        outer edges; NaN pixels are outside.
        """
        uv = check_uv(uv_px)
        with np.errstate(invalid="ignore"):
            return (
                (uv[:, 0] >= -0.5)
                & (uv[:, 0] <= self.width - 0.5)
                & (uv[:, 1] >= -0.5)
                & (uv[:, 1] <= self.height - 0.5)
            )

    def valid_pixel_mask(self, uv_px: np.ndarray, exact: bool = False) -> np.ndarray:
        """Raw pixels (N, 2) inside the image whose ray lies in the valid field, (N,) bool.

        In ``[-0.5, width - 0.5] x [-0.5, height - 0.5]`` (:meth:`inside_image`) and
        :meth:`unproject` gives a ray within :meth:`valid_alpha_rad` (the front half
        for the sphere mapping without a fold, :meth:`pixel_hemisphere` with one).
        """
        uv = check_uv(uv_px)
        inside = self.inside_image(uv)
        out = np.zeros(len(uv), bool)
        if inside.any():
            sub = uv[inside]
            hemi = self.pixel_hemisphere(sub, exact=exact)
            out[inside] = self.valid_mask(self.unproject(sub, hemisphere=hemi, exact=exact))
        return out

    def distortion_px(self, uv_px: np.ndarray, exact: bool = False) -> np.ndarray:
        """Total measurement correction at raw pixels (N, 2): learned + Brown, px.

        As in the adjustment: the learned field at the raw pixel, then Brown
        at the pixel it corrected, ``uv - pp - ideal = learned(uv) + brown(uv -
        learned(uv) - pp)``. The learned field from :meth:`correction_table`,
        or with ``exact`` from the correction itself.
        """
        uv = check_uv(uv_px)
        if not exact and self.correction is not None:
            table = self.distortion_table()
            if table is not None:
                return table.predict(uv)
        delta = np.zeros_like(uv)
        if self.correction is not None:
            delta += self._learned(uv, exact)
        if self.brown:
            delta += brown_distortion(
                uv - delta - self.principal_point_px, self.brown, self.brown_scale_px
            )
        return delta

    def ideal_from_pixels(self, uv_px: np.ndarray, exact: bool = False) -> np.ndarray:
        """Corrected image coordinates relative to the principal point, (N, 2) px.

        ``exact``: the learned correction itself rather than its table.
        """
        uv = check_uv(uv_px)
        return uv - self.principal_point_px - self.distortion_px(uv, exact)

    def _brown_input(self, uv: np.ndarray, exact: bool = False) -> np.ndarray:
        """Where the Brown terms act: the pixel less its learned correction, less the
        principal point (N, 2) px."""
        corrected = uv if self.correction is None else uv - self._learned(uv, exact)
        return corrected - self.principal_point_px

    def measurement_metric(self, uv_px: np.ndarray, exact: bool = False) -> np.ndarray | None:
        """The adjustment's residual metric at raw pixels: ``M = A^-1`` (N, 2, 2) or None.

        The adjustment weighs ``M (ideal_from_pixels(uv) - ideal(P))`` (px), with ``A``
        the decentering and affinity part of ``I - d brown / d uv`` at the measurement
        (:func:`decentering_affinity_matrix`, :func:`sphere_residual`): raw pixels to first
        order with the radial mapping. A frozen calibration's factors and resections
        use the same ``M``, constant per observation, so that the calibration's
        ``sigma_px`` means the same there.

        Parameters
        ----------
        uv_px : ndarray, shape (N, 2)
            Raw measured pixels.
        exact : bool
            The learned correction itself rather than its table.

        Returns
        -------
        ndarray, shape (N, 2, 2), or None
            None when the calibration has no ``p1, p2, a1, a2`` (``M = I``); NaN where
            ``A`` is singular.
        """
        uv = check_uv(uv_px)
        if not _has_pa(self.brown):
            return None
        A = decentering_affinity_matrix(
            self._brown_input(uv, exact), self.brown, self.brown_scale_px
        )
        det = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
        det = np.where(np.abs(det) > 1e-12, det, np.nan)  # a fold of the affinity: no metric
        adj = np.stack([A[:, 1, 1], -A[:, 0, 1], -A[:, 1, 0], A[:, 0, 0]], 1).reshape(-1, 2, 2)
        return adj / det[:, None, None]

    def pixel_residuals(
        self, uv_px: np.ndarray, ideal_residuals_px: np.ndarray, exact: bool = False
    ) -> np.ndarray:
        """Residuals in raw pixels from the adjustment's residuals (:func:`sphere_residual`).

        The adjustment's residual is ``A^-1 e`` with ``e = ideal_from_pixels(uv) -
        ideal(P)`` in corrected coordinates and ``A`` the decentering and affinity
        part of ``I - d brown / d uv`` (:func:`decentering_affinity_matrix`);
        OpenCV-style statistics need ``uv - project(P)``. To first order ``uv -
        project(P) = (I - d brown / d uv)^-1 e`` (the learned field's gradient, well
        below 1 px/px, is neglected), which is also what a strongly compressing Brown
        model at the rim amplifies; with the radial mapping it is the adjustment's own.

        Parameters
        ----------
        uv_px : ndarray, shape (N, 2)
            Raw measurements.
        ideal_residuals_px : ndarray, shape (N, 2)
            The adjustment's residuals (px).

        Returns
        -------
        residuals_px : ndarray, shape (N, 2)
        """
        uv = check_uv(uv_px)
        e = check_uv(ideal_residuals_px, "ideal_residuals_px")
        if not self.brown:
            return e.copy()
        xbar = self._brown_input(uv, exact)
        A = decentering_affinity_matrix(xbar, self.brown, self.brown_scale_px)
        e = np.einsum("nij,nj->ni", A, e)  # back to corrected coordinates
        _, J, _ = brown_distortion(xbar, self.brown, self.brown_scale_px, jacobians=True)
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
        out = ideal_projection(
            p, self._radial_coeffs(), jacobians=jacobians, warp=self._radial_warp()
        )
        if not jacobians:
            return self.c * out
        return self.c * out[0], self.c * out[1]

    def project(
        self,
        points_cam: np.ndarray,
        max_iterations: int = 50,
        tol_px: float = 1e-9,
        exact: bool = False,
        valid_only: bool = True,
    ) -> np.ndarray:
        """Project camera-frame points to raw pixels.

        The pixel returned satisfies the adjustment's residual
        (:func:`sphere_residual`): ``ideal_from_pixels(uv) = ideal_from_points(P)``.
        With the sphere mapping and Brown terms that equation has two
        solutions for a lens seeing past 90 deg: the Brown map ``w -> w - pp -
        brown(w - pp)`` (``w`` the corrected pixel) rises to a fold (the
        image of 90 deg) and falls beyond it, where the image radius keeps
        growing while the ideal radius ``c sin(alpha)`` shrinks. A ray in
        front of the camera (``z >= 0``) gets the solution inside the fold
        (where that map preserves orientation, :meth:`pixel_hemisphere`
        ``+1``), a ray behind it (``z < 0``) the one beyond the fold
        (``-1``). Where the map does not fold along the ray's azimuth (no
        Brown terms, or terms that do not compress the rim), the sphere's own
        two-to-one holds: a ray behind the camera shares the pixel of its
        mirror image in front (``unproject`` then needs ``hemisphere=-1``).

        Parameters
        ----------
        points_cam : ndarray, shape (N, 3)
            Points in the camera frame (x right, y down, z forward); any
            direction, including behind the camera.
        max_iterations, tol_px
            Inversion of the measurement corrections: Newton steps on the
            Brown part (its exact Jacobian; where they do not reach the
            ray's side of the fold, a bracketed solve along the ray's
            azimuth and Newton steps that stay on that side), then the
            learned correction as a fixed point ``uv = w + learned(uv)``,
            which converges when the learned correction changes by less than
            1 px per px (Lipschitz constant < 1).
        exact : bool
            False (default): the fixed point uses the tabulated correction
            (:meth:`correction_table`, within 0.01 px RMS of the correction);
            True: the correction itself (a kNN search per point and iteration).
        valid_only : bool
            True (default): NaN for rays past :meth:`valid_alpha_rad` (the
            observed field plus :data:`VALID_MARGIN_RAD`, and the radial
            mapping's one-to-one field), which the model would otherwise fold
            back into the image, and, when the camera holds a valid region
            (:attr:`valid_region_alpha_rad`, by request:
            :func:`gtsam_sphere.analysis.uncertainty.with_valid_region`), for
            rays outside it. False: every ray the model has a pixel for.

        Returns
        -------
        uv_px : ndarray, shape (N, 2)
            NaN where the model has no pixel for the point:

            - with ``valid_only``, a ray beyond :meth:`valid_alpha_rad` or
              outside the valid region (:meth:`valid_mask` is ``False``);
            - the perspective centre itself (``|P| = 0``);
            - sphere mapping with Brown terms, a ray within
              :meth:`fold_profile` ``gap_deg`` of 90 deg on an azimuth where
              the fold's ideal radius stays below ``c``: the residual has no
              zero there (the 90 deg gap, see :meth:`fold_profile`);
            - a ray behind the camera that no pixel beyond the fold reaches:
              the Brown polynomial turns up again first, or, close to the
              antipode of the axis, where the back branch's image shrinks to
              a point, decentering moves that point aside. The antipode itself
              (``P[:2] = 0``, ``z < 0``) is NaN whenever the map folds: every
              azimuth meets there.
        """
        p = check_points_cam(points_cam)
        alpha = None
        with np.errstate(invalid="ignore", divide="ignore"):
            if not exact and self.radial is not None:
                ideal, alpha = self._ideal_radial_fast(p)
            else:
                ideal = self.c * ideal_projection(
                    p, self._radial_coeffs(), warp=self._radial_warp()
                )
        if valid_only:
            limit = self.valid_alpha_rad()
            if limit < math.pi:
                with np.errstate(invalid="ignore"):
                    if alpha is None:
                        alpha = np.arctan2(np.hypot(p[:, 0], p[:, 1]), p[:, 2])
                    ideal[~(alpha <= limit)] = np.nan
            if self.valid_region_alpha_rad is not None:
                ideal[~self.valid_mask(p)] = np.nan
        pp = self.principal_point_px
        if not exact and self.correction is not None:
            table = self.distortion_table()
            if table is not None:  # one fixed point on the whole tabulated correction
                return self._invert_table(pp + ideal, table, max_iterations, tol_px)
        uv = pp + ideal
        if not self.brown and self.correction is None:
            return uv
        # 1. the corrected pixel w: w - pp - brown(w - pp) = ideal, on the ray's side of the fold
        w = uv
        if self.brown:
            back = p[:, 2] < 0 if self.radial is None else np.zeros(len(p), bool)
            w = self._invert_brown(ideal, back, max_iterations, tol_px)
        if self.correction is None:
            return w
        # 2. the raw pixel: uv - learned(uv) = w (fixed point)
        if not exact:
            return self._invert_table(w, self.correction_table(), max_iterations, tol_px)
        uv = w.copy()
        for _ in range(max_iterations):
            new = w + self.correction.predict(np.nan_to_num(uv))
            step = new - uv
            uv = new
            if np.all(~np.isfinite(step) | (np.abs(step) < tol_px)):
                break
        return uv

    @staticmethod
    def _invert_table(
        w: np.ndarray, table: CorrectionTable, max_iterations: int, tol_px: float
    ) -> np.ndarray:
        """Raw pixels ``uv`` (N, 2) with ``uv - table(uv) = w`` (:meth:`CorrectionTable.invert`)."""
        return table.invert(w, max_iterations, tol_px)

    # -- inversion of the Brown map --------------------------------------------------------------

    def _brown_map(self, w: np.ndarray, ideal: np.ndarray):
        """Residual ``w - pp - brown(w - pp) - ideal`` (N, 2), Jacobian entries, determinant."""
        xbar = w - self.principal_point_px
        with np.errstate(invalid="ignore", over="ignore"):
            delta, J, _ = brown_distortion(xbar, self.brown, self.brown_scale_px, jacobians=True)
            f = xbar - delta - ideal
            a, b = 1.0 - J[:, 0, 0], -J[:, 0, 1]
            c, d = -J[:, 1, 0], 1.0 - J[:, 1, 1]
            det = a * d - b * c
        return f, (a, b, c, d), det

    @staticmethod
    def _newton_step(f: np.ndarray, A: tuple, det: np.ndarray) -> np.ndarray:
        """``A^-1 f`` for 2x2 matrices given by entries (NaN where singular)."""
        a, b, c, d = A
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            return (
                np.column_stack([d * f[:, 0] - b * f[:, 1], a * f[:, 1] - c * f[:, 0]])
                / det[:, None]
            )

    def _brown_tolerance(self, w: np.ndarray, ideal: np.ndarray) -> np.ndarray:
        """Accepted residual (px) of the Brown inversion: 1e-11 of the coordinates involved."""
        with np.errstate(invalid="ignore", over="ignore"):
            size = np.abs(w - self.principal_point_px).max(1) + np.abs(ideal).max(1)
        return 1e-11 * (size + self.c)

    def _fold_free_radius(self) -> float:
        """Radius ``u`` (units of ``brown_scale_px``) inside which the Brown map cannot fold.

        A lower bound over all azimuths of the first maximum of
        :func:`_brown_line_coeffs`' polynomial: ``inf`` when no azimuth folds
        within ``FOLD_HORIZON``.
        """
        g = {t: float(self.brown.get(t, 0.0)) for t in BROWN_TERMS}
        b1 = 1.0 - abs(g["a1"]) - 0.5 * abs(g["a2"])
        if b1 <= 0:
            return 0.0
        pos = [max(g["k1"], 0.0), max(g["k2"], 0.0), max(g["k3"], 0.0)]
        p = math.hypot(g["p1"], g["p2"])
        if p == 0 and not any(pos):
            return math.inf

        def slope(u: float) -> float:  # a lower bound of the derivative on every azimuth
            return b1 - 6 * p * u - 3 * pos[0] * u**2 - 5 * pos[1] * u**4 - 7 * pos[2] * u**6

        if slope(FOLD_HORIZON) > 0:
            return math.inf
        lo, hi = 0.0, 1.0
        while slope(hi) > 0:
            lo, hi = hi, 2 * hi
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if slope(mid) > 0 else (lo, mid)
        return lo

    def _invert_brown(
        self, ideal: np.ndarray, back: np.ndarray, max_iterations: int, tol_px: float
    ) -> np.ndarray:
        """Corrected pixels ``w`` (N, 2) with ``w - pp - brown(w - pp) = ideal``, NaN if none.

        ``back`` marks rays behind the camera: they get the solution beyond
        the fold where the map folds along their azimuth, else the front one.
        """
        pp = self.principal_point_px
        s = self.brown_scale_px
        n = len(ideal)
        u_free = self._fold_free_radius()
        # plain Newton from the ideal point: the front solution of almost every ray; a ray
        # behind the camera keeps it only if the map folds nowhere (its mirror's pixel)
        plain = np.flatnonzero(np.all(np.isfinite(ideal), axis=1) & (~back | math.isinf(u_free)))
        w0 = pp + ideal[plain]
        active = np.arange(len(plain))
        for _ in range(max_iterations):
            if len(active) == 0:
                break
            f, A, det = self._brown_map(w0[active], ideal[plain[active]])
            step = self._newton_step(f, A, det)
            w0[active] -= step
            active = active[np.any(np.abs(step) >= tol_px, axis=1)]
        f, _, det = self._brown_map(w0, ideal[plain])
        with np.errstate(invalid="ignore"):
            good = (
                (np.linalg.norm(f, axis=1) <= self._brown_tolerance(w0, ideal[plain]))
                & (det > 0)
                & (np.linalg.norm(w0 - pp, axis=1) < u_free * s)
            )
        w = np.full((n, 2), np.nan)
        w[plain[good]] = w0[good]
        done = np.zeros(n, bool)
        done[plain[good]] = True
        rest = np.flatnonzero(~done & np.all(np.isfinite(ideal), axis=1))
        if len(rest):
            w[rest] = self._invert_brown_along_azimuth(
                ideal[rest], back[rest], max_iterations, tol_px
            )
        return w

    def _invert_brown_along_azimuth(
        self, ideal: np.ndarray, back: np.ndarray, max_iterations: int, tol_px: float
    ) -> np.ndarray:
        """The robust inversion: a bracketed solve along the azimuth, then 2-D Newton on one side.

        Along the line of pixels in the direction of the ideal point the
        radial part of the map is a polynomial (:func:`_brown_line_coeffs`):
        increasing up to its first maximum ``u_f`` (the fold), decreasing to
        the next minimum ``u_m``. The front solution lies in ``[0, u_f]``, the
        back one in ``[u_f, u_m]``; Newton steps (with the decentering and
        affinity terms) then refine it without crossing the fold (the sign of
        the Jacobian determinant is kept).
        """
        pp = self.principal_point_px
        s = self.brown_scale_px
        radius = np.linalg.norm(ideal, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            d = np.where(radius[:, None] > 0, ideal / radius[:, None], np.array([1.0, 0.0]))
        coeffs = _brown_line_coeffs(self.brown, d)
        u_f, u_m = _turning_points(coeffs)
        beyond = back & np.isfinite(u_f)  # behind the camera and the map folds on this azimuth
        lo = np.where(beyond, u_f, 0.0)
        hi = np.where(beyond, u_m, u_f)
        sign = np.where(beyond, -1.0, 1.0)
        u = _solve_monotone(coeffs, radius / s, lo, hi, sign)
        # no 1-D solution: start at the fold; the 2-D fold differs slightly from the radial
        # maximum (decentering), so Newton may still find a solution on the right side
        u = np.where(np.isnan(u) & np.isfinite(u_f), u_f, u)
        # a start between the radial maximum and the 2-D fold: move it to the right side
        # (outwards for the back, inwards for the front)
        nudge = 1e-9 * np.maximum(u, 1e-300)
        for _ in range(24):  # up to 1e-2 u
            _, _, det = self._brown_map(pp + (s * u)[:, None] * d, ideal)
            wrong = np.isfinite(u) & (np.sign(det) != sign)
            if not wrong.any():
                break
            u = np.where(wrong, np.maximum(u - sign * nudge, 0.0), u)
            nudge = np.where(wrong, 2.0 * nudge, nudge)
        w = pp + (s * u)[:, None] * d
        w = self._newton_on_one_side(w, ideal, sign, max_iterations, tol_px)
        f, _, det = self._brown_map(w, ideal)
        with np.errstate(invalid="ignore"):
            ok = (
                (np.linalg.norm(f, axis=1) <= self._brown_tolerance(w, ideal))
                & (np.sign(det) == sign)
                & (coeffs[:, 1] > 0)
                & ~(beyond & (radius == 0))  # the antipode of the axis: every azimuth meets
            )
        w[~ok] = np.nan
        return w

    def _newton_on_one_side(
        self,
        w: np.ndarray,
        ideal: np.ndarray,
        sign: np.ndarray,
        max_iterations: int,
        tol_px: float,
    ) -> np.ndarray:
        """Newton on the Brown map from ``w``, halving steps that cross the fold or do not descend.

        ``sign`` (N,) is the side: the sign of the map's Jacobian determinant
        to keep. Stops where no halved step reduces the residual or the
        step falls below ``tol_px``.
        """
        w = w.copy()
        f, A, det = self._brown_map(w, ideal)
        active = np.flatnonzero(np.all(np.isfinite(w), axis=1))
        for _ in range(max_iterations + 10):
            if len(active) == 0:
                break
            sub_f = f[active]
            step = self._newton_step(sub_f, tuple(x[active] for x in A), det[active])
            norm_f = np.linalg.norm(sub_f, axis=1)
            lam = np.ones(len(active))
            accepted = np.zeros(len(active), bool)
            new_w = w[active].copy()
            for _ in range(40):
                todo = np.flatnonzero(~accepted & np.all(np.isfinite(step), axis=1))
                if len(todo) == 0:
                    break
                trial = w[active[todo]] - lam[todo, None] * step[todo]
                f_t, _, det_t = self._brown_map(trial, ideal[active[todo]])
                with np.errstate(invalid="ignore"):
                    ok = (np.sign(det_t) == sign[active[todo]]) & (
                        np.linalg.norm(f_t, axis=1) < norm_f[todo]
                    )
                accepted[todo[ok]] = True
                new_w[todo[ok]] = trial[ok]
                lam[todo[~ok]] *= 0.5
            moved = accepted & np.any(np.abs(new_w - w[active]) > tol_px, axis=1)
            w[active] = new_w
            if moved.any():
                idx = active[moved]
                f_new, A_new, det_new = self._brown_map(w[idx], ideal[idx])
                f[idx] = f_new
                det[idx] = det_new
                for x, y in zip(A, A_new):
                    x[idx] = y
            active = active[moved]
        return w

    def max_alpha_rad(self) -> float:
        """Largest incidence angle (rad) up to which the radial mapping increases (<= pi)."""
        coeffs = self._radial_coeffs()
        if coeffs is None:
            return math.pi / 2
        key = (tuple(coeffs), self._radial_warp())
        if self._max_alpha_key == key:
            return self._max_alpha
        grid = np.linspace(0.0, math.pi, 2049)
        _, dg, _ = radial_g(grid, coeffs, derivative=True, warp=self._radial_warp())
        bad = np.flatnonzero(dg <= 0)
        self._max_alpha = float(grid[bad[0] - 1]) if len(bad) else math.pi
        self._max_alpha_key = key
        return self._max_alpha

    def pixel_hemisphere(self, uv_px: np.ndarray, exact: bool = False) -> np.ndarray:
        """The half of the image sphere on which :meth:`project` puts each pixel's ray.

        Sphere mapping with Brown terms: ``-1`` (back, beyond the fold) where
        the Brown map ``w -> w - pp - brown(w - pp)`` of the corrected pixel
        ``w = uv - learned(uv)`` reverses orientation (negative Jacobian
        determinant), ``+1`` (front) elsewhere, NaN where that map has
        carried the pixel past the antipode of the axis (its ideal point
        points away from the pixel: no ray). ``unproject(uv,
        hemisphere=pixel_hemisphere(uv))`` then inverts ``project`` on both
        sides of the fold, as long as the Brown polynomial turns once inside
        the image (:meth:`fold_profile`). Without Brown terms, and for the
        radial mapping, all ``+1``.

        Parameters
        ----------
        uv_px : ndarray, shape (N, 2)
            Raw pixels.

        Returns
        -------
        hemisphere : ndarray, shape (N,)
            ``+1.0``, ``-1.0`` or NaN.
        """
        uv = check_uv(uv_px)
        h = np.ones(len(uv))
        if self.radial is not None or not self.brown:
            return h
        w = uv if self.correction is None else uv - self._learned(uv, exact)
        xbar = w - self.principal_point_px
        f, _, det = self._brown_map(w, np.zeros_like(w))
        with np.errstate(invalid="ignore", over="ignore"):
            h[det < 0] = -1.0
            h[np.sum(f * xbar, axis=1) < 0] = np.nan
        return h

    def fold_profile(self, azimuth_rad: np.ndarray) -> dict[str, np.ndarray]:
        """Where the sphere + Brown model folds at 90 deg, and the gap it leaves there.

        On the line of corrected pixels from the principal point in
        direction ``azimuth_rad`` the ideal radius rises to a maximum at the
        fold and falls beyond it (a lens seeing past 90 deg). The adjustment
        does not tie that maximum to ``c`` (the sphere's 90 deg): near 90 deg
        the ideal radius ``c sin(alpha)`` changes by ``c (1 - cos(d_alpha))``,
        about 0.005 px at 0.3 deg, far below the noise, so a fit leaves it a
        few 1e-5 of ``c`` off, differently on each azimuth (decentering
        ``p1, p2`` tilts it). Where it stays below ``c`` the rays within
        ``gap_deg`` of 90 deg (both sides) have no pixel (:meth:`project`
        gives NaN; the pixels on either side of the gap are a fraction of a
        pixel apart); where it exceeds ``c`` the ``no_ray_px`` of pixels
        around the fold have no ray (:meth:`unproject` gives NaN) and
        :meth:`project` jumps across them at 90 deg. Either way the rays of
        the pixels near the fold are off by up to about ``gap_deg`` (for
        ``ideal_max > 1``, ``degrees(arccos(1 / ideal_max))``), decaying
        away from 90 deg: the sphere mapping cannot place rays near 90 deg
        better than ``sqrt(2 |1 - ideal_max|)`` rad; the radial mapping has
        no such weakness. Evaluated on the radial component (exact for
        ``k1-k3``, ``a1``; ``p1, p2, a2`` also move the ideal point sideways,
        which changes its radius by the square of that shift).

        Parameters
        ----------
        azimuth_rad : ndarray, shape (N,)
            Directions in the image from the principal point (``atan2(dv, du)``).

        Returns
        -------
        profile : dict of ndarray, shape (N,)
            ``radius_px``: distance of the fold from the principal point in
            corrected pixels (``inf`` where the map does not fold);
            ``ideal_max``: the largest ideal radius on the azimuth, relative
            to ``c`` (``inf`` without a fold); ``gap_deg``: half-width of the
            band of rays around 90 deg without a pixel (0 where
            ``ideal_max >= 1``); ``no_ray_px``: width of the band of pixels
            without a ray across the fold (0 where ``ideal_max <= 1``).
        """
        phi = np.atleast_1d(np.asarray(azimuth_rad, float))
        n = len(phi)
        out = {
            "radius_px": np.full(n, np.inf),
            "ideal_max": np.full(n, np.inf),
            "gap_deg": np.zeros(n),
            "no_ray_px": np.zeros(n),
        }
        if self.radial is not None or not self.brown:
            return out
        s = self.brown_scale_px
        d = np.column_stack([np.cos(phi), np.sin(phi)])
        coeffs = _brown_line_coeffs(self.brown, d)
        u_f, u_m = _turning_points(coeffs)
        fold = np.isfinite(u_f)
        peak = np.full(n, np.inf)
        peak[fold] = _poly_eval(coeffs[fold], u_f[fold]) * s / self.c
        out["radius_px"] = s * u_f
        out["ideal_max"] = peak
        below = fold & (peak < 1)
        out["gap_deg"][below] = np.degrees(np.arccos(peak[below]))
        above = fold & (peak > 1)
        if above.any():
            target = np.full(above.sum(), self.c / s)
            c_above = coeffs[above]
            u_in = _solve_monotone(c_above, target, np.zeros(len(target)), u_f[above], 1.0)
            u_out = _solve_monotone(c_above, target, u_f[above], u_m[above], -1.0)
            out["no_ray_px"][above] = s * (u_out - u_in)
        return out

    def unproject(
        self, uv_px: np.ndarray, hemisphere: float | np.ndarray = 1.0, exact: bool = False
    ) -> np.ndarray:
        """Unit rays in the camera frame for raw pixels.

        Parameters
        ----------
        uv_px : ndarray, shape (N, 2)
        hemisphere : float or ndarray (N,)
            Sphere mapping only: ``+1`` front half of the image sphere
            (incidence below 90 deg), ``-1`` back half. The sphere's two
            halves share the image disc, so a pixel alone cannot tell them
            apart; see ``docs/conventions.md``. With Brown terms that fold
            the image (a lens past 180 deg), :meth:`pixel_hemisphere` tells
            which side of the fold a pixel is on. NaN gives a NaN ray. The
            radial mapping is one-to-one up to :meth:`max_alpha_rad` and
            ignores it.
        exact : bool
            The learned correction itself rather than its table
            (:meth:`correction_table`).

        Returns
        -------
        rays : ndarray, shape (N, 3)
            NaN where the corrected point falls outside the model's image
            (the sphere's disc of radius ``c``; beyond ``g(max_alpha)`` for
            the radial mapping). Pixels beyond the valid field still get
            their ray: :meth:`valid_pixel_mask` tells them apart.
        """
        if not exact and self.radial is not None:
            fast = self._unproject_radial_fast(uv_px)
            if fast is not None:
                return fast
        with np.errstate(invalid="ignore", over="ignore"):
            m = self.ideal_from_pixels(uv_px, exact) / self.c
        bad = ~np.isfinite(m).all(axis=1)
        m[bad] = np.nan
        coeffs = self._radial_coeffs()
        if coeffs is None:
            with np.errstate(invalid="ignore", over="ignore"):
                rho2 = (m**2).sum(1)
                # the rim (90 deg) rounds to rho2 = 1 + eps: clip inside the tolerance
                z = np.sqrt(np.clip(1.0 - rho2, 0.0, None)) * np.sign(np.asarray(hemisphere, float))
            rays = np.column_stack([m, z * np.ones(len(m))])
            with np.errstate(invalid="ignore"):
                rays[~(rho2 <= 1.0 + 1e-12) | np.isnan(rays[:, 2])] = np.nan
            return rays
        with np.errstate(over="ignore"):
            r = np.hypot(m[:, 0], m[:, 1])
        a_max = self.max_alpha_rad()
        warp = self._radial_warp()
        g_max = float(radial_g(np.array([a_max]), coeffs, warp=warp)[0])
        # start from a table of g (monotone up to a_max) and its bracket: Newton alone
        # can cycle where a strong warp bends g
        grid = np.linspace(0.0, a_max, 1025)
        g_grid = radial_g(grid, coeffs, warp=warp)
        j = np.clip(np.searchsorted(g_grid, r), 1, len(grid) - 1)
        lo, hi = grid[j - 1], grid[j]
        lo = np.where(r > g_grid[-1], a_max, lo)
        alpha = np.clip(np.interp(r, g_grid, grid), lo, hi)
        for _ in range(60):  # safeguarded Newton on g(alpha) = r
            g, dg, _ = radial_g(alpha, coeffs, derivative=True, warp=warp)
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
        if self.observed_alpha_rad is not None:
            d["observed_alpha_rad"] = self.observed_alpha_rad
        if self.valid_region_alpha_rad is not None:
            d["valid_region_alpha_rad"] = list(self.valid_region_alpha_rad)
        return d
