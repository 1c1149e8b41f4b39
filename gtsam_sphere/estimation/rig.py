"""Rig calibration: each camera alone, averaged extrinsics, then the joint adjustment.

A rig (``dataset@2``) is several cameras fixed to one body; images that share a
``frame`` were taken at one rig pose. This module calibrates it in four steps:

1. every camera is calibrated alone by the single-camera pipeline
   (:func:`gtsam_sphere.estimation.calibrate.calibrate`, each camera with its own options),
   all in the dataset's world frame (the targets tie them);
2. ``cam_from_rig`` of each camera is the robust average, over the frames it shares
   with an already placed camera, of the relative pose
   ``cam_from_world_b * inverse(cam_from_world_a) * cam_from_rig_a``: the cameras are
   placed along a maximum spanning tree (most shared frames first) grown from
   ``cameras[0]``, whose frame is the rig frame (``cam_from_rig`` = identity).
   Rotations: chordal L2 mean (the weighted sum of the matrices projected onto
   SO(3)) with iteratively reweighted Cauchy weights on the angular deviations;
   translations: the per-axis median, then the same reweighted mean;
3. ``rig_from_world`` of each frame is the same robust mean over the frame's
   cameras of ``inverse(cam_from_rig) * cam_from_world``, and every framed image
   gets ``cam_from_world = cam_from_rig * rig_from_world`` (an image without a frame
   keeps its own pose);
4. the joint rig adjustment (:func:`.rig_joint.adjust_rig_jointly`): one graph in
   which the frames' ``rig_from_world``, the cameras' ``cam_from_rig`` and intrinsics,
   the unframed images' poses and the targets are variables, every observation
   predicted through ``cam_from_rig * rig_from_world`` (each camera's kNN correction
   from step 1 held fixed, or re-learned there with ``knn_rounds``), robustly weighted
   (Huber) as the single-camera stages.

The precision of each camera's extrinsics is their marginal covariance in the joint
graph (``gtsam.Marginals``); the spread of the relative poses of step 2 over the
frames is kept beside it. ``statistics["rig_adjustment"]`` says which steps ran
(:data:`RIG_ADJUSTMENT`, or :data:`RIG_ADJUSTMENT_AVERAGED` without step 4), and
``statistics["rms_px_rig"]`` gives the reprojection error of the rig's poses.

Poses follow the data contract: ``cam_from_world = (R, t)`` maps ``p_cam = R @ p_world + t``;
``cam_from_rig`` maps rig-frame points to the camera frame, ``rig_from_world`` world
points to the rig frame. Units are the dataset's.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from ..core.camera import Model, radial_terms
from ..core.errors import DegenerateGeometryError
from ..core.lie import nearest_rotation
from ..core.lie import rotation_angle as rotation_angle  # re-exported
from ..core.robust import MEDIAN_NORM_3D, Loss, robust_weight
from ..io.calibration import Calibration, RigCalibration
from ..io.dataset import Dataset, DatasetError, RigDataset, read_json, split_rig
from .calibrate import (
    LOST_TO_OUTLIERS_REASON,
    MIN_MEAN_REDUNDANCY,
    MIN_SIGMA_PX,
    OUTLIER_SHARE,
    PRINCIPAL_POINT_SIGMA_LIMIT_DEG,
    UNRELIABLE_TAG,
    CalibrationOptions,
    Distrust,
    calibrate,
    low_redundancy,
    principal_point_sigma_deg,
    targets_extent,
    targets_off_prior,
)
from .diagnose import ProblemCode, image_groups
from .optimize import OptimizerOptions
from .rig_joint import (
    MAX_STAGES,
    adjust_rig_jointly,
    joint_images,
    precision_from_covariance,
)

logger = logging.getLogger(__name__)

#: ``statistics["rig_adjustment"]`` with the joint adjustment (the default)
RIG_ADJUSTMENT = "joint (per-camera initialisation, averaged extrinsics, one graph)"
#: ``statistics["rig_adjustment"]`` without it (``joint=False``)
RIG_ADJUSTMENT_AVERAGED = "per-camera + averaged extrinsics"
#: Cauchy scale of the robust means, in robust standard deviations of the deviations
CAUCHY_K = 3.0

Pose = tuple[np.ndarray, np.ndarray]

#: the former name of :func:`gtsam_sphere.core.lie.nearest_rotation`
project_to_rotation = nearest_rotation


# -- pose algebra ------------------------------------------------------------------


def compose(a: Pose, b: Pose) -> Pose:
    """``a * b`` for poses ``(R (3, 3), t (3,))``: first ``b``, then ``a``."""
    return a[0] @ b[0], a[0] @ b[1] + a[1]


def inverse(a: Pose) -> Pose:
    """The inverse pose: ``(R^T, -R^T t)``."""
    return a[0].T, -a[0].T @ a[1]


@dataclass
class PoseMean:
    """A robust mean of several samples of one pose, with the samples' spread.

    Attributes
    ----------
    R : ndarray, shape (3, 3)
    t : ndarray, shape (3,)
        The mean pose.
    weights : ndarray, shape (n,)
        Final robust weight of each sample, in ``[0, 1]``: the product of its
        rotation and translation weights.
    downweighted : ndarray of bool, shape (n,)
        Samples whose rotation or translation weight is below 1/2 (beyond
        ``CAUCHY_K`` robust standard deviations from the mean).
    rotation_deviation_rad : ndarray, shape (n,)
        Angle between each sample's rotation and ``R``.
    translation_deviation : ndarray, shape (n, 3)
        Each sample's ``t`` minus the mean ``t`` (units of the samples).
    """

    R: np.ndarray
    t: np.ndarray
    weights: np.ndarray
    downweighted: np.ndarray
    rotation_deviation_rad: np.ndarray
    translation_deviation: np.ndarray

    def spread(self) -> dict:
        """The samples' spread: how well they agree (the precision of the mean).

        Returns
        -------
        dict
            ``n_frames`` (samples), ``n_frames_downweighted`` (weight below 1/2),
            ``rotation_spread_deg`` (weighted RMS angle between a sample and the
            mean), ``rotation_max_deg``, ``translation_spread`` (3,) (weighted RMS
            of each axis' deviation), ``translation_spread_norm`` (weighted RMS of
            the 3-D deviation), ``translation_max``, and the standard errors of the
            mean ``rotation_sigma_deg`` / ``translation_sigma`` (3,) (the spread
            over the square root of the effective number of samples; frames are
            treated as independent, which the shared intrinsics make optimistic).
            Spreads are ``None`` for a single sample (no precision can be
            estimated). Translations in the units of the samples.
        """
        w = self.weights
        n = len(w)
        out: dict = {
            "n_frames": int(n),
            "n_frames_downweighted": int(np.sum(self.downweighted)),
            "rotation_max_deg": float(np.degrees(np.max(self.rotation_deviation_rad))),
            "translation_max": float(np.max(np.linalg.norm(self.translation_deviation, axis=1))),
        }
        if n < 2:
            out.update(
                rotation_spread_deg=None,
                translation_spread=None,
                translation_spread_norm=None,
                rotation_sigma_deg=None,
                translation_sigma=None,
            )
            return out
        sw = float(np.sum(w))
        n_eff = sw**2 / float(np.sum(w**2))
        rot = float(np.degrees(np.sqrt(np.sum(w * self.rotation_deviation_rad**2) / sw)))
        axis = np.sqrt(np.sum(w[:, None] * self.translation_deviation**2, axis=0) / sw)
        out.update(
            rotation_spread_deg=rot,
            translation_spread=axis,
            translation_spread_norm=float(np.sqrt(np.sum(axis**2))),
            rotation_sigma_deg=rot / np.sqrt(n_eff),
            translation_sigma=axis / np.sqrt(n_eff),
        )
        return out


def _cauchy_weights(d: np.ndarray, floor: float) -> np.ndarray:
    """Cauchy weights of non-negative deviations ``d`` with a robust (median) scale."""
    scale = max(float(np.median(d)) / MEDIAN_NORM_3D, floor)
    return robust_weight(d, Loss.CAUCHY, CAUCHY_K * scale)[0]


def robust_pose_mean(R: np.ndarray, t: np.ndarray, iterations: int = 50) -> PoseMean:
    """Robust mean of pose samples: reweighted chordal L2 rotation, reweighted translation.

    Rotation: ``nearest_rotation(sum_i w_i R_i)`` (the chordal L2 mean), the
    weights ``w_i`` Cauchy weights of the angle between ``R_i`` and the mean, scaled
    by their median, iterated to a fixed point. Translation: the per-axis median,
    then the weighted mean with Cauchy weights of ``|t_i - t|``, iterated likewise.
    A sample's final weight is the product of its two weights.

    Parameters
    ----------
    R : ndarray, shape (n, 3, 3)
        Rotation samples (n >= 1).
    t : ndarray, shape (n, 3)
        Translation samples, any units.
    iterations : int
        Largest number of reweighting steps.

    Returns
    -------
    PoseMean
    """
    R = np.asarray(R, float).reshape(-1, 3, 3)
    t = np.asarray(t, float).reshape(-1, 3)
    n = len(R)
    if n == 0:
        raise ValueError("robust_pose_mean needs at least one sample")
    w_rot = np.ones(n)
    R_mean = nearest_rotation(np.einsum("n,nij->ij", w_rot, R))
    for _ in range(iterations):
        angle = rotation_angle(np.einsum("ji,njk->nik", R_mean, R))
        w_new = _cauchy_weights(angle, 1e-12)
        R_mean = nearest_rotation(np.einsum("n,nij->ij", w_new, R))
        converged = np.max(np.abs(w_new - w_rot)) < 1e-10
        w_rot = w_new
        if converged:
            break
    angle = rotation_angle(np.einsum("ji,njk->nik", R_mean, R))

    t_mean = np.median(t, axis=0)
    floor = 1e-12 * (1.0 + float(np.max(np.abs(t))))
    w_t = np.ones(n)
    for _ in range(iterations):
        w_new = _cauchy_weights(np.linalg.norm(t - t_mean, axis=1), floor)
        t_mean = np.sum(w_new[:, None] * t, axis=0) / np.sum(w_new)
        converged = np.max(np.abs(w_new - w_t)) < 1e-10
        w_t = w_new
        if converged:
            break
    return PoseMean(
        R=R_mean,
        t=t_mean,
        weights=w_rot * w_t,
        downweighted=(w_rot < 0.5) | (w_t < 0.5),
        rotation_deviation_rad=angle,
        translation_deviation=t - t_mean,
    )


# -- options -----------------------------------------------------------------------


def parse_camera_models(specs: list[str] | None, camera_ids: list[str]) -> dict[str, Model]:
    """Per-camera models from ``--camera-model ID=MODEL`` options.

    Parameters
    ----------
    specs : list of str or None
        Each ``"cam1=radial+knn"``.
    camera_ids : list of str
        The rig's cameras.

    Returns
    -------
    dict of str -> Model
        Only the cameras named.

    Raises
    ------
    DatasetError
        A malformed item, an unknown camera or model, a camera named twice.
    """
    out: dict[str, Model] = {}
    models = [m.value for m in Model]
    for spec in specs or []:
        cid, sep, name = spec.partition("=")
        cid, name = cid.strip(), name.strip()
        if not sep or not cid or not name:
            raise DatasetError(f"--camera-model {spec!r}: expected CAMERA=MODEL, e.g. cam1=radial")
        if cid not in camera_ids:
            raise DatasetError(
                f"--camera-model {spec!r}: unknown camera {cid!r} (cameras are {camera_ids})"
            )
        if name not in models:
            raise DatasetError(f"--camera-model {spec!r}: unknown model {name!r} (one of {models})")
        if cid in out:
            raise DatasetError(f"--camera-model: camera {cid!r} is given a model twice")
        out[cid] = Model(name)
    return out


def camera_options(
    base: CalibrationOptions,
    camera_ids: list[str],
    models: dict[str, Model] | None = None,
    brown_terms_given: bool = False,
) -> dict[str, CalibrationOptions]:
    """One :class:`CalibrationOptions` per camera: ``base`` with that camera's model.

    Parameters
    ----------
    base : CalibrationOptions
        Options for every camera (``--model`` and the rest).
    camera_ids : list of str
    models : dict of str -> Model, optional
        Per-camera model overrides (``--camera-model``).
    brown_terms_given : bool
        Whether ``base.brown_terms`` was chosen by the user (``--ap``); if not, a
        camera with another model gets that model's default terms.

    Returns
    -------
    dict of str -> CalibrationOptions
    """
    models = models or {}
    out = {}
    for cid in camera_ids:
        model = models.get(cid, base.model)
        if model == base.model:
            out[cid] = base
        else:
            terms = base.brown_terms if brown_terms_given else None
            out[cid] = replace(base, model=model, brown_terms=terms)
    return out


# -- the rig calibration -----------------------------------------------------------


def _framed_poses(calib: Calibration, frame_of: dict[str, str | None]) -> dict[str, Pose]:
    """Frame id -> ``cam_from_world`` of the camera's adjusted images that have a frame."""
    out = {}
    for iid, R, t in zip(calib.image_ids, calib.cam_from_world_R, calib.cam_from_world_t):
        frame = frame_of.get(iid)
        if frame is not None:
            out[frame] = (R, t)
    return out


