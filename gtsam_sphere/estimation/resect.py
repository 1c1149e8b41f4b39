"""Resection: the pose of one image with the calibration held fixed.

Used to test a calibration on images it was not estimated from (hold-out
evaluation) and to predict where a board's corners fall in an image (periphery
recovery in :mod:`.detect`).

Two steps:

1. P3P + RANSAC (:func:`.p3p.ransac_pose`) on the rays ``camera.unproject(uv)``.
   The ``radial`` mapping is one-to-one up to its largest incidence angle, so
   every pixel has one ray. The ``sphere`` mapping is two-to-one past 90 degrees
   (the front and back halves of the sphere share the image disc): the rays are
   first taken on the front half; when that explains too few observations the
   back half is tried as well, and after the pose is found every ray is put on
   the half its predicted point lies on.
2. A robust Levenberg-Marquardt on the 6 pose parameters minimising the pixel
   residual of the collinearity condition (``docs/conventions.md``)::

       e = M (ideal_from_pixels(uv) - ideal_from_points(R X + t))      (px)

   with ``M`` the calibration's residual metric
   (:meth:`.SphereCamera.measurement_metric`, the identity without decentering
   and affinity terms), the analytic Jacobian of
   :meth:`.SphereCamera.ideal_from_points`,
   Huber weights and a robust scale (``median(|e|) / sqrt(2 ln 2)``)
   re-estimated between stages, as in the bundle adjustment. The measurement
   corrections (Brown, kNN) are applied to the measurements once, so a learned
   correction costs one ``predict`` call.

The residuals returned are in raw pixels, ``uv - camera.project(R X + t)``,
OpenCV's reprojection error, so the RMS compares with ``cv2.solvePnP`` +
``cv2.projectPoints``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.camera import SphereCamera, check_uv
from ..core.least_squares import Damping, LMStatus, levenberg_marquardt, ridge_scaling
from ..core.lie import skew, so3_exp
from ..core.p3p import ransac_pose
from ..core.robust import Loss, robust_sigma_px, robust_weight

__all__ = ["ResectionResult", "resect"]


@dataclass
class ResectionResult:
    """Outcome of :func:`resect`.

    Attributes
    ----------
    R : ndarray, shape (3, 3)
        ``cam_from_world`` rotation (``p_cam = R @ p_world + t``); NaN on failure.
    t : ndarray, shape (3,)
        ``cam_from_world`` translation, world units; NaN on failure.
    residuals_px : ndarray, shape (N, 2)
        Raw-pixel reprojection errors ``uv - camera.project(R @ X + t)`` (measured
        minus predicted) of every input observation; NaN on failure.
    rms_px : float
        ``sqrt(mean(du^2 + dv^2))`` over the inliers (OpenCV's definition).
    rms_px_all : float
        The same over every observation with a finite residual, outliers included.
    inlier_mask : ndarray of bool, shape (N,)
        Observations within ``outlier_sigmas * sigma_px`` of the prediction (ideal
        pixels) after the final adjustment.
    sigma_px : float
        Robust scale of the ideal-pixel residuals used for the weights (px).
    incidence_deg : ndarray, shape (N,)
        Incidence angle of each target in the camera frame, degrees in [0, 180].
    status : str
        ``"ok"``, or why the resection failed (then ``success`` is False).
    success : bool
    iterations : int
        Levenberg-Marquardt iterations over all stages.
    """

    R: np.ndarray
    t: np.ndarray
    residuals_px: np.ndarray
    rms_px: float
    rms_px_all: float
    inlier_mask: np.ndarray
    sigma_px: float
    incidence_deg: np.ndarray
    status: str
    success: bool
    iterations: int = 0

    @property
    def n_inliers(self) -> int:
        """Number of inliers."""
        return int(self.inlier_mask.sum())


def _check_inputs(uv_px, xyz_world) -> tuple[np.ndarray, np.ndarray]:
    uv = np.asarray(uv_px, dtype=float)
    xyz = np.asarray(xyz_world, dtype=float)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"uv_px must have shape (N, 2), got {uv.shape}")
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz_world must have shape (N, 3), got {xyz.shape}")
    if len(uv) != len(xyz):
        raise ValueError(
            f"uv_px and xyz_world must have the same number of rows, got shapes "
            f"{uv.shape} and {xyz.shape}"
        )
    return check_uv(uv), xyz


#: damping of the pose adjustment: 10 tries per iteration, equal cost accepted
_POSE_DAMPING = Damping(initial=1e-4, max_tries=10, accept_equal=True, scaling=ridge_scaling)


def _adjust_pose(
    camera: SphereCamera,
    ideal_meas: np.ndarray,
    xyz: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    sigma_px: float | None,
    loss_threshold: float,
    min_sigma_px: float,
    max_iterations: int,
    max_stages: int = 6,
    metric: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Robust LM over the pose; returns ``R, t, sigma_px, iterations``.

    ``metric``: ``M`` (N, 2, 2) of :meth:`.SphereCamera.measurement_metric` or None.

    The perturbation acts on the camera-frame point, ``p <- Exp(w) p + v``, so
    ``d p / d w = -[p]x`` and ``d p / d v = I``; the pose follows as
    ``R <- Exp(w) R``, ``t <- Exp(w) t + v``.
    """
    usable = np.all(np.isfinite(ideal_meas), axis=1) & np.all(np.isfinite(xyz), axis=1)
    z = ideal_meas[usable]
    X = xyz[usable]
    M = None if metric is None else metric[usable]

    def residual(R_, t_):
        p = X @ R_.T + t_
        e = z - camera.ideal_from_points(p)
        return p, (e if M is None else np.einsum("nij,nj->ni", M, e))

    def cost_of(e, sigma):
        r = np.linalg.norm(e, axis=1) / sigma
        _, rho = robust_weight(np.where(np.isfinite(r), r, 1e6), Loss.HUBER, loss_threshold)
        return float(rho.sum())

    # the residuals of the last linearisation and of the last trial pose: the stage's
    # final residuals are the one of the two that belongs to the pose it ends at
    last: dict = {}

    def linearize(pose, sigma):
        R_, t_ = pose
        p = X @ R_.T + t_
        pred, J = camera.ideal_from_points(p, jacobians=True)
        e = z - pred
        if M is not None:
            e = np.einsum("nij,nj->ni", M, e)
            J = np.einsum("nij,njk->nik", M, J)
        last["linearized"] = e
        r = np.linalg.norm(e, axis=1) / sigma
        ok = np.isfinite(r) & np.all(np.isfinite(J), axis=(1, 2))
        w, _ = robust_weight(np.where(ok, r, 0.0), Loss.HUBER, loss_threshold)
        w = np.where(ok, w, 0.0)
        # de/dxi = -J @ [-[p]x | I]
        dp = np.concatenate([-skew(p), np.broadcast_to(np.eye(3), (len(p), 3, 3))], 2)
        A = -np.einsum("nij,njk->nik", np.where(ok[:, None, None], J, 0.0), dp)
        e0 = np.where(ok[:, None], e, 0.0)
        H = np.einsum("n,nki,nkj->ij", w, A, A)
        g = np.einsum("n,nki,nk->i", w, A, e0)
        return H, g

    def retract(pose, delta):
        rot = so3_exp(delta[:3])
        return rot @ pose[0], rot @ pose[1] + delta[3:]

    def small(c_old, c_new, delta):
        return (c_old - c_new) / max(c_old, 1e-300) < 1e-12 or np.linalg.norm(delta) < 1e-12

    _, e = residual(R, t)
    r0 = np.linalg.norm(e, axis=1)
    if sigma_px is None:
        sigma = robust_sigma_px(r0, min_sigma_px)
    else:
        sigma = float(sigma_px)
    iterations = 0
    for _stage in range(max_stages):

        def cost(pose, sigma=sigma):
            _, e_trial = residual(*pose)
            last["trial"] = e_trial
            return cost_of(e_trial, sigma)

        fit = levenberg_marquardt(
            (R, t),
            cost,
            lambda pose, sigma=sigma: linearize(pose, sigma),
            retract=retract,
            converged=small,
            damping=_POSE_DAMPING,
            max_iterations=max_iterations,
            cost0=cost_of(e, sigma),
        )
        R, t = fit.x
        iterations += fit.iterations
        if fit.status is LMStatus.STALLED:
            e = last["linearized"]
        elif fit.iterations:
            e = last["trial"]
        if sigma_px is not None:
            break
        r = np.linalg.norm(e, axis=1)
        new = robust_sigma_px(r, min_sigma_px)
        done = abs(new - sigma) <= 0.05 * sigma
        sigma = new
        if done:
            break
    u, _, vt = np.linalg.svd(R)
    R = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return R, t, sigma, iterations


def _failure(n: int, status: str) -> ResectionResult:
    return ResectionResult(
        R=np.full((3, 3), np.nan),
        t=np.full(3, np.nan),
        residuals_px=np.full((n, 2), np.nan),
        rms_px=float("nan"),
        rms_px_all=float("nan"),
        inlier_mask=np.zeros(n, bool),
        sigma_px=float("nan"),
        incidence_deg=np.full(n, np.nan),
        status=status,
        success=False,
    )


def resect(
    camera: SphereCamera,
    uv_px: np.ndarray,
    xyz_world: np.ndarray,
    rng: np.random.Generator | None = None,
    *,
    ransac_threshold_px: float = 4.0,
    ransac_iterations: int = 1000,
    sigma_px: float | None = None,
    loss_threshold: float = 2.45,
    outlier_sigmas: float = 5.0,
    min_sigma_px: float = 0.02,
    max_iterations: int = 50,
    initial_pose: tuple[np.ndarray, np.ndarray] | None = None,
) -> ResectionResult:
    """Pose of one image from its observations, with the calibration held fixed.

    Parameters
    ----------
    camera : SphereCamera
        The calibrated camera (any model: sphere, Brown, radial, learned correction).
    uv_px : ndarray, shape (N, 2)
        Measured pixels (OpenCV convention, ``(0, 0)`` the centre of the top-left pixel).
    xyz_world : ndarray, shape (N, 3)
        The observed targets' coordinates in the world frame (e.g. a board's frame),
        held fixed.
    rng : numpy.random.Generator, optional
        RANSAC's random samples (default ``np.random.default_rng(0)``).
    ransac_threshold_px : float
        RANSAC inlier threshold, in pixels, turned into an angle with ``camera.c``.
    ransac_iterations : int
        Upper bound on RANSAC's minimal samples (it stops earlier, adaptively).
    sigma_px : float, optional
        Noise of one image coordinate (px) for the Huber weights; ``None`` estimates it
        from the residuals (robust, ``median(|e|) / sqrt(2 ln 2)``, at least
        ``min_sigma_px``).
    loss_threshold : float
        Huber threshold in units of ``sigma_px``.
    outlier_sigmas : float
        An observation is an outlier when its ideal-pixel residual exceeds this many
        ``sigma_px``.
    min_sigma_px : float
        Floor of the estimated scale (px), so noise-free data keep their inliers.
    max_iterations : int
        Levenberg-Marquardt iterations per robust stage.
    initial_pose : (R (3, 3), t (3,)), optional
        ``cam_from_world`` start; skips RANSAC.

    Returns
    -------
    ResectionResult
        ``cam_from_world`` ``R, t``, raw-pixel residuals (N, 2), RMS, inlier mask and
        status. A failure (fewer than 4 usable observations, no consistent pose) is
        reported in ``status`` with NaN pose and residuals, never raised.

    Raises
    ------
    ValueError
        If ``uv_px`` is not (N, 2), ``xyz_world`` not (N, 3), or their N differ; the
        message names the shapes.
    """
    uv, xyz = _check_inputs(uv_px, xyz_world)
    n = len(uv)
    rng = np.random.default_rng(0) if rng is None else rng
    ideal_meas = camera.ideal_from_pixels(uv)
    metric = camera.measurement_metric(uv)
    usable = np.all(np.isfinite(uv), axis=1) & np.all(np.isfinite(xyz), axis=1)
    if usable.sum() < 4:
        return _failure(n, f"only {int(usable.sum())} usable observations (need at least 4)")

    if initial_pose is not None:
        R0 = np.asarray(initial_pose[0], float).reshape(3, 3)
        t0 = np.asarray(initial_pose[1], float).reshape(3)
    else:
        thr_rad = max(ransac_threshold_px / camera.c, 1e-5)
        hemispheres = [1.0] if camera.mapping == "radial" else [1.0, -1.0]
        best = None
        for hemi in hemispheres:
            rays = camera.unproject(uv, hemisphere=hemi)
            rays[~usable] = np.nan
            res = ransac_pose(rays, xyz, thr_rad, rng, max_iterations=ransac_iterations)
            if res.success and (best is None or res.n_inliers > best.n_inliers):
                best = res
            if best is not None and best.n_inliers >= 0.5 * usable.sum():
                break
        if best is None:
            return _failure(n, f"P3P + RANSAC found no pose ({res.reason})")
        R0, t0 = best.R, best.t
        if camera.mapping == "sphere":
            # every ray on the half of the sphere its predicted point lies on, then again
            z = (xyz @ R0.T + t0)[:, 2]
            rays = camera.unproject(uv, hemisphere=np.where(z < 0, -1.0, 1.0))
            rays[~usable] = np.nan
            again = ransac_pose(rays, xyz, thr_rad, rng, max_iterations=ransac_iterations)
            if again.success and again.n_inliers >= best.n_inliers:
                R0, t0 = again.R, again.t

    R, t, sigma, iters = _adjust_pose(
        camera,
        ideal_meas,
        xyz,
        R0,
        t0,
        sigma_px,
        loss_threshold,
        min_sigma_px,
        max_iterations,
        metric=metric,
    )
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return _failure(n, "the pose adjustment diverged")
    p = xyz @ R.T + t
    e_ideal = ideal_meas - camera.ideal_from_points(p)
    if metric is not None:
        e_ideal = np.einsum("nij,nj->ni", metric, e_ideal)
    r_ideal = np.linalg.norm(e_ideal, axis=1)
    inliers = usable & np.isfinite(r_ideal) & (r_ideal <= outlier_sigmas * sigma)
    residuals = np.full((n, 2), np.nan)
    # every usable corner gets its residual, past the calibrated field too (nothing dropped)
    residuals[usable] = uv[usable] - camera.project(p[usable], valid_only=False)
    r = np.linalg.norm(residuals, axis=1)
    finite = np.isfinite(r)
    inc = np.degrees(np.arctan2(np.hypot(p[:, 0], p[:, 1]), p[:, 2]))
    if inliers.sum() < 4:
        status = f"only {int(inliers.sum())} of {n} observations fit the pose"
        success = False
    else:
        status, success = "ok", True
    return ResectionResult(
        R=R,
        t=t,
        residuals_px=residuals,
        rms_px=float(np.sqrt(np.mean(r[inliers] ** 2))) if inliers.any() else float("nan"),
        rms_px_all=float(np.sqrt(np.mean(r[finite] ** 2))) if finite.any() else float("nan"),
        inlier_mask=inliers,
        sigma_px=float(sigma),
        incidence_deg=inc,
        status=status,
        success=success,
        iterations=iters,
    )
