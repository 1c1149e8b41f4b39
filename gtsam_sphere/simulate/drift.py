"""Seeded simulation of a fisheye whose principal distance drifts, and its online tracking.

World frame: a box room ``room_size_m = (length, width, height)`` centred on the
origin, ``Z`` up, metres, with point landmarks uniform over its six faces (a
known map). A ~190 degree radial fisheye (:func:`~gtsam_sphere.simulate.building.fisheye_camera`)
moves on a horizontal ellipse through the room (height 1.4 m above the floor,
looking along its path with a slow wobble); frame ``t`` is taken with principal
distance ``c_t = c_0 + drift_px * t / (T - 1)`` (px), every other intrinsic fixed.
Each frame observes up to ``obs_per_frame`` landmarks inside the image with
Gaussian pixel noise ``noise_px``; odometry between frames is the true relative
pose perturbed by ``odometry_sigma`` (rad, m).

:func:`track_drift` runs :class:`~gtsam_sphere.estimation.online_intrinsics.IntrinsicsTracker`
(iSAM2) over such a sequence, starting from the calibration at ``c_0`` with a
prior of ``prior_sigma_px`` on ``c``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import gtsam
import numpy as np

from ..core.camera import SphereCamera
from ..estimation.graph import NoiseOptions
from ..estimation.online_intrinsics import IntrinsicsTracker, OnlineIntrinsics
from .building import fisheye_camera


@dataclass
class DriftSequence:
    """A simulated sequence (see the module docstring).

    Attributes
    ----------
    camera : SphereCamera
        The calibration (``c = c_0``).
    c_true_px : ndarray, shape (T,)
        Principal distance of each frame.
    world_from_cam : list of gtsam.Pose3, length T
    points_world : ndarray, shape (P, 3)
    frames : list of (ndarray (n, 2) raw px, ndarray (n,) landmark index)
    odometry : list of gtsam.Pose3, length T - 1
        Measured ``cam_{t-1}_from_cam_t``.
    odometry_noise : gtsam.noiseModel.Base
    noise_px : float
    """

    camera: SphereCamera
    c_true_px: np.ndarray
    world_from_cam: list
    points_world: np.ndarray
    frames: list
    odometry: list
    odometry_noise: gtsam.noiseModel.Base
    noise_px: float


def _room_points(n: int, size: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``n`` points uniform over the faces of the box ``[-size/2, size/2]`` (area-weighted)."""
    L, W, H = size
    areas = np.array([W * H, W * H, L * H, L * H, L * W, L * W])
    face = rng.choice(6, size=n, p=areas / areas.sum())
    p = rng.uniform(-0.5, 0.5, size=(n, 3)) * size
    axis = face // 2
    p[np.arange(n), axis] = np.where(face % 2 == 0, -0.5, 0.5) * size[axis]
    return p