def _disconnected_error(remaining: list[str], placed: list[str]) -> DatasetError:
    return DatasetError(
        f"camera(s) {remaining} share no frame with camera(s) {placed}: their "
        "cam_from_rig cannot be found. Capture rig frames (images taken at one rig "
        "pose, given the same 'frame' id) in which each of them and one of "
        f"{placed} both see at least 4 targets (the cameras need not see the same "
        "targets: surveyed targets tie them); images without a 'frame', or skipped "
        "by the calibration of their camera, do not count"
    )


def check_rig_connected(camera_ids: list[str], frames: dict[str, set[str]]) -> None:
    """Raise :class:`DatasetError` unless shared frames link every camera to ``camera_ids[0]``.

    Parameters
    ----------
    camera_ids : list of str
    frames : dict of str -> set of str
        Camera id -> the frames in which it has an image.
    """
    placed = [camera_ids[0]]
    remaining = list(camera_ids[1:])
    grew = True
    while remaining and grew:
        grew = False
        for b in list(remaining):
            if any(frames[b] & frames[a] for a in placed):
                placed.append(b)
                remaining.remove(b)
                grew = True
    if remaining:
        raise _disconnected_error(remaining, placed)


def place_cameras(
    camera_ids: list[str], poses: dict[str, dict[str, Pose]], say: Callable[[str], None]
) -> tuple[dict[str, Pose], dict[str, dict]]:
    """``cam_from_rig`` of every camera by averaged relative poses along a spanning tree.

    Starting from ``camera_ids[0]`` (identity), the camera that shares the most
    frames with an already placed camera is placed next, from the frames it
    shares with that camera (its parent), until all are placed.

    Parameters
    ----------
    camera_ids : list of str
    poses : dict of str -> dict of str -> (R (3, 3), t (3,))
        Camera id -> frame id -> adjusted ``cam_from_world`` of its image in that frame.
    say : callable(str)
        Progress lines.

    Returns
    -------
    cam_from_rig : dict of str -> (R (3, 3), t (3,))
    precision : dict of str -> dict
        Per camera: ``parent`` (the camera it was placed from, ``None`` for the
        reference) and the spread of its relative poses (:meth:`PoseMean.spread`).

    Raises
    ------
    DatasetError
        Cameras that share no frame with the placed ones (named, with what to capture).
    """
    ref = camera_ids[0]
    identity = (np.eye(3), np.zeros(3))
    cam_from_rig: dict[str, Pose] = {ref: identity}
    precision: dict[str, dict] = {
        ref: {"parent": None, "n_frames": len(poses[ref]), "reference": True}
    }
    remaining = list(camera_ids[1:])
    while remaining:
        best = (0, "", "")
        for b in remaining:
            for a in cam_from_rig:
                n = len(poses[a].keys() & poses[b].keys())
                if n > best[0]:
                    best = (n, b, a)
        n, b, a = best
        if n == 0:
            raise _disconnected_error(remaining, list(cam_from_rig))
        frames = [f for f in poses[b] if f in poses[a]]
        R_s, t_s = [], []
        for f in frames:
            # cam_from_rig_b = cam_from_world_b * world_from_cam_a * cam_from_rig_a
            R, t = compose(compose(poses[b][f], inverse(poses[a][f])), cam_from_rig[a])
            R_s.append(R)
            t_s.append(t)
        mean = robust_pose_mean(np.array(R_s), np.array(t_s))
        cam_from_rig[b] = (mean.R, mean.t)
        precision[b] = {"parent": a, "frames": frames, **mean.spread()}
        spread = precision[b]
        if spread["rotation_spread_deg"] is None:
            logger.warning(
                "camera %r: cam_from_rig rests on a single frame (%s) shared with %r: its "
                "precision cannot be estimated; capture more frames with both cameras",
                b,
                frames[0],
                a,
            )
            say(f"camera {b}: cam_from_rig from 1 frame shared with {a} (no spread)")
        else:
            say(
                f"camera {b}: cam_from_rig from {n} frames shared with {a}: angle "
                f"{np.degrees(rotation_angle(mean.R)):.3f} deg, |t| {np.linalg.norm(mean.t):.6g}; "
                f"spread {spread['rotation_spread_deg']:.4f} deg, "
                f"{spread['translation_spread_norm']:.4g} (dataset units), "
                f"{spread['n_frames_downweighted']} frames down-weighted"
            )
        remaining.remove(b)
    return cam_from_rig, precision


