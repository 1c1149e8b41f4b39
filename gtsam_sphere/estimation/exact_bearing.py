"""Exact bearings on ``Pose3``: GTSAM C++ factors with the pixel metric on the ray's tangent plane.

The isotropic ``gtsam.BearingFactor3D`` of
:func:`~gtsam_sphere.estimation.external.make_bearing_factors` gives every
observation one angular sigma, which is wrong wherever a fisheye's radial and
tangential scales differ. ``gtsam.GeneralSFMFactorSphericalCamera`` takes a
full 2x2 noise, but its variables are ``gtsam.SphericalCamera``, which do not
mix with ``Pose3`` odometry, priors or IMU factors. The builders here put each
observation into a stock C++ factor on ``Pose3`` + ``Point3`` with the
*exact* local pixel metric:

**Virtual camera per observation.** Let ``m`` be the measured unit ray (camera
frame, from :func:`~gtsam_sphere.core.rays.bearings`, measurement corrections
included) and ``B = [b1, b2]`` (3 x 2) an orthonormal basis of its tangent plane
with ``b1 x b2 = m``. The rotation ``R_v = [b1, b2, m]`` defines a virtual pinhole
camera looking along ``m``; a predicted camera-frame point ``P`` projects in it to
the gnomonic coordinates ``t = (b1 . P, b2 . P) / (m . P)`` (dimensionless,
``tan`` of the angles off ``m``), which is ``0`` on the measured ray and equal to
the tangent-plane displacement of the predicted ray to first order.

**Noise on the tangent plane.** The pixel path's residual (``M (ideal_from_pixels(uv) -
ideal_from_points(P))``, px, with ``M`` the calibration's residual metric,
:meth:`~gtsam_sphere.core.camera.SphereCamera.measurement_metric`, the identity without
decentering and affinity terms; see ``docs/conventions.md``) changes with ``t`` as ``d e
= -M J B dt`` with ``J`` (2 x 3, px per unit) the model's ``d ideal / d P`` at ``m``. A
pixel noise of square-root information ``S_px`` (2 x 2, 1/px) is therefore ``A = S_px M
J B`` (2 x 2, 1/rad) on ``t``. Its QR factorisation ``A = Q U`` (``U`` upper triangular,
positive diagonal) gives ``|A t| = |U t|``, so ``U`` becomes the virtual camera's
calibration ``gtsam.Cal3_S2(fx=U00, fy=U11, s=U01, u0=0, v0=0)``, the measurement is
``(0, 0)`` and the noise model is ``gtsam.noiseModel.Unit`` (or ``Robust`` around it:
the M-estimator then acts on the same whitened norm, in sigmas, as on the pixel path).
The factor is ``gtsam.GenericProjectionFactorCal3_S2`` with ``body_P_sensor =
body_from_cam * Pose3(R_v, 0)``: the pose variable is ``world_from_body``
(``world_from_cam`` for a single camera, ``body = cam``), so the rig case is the same
factor with a fixed ``body_from_cam`` per camera.

Exact means: the whitened error equals the pixel path's whitened error to first
order at the measured ray (equal information matrices there, tested), and its
Jacobians are GTSAM's own analytic ones. Second-order differences (gnomonic
``tan`` versus the model's own mapping of the residual, the metric taken at the
measured instead of the predicted ray) are far below the noise for residuals of
a few pixels. A point more than 90 degrees off its measured ray (a gross
outlier) is behind the virtual camera: the factor returns GTSAM's cheirality
error ``2 fx`` with zero Jacobians (``throwCheirality=False``).

The same virtual cameras give a landmark-free variant:
:func:`exact_bearing_smart_factor` (``gtsam.SmartProjectionRigFactorPinholePoseCal3_S2``,
one virtual camera per observation in its ``CameraSet``; smart factors need an
isotropic noise, which the whitened form provides).

Pixel noise convention: by default the noise is that of the pixel path's
residual (``M`` times the ideal coordinates), as on the pixel path
(:class:`~gtsam_sphere.estimation.external.ProjectionBlocks`), so that both
paths weight alike. With ``raw_pixels=True`` it is the noise of the raw
measured pixels, carried through the measurement corrections' Jacobian ``D = d
ideal / d uv`` (central differences of ``camera.ideal_from_pixels``, 0.25 px
steps): ``S_ideal = S_px D^-1``. ``D`` differs from the identity by the Brown
terms' and the learned field's gradients (a few percent at a fisheye's rim).
"""

