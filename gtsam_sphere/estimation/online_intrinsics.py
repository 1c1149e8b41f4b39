"""Intrinsics that adapt online: the calibration's intrinsics as a GTSAM variable.

A lens whose principal distance or principal point drifts (temperature, focus)
needs its intrinsics estimated along with the trajectory. This module puts the
calibration's intrinsics vector ``theta = [xp, yp, c, *radial, *brown]`` (px,
px, px, dimensionless; the layout of the calibration graph,
``docs/conventions.md``) into a user's graph as ``gtsam.Vector`` variables:

- :meth:`OnlineIntrinsics.prior_factor`: ``theta_0`` seeded with the
  calibration and its covariance (``statistics.intrinsics_covariance``, or one
  given) as a ``gtsam.PriorFactorVector``;
- :meth:`OnlineIntrinsics.drift_factor`: a random walk ``theta_{t+1} - theta_t
  ~ N(0, diag(sigma^2) dt)`` between consecutive intrinsics variables
  (``gtsam.BetweenFactorVector``); the sigmas say which parameters may drift and
  how fast (the others are held by a tight sigma);
- :meth:`OnlineIntrinsics.observation_factor`: a frame's pixel observations as
  one vectorised ``gtsam.CustomFactor``, the calibration graph's own
  :class:`~gtsam_sphere.estimation.graph.ObservationBlock` with its
  ``intrinsics_key`` (residual ``e = w - pp - brown(w - pp) - ideal(P)`` in px,
  ``w`` the measured pixel minus the frozen learned correction, the Brown terms
  and the mapping evaluated at the current ``theta``; analytic Jacobians for the
  ``world_from_cam`` pose, free landmarks and ``theta``; per-observation
  M-estimator).

All of it works in ``gtsam.ISAM2`` (hold ``isam.getLinearizationPoint()`` in a
variable while it lives, see :mod:`~gtsam_sphere.estimation.external`).
The learned kNN correction stays frozen: it is a function of the raw pixel and
its table (``camera.correction_table()``, as ``camera.project`` and the pixel
factors of :mod:`~gtsam_sphere.estimation.external` use it) is subtracted from
the measurements once, when a factor is built.
"""

from __future__ import annotations

import functools

import gtsam
import numpy as np

from ..core.camera import check_uv
from ..core.rays import camera_of
from .graph import NoiseOptions, ObservationBlock
from .rig_joint import camera_with_theta, theta_of, warp_of

__all__ = [
    "IntrinsicsTracker",
    "OnlineIntrinsics",
    "camera_pose_key",
    "intrinsics_key",
    "landmark_key",
]


def intrinsics_key(t: int) -> int:
    """GTSAM key ``i{t}`` of the intrinsics at time step ``t`` (the tracker's)."""
    return gtsam.symbol("i", t)


def landmark_key(j: int) -> int:
    """GTSAM key ``l{j}`` of map landmark ``j`` (the tracker's, with ``map_sigma_m``)."""
    return gtsam.symbol("l", j)


def camera_pose_key(t: int) -> int:
    """GTSAM key ``x{t}`` of the ``world_from_cam`` pose at time step ``t`` (the tracker's)."""
    return gtsam.symbol("x", t)