def _rig_residuals(calib: Calibration, camera, R: np.ndarray, t: np.ndarray, xyz_of: dict):
    """Raw-pixel residuals (N, 2) of a camera's observations with given poses and targets.

    ``R, t`` map the camera's image ids (in ``calib.image_ids`` order) to the rig's
    ``cam_from_world``; ``xyz_of`` maps target id -> world coordinates. NaN rows
    where the model has no pixel for the point.
    """
    obs = calib.extra.get("observations", {})
    index = {iid: k for k, iid in enumerate(calib.image_ids)}
    ims = np.array([index[i] for i in obs.get("image", [])], int)
    if len(ims) == 0:
        return np.zeros((0, 2))
    xyz = np.array([xyz_of[tg] for tg in obs["target"]], float)
    pc = np.einsum("nij,nj->ni", R[ims], xyz) + t[ims]
    with np.errstate(invalid="ignore", divide="ignore"):
        uv = camera.project(pc, valid_only=False)
    return np.asarray(obs["uv_px"], float) - uv


def _rms(res: np.ndarray) -> float | None:
    ok = np.isfinite(res).all(axis=1)
    return float(np.sqrt(np.mean(np.sum(res[ok] ** 2, axis=1)))) if ok.any() else None


def largest_connected_part(
    dataset: Dataset, error: DegenerateGeometryError, framed: set[str], joint: bool
) -> tuple[Dataset, dict] | None:
    """A rig camera whose own images form groups that share no target: its largest
    group to calibrate alone, and the other groups' observations for the joint graph.

    In a rig the camera's other groups are still held: their frames' poses come from
    the other cameras, so the joint adjustment (:func:`.rig_joint.adjust_rig_jointly`)
    takes them back. This applies only when the camera's calibration was refused for
    disconnected groups alone (``error``'s fatal problems are all
    ``disconnected-network``), the joint adjustment runs and every image outside the
    largest group has a frame; else None (the refusal stands). A narrow camera of a
    free-network rig (no target sigma) meets this: its images see parts of the room
    the other cameras link (``simulate --rig mixed --frames 6 --seed 1``, every sigma
    removed: the pinhole's images form 2-3 groups).

    Parameters
    ----------
    dataset : Dataset
        The camera's part of the rig (:func:`split_rig`).
    error : DegenerateGeometryError
        Its calibration's refusal.
    framed : set of str
        Ids of the rig's images that have a frame.
    joint : bool
        Whether the joint adjustment runs.

    Returns
    -------
    (Dataset, dict) or None
        The largest group's dataset (the other images neither skipped nor dropped
        there) and the other observations: ``image``, ``target`` (lists of ids),
        ``uv_px`` (K, 2).
    """
    codes = {p.code for p in error.problems}
    if not joint or codes != {ProblemCode.DISCONNECTED}:
        return None
    groups = image_groups(dataset)
    if len(groups) < 2:
        return None
    keep = np.zeros(len(dataset.image_ids), bool)
    keep[groups[0]] = True
    if any(dataset.image_ids[i] not in framed for i in np.flatnonzero(~keep)):
        return None
    main = replace(dataset.subset_images(keep), skipped_images=list(dataset.skipped_images))
    rest = ~keep[dataset.obs_image]
    others = {
        "image": [dataset.image_ids[i] for i in dataset.obs_image[rest]],
        "target": [dataset.target_ids[j] for j in dataset.obs_target[rest]],
        "uv_px": dataset.uv_px[rest],
    }
    return main, others


#: a rig camera that cannot be calibrated alone, even on its largest group of images,
#: is seeded with the free targets held at their approximate coordinates with this
#: sigma, as a fraction of the targets' extent (:func:`_seed_on_approximate_targets`)
SEED_TARGET_SIGMA_FRACTION = 0.01


def _seed_on_approximate_targets(
    dataset: Dataset,
    options: CalibrationOptions,
    progress: Callable[[str], None],
    error: DegenerateGeometryError,
    say: Callable[[str], None],
    cid: str,
    why: str | None = None,
) -> Calibration:
    """A rig camera's own calibration when even its largest group of images cannot be
    calibrated alone: every image, each free target a weighted control point at its
    approximate coordinates (sigma :data:`SEED_TARGET_SIGMA_FRACTION` of the targets'
    extent). Only a start for the joint adjustment, which frees the targets again and
    adjusts the camera with the others (``statistics["seeded_on_approximate_targets"]``:
    the sigma used; the joint adjustment then settles what :data:`JOINT_SETTLE_RULES`
    lists). A narrow camera of a free-network rig (``simulate --rig mixed --frames 6
    --seed 3``, every sigma removed) had 6 images in groups of 3, 2 and 1 that shared
    no target, and in its largest group the targets were each seen once: the rig was
    refused.

    Parameters
    ----------
    dataset : Dataset
        The camera's part of the rig.
    options : CalibrationOptions
    progress, say : callable(str)
        The camera's prefixed progress, and the rig's.
    error : DegenerateGeometryError
        Why its largest group could not be calibrated (raised again when seeding fails
        too, or when the dataset has no free target to seed with).
    cid : str
        The camera's id.
    why : str, optional
        Why the camera is seeded when its largest group did calibrate (default: that
        group could not be calibrated, ``error``).

    Returns
    -------
    Calibration
    """
    free = np.isnan(dataset.target_sigma)
    extent = targets_extent(dataset.target_xyz[np.unique(dataset.obs_target)])
    if not free.any() or not extent > 0:
        raise error
    sigma = SEED_TARGET_SIGMA_FRACTION * extent
    say(
        f"camera {cid}: "
        + (why or f"even its largest group cannot be calibrated alone ({error})")
        + "; "
        f"seeding it on all {len(dataset.image_ids)} of its images with the free targets "
        f"held at their approximate coordinates (sigma {sigma:.4g} {dataset.units}); "
        "the joint adjustment frees them again"
    )
    seeded = replace(dataset, target_sigma=np.where(free, sigma, dataset.target_sigma))
    try:
        calib = calibrate(seeded, options, progress, keep_connected=False)
    except DegenerateGeometryError:
        raise error from None
    calib.statistics["seeded_on_approximate_targets"] = sigma
    return calib