from __future__ import annotations

import gtsam
import numpy as np

from ..core.camera import check_uv
from ..core.rays import bearings, camera_of
from .engine import check_keys

__all__ = [
    "ExactBearings",
    "exact_bearing_factors",
    "exact_bearing_smart_factor",
    "rig_exact_bearing_factors",
    "tangent_sqrt_information",
]


def _pixel_sqrt_information(pixel_noise, n: int) -> tuple[np.ndarray, object]:
    """Square-root information (n, 2, 2) (1/px) and the M-estimator (or None) of a pixel noise.

    ``pixel_noise``: a standard deviation per axis (px), a covariance (2, 2) or
    (n, 2, 2) (px^2), or a 2-D ``gtsam.noiseModel`` in pixels (Gaussian, or
    ``Robust`` around one: its M-estimator is returned).
    """
    mest = None
    if isinstance(pixel_noise, gtsam.noiseModel.Base):
        base = pixel_noise
        if isinstance(base, gtsam.noiseModel.Robust):
            base, mest = base.noise(), base.robust()
        if base.dim() != 2 or not isinstance(base, gtsam.noiseModel.Gaussian):
            raise ValueError("the pixel noise model must be a 2-D Gaussian (optionally Robust)")
        S = np.asarray(base.Whiten(np.eye(2)), float)
        return np.broadcast_to(S, (n, 2, 2)), mest
    arr = np.asarray(pixel_noise, float)
    if arr.ndim == 0:
        if not arr > 0:
            raise ValueError(f"sigma_px must be positive, got {float(arr)}")
        return np.broadcast_to(np.eye(2) / float(arr), (n, 2, 2)), None
    if arr.shape == (2, 2):
        arr = np.broadcast_to(arr, (n, 2, 2))
    if arr.shape != (n, 2, 2):
        raise ValueError(f"pixel covariance must have shape (2, 2) or ({n}, 2, 2), got {arr.shape}")
    # cov = L L^T  ->  information = L^-T L^-1: S = L^-1 whitens (|S e|^2 = e^T cov^-1 e)
    L = np.linalg.cholesky(arr)
    return np.linalg.inv(L), None


def _ray_bases(rays: np.ndarray) -> np.ndarray:
    """Rotations (n, 3, 3) ``[b1, b2, m]`` with ``b1 x b2 = m`` for unit rays ``m`` (n, 3)."""
    axis = np.eye(3)[np.argmin(np.abs(rays), axis=1)]
    b1 = np.cross(rays, axis)
    b1 /= np.linalg.norm(b1, axis=1, keepdims=True)
    b2 = np.cross(rays, b1)
    return np.stack([b1, b2, rays], axis=2)


def tangent_sqrt_information(
    calibration_or_camera, rays: np.ndarray, pixel_sqrt_info: np.ndarray, bases: np.ndarray
) -> np.ndarray:
    """Square-root information on the tangent plane of each ray: ``A = S_px J B``.

    Parameters
    ----------
    calibration_or_camera : Calibration or SphereCamera
    rays : ndarray, shape (n, 3)
        Unit rays, camera frame.
    pixel_sqrt_info : ndarray, shape (n, 2, 2)
        Square-root information of the ideal-pixel noise (1/px).
    bases : ndarray, shape (n, 3, 3)
        Columns ``b1, b2`` span each ray's tangent plane (the third is ignored).

    Returns
    -------
    A : ndarray, shape (n, 2, 2)
        1/rad, acting on tangent coordinates in the basis ``(b1, b2)``:
        ``|A t|`` is the whitened pixel residual of a ray rotated by ``t``.
    """
    camera = camera_of(calibration_or_camera)
    _, J = camera.ideal_from_points(rays, jacobians=True)  # (n, 2, 3), |ray| = 1
    return np.einsum("nab,nbc,ncd->nad", pixel_sqrt_info, J, bases[:, :, :2])