def _look(forward: np.ndarray, up: np.ndarray) -> np.ndarray:
    """``R_wc`` of a camera looking along ``forward`` (z) with ``-up`` as its y axis (down)."""
    z = forward / np.linalg.norm(forward)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def simulate_drift(
    n_frames: int = 120,
    drift_px: float = 3.0,
    obs_per_frame: int = 60,
    noise_px: float = 0.5,
    n_points: int = 400,
    room_size_m: tuple[float, float, float] = (6.0, 4.0, 3.0),
    odometry_sigma: tuple[float, float] = (0.005, 0.01),
    camera: SphereCamera | None = None,
    seed: int = 0,
) -> DriftSequence:
    """Simulate the sequence of the module docstring (seeded; all units px, m, rad)."""
    rng = np.random.default_rng(seed)
    camera = camera or fisheye_camera(190.0)
    size = np.asarray(room_size_m, float)
    points = _room_points(n_points, size, rng)
    s = np.linspace(0.0, 2 * np.pi, n_frames, endpoint=False)
    centre = np.column_stack(
        [0.3 * size[0] * np.cos(s), 0.3 * size[1] * np.sin(s), 1.4 - 0.5 * size[2] + 0 * s]
    )
    tangent = np.column_stack([-size[0] * np.sin(s), size[1] * np.cos(s), 0 * s])
    c_true = camera.c + drift_px * np.arange(n_frames) / max(n_frames - 1, 1)
    poses, frames = [], []
    for t in range(n_frames):
        wobble = 0.15 * np.array([np.sin(3 * s[t]), 0.5 * np.cos(2 * s[t]), 0.0])
        R = _look(tangent[t] + np.linalg.norm(tangent[t]) * wobble, np.array([0.0, 0.0, 1.0]))
        pose = gtsam.Pose3(gtsam.Rot3(R), centre[t])
        poses.append(pose)
        pc = (points - centre[t]) @ R
        cam_t = replace(camera, c=float(c_true[t]))
        uv = cam_t.project(pc)
        margin = 2.0
        ok = np.isfinite(uv).all(1) & (np.linalg.norm(pc, axis=1) > 0.3)
        ok &= (uv >= margin).all(1) & (uv[:, 0] <= camera.width - 1 - margin)
        ok &= uv[:, 1] <= camera.height - 1 - margin
        idx = np.flatnonzero(ok)
        if len(idx) > obs_per_frame:
            idx = np.sort(rng.choice(idx, obs_per_frame, replace=False))
        frames.append((uv[idx] + rng.normal(scale=noise_px, size=(len(idx), 2)), idx))
    sr, st = odometry_sigma
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.r_[[sr] * 3, [st] * 3])
    odometry = []
    for t in range(1, n_frames):
        rel = poses[t - 1].between(poses[t])
        err = np.r_[rng.normal(scale=sr, size=3), rng.normal(scale=st, size=3)]
        odometry.append(rel.retract(err))
    return DriftSequence(camera, c_true, poses, points, frames, odometry, noise, noise_px)


def track_drift(
    seq: DriftSequence,
    c_drift_sigma_px: float = 0.05,
    prior_sigma_px: float = 0.2,
    other_sigma: float = 1e-3,
    map_sigma_m: float | None = None,
    seed: int = 0,
) -> dict:
    """Track the sequence's intrinsics with iSAM2; returns the estimates of ``c`` (px).

    Parameters
    ----------
    c_drift_sigma_px : float
        Random-walk sigma of ``c`` per frame (px).
    prior_sigma_px : float
        Prior sigma of the calibration's ``xp, yp, c`` (px); ``other_sigma`` for
        the other intrinsics (their units).
    map_sigma_m : float or None
        None: the map is exact (known points). Else the tracker is given a map whose
        coordinates are off by Gaussian noise of this sigma (m, seeded by ``seed``),
        and estimates the landmarks with that prior.

    Returns
    -------
    dict
        ``c_true`` (T,), ``c_filtered`` (T,: each frame's estimate right after its
        update), ``c_smoothed`` (T,: given all frames), ``c_frozen`` (T,: the
        calibration, never updated), ``seconds`` (wall clock of the tracking).
    """
    import time

    prior = np.full(3 + len(seq.camera.radial or ()) + len(seq.camera.brown), other_sigma)
    prior[:3] = prior_sigma_px
    online = OnlineIntrinsics(
        seq.camera, covariance=np.diag(prior**2), noise=NoiseOptions(sigma_px=seq.noise_px)
    )
    sigmas = online.drift_sigmas({"c_px": c_drift_sigma_px}, hold=0.01)
    tracker = IntrinsicsTracker(online, sigmas, map_sigma_m=map_sigma_m)
    points = seq.points_world
    if map_sigma_m is not None:
        rng = np.random.default_rng(seed)
        points = points + rng.normal(scale=map_sigma_m, size=points.shape)
    t0 = time.perf_counter()
    guess = seq.world_from_cam[0]
    for t, (uv, idx) in enumerate(seq.frames):
        odo = None
        if t > 0:
            odo = (seq.odometry[t - 1], seq.odometry_noise)
            guess = tracker.pose(t - 1).compose(seq.odometry[t - 1])
        tracker.add_frame(uv, points[idx], guess, odometry=odo, landmark_ids=idx)
    seconds = time.perf_counter() - t0
    c = online.names.index("c_px")
    return {
        "c_true": seq.c_true_px,
        "c_filtered": np.array([th[c] for th in tracker.estimates]),
        "c_smoothed": tracker.smoothed()[:, c],
        "c_frozen": np.full(len(seq.frames), seq.camera.c),
        "seconds": seconds,
    }