def calibrate_rig(
    rig: RigDataset,
    options: CalibrationOptions | dict[str, CalibrationOptions] | None = None,
    progress: Callable[[str], None] | None = None,
    joint: bool = True,
    knn_rounds: int = 0,
) -> RigCalibration:
    """Calibrate a rig: each camera alone, averaged extrinsics, then the joint adjustment.

    See the module docstring for the steps.

    Parameters
    ----------
    rig : RigDataset
        A validated ``dataset@2``.
    options : CalibrationOptions or dict of str -> CalibrationOptions, optional
        The same options for every camera, or one per camera id
        (:func:`camera_options`); default ``CalibrationOptions()``.
    progress : callable(str), optional
        Receives progress lines (each camera's prefixed with ``[id]``).
    joint : bool
        Run the joint rig adjustment (default); False stops at the averaged
        extrinsics (the first version).
    knn_rounds : int
        Rounds of re-learning each camera's kNN correction in the joint graph
        (:func:`.rig_joint.adjust_rig_jointly`); 0 holds the per-camera ones.

    Returns
    -------
    RigCalibration
        Per camera the model (the jointly adjusted intrinsics) and its statistics
        (``statistics["cameras"][id]``: the camera's own adjustment's, plus
        ``rms_px_rig``, ``sigma_px_rig``, ``intrinsics_sigma_rig`` and
        ``cam_from_rig_precision``), ``cam_from_rig``, per frame ``rig_from_world``,
        per image ``cam_from_world`` (rig-composed for framed images), the targets
        (jointly adjusted; without ``joint`` the mean over the cameras of their
        adjusted coordinates), and whole-rig statistics: ``rms_px`` (the cameras'
        own adjustments pooled), ``rms_px_rig`` (with the rig's poses and targets),
        ``trusted`` / ``distrust`` (naming the camera), ``rig_adjustment``,
        ``joint`` (the joint adjustment's status, iterations, stages, datum).

    Raises
    ------
    DatasetError
        Cameras that share no frame with the others (checked before any
        calibration, and again with the images the calibrations kept); a camera
        whose calibration fails on its input (every failing camera named, with its
        message).
    """
    say = progress or (lambda _line: None)
    ids = rig.camera_ids
    if options is None or isinstance(options, CalibrationOptions):
        per_camera = dict.fromkeys(ids, options or CalibrationOptions())
    else:
        per_camera = {cid: options.get(cid, CalibrationOptions()) for cid in ids}
    datasets = split_rig(rig)
    # before hours of work: are the cameras linked by shared frames at all?
    check_rig_connected(
        ids,
        {
            cid: {f for f, c in zip(rig.image_frame, rig.image_camera) if f and ids[c] == cid}
            for cid in ids
        },
    )

    framed = {i for i, f in zip(rig.image_ids, rig.image_frame) if f}
    calibs: dict[str, Calibration] = {}
    # cameras calibrated on their largest group whose result alone is not trusted (e.g.
    # intrinsics undetermined, not converged), with the error that split them: reseeded
    # when the joint adjustment from them does not converge
    untrusted_groups: dict[str, DegenerateGeometryError] = {}
    failures: list[tuple[str, BaseException]] = []
    # a camera's targets seen once: its own adjustment leaves them out and warns, but
    # the joint graph takes them back and reports what it cannot determine itself
    held = _HeldForTheJoint(say) if joint else None
    diagnose_log = logging.getLogger(f"{__package__}.diagnose")
    if held is not None:
        diagnose_log.addFilter(held)
    try:
        for k, cid in enumerate(ids):
            ds = datasets[cid]
            say(
                f"camera {cid} ({k + 1}/{len(ids)}): {len(ds.image_ids)} images, "
                f"{ds.n_observations} observations, model {per_camera[cid].model}"
            )

            prefixed = _camera_progress(say, cid)
            try:
                try:
                    calibs[cid] = calibrate(ds, per_camera[cid], prefixed, keep_connected=False)
                except DegenerateGeometryError as exc:
                    part = largest_connected_part(ds, exc, framed, joint)
                    if part is None:
                        raise
                    main, rest = part
                    say(
                        f"camera {cid}: its own images form groups that share no target; "
                        f"calibrating it on the largest group ({len(main.image_ids)} images); "
                        f"the other {len(set(rest['image']))} images join in the rig's joint "
                        "adjustment through their frames"
                    )
                    try:
                        calibs[cid] = calibrate(
                            main, per_camera[cid], prefixed, keep_connected=False
                        )
                    except DegenerateGeometryError as small:
                        calibs[cid] = _seed_on_approximate_targets(
                            ds, per_camera[cid], prefixed, small, say, cid
                        )
                    else:
                        calibs[cid].extra["joint_only_observations"] = rest
                        calibs[cid].statistics["n_images_joint_only"] = len(set(rest["image"]))
                        if calibs[cid].statistics.get("distrust"):
                            untrusted_groups[cid] = exc
            except (DatasetError, ValueError) as exc:  # bad or degenerate input of this camera
                failures.append((cid, exc))
                say(f"camera {cid}: calibration failed: {exc}")
    finally:
        if held is not None:
            diagnose_log.removeFilter(held)
    if failures:
        lines = "; ".join(f"camera {cid!r}: {' '.join(str(e).split())}" for cid, e in failures)
        raise DatasetError(
            f"{len(failures)} of {len(ids)} cameras could not be calibrated, so the rig "
            f"cannot be: {lines}"
        ) from failures[0][1]

    result = assemble_rig(rig, calibs, per_camera, say, joint, knn_rounds=knn_rounds)
    if not untrusted_groups or "joint" not in result.statistics:
        return result
    if _joint_settles(result, untrusted_groups):
        return result
    # the joint graph started from a doubtful lens (e.g. a largest group fitted exactly):
    # once more, each such camera seeded on all its images
    say(
        "the joint rig adjustment did not converge or left the intrinsics undetermined, "
        "starting from "
        + ", ".join(f"camera {cid}'s largest group" for cid in untrusted_groups)
        + " (not trusted alone): seeding it on all its images and adjusting again"
    )
    reseeded = dict(calibs)
    if held is not None:
        diagnose_log.addFilter(held)
    try:
        for cid, exc in untrusted_groups.items():
            try:
                reseeded[cid] = _seed_on_approximate_targets(
                    datasets[cid],
                    per_camera[cid],
                    _camera_progress(say, cid),
                    exc,
                    say,
                    cid,
                    why="its largest group is not trusted alone and the joint adjustment "
                    "from it did not converge or determine its intrinsics",
                )
            except DegenerateGeometryError:
                say(f"camera {cid}: cannot be seeded either; keeping its largest group")
    finally:
        if held is not None:
            diagnose_log.removeFilter(held)
    if all(reseeded[cid] is calibs[cid] for cid in untrusted_groups):
        return result
    second = assemble_rig(rig, reseeded, per_camera, say, joint, knn_rounds=knn_rounds)
    if _joint_settles(second, untrusted_groups):
        return second
    say(
        "the joint rig adjustment from the seeds did not converge or determine them "
        "either: the first kept"
    )
    return result


def _camera_progress(say: Callable[[str], None], cid: str) -> Callable[[str], None]:
    """Camera ``cid``'s progress: each line to ``say`` prefixed with ``[cid]``."""
    return lambda line: say(f"[{cid}] {line}")


def _joint_settles(result: RigCalibration, cids) -> bool:
    """The rig's joint adjustment converged and determines the intrinsics (a marginal
    covariance) of every camera of ``cids``."""
    cams = result.statistics["cameras"]
    return bool(result.statistics["joint"]["converged"]) and all(
        cams[cid].get("intrinsics_sigma_rig") is not None for cid in cids
    )


class _HeldForTheJoint(logging.Filter):
    """Turns a rig camera's ``undetermined-targets`` warnings into progress lines.

    Its own adjustment leaves out the targets it sees in one image only, and
    :mod:`.diagnose` warns "capture more images"; in a rig the joint adjustment takes
    those observations back (another camera may see the target), and its own notes say
    which targets stay undetermined. ``say`` receives the line instead.
    """

    def __init__(self, say: Callable[[str], None]):
        super().__init__()
        self.say = say

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if f"[{ProblemCode.UNDETERMINED_TARGETS}]" not in message:
            return True
        self.say(f"{message.split(' -> ')[0]} (the joint adjustment takes them back)")
        return False


def _joint_outlier_share_ok(cid: str, statistics: dict, jr) -> bool:
    """Camera ``cid``'s blunders in the joint graph are at most ``calibrate.OUTLIER_SHARE``
    of its observations there."""
    n = int(np.isfinite(jr.residuals_px[cid]).all(axis=1).sum())
    return jr.n_outliers.get(cid, 0) <= OUTLIER_SHARE * max(n, 1)


