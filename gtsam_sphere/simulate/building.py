"""Seeded simulation of a fisheye trajectory through a corridor of rooms (map refinement).

World frame: ``X`` along the corridor, ``Y`` across it, ``Z`` up, metres.
The building is a row of ``n_rooms`` box rooms of size ``room_size_m =
(length, width, height)``; room ``r`` spans ``X`` in ``[r L, (r + 1) L]``.
Neighbouring rooms share a wall with a door (``door_size_m`` wide and high,
centred across the corridor). Point landmarks lie on the floor, the ceiling
and the walls of every room (uniform over the area, no landmark in a door).

The camera (a :class:`~gtsam_sphere.core.camera.SphereCamera`, by default a
~190 degree radial-mapping fisheye from :func:`fisheye_camera`) moves along a
smooth path through every door, ``images_per_room`` images per room, looking
forward with a slow heading, pitch and roll wobble. Camera frame as in
``docs/conventions.md``: ``x`` right, ``y`` down, ``z`` forward.

A landmark is observed in an image when it belongs to the room the camera is
in (rooms are convex boxes, so nothing inside a room is occluded, and the
walls hide the other rooms; the doors are ignored), lies inside the lens's
field of view (``alpha <= fov / 2``) and the image, at least
``margin_px`` from the border, and at least ``min_range_m`` away.
Observations get Gaussian pixel noise (``noise_px`` per axis) and a fraction
``outlier_rate`` of them a gross error of ``outlier_px`` in a random direction.

Everything is vectorised per room, so a million observations take a few
seconds. The landmark density is set from ``obs_per_image`` with a pilot
estimate of the visible fraction, so the observation count is close to
``n_images * obs_per_image`` (within a few percent).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..core.camera import SphereCamera

__all__ = [
    "BuildingOptions",
    "BuildingPart",
    "BuildingScene",
    "building_map_problem",
    "building_parts",
    "fisheye_camera",
    "perturb_poses",
    "room_aligned_rms_m",
    "rotation_exp",
    "simulate_building",
]


def fisheye_camera(
    fov_deg: float = 190.0, size_px: int = 1024, g3: float = -0.03, fill: float = 0.47
) -> SphereCamera:
    """A calibrated fisheye on the radial mapping (``c * g(alpha)``, one odd term).

    Parameters
    ----------
    fov_deg : float
        Full field of view (deg); the image circle at ``fov / 2`` has radius
        ``fill * size_px`` (px).
    size_px : int
        Square image side (px); principal point at the image centre.
    g3 : float
        Cubic term of :func:`~gtsam_sphere.core.camera.radial_g` (dimensionless,
        ``0`` is equidistant).
    fill : float
        Image-circle radius as a fraction of the image side.

    Returns
    -------
    SphereCamera
        ``mapping == "radial"``, ``radial = {"g3": g3}``.
    """
    from ..core.camera import radial_g

    half = math.radians(0.5 * fov_deg)
    g_half = float(radial_g(np.array([half]), np.array([g3]))[0])
    c = fill * size_px / g_half
    centre = 0.5 * (size_px - 1)
    return SphereCamera(width=size_px, height=size_px, xp=centre, yp=centre, c=c, radial={"g3": g3})


@dataclass
class BuildingOptions:
    """Everything that defines a simulated building trajectory.

    Attributes
    ----------
    n_images : int
        Number of images along the trajectory.
    obs_per_image : float
        Target mean number of observations per image.
    images_per_room : int
        Images taken in each room (sets the number of rooms).
    room_size_m : tuple of float
        Room length (along the corridor, ``X``), width (``Y``), height (``Z``), metres.
    door_size_m : tuple of float
        Door width and height (m).
    fov_deg : float
        Field of view of the default camera (deg); ignored with ``camera``.
    camera : SphereCamera or None
        The lens; None: :func:`fisheye_camera` with ``fov_deg``.
    noise_px : float
        Pixel noise standard deviation per axis (px).
    outlier_rate : float
        Fraction of observations given a gross error.
    outlier_px : tuple of float
        Range of the gross error magnitude (px).
    margin_px : float
        Minimum distance of an observation from the image border (px).
    min_range_m : float
        Minimum camera-to-landmark distance (m).
    min_track : int
        Landmarks seen in fewer images are dropped (with their observations);
        2 keeps every landmark triangulable.
    path_height_m : float
        Mean camera height above the floor (m).
    seed : int
        Seed of the generator.
    """

    n_images: int = 500
    obs_per_image: float = 200.0
    images_per_room: int = 25
    room_size_m: tuple[float, float, float] = (6.0, 4.0, 3.0)
    door_size_m: tuple[float, float] = (1.0, 2.1)
    fov_deg: float = 190.0
    camera: SphereCamera | None = None
    noise_px: float = 0.5
    outlier_rate: float = 0.0
    outlier_px: tuple[float, float] = (20.0, 80.0)
    margin_px: float = 2.0
    min_range_m: float = 0.3
    min_track: int = 2
    path_height_m: float = 1.4
    seed: int = 0

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first inconsistent option."""
        if self.n_images < 2:
            raise ValueError(f"n_images must be >= 2, got {self.n_images}")
        if self.images_per_room < 1:
            raise ValueError(f"images_per_room must be >= 1, got {self.images_per_room}")
        if self.obs_per_image <= 0:
            raise ValueError(f"obs_per_image must be > 0, got {self.obs_per_image}")
        length, width, height = self.room_size_m
        if min(length, width, height) <= 0:
            raise ValueError(f"room_size_m must be positive, got {self.room_size_m}")
        if not 0 < self.path_height_m < height:
            raise ValueError(f"path_height_m {self.path_height_m} must lie inside the room")
        if not 0.0 <= self.outlier_rate < 1.0:
            raise ValueError(f"outlier_rate must be in [0, 1), got {self.outlier_rate}")
        if self.noise_px < 0:
            raise ValueError(f"noise_px must be >= 0, got {self.noise_px}")


