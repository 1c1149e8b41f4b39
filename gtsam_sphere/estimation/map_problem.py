"""A mapped sequence to refine with a frozen calibration: the data, its graph, its global solve.

A :class:`MapProblem` holds, as flat numpy arrays, everything the map refinement
needs: the frozen camera, the observations (raw pixels, image and landmark of
each), the initial ``world_from_cam`` poses and landmarks (world frame, metres,
GTSAM convention ``p_world = R @ p_cam + t``), and the datum: priors on landmarks
(surveyed targets), priors on poses and relative-pose (odometry) factors.

Images and landmarks carry global integer ids (``image_ids``, ``point_ids``):
the same class describes a whole map and one submap of it
(:meth:`MapProblem.submap`), so a submap can be built, shipped to a worker and
turned into a graph without the rest of the map, and the keys of its variables
(:func:`~gtsam_sphere.estimation.graph.pose_key` / ``point_key`` of the global
ids) are the keys of the whole map's graph.

:meth:`MapProblem.graph` builds the graph: the observations as the factor
engine's frozen-calibration blocks
(:class:`~gtsam_sphere.estimation.external.ProjectionBlocks`, Huber per
observation, pixel residuals of the ideal image), ``gtsam.PriorFactorPoint3`` /
``PriorFactorPose3`` and ``gtsam.BetweenFactorPose3``.
:func:`refine_global` is the single-process path: the package's one Python LM
(:func:`~gtsam_sphere.estimation.optimize.levenberg_marquardt`) on that graph.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import gtsam
import numpy as np

from ..core.camera import SphereCamera
from ..core.errors import InputError
from .external import ProjectionBlocks
from .graph import point_key, pose_key
from .optimize import levenberg_marquardt

__all__ = ["MapGraph", "MapProblem", "RefineResult", "map_problem_from_dataset", "refine_global"]


def _empty(*shape) -> np.ndarray:
    return np.zeros((0, *shape))


@dataclass
class MapProblem:
    """Observations, initial values and datum of a map (or of one submap of it).

    Attributes
    ----------
    camera : SphereCamera
        The frozen calibration (every observation's camera).
    uv_px : ndarray, shape (N, 2)
        Raw measured pixels (OpenCV convention, ``docs/conventions.md``).
    obs_image : ndarray of int, shape (N,)
        Row of ``image_ids`` of each observation.
    obs_point : ndarray of int, shape (N,)
        Row of ``point_ids`` of each observation.
    world_from_cam_R : ndarray, shape (M, 3, 3)
    world_from_cam_t : ndarray, shape (M, 3)
        Initial poses, ``p_world = R @ p_cam + t`` (m).
    points_world : ndarray, shape (L, 3)
        Initial landmarks, world frame (m).
    image_ids, point_ids : ndarray of int, shapes (M,), (L,)
        Global ids of the rows (keys ``pose_key(id)``, ``point_key(id)``).
    sigma_px : float
        Pixel noise standard deviation per axis (px).
    huber_k : float or None
        Huber threshold in sigmas on each observation's whitened norm; None: least squares.
    point_prior_sigma_m : ndarray, shape (L,)
        Isotropic prior on each landmark at ``point_prior_world`` (m); NaN: no prior.
    point_prior_world : ndarray, shape (L, 3)
        Prior means (surveyed coordinates), world frame (m).
    pose_prior_image : ndarray of int, shape (P,)
        Global image ids with a pose prior.
    pose_prior_R, pose_prior_t : ndarray, shapes (P, 3, 3), (P, 3)
        Prior ``world_from_cam`` means (m).
    pose_prior_sigma : ndarray, shape (P, 6)
        Standard deviations of the tangent ``[omega (rad), v (m)]``.
    odometry_from, odometry_to : ndarray of int, shape (Q,)
        Global image ids of each relative-pose factor.
    odometry_R, odometry_t : ndarray, shapes (Q, 3, 3), (Q, 3)
        Measured ``from_T_to = world_from_from^-1 world_from_to`` (m).
    odometry_sigma : ndarray, shape (Q, 6)
        Standard deviations of ``[omega (rad), v (m)]``.
    cameras : list of SphereCamera, optional
        Several frozen cameras (a rig); default ``[camera]``.
    obs_camera : ndarray of int, shape (N,), optional
        Index into ``cameras`` of each observation; default all 0.
    """

    camera: SphereCamera
    uv_px: np.ndarray
    obs_image: np.ndarray
    obs_point: np.ndarray
    world_from_cam_R: np.ndarray
    world_from_cam_t: np.ndarray
    points_world: np.ndarray
    image_ids: np.ndarray | None = None
    point_ids: np.ndarray | None = None
    sigma_px: float = 0.5
    huber_k: float | None = 2.45
    point_prior_sigma_m: np.ndarray | None = None
    point_prior_world: np.ndarray | None = None
    pose_prior_image: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    pose_prior_R: np.ndarray = field(default_factory=lambda: _empty(3, 3))
    pose_prior_t: np.ndarray = field(default_factory=lambda: _empty(3))
    pose_prior_sigma: np.ndarray = field(default_factory=lambda: _empty(6))
    odometry_from: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    odometry_to: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    odometry_R: np.ndarray = field(default_factory=lambda: _empty(3, 3))
    odometry_t: np.ndarray = field(default_factory=lambda: _empty(3))
    odometry_sigma: np.ndarray = field(default_factory=lambda: _empty(6))
    cameras: list | None = None
    obs_camera: np.ndarray | None = None

    def __post_init__(self):
        self.uv_px = np.asarray(self.uv_px, float).reshape(-1, 2)
        self.obs_image = np.asarray(self.obs_image, np.int64).reshape(-1)
        self.obs_point = np.asarray(self.obs_point, np.int64).reshape(-1)
        self.world_from_cam_R = np.asarray(self.world_from_cam_R, float).reshape(-1, 3, 3)
        self.world_from_cam_t = np.asarray(self.world_from_cam_t, float).reshape(-1, 3)
        self.points_world = np.asarray(self.points_world, float).reshape(-1, 3)
        M, L = len(self.world_from_cam_t), len(self.points_world)
        if self.image_ids is None:
            self.image_ids = np.arange(M, dtype=np.int64)
        if self.point_ids is None:
            self.point_ids = np.arange(L, dtype=np.int64)
        self.image_ids = np.asarray(self.image_ids, np.int64)
        self.point_ids = np.asarray(self.point_ids, np.int64)
        if self.point_prior_sigma_m is None:
            self.point_prior_sigma_m = np.full(L, np.nan)
        if self.point_prior_world is None:
            self.point_prior_world = self.points_world.copy()
        self.point_prior_sigma_m = np.asarray(self.point_prior_sigma_m, float).reshape(-1)
        self.point_prior_world = np.asarray(self.point_prior_world, float).reshape(-1, 3)
        if self.cameras is None:
            self.cameras = [self.camera]
        if self.obs_camera is None:
            self.obs_camera = np.zeros(len(self.obs_image), np.int64)
        self.obs_camera = np.asarray(self.obs_camera, np.int64).reshape(-1)

    # ------------------------------------------------------------------ checks and sizes

    @property
    def n_observations(self) -> int:
        """Number of observations N."""
        return len(self.obs_image)

    @property
    def n_images(self) -> int:
        """Number of images (poses) M."""
        return len(self.image_ids)

    @property
    def n_points(self) -> int:
        """Number of landmarks L."""
        return len(self.point_ids)

    def validate(self) -> None:
        """Raise :class:`~gtsam_sphere.core.errors.InputError` naming the first bad item."""
        n, M, L = self.n_observations, self.n_images, self.n_points
        if n == 0:
            raise InputError("the map has no observations")
        if len(self.obs_point) != n or len(self.uv_px) != n:
            raise InputError("uv_px, obs_image and obs_point must have one row per observation")
        if len(self.world_from_cam_R) != M or len(self.point_prior_sigma_m) != L:
            raise InputError("one initial pose per image and one prior sigma per landmark needed")
        if len(self.obs_camera) != n:
            raise InputError("obs_camera must have one row per observation")
        for name, idx, size in (
            ("obs_image", self.obs_image, M),
            ("obs_point", self.obs_point, L),
            ("obs_camera", self.obs_camera, len(self.cameras)),
        ):
            bad = np.flatnonzero((idx < 0) | (idx >= size))
            if len(bad):
                raise InputError(f"observation {bad[0]}: {name} {idx[bad[0]]} is out of range")
        bad = np.flatnonzero(~np.isfinite(self.uv_px).all(1))
        if len(bad):
            raise InputError(f"observation {bad[0]}: uv_px {self.uv_px[bad[0]].tolist()}")
        for name, arr in (
            ("pose", self.world_from_cam_t),
            ("landmark", self.points_world),
        ):
            bad = np.flatnonzero(~np.isfinite(arr).all(1))
            if len(bad):
                raise InputError(f"{name} {bad[0]}: initial value is not finite")
        if not (self.sigma_px > 0 and math.isfinite(self.sigma_px)):
            raise InputError(f"sigma_px must be > 0, got {self.sigma_px}")
        seen = np.bincount(self.obs_point, minlength=L)
        if (seen == 0).any():
            j = int(np.flatnonzero(seen == 0)[0])
            raise InputError(f"landmark {self.point_ids[j]} has no observation")

    # ------------------------------------------------------------------ keys and values

    def pose_keys(self) -> np.ndarray:
        """GTSAM keys of the poses, shape (M,), uint64."""
        return np.array([pose_key(int(i)) for i in self.image_ids], np.uint64)

    def point_keys(self) -> np.ndarray:
        """GTSAM keys of the landmarks, shape (L,), uint64."""
        return np.array([point_key(int(j)) for j in self.point_ids], np.uint64)

    def initial_values(self) -> gtsam.Values:
        """The initial ``gtsam.Values``: ``Pose3`` world_from_cam and ``Point3`` (world, m)."""
        return values_from_arrays(
            self.pose_keys(),
            self.world_from_cam_R,
            self.world_from_cam_t,
            self.point_keys(),
            self.points_world,
        )

    # ------------------------------------------------------------------ submaps

    def submap(self, image_rows: np.ndarray, prior_points: np.ndarray | None = None) -> MapProblem:
        """The part of the map its images ``image_rows`` observe.

        Observations of those images, the landmarks they see (with their priors),
        the pose priors of those images, and the odometry factors that start at one
        of them (the image they end at is added as a variable when it is not in
        ``image_rows``: it is then shared with the submap that owns it).

        Parameters
        ----------
        image_rows : array_like of int
            Rows of ``image_ids``.
        prior_points : ndarray of bool, shape (L,), optional
            Landmarks whose prior this submap carries (default: all it sees). A
            landmark seen from several submaps must have its prior in one only,
            or the prior counts twice.

        Returns
        -------
        MapProblem
            Rows renumbered; ``image_ids`` and ``point_ids`` keep the global ids.
        """
        rows = np.unique(np.asarray(image_rows, np.int64))
        own = np.zeros(self.n_images, bool)
        own[rows] = True
        obs = np.flatnonzero(own[self.obs_image])
        row_of_id = {int(g): k for k, g in enumerate(self.image_ids)}
        own_ids = self.image_ids[rows]
        odo = np.flatnonzero(np.isin(self.odometry_from, own_ids))
        extra = np.setdiff1d(self.odometry_to[odo], own_ids)
        image_rows_all = np.r_[rows, [row_of_id[int(g)] for g in extra]].astype(np.int64)
        new_image = np.full(self.n_images, -1, np.int64)
        new_image[image_rows_all] = np.arange(len(image_rows_all))
        points = np.unique(self.obs_point[obs])
        new_point = np.full(self.n_points, -1, np.int64)
        new_point[points] = np.arange(len(points))
        pp = np.flatnonzero(np.isin(self.pose_prior_image, own_ids))
        prior_sigma = self.point_prior_sigma_m[points]
        if prior_points is not None:
            prior_sigma = np.where(np.asarray(prior_points, bool)[points], prior_sigma, np.nan)
        return MapProblem(
            camera=self.camera,
            uv_px=self.uv_px[obs],
            obs_image=new_image[self.obs_image[obs]],
            obs_point=new_point[self.obs_point[obs]],
            world_from_cam_R=self.world_from_cam_R[image_rows_all],
            world_from_cam_t=self.world_from_cam_t[image_rows_all],
            points_world=self.points_world[points],
            image_ids=self.image_ids[image_rows_all],
            point_ids=self.point_ids[points],
            sigma_px=self.sigma_px,
            huber_k=self.huber_k,
            point_prior_sigma_m=prior_sigma,
            point_prior_world=self.point_prior_world[points],
            pose_prior_image=self.pose_prior_image[pp],
            pose_prior_R=self.pose_prior_R[pp],
            pose_prior_t=self.pose_prior_t[pp],
            pose_prior_sigma=self.pose_prior_sigma[pp],
            odometry_from=self.odometry_from[odo],
            odometry_to=self.odometry_to[odo],
            odometry_R=self.odometry_R[odo],
            odometry_t=self.odometry_t[odo],
            odometry_sigma=self.odometry_sigma[odo],
            cameras=self.cameras,
            obs_camera=self.obs_camera[obs],
        )

    def nbytes(self) -> int:
        """Memory of the arrays (bytes): what a worker holding this submap receives."""
        return int(sum(v.nbytes for v in vars(self).values() if isinstance(v, np.ndarray)))

    # ------------------------------------------------------------------ the graph

    def graph(self) -> MapGraph:
        """The factor graph of this (sub)map.

        Returns
        -------
        MapGraph
            ``graph`` (``gtsam.NonlinearFactorGraph``) and the ``blocks`` that own
            its observation factors' callbacks (keep both alive together).
        """
        M = gtsam.noiseModel
        graph = gtsam.NonlinearFactorGraph()
        pk, lk = self.pose_keys(), self.point_keys()
        noise = M.Isotropic.Sigma(2, float(self.sigma_px))
        if self.huber_k is not None:
            noise = M.Robust.Create(M.mEstimator.Huber.Create(float(self.huber_k)), noise)
        blocks = []
        for c, camera in enumerate(self.cameras):
            sel = np.flatnonzero(self.obs_camera == c)
            if len(sel) == 0:
                continue
            pose, point = pk[self.obs_image[sel]], lk[self.obs_point[sel]]
            blocks.append(ProjectionBlocks(camera, self.uv_px[sel], pose, point, noise, max_obs=8))
            for f in blocks[-1].factors():
                graph.add(f)
        models: dict[float, gtsam.noiseModel.Base] = {}
        for j in np.flatnonzero(np.isfinite(self.point_prior_sigma_m)):
            s = max(float(self.point_prior_sigma_m[j]), 1e-9)
            model = models.setdefault(s, M.Isotropic.Sigma(3, s))
            graph.add(gtsam.PriorFactorPoint3(int(lk[j]), self.point_prior_world[j], model))
        for q in range(len(self.pose_prior_image)):
            pose = gtsam.Pose3(gtsam.Rot3(self.pose_prior_R[q]), self.pose_prior_t[q])
            model = M.Diagonal.Sigmas(np.asarray(self.pose_prior_sigma[q], float))
            graph.add(gtsam.PriorFactorPose3(pose_key(int(self.pose_prior_image[q])), pose, model))
        for q in range(len(self.odometry_from)):
            rel = gtsam.Pose3(gtsam.Rot3(self.odometry_R[q]), self.odometry_t[q])
            model = M.Diagonal.Sigmas(np.asarray(self.odometry_sigma[q], float))
            a, b = pose_key(int(self.odometry_from[q])), pose_key(int(self.odometry_to[q]))
            graph.add(gtsam.BetweenFactorPose3(a, b, rel, model))
        return MapGraph(graph=graph, blocks=blocks)


@dataclass
class MapGraph:
    """A map's ``gtsam.NonlinearFactorGraph`` and its blocks (one per camera, owning callbacks)."""

    graph: gtsam.NonlinearFactorGraph
    blocks: list


def values_from_arrays(pose_keys, R, t, point_keys, points) -> gtsam.Values:
    """``gtsam.Values`` of ``Pose3`` (world_from_cam, (M,3,3), (M,3) m) and ``Point3`` (L,3)."""
    values = gtsam.Values()
    for k, Ri, ti in zip(pose_keys, R, t):
        values.insert(int(k), gtsam.Pose3(gtsam.Rot3(Ri), ti))
    for k, p in zip(point_keys, points):
        values.insert(int(k), np.asarray(p, float))
    return values


def arrays_from_values(values: gtsam.Values, pose_keys, point_keys):
    """Inverse of :func:`values_from_arrays`: ``(R (M,3,3), t (M,3), points (L,3))``."""
    R = np.empty((len(pose_keys), 3, 3))
    t = np.empty((len(pose_keys), 3))
    for q, k in enumerate(pose_keys):
        pose = values.atPose3(int(k))
        R[q] = pose.rotation().matrix()
        t[q] = pose.translation()
    P = np.empty((len(point_keys), 3))
    for q, k in enumerate(point_keys):
        P[q] = values.atPoint3(int(k))
    return R, t, P


@dataclass
class RefineResult:
    """Outcome of a map refinement (global or partitioned).

    Attributes
    ----------
    world_from_cam_R : ndarray, shape (M, 3, 3)
    world_from_cam_t : ndarray, shape (M, 3)
        Refined poses, rows of the problem's images (m).
    points_world : ndarray, shape (L, 3)
        Refined landmarks, world frame (m).
    initial_error, error : float
        GTSAM's cost (half the weighted sum of squares, robust) before and after.
    iterations : int
    status : LMStatus
    iteration_s : list of float
        Wall-clock seconds of each iteration.
    stats : dict
        Engine-specific figures (partitions, separator size, workers, memory).
    """

    world_from_cam_R: np.ndarray
    world_from_cam_t: np.ndarray
    points_world: np.ndarray
    initial_error: float
    error: float
    iterations: int
    status: object
    iteration_s: list = field(default_factory=list)
    stats: dict = field(default_factory=dict)

    @classmethod
    def from_run(cls, R, t, points, info: dict, stats: dict) -> RefineResult:
        """The result of a run: poses ``R`` (M, 3, 3), ``t`` (M, 3) world_from_cam (m),
        ``points`` (L, 3) world (m), and the LM's ``info`` (``initial_error``, ``error``,
        ``iterations``, ``status``, ``iteration_s``)."""
        return cls(
            world_from_cam_R=R,
            world_from_cam_t=t,
            points_world=points,
            initial_error=float(info["initial_error"]),
            error=float(info["error"]),
            iterations=int(info["iterations"]),
            status=info["status"],
            iteration_s=list(info["iteration_s"]),
            stats=stats,
        )

    @property
    def converged(self) -> bool:
        """True when the optimiser's convergence test passed."""
        return str(self.status) == "converged"


def lm_params(max_iterations: int = 100, relative_tolerance: float = 1e-5):
    """GTSAM's default LM parameters with these two changed (shared by both engines)."""
    p = gtsam.LevenbergMarquardtParams()
    p.setMaxIterations(int(max_iterations))
    p.setRelativeErrorTol(float(relative_tolerance))
    return p


def refine_global(
    problem: MapProblem, max_iterations: int = 100, relative_tolerance: float = 1e-5
) -> RefineResult:
    """Refine a whole map in one process: :func:`levenberg_marquardt` on :meth:`MapProblem.graph`.

    Parameters
    ----------
    problem : MapProblem
    max_iterations : int
    relative_tolerance : float
        LM stops when an accepted step lowers the cost by less than this fraction.

    Returns
    -------
    RefineResult
    """
    problem.validate()
    built = problem.graph()
    values, info = levenberg_marquardt(
        built.graph, problem.initial_values(), lm_params(max_iterations, relative_tolerance)
    )
    R, t, P = arrays_from_values(values, problem.pose_keys(), problem.point_keys())
    return RefineResult.from_run(R, t, P, info, {"engine": "local", "partitions": 1})


def map_problem_from_dataset(
    dataset,
    camera,
    initial_cam_from_world: dict | None = None,
    sigma_px: float = 0.5,
    huber_k: float | None = 2.45,
    datum_sigma: float = 1.0,
    cam_from_rig: dict | None = None,
    frame_sigma: float = 1e-4,
) -> tuple[MapProblem, list[str], list[str]]:
    """A :class:`MapProblem` from a ``dataset@1`` (or a ``dataset@2`` rig) and its frozen camera(s).

    Poses start from ``initial_cam_from_world`` where given (in a rig, also
    through the rig from another image of the same frame), else from a
    resection of the image against the targets' approximate coordinates
    (:func:`~gtsam_sphere.estimation.resect.resect`). The datum: each observed
    target has a prior at its approximate coordinates with its ``sigma``
    (``0``: held to 1e-6 of the units), or ``datum_sigma`` when the file gives
    none (a free network's approximate coordinates). In a rig, every image keeps
    a pose of its own and the images of one frame are tied to the frame's first
    image by a relative-pose factor at the calibrated ``cam_a_from_rig
    rig_from_cam_b`` with ``frame_sigma`` (rad and units): the rig stays rigid to
    that tolerance, the extrinsics frozen like the intrinsics.

    Parameters
    ----------
    dataset : Dataset or RigDataset
        From :func:`~gtsam_sphere.io.map_file.load_map`.
    camera : SphereCamera, or dict of str -> SphereCamera
        The frozen calibration; a dict (camera id -> camera) for a rig.
    initial_cam_from_world : dict, optional
        Image id -> ``(R (3, 3), t (3,))`` ``cam_from_world`` start (units of the dataset).
    sigma_px : float
        Pixel noise per axis (px).
    huber_k : float or None
        Huber threshold (sigmas); None: least squares.
    datum_sigma : float
        Prior standard deviation of targets without ``sigma`` (units of the dataset).
    cam_from_rig : dict of str -> (R (3, 3), t (3,)), optional
        A rig's extrinsics (needed to tie the images of a frame).
    frame_sigma : float
        Standard deviation of the frame ties (rad, units; 1e-4: 0.1 mm in metres).
        Much stiffer ties make the normal equations ill-conditioned (at 1e-6 the
        global LM took 14 iterations instead of 4 on the test rig and stopped
        3e-5 above the partitioned solve's cost).

    Returns
    -------
    problem : MapProblem
    image_ids : list of str
        Id of each image row.
    target_ids : list of str
        Id of each landmark row (the observed targets).

    Raises
    ------
    InputError
        An image that cannot be posed, or a rig camera the calibration lacks (names it).
    """
    from .resect import resect

    initial_cam_from_world = dict(initial_cam_from_world or {})
    rig = hasattr(dataset, "camera_ids")
    if rig:
        missing = [c for c in dataset.camera_ids if c not in camera]
        if missing:
            raise InputError(f"the calibration has no camera {missing[0]!r} of the map")
        cameras = [camera[c] for c in dataset.camera_ids]
        image_camera = np.asarray(dataset.image_camera, np.int64)
    else:
        cameras = [camera]
        image_camera = np.zeros(len(dataset.image_ids), np.int64)
    if rig and cam_from_rig is not None:
        _start_from_frames(dataset, cam_from_rig, initial_cam_from_world)
    used = np.unique(dataset.obs_target)
    row = np.full(len(dataset.target_ids), -1, np.int64)
    row[used] = np.arange(len(used))
    M = len(dataset.image_ids)
    R = np.empty((M, 3, 3))
    t = np.empty((M, 3))
    for i, iid in enumerate(dataset.image_ids):
        if iid in initial_cam_from_world:
            Rc, tc = (np.asarray(a, float) for a in initial_cam_from_world[iid])
        else:
            sel = dataset.obs_image == i
            res = resect(
                cameras[image_camera[i]],
                dataset.uv_px[sel],
                dataset.target_xyz[dataset.obs_target[sel]],
            )
            if not np.all(np.isfinite(res.R)):
                raise InputError(
                    f"image {iid!r}: no initial pose (resection: {res.status}); "
                    "give images[].cam_from_world in the map"
                )
            Rc, tc = res.R, res.t
        R[i], t[i] = Rc.T, -Rc.T @ tc  # world_from_cam
    ties = _frame_ties(dataset, cam_from_rig, frame_sigma) if rig else None
    sigma = dataset.target_sigma[used].astype(float)
    sigma = np.where(np.isnan(sigma), datum_sigma, np.maximum(sigma, 1e-6))
    extra = {}
    if ties is not None:
        extra = dict(
            odometry_from=ties[0],
            odometry_to=ties[1],
            odometry_R=ties[2],
            odometry_t=ties[3],
            odometry_sigma=np.full((len(ties[0]), 6), frame_sigma),
        )
    problem = MapProblem(
        camera=cameras[0],
        uv_px=dataset.uv_px,
        obs_image=dataset.obs_image,
        obs_point=row[dataset.obs_target],
        world_from_cam_R=R,
        world_from_cam_t=t,
        points_world=dataset.target_xyz[used],
        sigma_px=sigma_px,
        huber_k=huber_k,
        point_prior_sigma_m=sigma,
        point_prior_world=dataset.target_xyz[used],
        cameras=cameras,
        obs_camera=image_camera[dataset.obs_image],
        **extra,
    )
    return problem, list(dataset.image_ids), [dataset.target_ids[j] for j in used]


def _start_from_frames(dataset, cam_from_rig, initial: dict) -> None:
    """Start images without a pose from a posed image of their frame (through the rig)."""
    rig_from_world: dict[str, tuple] = {}
    for i, frame in enumerate(dataset.image_frame):
        iid = dataset.image_ids[i]
        if frame is None or frame in rig_from_world or iid not in initial:
            continue
        Rc, tc = (
            np.asarray(a, float) for a in cam_from_rig[dataset.camera_ids[dataset.image_camera[i]]]
        )
        R, t = (np.asarray(a, float) for a in initial[iid])
        rig_from_world[frame] = (Rc.T @ R, Rc.T @ (t - tc))
    for i, frame in enumerate(dataset.image_frame):
        iid = dataset.image_ids[i]
        if frame in rig_from_world and iid not in initial:
            Rc, tc = (
                np.asarray(a, float)
                for a in cam_from_rig[dataset.camera_ids[dataset.image_camera[i]]]
            )
            R, t = rig_from_world[frame]
            initial[iid] = (Rc @ R, Rc @ t + tc)


def _frame_ties(dataset, cam_from_rig, frame_sigma):
    """Relative poses ``a_T_b = cam_a_from_rig rig_from_cam_b`` within each frame."""
    if cam_from_rig is None:
        raise InputError("a rig map needs the rig's cam_from_rig (a calibration@2)")
    first: dict[str, int] = {}
    a_rows, b_rows, Rs, ts = [], [], [], []
    for i, frame in enumerate(dataset.image_frame):
        if frame is None:
            continue
        if frame not in first:
            first[frame] = i
            continue
        a = first[frame]
        Ra, ta = cam_from_rig[dataset.camera_ids[dataset.image_camera[a]]]
        Rb, tb = cam_from_rig[dataset.camera_ids[dataset.image_camera[i]]]
        Rab = np.asarray(Ra) @ np.asarray(Rb).T
        a_rows.append(a)
        b_rows.append(i)
        Rs.append(Rab)
        ts.append(np.asarray(ta) - Rab @ np.asarray(tb))
    n = len(a_rows)
    return (
        np.array(a_rows, np.int64),
        np.array(b_rows, np.int64),
        np.array(Rs).reshape(n, 3, 3),
        np.array(ts).reshape(n, 3),
    )