#: a camera whose observations beyond 5 sigma in the joint graph outnumber those of its
#: own adjustment by more than this share of its joint observations, and by more than
#: :data:`JOINT_NEW_OUTLIERS_MIN`, disagrees with the other cameras where their rays meet
#: (:func:`joint_new_outliers`). A KB 197 deg and a double-sphere 297 deg lens back to
#: back (``bench_rig.py --random 2 --seed 7 --only r01``): the double sphere's rim, where
#: the two share targets, is missed by pixels, and the KB camera, without an outlier
#: alone, had 31 of its 1,652 observations beyond 5 sigma jointly (40 with free targets);
#: its cam_from_rig was 4.4 sigma off, trusted. The other 35 rigs of seeds 5-7: at most
#: one more outlier jointly than alone.
JOINT_NEW_OUTLIER_SHARE = 0.01
JOINT_NEW_OUTLIERS_MIN = 10


def joint_new_outliers(cid: str, statistics: dict, jr) -> int | None:
    """How many more of camera ``cid``'s observations are beyond 5 sigma in the joint
    graph than in its own adjustment (``statistics``, its own); None for a camera its
    own adjustment saw part of the data of (:func:`_saw_part_alone`: not comparable)."""
    if _saw_part_alone(statistics) or "n_outliers" not in statistics:
        return None
    return int(jr.n_outliers.get(cid, 0)) - int(statistics["n_outliers"])


def joint_disagreement(cid: str, statistics: dict, jr) -> str:
    """Why camera ``cid`` disagrees with the rest of the rig ("" when it does not): its
    observations beyond 5 sigma in the joint graph outnumber its own adjustment's by more
    than :data:`JOINT_NEW_OUTLIER_SHARE` of its joint observations and
    :data:`JOINT_NEW_OUTLIERS_MIN` (:func:`joint_new_outliers`)."""
    new = joint_new_outliers(cid, statistics, jr)
    if new is None:
        return ""
    n = int(np.isfinite(jr.residuals_px[cid]).all(axis=1).sum())
    if new <= max(JOINT_NEW_OUTLIERS_MIN, JOINT_NEW_OUTLIER_SHARE * n):
        return ""
    return (
        f"{jr.n_outliers.get(cid, 0)} of its {n} observations are beyond 5 sigma in the "
        f"joint rig adjustment against {statistics['n_outliers']} in its own: the cameras "
        "disagree where their rays meet, so cam_from_rig is pulled by a misfit its sigma "
        "does not hold (a lens model that does not follow the part of the field the "
        "cameras share, often a rim that grows steeply, or a rig that moved between "
        "frames); compare the cameras' residuals by incidence angle"
    )


def _terms_chosen(options: CalibrationOptions) -> bool:
    """The camera's radial and Brown terms are chosen by the data (a radial model with
    term selection and free intrinsics): the joint graph may choose them again."""
    return options.model.uses_radial and options.select_terms and options.fixed_intrinsics is None


def _fitted_exactly(cid: str, statistics: dict, jr) -> bool:
    """The camera's own robust scale ended at the floor (``calibrate.MIN_SIGMA_PX``)."""
    return float(statistics.get("sigma_px", np.inf)) <= MIN_SIGMA_PX * (1.0 + 1e-9)


def _joint_unfolds(cid: str, statistics: dict, jr) -> bool:
    """Camera ``cid``'s jointly adjusted radial mapping keeps increasing over the whole
    field its observations span in the joint graph (``jr.max_incidence_deg``)."""
    cam = jr.cameras.get(cid)
    field = jr.max_incidence_deg.get(cid)
    if cam is None or field is None:
        return False
    return cam.radial is None or float(np.degrees(cam.max_alpha_rad())) >= field


def _saw_part_alone(statistics: dict) -> bool:
    """The camera's own calibration saw part of its data only: its largest group of
    images (:func:`largest_connected_part`), a seed (:func:`_seed_on_approximate_targets`),
    or fewer observations than it left out for the joint graph to take back (targets it
    saw once: a ring camera of a free network, 4 frames, kept 29 of 131 and fitted
    them exactly, its intrinsics singular alone, determined jointly)."""
    return (
        statistics.get("n_images_joint_only", 0) > 0
        or "seeded_on_approximate_targets" in statistics
        or statistics.get("n_undetermined_observations", 0) > statistics.get("n_observations", 0)
    )


#: the joint graph takes back at least this fraction of a camera's own observations
#: (targets it saw once, which other cameras fix) before its terms are chosen again there
#: (:func:`_joint_widens`)
JOINT_WIDENS_FRACTION = 0.5


def _joint_widens(statistics: dict) -> bool:
    """The joint graph adds, to the observations the camera's own adjustment kept, at
    least :data:`JOINT_WIDENS_FRACTION` of them again: targets it saw once, mostly at the
    edge of its field where its neighbours' fields overlap. Its own terms were chosen on
    the narrower field and its mapping is extrapolated over the rest."""
    kept = statistics.get("n_observations", 0)
    return statistics.get("n_undetermined_observations", 0) >= JOINT_WIDENS_FRACTION * kept > 0


def _joint_covers(cid: str, jr) -> bool:
    """The joint adjustment ``jr`` converged with a covariance of camera ``cid``'s
    intrinsics."""
    return jr is not None and jr.result.converged and jr.intrinsics_sigma.get(cid) is not None


def _joint_determines(cid: str, statistics: dict, jr) -> bool:
    """:func:`_joint_covers`, and the camera was calibrated alone on part of its images
    only."""
    return _saw_part_alone(statistics) and _joint_covers(cid, jr)


@dataclass(frozen=True)
class JointSettle:
    """How the joint adjustment settles one reason not to trust a camera's own adjustment.

    Only for a camera its own adjustment saw part of the data of, when the joint
    adjustment converged with a covariance of its intrinsics (:func:`_joint_determines`);
    then when ``holds(cid, statistics, jr)`` too. ``explain(cid, statistics, jr,
    camera_stats)`` ends the warning the reason becomes ("" or "; ...")."""

    holds: Callable[[str, dict, object], bool]
    explain: Callable[[str, dict, object, dict], str]
    #: False: also for a camera its own adjustment saw all the data of (the reason is
    #: about what the other cameras' rays add, not about the images it left out)
    part_only: bool = True


def _always(cid: str, statistics: dict, jr) -> bool:
    return True


def _nothing_to_add(cid: str, statistics: dict, jr, camera_stats: dict) -> str:
    return ""


def _explain_unfolds(cid: str, statistics: dict, jr, camera_stats: dict) -> str:
    return (
        f"; its jointly adjusted mapping does not fold inside the "
        f"{jr.max_incidence_deg[cid]:.1f} deg the joint graph observes"
    )


def _explain_exact(cid: str, statistics: dict, jr, camera_stats: dict) -> str:
    return (
        f"; alone it fitted its observations exactly (robust scale at the "
        f"{MIN_SIGMA_PX:g} px floor), so its kNN loop had nothing to learn"
    )


def _explain_outliers(cid: str, statistics: dict, jr, camera_stats: dict) -> str:
    return (
        f"; in the joint graph {jr.n_outliers[cid]} of its "
        f"{camera_stats[cid]['n_observations_rig']} observations are beyond 5 sigma"
    )


def _joint_principal_point_precise(cid: str, statistics: dict, jr) -> bool:
    """Camera ``cid``'s principal point sigma in the joint adjustment is within
    ``calibrate.PRINCIPAL_POINT_SIGMA_LIMIT_DEG`` of its principal distance."""
    sig = jr.intrinsics_sigma.get(cid) or {}
    c = float(jr.cameras[cid].c)
    if "xp_px" not in sig or "yp_px" not in sig or not c > 0:
        return False
    angle_deg = principal_point_sigma_deg(sig["xp_px"], sig["yp_px"], c)
    return angle_deg <= PRINCIPAL_POINT_SIGMA_LIMIT_DEG


def _explain_precise(cid: str, statistics: dict, jr, camera_stats: dict) -> str:
    sig = jr.intrinsics_sigma[cid]
    return f"; jointly its principal point's sigma is {sig['xp_px']:.1f} / {sig['yp_px']:.1f} px"


def _joint_redundant(cid: str, statistics: dict, jr) -> bool:
    """The joint adjustment's mean redundancy number is at least
    ``calibrate.MIN_MEAN_REDUNDANCY``."""
    return bool(jr.mean_redundancy >= MIN_MEAN_REDUNDANCY)