def _measurement_jacobian(camera, uv: np.ndarray, step_px: float = 0.25) -> np.ndarray:
    """``D = d ideal / d uv`` (n, 2, 2) at raw pixels, by central differences (px/px)."""
    D = np.empty((len(uv), 2, 2))
    for c in range(2):
        h = np.zeros(2)
        h[c] = step_px
        D[:, :, c] = (camera.ideal_from_pixels(uv + h) - camera.ideal_from_pixels(uv - h)) / (
            2 * step_px
        )
    return D


def _upper_triangular(A: np.ndarray) -> np.ndarray:
    """``U`` (n, 2, 2), upper triangular with positive diagonal, with ``U^T U = A^T A``."""
    _, U = np.linalg.qr(A)
    s = np.sign(np.diagonal(U, axis1=1, axis2=2))
    s[s == 0] = 1.0
    return U * s[:, :, None]


class ExactBearings:
    """Virtual cameras of pixel observations: what the exact-bearing factors are made of.

    Parameters
    ----------
    calibration_or_camera : Calibration or SphereCamera
    uv_px : array_like, shape (n, 2)
        Raw measured pixels (OpenCV convention).
    pixel_noise : float, ndarray (2, 2) or (n, 2, 2), or gtsam.noiseModel.Base
        Noise of the (ideal) pixel coordinates: sigma per axis (px), covariance
        (px^2), or a 2-D pixel noise model (Gaussian or ``Robust`` around one).
    hemisphere : float or array_like, shape (n,)
        Sphere mapping only, see :func:`~gtsam_sphere.core.rays.bearings`.
    body_from_cam : gtsam.Pose3, or list of them (n,), or None
        Fixed pose of the camera in the body whose ``world_from_body`` is the
        variable (None: identity, the variable is ``world_from_cam``); dataset units.
    raw_pixels : bool
        ``pixel_noise`` is the noise of the raw pixels, carried through the
        measurement corrections (default: of the ideal coordinates, as the pixel path).

    Attributes
    ----------
    rays : ndarray, shape (n, 3)
        Measured unit rays, camera frame.
    valid : ndarray of bool, shape (n,)
        Pixels with a ray and a finite, non-degenerate metric.
    sqrt_information : ndarray, shape (n, 2, 2)
        ``A = S_px M J B`` (1/rad; ``S_px D^-1 J B`` with ``raw_pixels``), tangent
        basis = the first two columns of ``cam_R_virtual``.
    calibration_upper : ndarray, shape (n, 2, 2)
        ``U`` with ``U^T U = A^T A``: the virtual cameras' ``Cal3_S2``.
    cam_R_virtual : ndarray, shape (n, 3, 3)
        Rotation camera <- virtual camera (columns ``b1, b2, ray``).
    mestimator : gtsam.noiseModel.mEstimator.Base or None
        From a ``Robust`` pixel noise model.
    """

    def __init__(
        self,
        calibration_or_camera,
        uv_px,
        pixel_noise=1.0,
        hemisphere=1.0,
        body_from_cam=None,
        raw_pixels: bool = False,
    ) -> None:
        uv = check_uv(uv_px)
        n = len(uv)
        S, self.mestimator = _pixel_sqrt_information(pixel_noise, n)
        camera = camera_of(calibration_or_camera)
        if raw_pixels:
            D = _measurement_jacobian(camera, uv)
            ok_d = np.isfinite(D).all((1, 2)) & (np.abs(np.linalg.det(D)) > 1e-12)
            D[~ok_d] = np.eye(2)
            S = S @ np.linalg.inv(D)
            S[~ok_d] = np.nan
        else:
            metric = camera.measurement_metric(uv)  # the pixel path's M
            if metric is not None:
                S = S @ metric
        self.rays = bearings(calibration_or_camera, uv, hemisphere)
        ok = np.isfinite(self.rays).all(1)
        safe = np.where(ok[:, None], self.rays, [0.0, 0.0, 1.0])
        self.cam_R_virtual = _ray_bases(safe)
        A = tangent_sqrt_information(calibration_or_camera, safe, S, self.cam_R_virtual)
        U = _upper_triangular(np.where(np.isfinite(A), A, 0.0))
        diag = np.diagonal(U, axis1=1, axis2=2)
        self.valid = ok & np.isfinite(A).all((1, 2)) & (diag > 1e-12 * np.abs(U).max()).all(1)
        self.sqrt_information = A
        self.calibration_upper = U
        if body_from_cam is None or isinstance(body_from_cam, gtsam.Pose3):
            self._body_from_cam = [body_from_cam or gtsam.Pose3()] * n
        else:
            self._body_from_cam = list(body_from_cam)
            if len(self._body_from_cam) != n:
                raise ValueError(f"body_from_cam must hold {n} poses, got {len(body_from_cam)}")

    def __len__(self) -> int:
        return len(self.rays)

    def _check(self, index) -> None:
        bad = np.flatnonzero(~self.valid[index])
        if len(bad):
            raise ValueError(
                f"{len(bad)} pixels have no usable ray or metric (first "
                f"{np.arange(len(self))[index][bad][:5].tolist()}); filter with .valid"
            )

    def calibration(self, k: int) -> gtsam.Cal3_S2:
        """The whitening calibration of observation ``k``: ``Cal3_S2(U00, U11, U01, 0, 0)``."""
        U = self.calibration_upper[k]
        return gtsam.Cal3_S2(float(U[0, 0]), float(U[1, 1]), float(U[0, 1]), 0.0, 0.0)

    def body_from_virtual(self, k: int) -> gtsam.Pose3:
        """``body_from_cam * Pose3(cam_R_virtual, 0)`` of observation ``k``."""
        return self._body_from_cam[k].compose(
            gtsam.Pose3(gtsam.Rot3(self.cam_R_virtual[k]), np.zeros(3))
        )

    def noise_model(self, robust=None) -> gtsam.noiseModel.Base:
        """Unit 2-D noise, inside ``Robust`` with ``robust`` (or the pixel model's M-estimator)."""
        unit = gtsam.noiseModel.Unit.Create(2)
        mest = robust if robust is not None else self.mestimator
        return unit if mest is None else gtsam.noiseModel.Robust.Create(mest, unit)

    def factors(self, pose_keys, point_keys, robust=None) -> list:
        """One ``gtsam.GenericProjectionFactorCal3_S2`` per observation.

        Parameters
        ----------
        pose_keys, point_keys : array_like of int, shape (n,) or scalar
            ``Pose3`` ``world_from_body`` (``world_from_cam`` without ``body_from_cam``)
            and ``Point3`` landmark (world frame) keys.
        robust : gtsam.noiseModel.mEstimator.Base or None
            M-estimator on the whitened norm (sigmas, as in pixel space);
            default: that of a ``Robust`` pixel noise model, else none.

        Returns
        -------
        list of gtsam.GenericProjectionFactorCal3_S2
            Error ``U t`` (whitened, dimensionless), measurement ``(0, 0)``.
        """
        n = len(self)
        pk = check_keys(pose_keys, n, "pose_keys")
        lk = check_keys(point_keys, n, "point_keys")
        self._check(slice(None))
        noise = self.noise_model(robust)
        zero = np.zeros(2)
        return [
            gtsam.GenericProjectionFactorCal3_S2(
                zero,
                noise,
                int(pk[k]),
                int(lk[k]),
                self.calibration(k),
                False,
                False,
                self.body_from_virtual(k),
            )
            for k in range(n)
        ]

    def smart_factor(
        self, pose_keys, params: gtsam.SmartProjectionParams | None = None
    ) -> gtsam.SmartProjectionRigFactorPinholePoseCal3_S2:
        """All observations as one landmark-free smart factor (one landmark's track).

        Parameters
        ----------
        pose_keys : array_like of int, shape (n,)
            ``Pose3`` ``world_from_body`` key of each observation (distinct).
        params : gtsam.SmartProjectionParams or None
            Default: GTSAM's, with the degeneracy mode ``ZERO_ON_DEGENERACY``.
        """
        n = len(self)
        pk = check_keys(pose_keys, n, "pose_keys")
        self._check(slice(None))
        rig = gtsam.CameraSetPinholePoseCal3_S2()
        for k in range(n):
            rig.push_back(gtsam.PinholePoseCal3_S2(self.body_from_virtual(k), self.calibration(k)))
        if params is None:
            params = gtsam.SmartProjectionParams()
            params.setDegeneracyMode(gtsam.DegeneracyMode.ZERO_ON_DEGENERACY)
        factor = gtsam.SmartProjectionRigFactorPinholePoseCal3_S2(
            gtsam.noiseModel.Unit.Create(2), rig, params
        )
        for k in range(n):
            factor.add(np.zeros(2), int(pk[k]), k)
        return factor