@dataclass
class BuildingScene:
    """Result of :func:`simulate_building` (truth and measurements).

    Attributes
    ----------
    camera : SphereCamera
        The lens (its ``project`` made the pixels).
    world_from_cam_R : ndarray, shape (M, 3, 3)
    world_from_cam_t : ndarray, shape (M, 3)
        True camera poses, GTSAM convention: ``p_world = R @ p_cam + t`` (m).
    points_world : ndarray, shape (L, 3)
        True landmarks, world frame (m). Every landmark is observed at least once.
    obs_image : ndarray of int, shape (N,)
        Image index per observation, in trajectory order (non-decreasing).
    obs_point : ndarray of int, shape (N,)
        Landmark index per observation.
    uv_px : ndarray, shape (N, 2)
        Measured raw pixels (noise and outliers included).
    uv_true_px : ndarray, shape (N, 2)
        Noise-free pixels.
    outlier : ndarray of bool, shape (N,)
        Observations given a gross error.
    room_of_image : ndarray of int, shape (M,)
    room_of_point : ndarray of int, shape (L,)
    options : BuildingOptions
    """

    camera: SphereCamera
    world_from_cam_R: np.ndarray
    world_from_cam_t: np.ndarray
    points_world: np.ndarray
    obs_image: np.ndarray
    obs_point: np.ndarray
    uv_px: np.ndarray
    uv_true_px: np.ndarray
    outlier: np.ndarray
    room_of_image: np.ndarray
    room_of_point: np.ndarray
    options: BuildingOptions

    @property
    def n_images(self) -> int:
        """Number of images M."""
        return len(self.world_from_cam_t)

    @property
    def n_points(self) -> int:
        """Number of landmarks L."""
        return len(self.points_world)

    @property
    def n_observations(self) -> int:
        """Number of observations N."""
        return len(self.obs_image)

    def points_cam(self, index: np.ndarray | slice | None = None) -> np.ndarray:
        """True camera-frame landmark coordinates of observations, shape (n, 3), metres.

        Parameters
        ----------
        index : index array or slice into the observations, or None for all.
        """
        idx = slice(None) if index is None else index
        i, j = self.obs_image[idx], self.obs_point[idx]
        d = self.points_world[j] - self.world_from_cam_t[i]
        return np.einsum("nji,nj->ni", self.world_from_cam_R[i], d)

    def true_bearings(self, index: np.ndarray | slice | None = None) -> np.ndarray:
        """True unit rays of observations, camera frame, shape (n, 3).

        Parameters
        ----------
        index : index array or slice into the observations, or None for all.
        """
        p = self.points_cam(index)
        return p / np.linalg.norm(p, axis=1, keepdims=True)