def _explain_redundant(cid: str, statistics: dict, jr, camera_stats: dict) -> str:
    return f"; jointly the mean redundancy number is {jr.mean_redundancy:.2f}"


#: the reasons not to trust a camera's own adjustment (:class:`Distrust` codes) that the
#: joint adjustment settles, for a camera its own adjustment saw part of the data of (its
#: largest group of images, :func:`largest_connected_part`; a seed on approximate
#: targets, :func:`_seed_on_approximate_targets`; or the targets it saw twice), and
#: what else must hold. Every other reason stands.
#:
#: - ``not-converged``, ``singular``: alone it saw part of its images; the joint graph
#:   adjusts it with all of them.
#: - ``fold``: moreover the jointly adjusted mapping keeps increasing over the whole field
#:   the camera's observations span in the joint graph (:func:`_joint_unfolds`).
#: - ``knn-unstable``: moreover its own robust scale ended at the floor
#:   (``calibrate.MIN_SIGMA_PX``, :func:`_fitted_exactly`): its kNN loop learned from
#:   residuals of hundredths of a pixel or less, and whether it became stable says
#:   nothing of the lens. Free mixed rig, 6 frames: seed 5 (seeded, 0.021 px RMS) was
#:   refused on it once the initialisation's refit changed, and seed 11 (largest group of
#:   4 images, 2e-13 px) always; their joint cam_from_rig are 0.11 deg / 2.7 mm and
#:   0.07 deg / 1.5 mm off, within 1.4 reported sigma.
#: - ``outliers`` (more than ``calibrate.OUTLIER_SHARE`` of its observations beyond 5
#:   sigma): moreover its share in the joint graph, at its joint scale, is within the
#:   limit (:func:`_joint_outlier_share_ok`): a ring camera of a free network, 4 frames,
#:   seed 9, kept 85 of its 275 observations alone, fitted them to 0.020 px, and 11 were
#:   "beyond 5 sigma" (0.1 px); jointly its scale is 0.29 px, its cam_from_rig within 3
#:   sigma.
#: - ``imprecise`` (a principal point sigma beyond
#:   ``calibrate.PRINCIPAL_POINT_SIGMA_LIMIT_DEG``): moreover the joint one is within it
#:   (:func:`_joint_principal_point_precise`).
#: - ``low-redundancy`` (a mean redundancy number below
#:   ``calibrate.MIN_MEAN_REDUNDANCY``), also for a camera that saw all its images alone:
#:   the other cameras' rays to its targets add redundancy its own adjustment lacks (a
#:   stereo pair of a free network that sees each target in two frames per camera: two
#:   rays alone, four jointly); settled when the joint graph's mean is at least the
#:   limit (:func:`_joint_redundant`). The joint graph's own mean below the limit is a
#:   reason not to trust the rig.
JOINT_SETTLE_RULES: dict[str, JointSettle] = {
    str(Distrust.NOT_CONVERGED): JointSettle(_always, _nothing_to_add),
    str(Distrust.SINGULAR): JointSettle(_always, _nothing_to_add),
    str(Distrust.FOLD): JointSettle(_joint_unfolds, _explain_unfolds),
    str(Distrust.KNN_UNSTABLE): JointSettle(_fitted_exactly, _explain_exact),
    str(Distrust.OUTLIERS): JointSettle(_joint_outlier_share_ok, _explain_outliers),
    str(Distrust.IMPRECISE): JointSettle(_joint_principal_point_precise, _explain_precise),
    str(Distrust.LOW_REDUNDANCY): JointSettle(
        _joint_redundant, _explain_redundant, part_only=False
    ),
}


def _joint_settles_reason(cid: str, code: str | None, statistics: dict, jr) -> bool:
    """The joint adjustment ``jr`` settles camera ``cid``'s own reason ``code``
    (:data:`JOINT_SETTLE_RULES`)."""
    rule = JOINT_SETTLE_RULES.get(code)
    if rule is None:
        return False
    if rule.part_only:
        determines = _joint_determines(cid, statistics, jr)
    else:
        determines = _joint_covers(cid, jr)
    return determines and rule.holds(cid, statistics, jr)