def exact_bearing_factors(
    calibration_or_camera,
    uv_px,
    pose_keys,
    point_keys,
    pixel_noise=1.0,
    robust=None,
    hemisphere=1.0,
    body_from_cam=None,
    raw_pixels: bool = False,
) -> list:
    """Exact-bearing C++ factors on ``Pose3`` + ``Point3`` for pixel observations.

    See the module docstring; ``ExactBearings(...).factors(pose_keys, point_keys, robust)``.

    Parameters
    ----------
    calibration_or_camera : Calibration or SphereCamera
    uv_px : array_like, shape (n, 2)
        Raw measured pixels; each must have a ray (``ExactBearings(...).valid``).
    pose_keys : array_like of int, shape (n,) or scalar
        ``gtsam.Pose3`` ``world_from_cam`` (or ``world_from_body`` with ``body_from_cam``).
    point_keys : array_like of int, shape (n,) or scalar
        ``gtsam.Point3`` landmarks, world frame.
    pixel_noise : float, ndarray (2, 2) or (n, 2, 2), or gtsam.noiseModel.Base
        Pixel noise (px, px^2 or a 2-D pixel model; a ``Robust`` model's
        M-estimator is kept).
    robust : gtsam.noiseModel.mEstimator.Base or None
        M-estimator on the whitened norm (threshold in sigmas).
    hemisphere : float or array_like, shape (n,)
    body_from_cam : gtsam.Pose3, list of (n,) gtsam.Pose3, or None
    raw_pixels : bool
        The noise is that of the raw pixels (see :class:`ExactBearings`).

    Returns
    -------
    list of gtsam.GenericProjectionFactorCal3_S2
    """
    eb = ExactBearings(
        calibration_or_camera, uv_px, pixel_noise, hemisphere, body_from_cam, raw_pixels
    )
    return eb.factors(pose_keys, point_keys, robust)