class OnlineIntrinsics:
    """The intrinsics of one calibrated camera as GTSAM variables (one per time step).

    Parameters
    ----------
    calibration_or_camera : Calibration or SphereCamera
    covariance : ndarray, shape (K, K), or None
        Prior covariance of ``theta`` (units of :attr:`names`, squared). None:
        the calibration's ``statistics["intrinsics_covariance"]`` (laid out as
        ``statistics["intrinsics_names"]``); a ``ValueError`` if absent.
    noise : NoiseOptions or None
        Pixel noise and M-estimator of the observations (default: sigma 1 px,
        Huber 2.45).

    Attributes
    ----------
    theta0 : ndarray, shape (K,)
        The calibration's intrinsics.
    names : list of str
        ``["xp_px", "yp_px", "c_px", *radial, *brown]``.
    covariance : ndarray, shape (K, K)
    """

    def __init__(self, calibration_or_camera, covariance=None, noise: NoiseOptions | None = None):
        self.camera = camera_of(calibration_or_camera)
        self.theta0, self.radial_names, self.brown_names = theta_of(self.camera)
        self.names = ["xp_px", "yp_px", "c_px", *(self.radial_names or ()), *self.brown_names]
        self.noise = noise or NoiseOptions()
        K = len(self.theta0)
        if covariance is None:
            stats = getattr(calibration_or_camera, "statistics", None) or {}
            cov, names = stats.get("intrinsics_covariance"), stats.get("intrinsics_names")
            if cov is None or names is None or not set(self.names) <= set(names):
                raise ValueError(
                    "no intrinsics covariance for "
                    f"{self.names} in the calibration's statistics: pass covariance="
                )
            idx = [list(names).index(n) for n in self.names]
            covariance = np.asarray(cov, float)[np.ix_(idx, idx)]
        self.covariance = np.asarray(covariance, float)
        if self.covariance.shape != (K, K):
            raise ValueError(f"covariance must be ({K}, {K}), got {self.covariance.shape}")

    def prior_factor(self, key: int, inflate: float = 1.0) -> gtsam.PriorFactorVector:
        """``theta`` at ``key`` ~ N(calibration, inflate^2 covariance)."""
        model = gtsam.noiseModel.Gaussian.Covariance(inflate**2 * self.covariance)
        return gtsam.PriorFactorVector(int(key), self.theta0, model)

    def drift_sigmas(self, per_step: dict[str, float], hold: float = 0.01) -> np.ndarray:
        """Random-walk sigmas (K,) per step (theta units).

        ``per_step[name]`` for the named parameters; the others get ``hold`` times
        their prior sigma (``sqrt(diag(covariance))``): held, not constrained (a far
        tighter hold, 1e-6 absolute, made iSAM2's elimination report an
        indeterminate system with free landmarks, measured).
        """
        unknown = set(per_step) - set(self.names)
        if unknown:
            raise KeyError(f"unknown intrinsics {sorted(unknown)}; names are {self.names}")
        held = float(hold) * np.sqrt(np.diag(self.covariance))
        return np.array([float(per_step.get(n, h)) for n, h in zip(self.names, held)])

    def drift_factor(self, key_from: int, key_to: int, sigmas: np.ndarray, dt: float = 1.0):
        """Random walk ``theta_to - theta_from ~ N(0, diag(sigmas^2) dt)`` (a BetweenFactorVector).

        Parameters
        ----------
        sigmas : ndarray, shape (K,)
            Per unit of ``dt`` (:meth:`drift_sigmas`), units of theta.
        dt : float
            Time (or steps) between the two variables.
        """
        s = np.asarray(sigmas, float) * np.sqrt(dt)
        model = gtsam.noiseModel.Diagonal.Sigmas(s)
        return gtsam.BetweenFactorVector(
            int(key_from), int(key_to), np.zeros(len(self.theta0)), model
        )

    def observation_factor(
        self,
        uv_px,
        pose_keys,
        intrinsics_key: int,
        point_keys=None,
        points_xyz=None,
    ) -> gtsam.CustomFactor:
        """The observations of one frame (or window) as one vectorised ``gtsam.CustomFactor``.

        Parameters
        ----------
        uv_px : array_like, shape (n, 2)
            Raw measured pixels.
        pose_keys : array_like of int, shape (n,) or scalar
            ``gtsam.Pose3`` ``world_from_cam`` keys (dataset units).
        intrinsics_key : int
            Key of the ``gtsam.Vector`` ``theta`` (K,) these observations share.
        point_keys : array_like of int, shape (n,), or None
            ``gtsam.Point3`` landmark keys (world frame); -1 (or None for all):
            a known point, taken from ``points_xyz``.
        points_xyz : ndarray, shape (n, 3), or None
            World coordinates of the known points (rows of free points ignored).

        Returns
        -------
        gtsam.CustomFactor
            Keys: landmarks, poses, ``intrinsics_key``; error ``2 n`` whitened
            pixels (observation ``k`` in rows ``2k, 2k+1``).
        """
        uv = check_uv(uv_px)
        n = len(uv)
        pk = np.asarray(pose_keys, np.int64).reshape(-1)
        pk = np.full(n, pk[0]) if pk.size == 1 else pk
        lk = np.full(n, -1, np.int64) if point_keys is None else np.asarray(point_keys, np.int64)
        if pk.shape != (n,) or lk.shape != (n,):
            raise ValueError(f"pose_keys and point_keys must have shape ({n},)")
        xyz = np.zeros((n, 3)) if points_xyz is None else np.asarray(points_xyz, float)
        if (lk < 0).any() and (points_xyz is None or xyz.shape != (n, 3)):
            raise ValueError(f"known points need points_xyz of shape ({n}, 3)")
        corrected = uv
        if self.camera.correction is not None:
            # the tabulated field, as camera.project and external's pixel factors use
            corrected = uv - self.camera.correction_table().predict(uv)
        poses = np.unique(pk)
        points = np.unique(lk[lk >= 0])
        point_local = np.where(lk >= 0, np.searchsorted(points, lk), -1)
        block = ObservationBlock(
            poses.tolist(),
            points.tolist(),
            np.searchsorted(poses, pk),
            point_local,
            xyz,
            corrected,
            self.brown_names,
            self.camera.brown_scale_px,
            self.noise,
            self.radial_names,
            intrinsics_key=int(intrinsics_key),
            radial_warp=warp_of(self.camera),
        )
        return block.factor()  # the factor holds the block (its callback's owner)

    def camera_at(self, theta: np.ndarray):
        """A copy of the camera with intrinsics ``theta`` (K,) (e.g. an estimate)."""
        return camera_with_theta(self.camera, np.asarray(theta, float))