def assemble_rig(
    rig: RigDataset,
    calibs: dict[str, Calibration],
    options: dict[str, CalibrationOptions],
    say: Callable[[str], None],
    joint: bool = True,
    fixed_extrinsics: dict[str, Pose] | None = None,
    knn_rounds: int = 0,
) -> RigCalibration:
    """Steps 2-4 of the rig calibration from the cameras' own calibrations.

    Parameters
    ----------
    rig : RigDataset
    calibs : dict of str -> Calibration
        Every camera's own calibration (:func:`calibrate` on :func:`split_rig`'s part).
    options : dict of str -> CalibrationOptions
        Per camera (the joint adjustment takes the optimiser, the loss threshold and
        ``fixed_intrinsics`` from them).
    say : callable(str)
    joint : bool
        Run the joint adjustment (step 4); False stops at the averaged extrinsics.
    fixed_extrinsics : dict of str -> (R (3, 3), t (3,)), optional
        Known ``cam_from_rig`` of every camera (the first the identity): used instead
        of the averaged ones and held in the joint adjustment (the oracle of a
        simulated rig); their sigma is then not reported.
    knn_rounds : int
        Rounds of re-learning each camera's kNN correction in the joint graph.

    Returns
    -------
    RigCalibration
        As :func:`calibrate_rig`.
    """
    ids = rig.camera_ids
    frame_of = dict(zip(rig.image_ids, rig.image_frame))
    poses = {cid: _framed_poses(calibs[cid], frame_of) for cid in ids}
    cam_from_rig, precision = place_cameras(ids, poses, say)
    if fixed_extrinsics is not None:
        cam_from_rig = {c: fixed_extrinsics[c] for c in ids}

    # rig_from_world per frame: robust mean over the frame's cameras
    frame_ids = [f for f in rig.frame_ids if any(f in poses[c] for c in ids)]
    rig_R, rig_t = [], []
    frame_spread = []
    for f in frame_ids:
        samples = [compose(inverse(cam_from_rig[c]), poses[c][f]) for c in ids if f in poses[c]]
        mean = robust_pose_mean(
            np.array([R for R, _ in samples]), np.array([t for _, t in samples])
        )
        rig_R.append(mean.R)
        rig_t.append(mean.t)
        if len(samples) > 1:
            frame_spread.append(mean.spread())
    frame_index = {f: k for k, f in enumerate(frame_ids)}

    # targets: mean over the cameras of their adjusted coordinates
    sums: dict[str, np.ndarray] = {}
    counts: dict[str, int] = {}
    for cid in ids:
        for tid, p in zip(calibs[cid].target_ids, calibs[cid].target_xyz):
            sums[tid] = sums.get(tid, 0.0) + p
            counts[tid] = counts.get(tid, 0) + 1
    target_ids = [tid for tid in rig.target_ids if tid in sums]
    xyz_of = {tid: sums[tid] / counts[tid] for tid in target_ids}

    adjustment = RIG_ADJUSTMENT_AVERAGED
    jr = None
    cameras = {c: calibs[c].camera for c in ids}
    if joint:
        first = options[ids[0]]
        fixed = {
            c: np.asarray(options[c].fixed_intrinsics, float)
            for c in ids
            if options[c].fixed_intrinsics is not None
        }
        # every term each camera's own run started with (the joint graph may choose again)
        full_terms = {
            c: (radial_terms(options[c].radial_terms), tuple(options[c].brown_terms or ()))
            for c in ids
        }
        jr = adjust_rig_jointly(
            rig,
            calibs,
            cam_from_rig,
            {f: (rig_R[k], rig_t[k]) for f, k in frame_index.items()},
            xyz_of,
            OptimizerOptions(first.optimizer, first.max_iterations),
            say,
            loss_threshold=first.loss_threshold,
            points_per_factor=first.points_per_factor,
            fixed_intrinsics=fixed,
            fixed_extrinsics=fixed_extrinsics is not None,
            knn_rounds=knn_rounds,
            seed=first.seed,
            reselect_terms={
                c: full_terms[c]
                for c in ids
                if (_saw_part_alone(calibs[c].statistics) or _joint_widens(calibs[c].statistics))
                # a seed saw every image (its targets held near their approximate
                # coordinates): its term set stands (free mixed 6 frames seed 3: g3
                # added back left 7 of its 165 observations carrying the noise)...
                and "seeded_on_approximate_targets" not in calibs[c].statistics
                and _terms_chosen(options[c])
            },
            # ...unless the joint graph shows it misfits (rig_joint.MISFIT_SCALE_RATIO)
            reselect_if_misfit={
                c: full_terms[c]
                for c in ids
                if "seeded_on_approximate_targets" in calibs[c].statistics
                and _terms_chosen(options[c])
            },
        )
        adjustment = RIG_ADJUSTMENT
        for cid in ids[1:]:
            precision[cid]["cam_from_rig_averaged"] = {
                "R": cam_from_rig[cid][0],
                "t": cam_from_rig[cid][1],
            }
            # the spread's standard error stays, renamed: it ignores the intrinsics
            for key in ("rotation_sigma_deg", "translation_sigma"):
                precision[cid][f"{key}_spread"] = precision[cid].pop(key, None)
        cam_from_rig = jr.cam_from_rig
        rig_R = [jr.rig_from_world[f][0] for f in frame_ids]
        rig_t = [jr.rig_from_world[f][1] for f in frame_ids]
        # the joint graph's targets: with those each camera saw once (no camera's own
        # result has them) and without those it cannot determine either
        gone = set(jr.undetermined_targets)
        target_ids = [
            tid
            for tid in rig.target_ids
            if (tid in xyz_of or tid in jr.target_xyz) and tid not in gone
        ]
        xyz_of = {tid: jr.target_xyz.get(tid, xyz_of.get(tid)) for tid in target_ids}
        cameras = jr.cameras
        for cid in ids[1:]:
            cov = jr.cam_from_rig_covariance[cid]
            if cov is None:
                precision[cid].update(rotation_sigma_deg=None, translation_sigma=None)
            else:
                precision[cid].update(precision_from_covariance(cov, cam_from_rig[cid][1]))
            precision[cid]["sigma_source"] = "marginal covariance of the joint adjustment"
            R, t = cam_from_rig[cid]
            pr = precision[cid]
            if pr.get("rotation_sigma_deg") is not None:
                say(
                    f"camera {cid}: joint cam_from_rig angle "
                    f"{np.degrees(rotation_angle(R)):.4f} deg, |t| {np.linalg.norm(t):.6g} "
                    f"+- {pr['rotation_sigma_deg']:.4f} deg, {pr['baseline_sigma']:.3g} "
                    "(dataset units)"
                )

    image_ids, image_camera, image_frame, R_all, t_all = [], [], [], [], []
    camera_stats: dict[str, dict] = {}
    camera_results: dict[str, dict] = {}
    res_rig_all = []
    for cid in ids:
        calib = calibs[cid]
        R_cam, t_cam = [], []
        own = list(zip(calib.image_ids, calib.cam_from_world_R, calib.cam_from_world_t))
        if jr is not None:
            # with the images only the rig holds (a camera whose own groups share no target)
            extra = joint_images(calib, frame_of, jr.rig_from_world)[len(calib.image_ids) :]
            own += [(i, None, None) for i in extra]
        for iid, R, t in own:
            frame = frame_of.get(iid)
            if jr is not None:
                R, t = jr.cam_from_world[iid]
            elif frame is not None:
                f = frame_index[frame]
                R, t = compose(cam_from_rig[cid], (rig_R[f], rig_t[f]))
            image_ids.append(iid)
            image_camera.append(cid)
            image_frame.append(frame)
            R_cam.append(R)
            t_cam.append(t)
        R_cam, t_cam = np.array(R_cam), np.array(t_cam)
        R_all.append(R_cam)
        t_all.append(t_cam)
        if jr is not None:
            res_rig = jr.residuals_px[cid]
        else:
            res_rig = _rig_residuals(calib, calib.camera, R_cam, t_cam, xyz_of)
        res_rig_all.append(res_rig)
        stats = dict(calib.statistics)
        stats["model"] = calib.model
        stats["rms_px_rig"] = _rms(res_rig)
        stats["n_observations_rig"] = int(np.isfinite(res_rig).all(axis=1).sum())
        stats["n_images_rig"] = len(own)
        stats["cam_from_rig_precision"] = precision[cid]
        if jr is not None:
            # the file's intrinsics are the joint ones; the rest of the statistics are
            # the camera's own adjustment's
            stats["sigma_px_rig"] = jr.sigma_px[cid]
            stats["n_outliers_rig"] = jr.n_outliers.get(cid, 0)
            stats["intrinsics_sigma_rig"] = jr.intrinsics_sigma[cid]
            stats["intrinsics_own"] = calib.camera.to_dict()
        camera_stats[cid] = stats
        camera_results[cid] = calib.extra

    n_obs = np.array([calibs[c].statistics["n_observations"] for c in ids], float)
    rms = np.array([calibs[c].statistics["rms_px"] for c in ids], float)
    distrust, settled = [], []
    for cid in ids:
        st = calibs[cid].statistics
        codes = st.get("distrust_codes", [None] * len(st.get("distrust", [])))
        for code, reason in zip(codes, st.get("distrust", [])):
            if _joint_settles_reason(cid, code, st, jr):
                rule = JOINT_SETTLE_RULES[code]
                how = rule.explain(cid, st, jr, camera_stats)
                alone = (
                    "its own adjustment on part of its data (its largest group of images, "
                    "or the targets it saw twice)"
                    if rule.part_only
                    else "its own adjustment, without the other cameras' rays"
                )
                settled.append(
                    f"camera {cid!r}: {alone}: {reason}; the joint adjustment, with the "
                    f"rest, converged and determines its intrinsics{how}"
                )
            else:
                distrust.append(f"camera {cid!r}: {reason}")
    for cid in ids if jr is not None else []:
        if not _joint_outlier_share_ok(cid, {}, jr):
            distrust.append(
                f"camera {cid!r}: {jr.n_outliers[cid]} of its "
                f"{camera_stats[cid]['n_observations_rig']} observations are beyond 5 sigma "
                "in the joint rig adjustment"
            )
        why = joint_disagreement(cid, calibs[cid].statistics, jr)
        if why:
            distrust.append(f"camera {cid!r}: {why}")
    if jr is not None and not jr.result.converged:
        distrust.append(f"the joint rig adjustment did not converge ({jr.result.describe()})")
    if jr is not None:
        why = low_redundancy(
            {
                "redundancy": jr.redundancy,
                "n_observations": sum(len(r) for r in jr.residuals_px.values()),
                "mean_redundancy": jr.mean_redundancy,
            }
        )
        if why:
            distrust.append(f"the joint rig adjustment: {why}")
        why = targets_off_prior(jr.target_shifts)
        if why:
            distrust.append(f"the joint rig adjustment: {why}")
    for cid, usable in (jr.unestimated_scales if jr is not None else {}).items():
        distrust.append(
            f"camera {cid!r}: only {usable} of its observations carry the noise in the "
            "joint rig adjustment (the others fix targets only its own rays see): its "
            f"robust scale was held at {jr.sigma_px[cid]:.4f} px, and neither its fit nor "
            "the precision of its cam_from_rig can be checked: capture views in which "
            "the other cameras see its targets too"
        )
    for cid in jr.unsettled_scales if jr is not None else []:
        distrust.append(
            f"camera {cid!r}: its robust scale in the joint rig adjustment did not settle "
            f"({jr.sigma_px[cid]:.4f} px after {MAX_STAGES} stages, or fallen to the "
            "floor: its observations fitted exactly), so its weights and the precision of "
            "its cam_from_rig are not reliable: too few observations for its parameters"
        )
    if (
        jr is not None
        and fixed_extrinsics is None
        and any(jr.cam_from_rig_covariance[c] is None for c in ids[1:])
    ):
        distrust.append(
            "the joint rig adjustment's normal equations are singular: the precision of "
            "cam_from_rig is unknown"
        )
    statistics = {
        "rig_adjustment": adjustment,
        "rms_px": float(np.sqrt(np.sum(n_obs * rms**2) / np.sum(n_obs))),
        "rms_px_rig": _rms(np.concatenate(res_rig_all)),
        "n_observations": int(n_obs.sum()),
        "n_rejected": int(sum(calibs[c].statistics["n_rejected"] for c in ids)),
        "n_cameras": len(ids),
        "n_frames": len(frame_ids),
        "n_images": len(image_ids),
        "n_images_skipped": int(sum(calibs[c].statistics["n_images_skipped"] for c in ids)),
        "n_targets": len(target_ids),
        "n_targets_undetermined": len(jr.undetermined_targets) if jr is not None else 0,
        "n_targets_unreliable": sum(
            why.endswith(UNRELIABLE_TAG) for why in jr.undetermined_reasons.values()
        )
        if jr is not None
        else 0,
        "n_targets_weak": int(np.sum(jr.target_precision.get("weak", []))) if jr is not None else 0,
        "weak_target_limit": jr.weak_target_limit if jr is not None else None,
        "converged": all(calibs[c].statistics["converged"] for c in ids)
        and (jr is None or jr.result.converged),
        "trusted": not distrust,
        "distrust": distrust,
        "untrusted_cameras": [c for c in ids if not calibs[c].statistics.get("trusted", True)],
        "warnings": [
            f"camera {c!r}: cam_from_rig rests on a single frame shared with "
            f"{precision[c]['parent']!r}; its precision is unknown"
            for c in ids
            if precision[c].get("parent") is not None and precision[c]["n_frames"] < 2
        ]
        + [f"the joint rig adjustment: {note}" for note in (jr.notes if jr else [])]
        + settled,
        "frame_spread_rotation_deg_median": float(
            np.median([s["rotation_spread_deg"] for s in frame_spread])
        )
        if frame_spread
        else None,
        "cameras": camera_stats,
    }
    if jr is not None:
        statistics["joint"] = {
            "status": str(jr.result.status.value),
            "converged": bool(jr.result.converged),
            "iterations": int(jr.result.history[-1]["iteration"]),
            "stages": jr.stages,
            "cost": float(jr.result.history[-1]["cost"]),
            "datum": jr.datum,
            "loss": jr.loss,
            "variance_factor": jr.variance_factor,
            "redundancy": jr.redundancy,
            "mean_redundancy": jr.mean_redundancy,
            **jr.target_shifts,
        }
    return RigCalibration(
        camera_ids=list(ids),
        cameras=cameras,
        models={c: calibs[c].model for c in ids},
        cam_from_rig=cam_from_rig,
        frame_ids=frame_ids,
        rig_from_world_R=np.array(rig_R, float).reshape(-1, 3, 3),
        rig_from_world_t=np.array(rig_t, float).reshape(-1, 3),
        image_ids=image_ids,
        image_camera=image_camera,
        image_frame=image_frame,
        cam_from_world_R=np.concatenate(R_all),
        cam_from_world_t=np.concatenate(t_all),
        target_ids=target_ids,
        target_xyz=np.array([xyz_of[tid] for tid in target_ids], float).reshape(-1, 3),
        statistics=statistics,
        units=rig.units,
        extra={
            "camera_results": camera_results,
            "skipped_images": [{"id": i, "reason": why} for i, why in rig.skipped_images],
            "undetermined_targets": [
                {"id": tid, "reason": jr.undetermined_reasons.get(tid, LOST_TO_OUTLIERS_REASON)}
                for tid in (jr.undetermined_targets if jr is not None else [])
            ],
            **(
                {"target_precision": _file_target_precision(jr, target_ids)}
                if jr is not None and jr.target_precision
                else {}
            ),
            "source": rig.source,
        },
    )