def exact_bearing_smart_factor(
    calibration_or_camera,
    uv_px,
    pose_keys,
    pixel_noise=1.0,
    hemisphere=1.0,
    body_from_cam=None,
    params: gtsam.SmartProjectionParams | None = None,
    raw_pixels: bool = False,
) -> gtsam.SmartProjectionRigFactorPinholePoseCal3_S2:
    """One landmark's track as a landmark-free smart factor on ``Pose3`` (:class:`ExactBearings`).

    ``uv_px`` (n, 2) are the observations of one landmark from the distinct
    ``Pose3`` variables ``pose_keys`` (n,). A ``Robust`` pixel model's
    M-estimator is ignored (smart factors take none).
    """
    eb = ExactBearings(
        calibration_or_camera, uv_px, pixel_noise, hemisphere, body_from_cam, raw_pixels
    )
    return eb.smart_factor(pose_keys, params)


def _pose_of(R_t) -> gtsam.Pose3:
    R, t = R_t
    return gtsam.Pose3(gtsam.Rot3(np.asarray(R, float)), np.asarray(t, float).reshape(3))


def rig_exact_bearing_factors(
    rig,
    camera_ids,
    uv_px,
    body_keys,
    point_keys,
    pixel_noise=1.0,
    robust=None,
    body_from_rig: gtsam.Pose3 | None = None,
    raw_pixels: bool = False,
) -> list:
    """Exact-bearing factors of a calibrated rig on ``world_from_body`` poses.

    Each observation's camera is held at its calibrated ``rig_from_cam`` (the
    inverse of the rig calibration's ``cam_from_rig``), so the factor's
    ``body_P_sensor`` is ``body_from_rig * rig_from_cam * Pose3(R_v, 0)``.

    Parameters
    ----------
    rig : RigCalibration (``calibration@2``) or any object with ``cameras``
        (id -> SphereCamera) and ``cam_from_rig`` (id -> ``(R (3, 3), t (3,))``,
        ``p_cam = R p_rig + t``, dataset units).
    camera_ids : sequence of str, length n
        Camera of each observation.
    uv_px : array_like, shape (n, 2)
        Raw measured pixels of that camera.
    body_keys : array_like of int, shape (n,) or scalar
        ``gtsam.Pose3`` ``world_from_body`` keys (one per rig frame).
    point_keys : array_like of int, shape (n,) or scalar
        ``gtsam.Point3`` landmark keys, world frame.
    pixel_noise : float, ndarray (2, 2) or (n, 2, 2), gtsam.noiseModel.Base, or dict
        As for :func:`exact_bearing_factors`; a dict gives one per camera id.
    robust : gtsam.noiseModel.mEstimator.Base or None
    body_from_rig : gtsam.Pose3 or None
        Pose of the rig frame in the body (e.g. an IMU); None: body = rig frame.
    raw_pixels : bool
        The noise is that of the raw pixels (see :class:`ExactBearings`).

    Returns
    -------
    list of gtsam.GenericProjectionFactorCal3_S2, in observation order.
    """
    uv = check_uv(uv_px)
    ids = np.asarray(list(camera_ids), dtype=object)
    if ids.shape != (len(uv),):
        raise ValueError(f"camera_ids must have length {len(uv)}, got {ids.shape}")
    bk = check_keys(body_keys, len(uv), "body_keys")
    lk = check_keys(point_keys, len(uv), "point_keys")
    b_from_r = body_from_rig or gtsam.Pose3()
    out: list = [None] * len(uv)
    for cid in dict.fromkeys(ids.tolist()):
        idx = np.flatnonzero(ids == cid)
        if cid not in rig.cameras:
            raise KeyError(f"camera {cid!r} is not in the rig ({list(rig.cameras)})")
        body_from_cam = b_from_r.compose(_pose_of(rig.cam_from_rig[cid]).inverse())
        noise = pixel_noise[cid] if isinstance(pixel_noise, dict) else pixel_noise
        if isinstance(noise, np.ndarray) and noise.ndim == 3:
            noise = noise[idx]
        eb = ExactBearings(
            rig.cameras[cid], uv[idx], noise, body_from_cam=body_from_cam, raw_pixels=raw_pixels
        )
        for k, f in zip(idx, eb.factors(bk[idx], lk[idx], robust)):
            out[k] = f
    return out