def rotation_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrices ``Exp(w)`` of rotation vectors (rad), (..., 3) -> (..., 3, 3)."""
    w = np.asarray(w, float)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    k = w / np.maximum(theta[..., 0], 1e-300)
    z = np.zeros(w.shape[:-1])
    K = np.stack(
        [
            np.stack([z, -k[..., 2], k[..., 1]], -1),
            np.stack([k[..., 2], z, -k[..., 0]], -1),
            np.stack([-k[..., 1], k[..., 0], z], -1),
        ],
        -2,
    )
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + np.sin(theta) * K + (1.0 - np.cos(theta)) * (K @ K)


def _trajectory(opts: BuildingOptions, n_rooms: int, rng: np.random.Generator):
    """Camera poses world_from_cam (M,3,3), (M,3) and room index (M,) along the corridor."""
    length, width, _ = opts.room_size_m
    M = opts.n_images
    # image k in room k // images_per_room, evenly spaced inside it
    room = np.minimum(np.arange(M) // opts.images_per_room, n_rooms - 1)
    within = (np.arange(M) - room * opts.images_per_room + 0.5) / opts.images_per_room
    within = np.clip(within, 0.0, 1.0)
    margin = 0.08
    x = (room + margin + (1.0 - 2.0 * margin) * within) * length
    phase = 2.0 * math.pi * x / length
    amp = 0.3 * width
    y = 0.5 * width + amp * np.sin(phase)
    z = opts.path_height_m + 0.15 * np.sin(0.5 * phase + rng.uniform(0, 2 * math.pi))
    heading = np.arctan2(amp * 2.0 * math.pi / length * np.cos(phase), 1.0)
    s = np.arange(M)
    yaw = heading + 0.35 * np.sin(2.0 * math.pi * s / 37.0 + rng.uniform(0, 2 * math.pi))
    pitch = 0.15 * np.sin(2.0 * math.pi * s / 53.0 + rng.uniform(0, 2 * math.pi))
    roll = 0.10 * np.sin(2.0 * math.pi * s / 29.0 + rng.uniform(0, 2 * math.pi))
    forward = np.column_stack(
        [np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)]
    )
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(forward, right)
    R0 = np.stack([right, down, forward], axis=2)  # columns: camera axes in the world
    R = R0 @ rotation_exp(np.column_stack([np.zeros(M), np.zeros(M), roll]))
    return R, np.column_stack([x, y, z]), room


def _landmarks_per_room(camera, R, t, room_of_image, opts, half_fov, rng) -> int:
    """Landmarks per room for ``opts.obs_per_image``: from the fraction of a pilot room's
    landmarks (2,000, drawn from ``rng``) that the first room's images see."""
    pilot = _room_landmarks(opts, 2000, rng)
    first = np.flatnonzero(room_of_image == 0)
    pc = np.einsum("mji,mnj->mni", R[first], pilot[None] - t[first, None])
    seen, _ = _visible(camera, pc.reshape(-1, 3), opts, half_fov)
    return max(4, int(round(opts.obs_per_image / max(float(seen.mean()), 1e-3))))


def _room_observations(camera, R, t, pw, opts, half_fov):
    """What images ``R`` (K, 3, 3), ``t`` (K, 3) (world_from_cam, m) see of a room's
    landmarks ``pw`` (L, 3): ``used`` (L,) the landmarks seen ``min_track`` times or more,
    ``ii, jj`` (N,) image and landmark of each observation (image-major: trajectory
    order, then landmark) and their noise-free pixels ``uv`` (N, 2)."""
    pc = np.einsum("mji,mnj->mni", R, pw[None] - t[:, None]).reshape(-1, 3)
    ok, uv = _visible(camera, pc, opts, half_fov)
    ok = ok.reshape(len(R), len(pw))
    used = ok.sum(0) >= max(opts.min_track, 1)
    ok &= used
    ii, jj = np.nonzero(ok)
    return used, ii, jj, uv.reshape(len(R), len(pw), 2)[ii, jj]