class IntrinsicsTracker:
    """iSAM2 over a sequence of frames seeing a map, intrinsics as a random walk.

    Variables per frame ``t``: ``x{t}`` (``Pose3`` ``world_from_cam``) and ``i{t}``
    (``theta``, K). Frame 0 gets :meth:`OnlineIntrinsics.prior_factor` and a pose
    prior; later frames a random walk from ``i{t-1}`` and an odometry factor from
    ``x{t-1}`` (or nothing when no odometry is given). The map's landmarks are
    known points (``map_sigma_m=None``) or ``Point3`` variables ``l{j}`` with an
    isotropic prior of ``map_sigma_m`` at their map coordinates, added when first
    seen (an imprecise map, refined along the way).

    Parameters
    ----------
    online : OnlineIntrinsics
    drift_sigmas : ndarray, shape (K,)
        Random-walk sigmas per frame (:meth:`OnlineIntrinsics.drift_sigmas`).
    isam_params : gtsam.ISAM2Params or None
        Default: relinearise at 1e-3, every update.
    map_sigma_m : float or None
        Standard deviation of the map's coordinates (dataset units); None: exact.

    Attributes
    ----------
    estimates : list of ndarray (K,)
        ``theta`` of each frame right after its update (filtered).
    """

    def __init__(
        self, online: OnlineIntrinsics, drift_sigmas, isam_params=None, map_sigma_m=None
    ) -> None:
        self.online = online
        self.map_sigma_m = map_sigma_m
        self._landmarks: set[int] = set()
        self.sigmas = np.asarray(drift_sigmas, float)
        if isam_params is None:
            isam_params = gtsam.ISAM2Params()
            isam_params.setRelinearizeThreshold(1e-3)
            isam_params.relinearizeSkip = 1
        self.isam = gtsam.ISAM2(isam_params)
        # held for the tracker's life: CustomFactor callbacks then receive it uncopied
        self._theta = self.isam.getLinearizationPoint()
        self.t = 0
        self.estimates: list[np.ndarray] = []
        self._last_theta = online.theta0.copy()

    def add_frame(
        self,
        uv_px,
        points_xyz,
        pose_guess: gtsam.Pose3,
        pose_prior_noise=None,
        odometry: tuple[gtsam.Pose3, gtsam.noiseModel.Base] | None = None,
        landmark_ids=None,
    ) -> np.ndarray:
        """Add frame ``t`` (observations of known points) and return its ``theta`` estimate.

        Parameters
        ----------
        uv_px : ndarray, shape (n, 2)
            Raw pixels of the frame.
        points_xyz : ndarray, shape (n, 3)
            World coordinates of the observed points (a known map).
        pose_guess : gtsam.Pose3
            Initial ``world_from_cam``.
        pose_prior_noise : gtsam.noiseModel.Base or None
            Frame 0 only: prior on ``pose_guess`` (6-D, default 1 m / 1 rad: weak).
        odometry : (gtsam.Pose3, noise model) or None
            ``cam_{t-1}_from_cam_t`` and its noise (ignored for frame 0).
        landmark_ids : array_like of int, shape (n,), or None
            Map index of each observed point; required with ``map_sigma_m``.
        """
        t = self.t
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        xk, ik = camera_pose_key(t), intrinsics_key(t)
        values.insert(xk, pose_guess)
        values.insert(ik, self._last_theta)
        if t == 0:
            graph.add(self.online.prior_factor(ik))
            noise = pose_prior_noise or gtsam.noiseModel.Isotropic.Sigma(6, 1.0)
            graph.add(gtsam.PriorFactorPose3(xk, pose_guess, noise))
        else:
            graph.add(self.online.drift_factor(intrinsics_key(t - 1), ik, self.sigmas))
            if odometry is not None:
                rel, noise = odometry
                graph.add(gtsam.BetweenFactorPose3(camera_pose_key(t - 1), xk, rel, noise))
        keys = None
        if self.map_sigma_m is not None:
            if landmark_ids is None:
                raise ValueError("a tracker with map_sigma_m needs landmark_ids")
            ids = np.asarray(landmark_ids, np.int64)
            xyz = np.asarray(points_xyz, float)
            keys = np.array([landmark_key(int(j)) for j in ids], np.int64)
            prior = gtsam.noiseModel.Isotropic.Sigma(3, float(self.map_sigma_m))
            for k, p in zip(keys.tolist(), xyz):
                if k not in self._landmarks:
                    self._landmarks.add(k)
                    values.insert(k, p)
                    graph.add(gtsam.PriorFactorPoint3(k, p, prior))
        graph.add(self.online.observation_factor(uv_px, xk, ik, keys, points_xyz))
        self.isam.update(graph, values)
        theta = np.asarray(_estimate_of(self.isam, ik).atVector(ik), float)
        self._last_theta = theta
        self.estimates.append(theta)
        self.t += 1
        return theta

    def smoothed(self) -> np.ndarray:
        """``theta`` of every frame given all frames (T, K)."""
        est = self.isam.calculateEstimate()
        return np.array([est.atVector(intrinsics_key(t)) for t in range(self.t)])

    def pose(self, t: int) -> gtsam.Pose3:
        """Current estimate of frame ``t``'s ``world_from_cam``."""
        k = camera_pose_key(t)
        return _estimate_of(self.isam, k).atPose3(k)


@functools.cache
def _keyed_estimate() -> bool:
    """Whether this GTSAM has ``ISAM2.calculateEstimate(keys)`` (4.3a1, the Python 3.10
    build, has not). Probed once on an empty ISAM2: a failed call on a real one costs
    its whole Bayes tree printed into pybind11's message (0.37 s per call on 12 frames;
    ``test_isam2_tracks_with_an_imprecise_map`` took 221 s there against 3.8 s)."""
    try:
        gtsam.ISAM2().calculateEstimate([0])
    except TypeError:
        return False
    except RuntimeError:  # the key is not there: the call exists
        return True
    return True


def _estimate_of(isam: gtsam.ISAM2, key: int) -> gtsam.Values:
    """iSAM2's estimate of ``key`` alone (constant per frame), or the whole estimate where
    GTSAM lacks the keyed call (:func:`_keyed_estimate`)."""
    if _keyed_estimate():
        return isam.calculateEstimate([key])
    return isam.calculateEstimate()