def _file_target_precision(jr, target_ids: list[str]) -> dict:
    """The joint graph's ``target_precision`` for the targets the rig file holds."""
    tp = jr.target_precision
    index = {tid: k for k, tid in enumerate(tp["target"])}
    keep = [tid for tid in target_ids if tid in index]
    rows = [index[tid] for tid in keep]
    out = {
        "target": keep,
        "intersection_sigma": np.asarray(tp["intersection_sigma"], float)[rows],
        "weak": np.asarray(tp["weak"], bool)[rows],
    }
    if "sigma" in tp:
        out["sigma"] = np.asarray(tp["sigma"], float)[rows]
    return out


# -- command line ------------------------------------------------------------------


def is_rig_dataset(path) -> bool:
    """True when the file at ``path`` is a ``dataset@2`` (rig) document.

    Raises :class:`DatasetError` when it cannot be read as JSON.
    """
    doc = read_json(path)
    return isinstance(doc, dict) and doc.get("format") == "gtsam-sphere/dataset@2"


def run_cli(args, base: CalibrationOptions, progress: Callable[[str], None] | None) -> int:
    """``gtsam-sphere calibrate RIG.json -o CALIB.json``: calibrate a rig, write ``calibration@2``.

    Parameters
    ----------
    args : argparse.Namespace
        ``dataset``, ``output``, ``camera_model`` (list of ``ID=MODEL`` or None),
        ``ap`` (``--ap``, None when not given), ``no_joint`` (``--no-joint``: stop at
        the averaged extrinsics).
    base : CalibrationOptions
        The options of every camera (``--model`` and the rest).
    progress : callable(str) or None

    Returns
    -------
    int
        0 when every camera is trusted, 1 when one is not (named on standard
        error); bad input raises :class:`DatasetError` (exit 2).
    """
    import sys

    from ..io.dataset import load_rig_dataset

    rig = load_rig_dataset(args.dataset)
    for iid, why in rig.skipped_images:
        print(f"warning: image {iid!r} skipped: {why}", file=sys.stderr)
    if rig.dropped:
        print(
            f"warning: {len(rig.dropped)} observations outside the image dropped",
            file=sys.stderr,
        )
    models = parse_camera_models(getattr(args, "camera_model", None), rig.camera_ids)
    options = camera_options(base, rig.camera_ids, models, getattr(args, "ap", None) is not None)
    calib = calibrate_rig(rig, options, progress, joint=not getattr(args, "no_joint", False))
    calib.save(args.output)
    st = calib.statistics
    print(
        f"{args.output}: rig of {len(calib.camera_ids)} cameras, {st['n_frames']} frames "
        f"({st['rig_adjustment']})"
    )
    print(
        f"  RMS (px) {st['rms_px']:.4f} in the cameras' own adjustments, "
        f"{_fmt(st['rms_px_rig'])} with the rig poses"
    )
    for cid in calib.camera_ids:
        cs = st["cameras"][cid]
        R, t = calib.cam_from_rig[cid]
        pr = cs["cam_from_rig_precision"]
        line = (
            f"  camera {cid}: {cs['model']}, RMS {cs['rms_px']:.4f} px "
            f"({_fmt(cs['rms_px_rig'])} with the rig poses), {cs['n_images']} images"
            + (
                f" alone, {cs['n_images_rig']} in the joint adjustment"
                if cs.get("n_images_rig", cs["n_images"]) != cs["n_images"]
                else ""
            )
            + ", "
            f"{'trusted' if cs.get('trusted', cs['converged']) else 'NOT trusted'}"
        )
        if pr.get("parent") is not None:
            line += (
                f"; cam_from_rig angle {np.degrees(rotation_angle(R)):.4f} deg, "
                f"|t| {np.linalg.norm(t):.6g} {calib.units} from {pr['n_frames']} frames "
                f"shared with {pr['parent']} (spread {_fmt(pr['rotation_spread_deg'])} deg, "
                f"{_fmt(pr['translation_spread_norm'])} {calib.units})"
            )
            if pr.get("baseline_sigma") is not None:
                line += (
                    f"; sigma {_fmt(pr['rotation_sigma_deg'])} deg, |t| "
                    f"{_fmt(pr['baseline_sigma'])} {calib.units} (joint adjustment)"
                )
        print(line)
    print(
        f"  targets adjusted / undetermined (of them unreliable) / weak: {st['n_targets']} / "
        f"{st.get('n_targets_undetermined', 0)} ({st.get('n_targets_unreliable', 0)}) / "
        f"{st.get('n_targets_weak', 0)}"
    )
    for note in st.get("warnings", []):
        logger.warning("%s", note)
    for reason in st["distrust"]:
        print(f"warning: do not trust this result: {reason}", file=sys.stderr)
    return 0 if st["trusted"] else 1


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.4g}"