def _room_landmarks(opts: BuildingOptions, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` landmarks on the surfaces of the room at the origin (X in [0, L]), (n, 3) m."""
    L, W, H = opts.room_size_m
    door_w, door_h = opts.door_size_m
    areas = np.array([L * W, L * W, L * H, L * H, W * H, W * H])
    out = np.empty((0, 3))
    while len(out) < n:
        k = int(1.3 * (n - len(out))) + 8
        face = rng.choice(6, size=k, p=areas / areas.sum())
        a, b = rng.uniform(size=(2, k))
        p = np.empty((k, 3))
        # floor, ceiling: (x, y); side walls: (x, z); end walls: (y, z)
        p[:, 0] = np.where(face < 4, a * L, np.where(face == 4, 0.0, L))
        p[:, 1] = np.where(face < 2, b * W, np.where(face == 2, 0.0, np.where(face == 3, W, a * W)))
        p[:, 2] = np.where(face == 0, 0.0, np.where(face == 1, H, b * H))
        in_door = (face >= 4) & (np.abs(p[:, 1] - 0.5 * W) < 0.5 * door_w) & (p[:, 2] < door_h)
        out = np.concatenate([out, p[~in_door]])
    return out[:n]


def _visible(camera: SphereCamera, pc: np.ndarray, opts: BuildingOptions, half_fov: float):
    """Mask (n,) of camera-frame points (n, 3) the camera images, and their pixels (n, 2)."""
    rng_m = np.linalg.norm(pc, axis=1)
    alpha = np.arctan2(np.hypot(pc[:, 0], pc[:, 1]), pc[:, 2])
    ok = (rng_m >= opts.min_range_m) & (alpha <= half_fov)
    uv = np.full((len(pc), 2), np.nan)
    if ok.any():
        uv[ok] = camera.project(pc[ok])
    m = opts.margin_px
    inside = (
        (uv[:, 0] >= m - 0.5)
        & (uv[:, 0] <= camera.width - 0.5 - m)
        & (uv[:, 1] >= m - 0.5)
        & (uv[:, 1] <= camera.height - 0.5 - m)
    )
    return ok & inside, uv


def simulate_building(options: BuildingOptions | None = None, **overrides) -> BuildingScene:
    """Simulate a fisheye trajectory through a corridor of rooms with point landmarks.

    Parameters
    ----------
    options : BuildingOptions or None
        Defaults if None.
    **overrides
        Fields of :class:`BuildingOptions` to replace (``n_images=2000, seed=3``).

    Returns
    -------
    BuildingScene
        Truth, observations in trajectory order and noisy pixels. Landmarks
        seen in fewer than ``min_track`` images are dropped (indices are
        renumbered).
    """
    from dataclasses import replace

    opts = replace(options or BuildingOptions(), **overrides)
    opts.validate()
    rng = np.random.default_rng(opts.seed)
    camera = opts.camera or fisheye_camera(opts.fov_deg)
    half_fov = math.radians(0.5 * opts.fov_deg) if opts.camera is None else camera.max_alpha_rad()
    n_rooms = max(1, math.ceil(opts.n_images / opts.images_per_room))
    R, t, room_of_image = _trajectory(opts, n_rooms, rng)
    length = opts.room_size_m[0]

    per_room = _landmarks_per_room(camera, R, t, room_of_image, opts, half_fov, rng)

    pts_all, img_all, pt_all, uv_all = [], [], [], []
    n_pts = 0
    for r in range(n_rooms):
        imgs = np.flatnonzero(room_of_image == r)
        if len(imgs) == 0:
            continue
        pw = _room_landmarks(opts, per_room, rng) + np.array([r * length, 0.0, 0.0])
        used, ii, jj, uv = _room_observations(camera, R[imgs], t[imgs], pw, opts, half_fov)
        new_index = np.cumsum(used) - 1 + n_pts
        img_all.append(imgs[ii])
        pt_all.append(new_index[jj])
        uv_all.append(uv)
        pts_all.append(pw[used])
        n_pts += int(used.sum())
    points = np.concatenate(pts_all)
    obs_image = np.concatenate(img_all)
    obs_point = np.concatenate(pt_all)
    uv_true = np.concatenate(uv_all)
    n = len(obs_image)
    uv = uv_true + rng.normal(scale=opts.noise_px, size=(n, 2))
    outlier = np.zeros(n, bool)
    n_out = int(round(opts.outlier_rate * n))
    if n_out:
        idx = rng.choice(n, size=n_out, replace=False)
        ang = rng.uniform(0, 2 * math.pi, n_out)
        mag = rng.uniform(*opts.outlier_px, n_out)
        uv[idx] += mag[:, None] * np.column_stack([np.cos(ang), np.sin(ang)])
        outlier[idx] = True
    room_of_point = np.floor(points[:, 0] / length).astype(int)
    room_of_point = np.clip(room_of_point, 0, n_rooms - 1)
    return BuildingScene(
        camera=camera,
        world_from_cam_R=R,
        world_from_cam_t=t,
        points_world=points,
        obs_image=obs_image,
        obs_point=obs_point,
        uv_px=uv,
        uv_true_px=uv_true,
        outlier=outlier,
        room_of_image=room_of_image,
        room_of_point=room_of_point,
        options=opts,
    )


def perturb_poses(
    R: np.ndarray,
    t: np.ndarray,
    sigma_rot_rad: float,
    sigma_m: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Perturb world_from_cam poses on the right: ``R Exp(w)``, ``t + R v``.

    Parameters
    ----------
    R : ndarray, shape (M, 3, 3)
    t : ndarray, shape (M, 3)
        world_from_cam (m).
    sigma_rot_rad, sigma_m : float
        Standard deviations per axis of ``w`` (rad) and ``v`` (m).
    rng : numpy.random.Generator

    Returns
    -------
    R_new : ndarray, shape (M, 3, 3)
    t_new : ndarray, shape (M, 3)
    """
    M = len(t)
    w = rng.normal(scale=sigma_rot_rad, size=(M, 3))
    v = rng.normal(scale=sigma_m, size=(M, 3))
    return R @ rotation_exp(w), t + np.einsum("mij,mj->mi", R, v)


def building_map_problem(scene: BuildingScene, seed: int = 1, odometry: bool = True):
    """The map refinement of a simulated building: perturbed start, gauge and odometry.

    The start perturbs the true poses (0.3 deg and 3 cm per axis, on the right) and
    landmarks (5 cm per axis); the first pose has a prior at its true value
    (1e-3 rad and m), and consecutive poses are tied by noisy odometry
    (0.1 deg, 1 cm per axis), as in ``benchmarks/bench_map.py``. Pixel noise
    model: ``scene.options.noise_px``, Huber 2.45.

    Parameters
    ----------
    scene : BuildingScene
    seed : int
        Seed of the perturbation and odometry noise.
    odometry : bool
        Tie consecutive poses (else the rooms are tied by nothing but the prior).

    Returns
    -------
    MapProblem
    """
    from ..estimation.map_problem import MapProblem

    rng = np.random.default_rng(seed)
    R, t = scene.world_from_cam_R, scene.world_from_cam_t
    R0, t0 = perturb_poses(R, t, math.radians(0.3), 0.03, rng)
    P0 = scene.points_world + rng.normal(scale=0.05, size=scene.points_world.shape)
    M = scene.n_images
    s_rot, s_m = math.radians(0.1), 0.01
    sig = np.tile(np.r_[[s_rot] * 3, [s_m] * 3], (M - 1, 1))
    dR = np.einsum("mji,mjk->mik", R[:-1], R[1:]) @ rotation_exp(
        rng.normal(scale=s_rot, size=(M - 1, 3))
    )
    dt = np.einsum("mji,mj->mi", R[:-1], t[1:] - t[:-1]) + rng.normal(scale=s_m, size=(M - 1, 3))
    odo = np.arange(M - 1) if odometry else np.zeros(0, np.int64)
    return MapProblem(
        camera=scene.camera,
        uv_px=scene.uv_px,
        obs_image=scene.obs_image,
        obs_point=scene.obs_point,
        world_from_cam_R=R0,
        world_from_cam_t=t0,
        points_world=P0,
        sigma_px=max(scene.options.noise_px, 1e-3),
        huber_k=2.45,
        pose_prior_image=np.array([0]),
        pose_prior_R=R[:1],
        pose_prior_t=t[:1],
        pose_prior_sigma=np.full((1, 6), 1e-3),
        odometry_from=odo,
        odometry_to=odo + 1,
        odometry_R=dR[odo],
        odometry_t=dt[odo],
        odometry_sigma=sig[odo],
    )


def room_aligned_rms_m(scene: BuildingScene, points_world: np.ndarray) -> float:
    """Landmark RMS error (m) after a 7-parameter similarity per room onto the truth.

    The walls hide one room from the next, so rooms are tied by odometry alone
    and drift with it; the per-room alignment measures the map's shape (as
    ``benchmarks/bench_map.py``).

    Parameters
    ----------
    scene : BuildingScene
    points_world : ndarray, shape (L, 3)
        Estimated landmarks, rows of ``scene.points_world`` (m).
    """
    from ..core.geometry import fit_similarity

    sq = []
    for r in np.unique(scene.room_of_point):
        idx = np.flatnonzero(scene.room_of_point == r)
        if len(idx) < 4:
            continue
        est = points_world[idx]
        aligned = fit_similarity(est, scene.points_world[idx]).apply(est)
        sq.append(np.sum((aligned - scene.points_world[idx]) ** 2, axis=1))
    return float(np.sqrt(np.mean(np.concatenate(sq))))


@dataclass
class BuildingPart:
    """A run of rooms of a building, generated alone: one submap of a map too big for a process.

    The building is :func:`simulate_building`'s (same options, same geometry) but
    every random draw is keyed by what it belongs to (the trajectory's phases by
    ``options.seed``, a room's landmarks and pixel noise by ``(seed, room)``, an
    image's start perturbation and odometry noise by ``(perturb_seed, image)``),
    so any part is generated in any process, alone, and parts agree on what they
    share: the first image of the next part (tied by odometry to this part's
    last image). The random streams differ from :func:`simulate_building`'s: a
    part series is a building of its own, not a cut of that function's.

    Start, gauge and odometry as :func:`building_map_problem` (0.3 deg and 3 cm
    per pose, 5 cm per landmark, prior on image 0, odometry 0.1 deg and 1 cm).
    No outliers (``outlier_rate`` must be 0).

    Attributes
    ----------
    options : BuildingOptions
        The whole building (``n_images`` is the whole map's).
    first_room, n_rooms : int
        Rooms ``first_room .. first_room + n_rooms - 1`` are this part's.
    perturb_seed : int
        Seed of the start perturbation and the odometry noise.
    """

    options: BuildingOptions
    first_room: int
    n_rooms: int
    perturb_seed: int = 1

    def image_range(self) -> range:
        """Global ids of this part's own images."""
        ipr = self.options.images_per_room
        a = self.first_room * ipr
        return range(a, min(self.options.n_images, a + self.n_rooms * ipr))

    @property
    def n_observations(self) -> int:
        """Expected observations (``obs_per_image`` per own image), for load balancing."""
        return int(len(self.image_range()) * self.options.obs_per_image)

    def build(self):
        """The part's :class:`~gtsam_sphere.estimation.map_problem.MapProblem` (global ids).

        Returns
        -------
        MapProblem
            Own images, plus the next part's first image when there is one (the
            odometry's end); landmark ids ``room * per_room + index``.
        """
        problem, _ = self._generate()
        return problem

    def truth(self) -> tuple[np.ndarray, np.ndarray]:
        """True landmarks of :meth:`build`'s rows, (L, 3) m, and their rooms (L,)."""
        _, truth = self._generate(truth_only=True)
        return truth

    def _generate(self, truth_only: bool = False):
        from ..estimation.map_problem import MapProblem

        opts = self.options
        opts.validate()
        if opts.outlier_rate:
            raise ValueError("BuildingPart generates no outliers: outlier_rate must be 0")
        camera = opts.camera or fisheye_camera(opts.fov_deg)
        half_fov = (
            math.radians(0.5 * opts.fov_deg) if opts.camera is None else camera.max_alpha_rad()
        )
        M = opts.n_images
        total_rooms = max(1, math.ceil(M / opts.images_per_room))
        R, t, room_of_image = _trajectory(opts, total_rooms, np.random.default_rng([opts.seed, 0]))
        rng = np.random.default_rng([opts.seed, 1])
        per_room = _landmarks_per_room(camera, R, t, room_of_image, opts, half_fov, rng)
        own = np.array(self.image_range(), np.int64)
        images = np.r_[own, [own[-1] + 1]] if own[-1] + 1 < M else own
        row_of_image = {int(g): q for q, g in enumerate(images)}
        length = opts.room_size_m[0]
        pts, ids, rooms, oi, op, uvs, p0 = [], [], [], [], [], [], []
        n_pts = 0
        for r in range(self.first_room, self.first_room + self.n_rooms):
            imgs = np.flatnonzero(room_of_image == r)
            if len(imgs) == 0:
                continue
            rr = np.random.default_rng([opts.seed, 2, r])
            pw = _room_landmarks(opts, per_room, rr) + np.array([r * length, 0.0, 0.0])
            used, ii, jj, uv = _room_observations(camera, R[imgs], t[imgs], pw, opts, half_fov)
            new_index = np.cumsum(used) - 1 + n_pts
            oi.append(np.array([row_of_image[int(g)] for g in imgs])[ii])
            op.append(new_index[jj])
            uvs.append(uv + rr.normal(scale=opts.noise_px, size=uv.shape))
            pts.append(pw[used])
            ids.append(r * per_room + np.flatnonzero(used))
            rooms.append(np.full(int(used.sum()), r))
            pr = np.random.default_rng([self.perturb_seed, 4, r])
            p0.append(pw[used] + pr.normal(scale=0.05, size=(int(used.sum()), 3)))
            n_pts += int(used.sum())
        truth = (np.concatenate(pts), np.concatenate(rooms))
        if truth_only:
            return None, truth
        R0, t0 = np.empty((len(images), 3, 3)), np.empty((len(images), 3))
        for q, i in enumerate(images):
            g = np.random.default_rng([self.perturb_seed, 3, int(i)])
            w, v = g.normal(scale=math.radians(0.3), size=3), g.normal(scale=0.03, size=3)
            R0[q] = R[i] @ rotation_exp(w)
            t0[q] = t[i] + R[i] @ v
        s_rot, s_m = math.radians(0.1), 0.01
        odo = own[own + 1 < M]
        dR, dt = np.empty((len(odo), 3, 3)), np.empty((len(odo), 3))
        for q, i in enumerate(odo):
            g = np.random.default_rng([self.perturb_seed, 5, int(i)])
            dR[q] = R[i].T @ R[i + 1] @ rotation_exp(g.normal(scale=s_rot, size=3))
            dt[q] = R[i].T @ (t[i + 1] - t[i]) + g.normal(scale=s_m, size=3)
        has_prior = self.first_room == 0
        problem = MapProblem(
            camera=camera,
            uv_px=np.concatenate(uvs),
            obs_image=np.concatenate(oi),
            obs_point=np.concatenate(op),
            world_from_cam_R=R0,
            world_from_cam_t=t0,
            points_world=np.concatenate(p0),
            image_ids=images,
            point_ids=np.concatenate(ids),
            sigma_px=max(opts.noise_px, 1e-3),
            huber_k=2.45,
            pose_prior_image=np.array([0] if has_prior else [], np.int64),
            pose_prior_R=R[:1] if has_prior else np.zeros((0, 3, 3)),
            pose_prior_t=t[:1] if has_prior else np.zeros((0, 3)),
            pose_prior_sigma=np.full((1 if has_prior else 0, 6), 1e-3),
            odometry_from=odo,
            odometry_to=odo + 1,
            odometry_R=dR,
            odometry_t=dt,
            odometry_sigma=np.tile(np.r_[[s_rot] * 3, [s_m] * 3], (len(odo), 1)),
        )
        return problem, truth


def building_parts(options: BuildingOptions, n_parts: int, perturb_seed: int = 1):
    """Cut a building into ``n_parts`` :class:`BuildingPart` s of whole rooms (as equal as can be).

    Parameters
    ----------
    options : BuildingOptions
    n_parts : int
    perturb_seed : int

    Returns
    -------
    parts : list of BuildingPart
    separator_image_ids : ndarray of int
        Images shared by two parts (each part's first image but the first's).
    """
    total_rooms = max(1, math.ceil(options.n_images / options.images_per_room))
    if not 1 <= n_parts <= total_rooms:
        raise ValueError(f"n_parts must be between 1 and the {total_rooms} rooms, got {n_parts}")
    bounds = np.linspace(0, total_rooms, n_parts + 1).round().astype(int)
    parts = [
        BuildingPart(options, int(a), int(b - a), perturb_seed)
        for a, b in zip(bounds[:-1], bounds[1:])
    ]
    shared = np.array([p.image_range()[0] for p in parts[1:]], np.int64)
    return parts, shared
