"""Joint rig adjustment: one graph for every camera of a rig.

The stage after the per-camera initialisation of :mod:`.rig` (each camera calibrated
alone, ``cam_from_rig`` averaged over the shared frames). Variables
(GTSAM's pose convention, as the single-camera graph: ``docs/conventions.md``):

- ``f{k}``: ``world_from_rig`` of frame ``k`` (``Pose3``, the inverse of the file's
  ``rig_from_world``);
- ``e{c}``: ``rig_from_cam`` of camera ``c >= 1`` (the inverse of ``cam_from_rig``); the
  first camera defines the rig frame and has no variable (the identity);
- ``x{i}``: ``world_from_cam`` of an image without a frame (a pose of its own);
- ``l{j}``: the targets, with the single-camera graph's priors and datum
  (:meth:`BundleProblem.add_priors`);
- ``k{c}``: camera ``c``'s intrinsics, in its own model's layout.

An observation of camera ``c`` in frame ``k`` is predicted with ``world_from_cam =
world_from_rig_k * rig_from_cam_c`` (:class:`ObservationBlock` with an extrinsic key);
its measurement is corrected by the camera's kNN field from the per-camera stage, held
fixed here (``knn_rounds``: trained again on the joint graph's residuals, the grey-box
loop's step, a few rounds; on the simulated rigs this changed the extrinsics by less
than their sigma). The observations of each camera form one vectorised set of blocks.

Robust weighting as in the single-camera stages: Huber per observation, the scale
``sigma_px`` of each camera re-estimated from its residuals (``median / sqrt(2 ln 2)``
of the residuals standardised by their redundancy numbers, a target's information
summed over every camera that sees it: :func:`rig_redundancy`) until it changes by less
than 5%; with gross outliers left (beyond 10 sigma, at least
:data:`~gtsam_sphere.estimation.calibrate.CAUCHY_MIN_FRACTION` of the observations) a
last stage with Cauchy's loss, as the single camera's; then the targets left on one
ray by outliers are not determined (out of the targets, listed). The precision of
``cam_from_rig`` is its marginal
covariance (``gtsam.Marginals``) in the final, robustly weighted graph, times the
a-posteriori variance factor when that exceeds 1 (the robust scale, from the median,
underestimates the spread of heavy-tailed residuals). On an in-model simulated rig
the errors it predicts match the true ones (RMS of the normalised errors 1.05 over 12
seeds, ``tests/test_rig_joint.py``); on the simulator's stereo rig (its lenses outside
the package's models, model ``radial``) 1.20 over 10 seeds, every error within 3 sigma,
and the joint stage lowered the mean error of ``cam_from_rig`` from 0.0144 to 0.0107 deg
and from 0.59 to 0.32 mm against the averaged extrinsics.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import gtsam
import numpy as np

from ..core.camera import WARP_TERM, SphereCamera
from ..core.geometry import fit_similarity_trimmed, incidence_deg
from ..core.robust import MIN_REDUNDANCY, robust_weight
from ..io.calibration import Calibration
from ..io.dataset import RigDataset
from .calibrate import (
    CAUCHY_MIN_FRACTION,
    LOST_TO_OUTLIERS_REASON,
    UNFIXED_REASON,
    UNRELIABLE_REASON,
    images_per_target,
    mean_redundancy,
    shift_over_sigma,
    targets_extent,
    targets_off_prior_statistics,
    terms_to_drop,
    unfixed_targets,
    unreliable_targets,
    weak_targets,
)
from .correct import blunders, train_correction
from .diagnose import undetermined_targets
from .graph import (
    BundleProblem,
    Datum,
    Loss,
    NoiseOptions,
    extrinsics_key,
    frame_key,
    intersection_sigma,
    intrinsics_key,
    observation_redundancy,
    point_key,
    pose_key,
    robust_sigma_px,
    target_covariances,
)
from .optimize import (
    OptimizationResult,
    OptimizerOptions,
    make_ordering,
    marginal_covariances,
    optimize,
)

Pose = tuple[np.ndarray, np.ndarray]

#: robust stages (Huber, each camera's sigma re-estimated) at most; a camera whose scale
#: still changes by 5 % after them is not trusted (4 until session 24: a narrow camera's
#: scale converging geometrically, 0.27, 0.21, 0.18, 0.17 px, settled at the 5th)
MAX_STAGES = 8
#: a camera's robust scale that returns to within this fraction of its estimate two
#: stages before, and alternates by at most :data:`ALTERNATION_SPAN` of the smaller
#: value, has settled on a two-cycle of the reweighting: the larger scale is kept (a
#: free mixed rig, 6 frames, seed 4: the pinhole's 0.3084 and 0.2906 px to the last stage,
#: refused as unsettled, its cam_from_rig within 1 sigma)
ALTERNATION_RTOL = 0.005
ALTERNATION_SPAN = 0.15
#: smallest robust scale, px (as the single-camera stages)
MIN_SIGMA_PX = 0.005
#: a camera's terms are chosen again in the joint graph (``reselect_terms``) only with at
#: least this many of its observations per intrinsic of the full set: a seeded pinhole
#: with 20 observations in 4 images, given 13 intrinsics, fitted them exactly and its
#: robust scale fell to the floor (0.23 -> 0.005 px), its cam_from_rig 5 sigmas off
RESELECT_OBS_PER_TERM = 10
#: a camera of ``reselect_if_misfit`` (seeded on approximate targets) whose robust scale
#: in the joint graph exceeds this times the largest of the other cameras' has its terms
#: chosen again (:func:`misfitting_cameras`). A free mixed rig, 6 frames, seed 19: the
#: pinhole (189 observations of 166 targets) was seeded, its targets at 1 % of their
#: extent absorbed its barrel distortion and term selection dropped every radial term;
#: jointly its scale was 0.444 px against the fisheye's 0.304 px, and its cam_from_rig 9
#: mm off along its axis at 3.6 reported sigma, trusted. Chosen again: 1.2 sigma. The
#: other seeded pinholes of seeds 0-19 were at 0.45-1.16 times the fisheye's scale (seed
#: 3, 1.16, refused when chosen again: 7 of its 165 observations left carrying the noise)
MISFIT_SCALE_RATIO = 1.3


def misfitting_cameras(sigma_px: dict[str, float], candidates: dict) -> list[str]:
    """The cameras of ``candidates`` whose robust scale (``sigma_px``, px, per camera id)
    exceeds :data:`MISFIT_SCALE_RATIO` times the largest of the other cameras'."""
    out = []
    for cid in candidates:
        others = [v for c, v in sigma_px.items() if c != cid]
        if others and sigma_px[cid] > MISFIT_SCALE_RATIO * max(others):
            out.append(cid)
    return out


#: a camera with fewer observations of local redundancy at least
#: :data:`~gtsam_sphere.core.robust.MIN_REDUNDANCY` keeps its robust scale in the joint
#: stages (a seeded pinhole whose 165 observations mostly fixed their own targets: 7
#: such, and the re-estimates fell 0.23 -> 0.068 -> 0.0068 -> 0.005 px against 0.3 px
#: of noise), and the rig is not trusted (its fit cannot be checked)
MIN_REDUNDANT_OBSERVATIONS = 20


def held_corrections(model, uv_px: np.ndarray) -> np.ndarray:
    """A camera's own kNN corrections at its observations in the joint graph, (N, 2) px.

    At a pixel the model was trained on, its prediction without that training point
    (``predict_without_self``, as the grey-box loop's own rounds correct each
    observation); elsewhere ``predict``. With the point itself, a distance-weighted
    field returns the point's own residual (zero distance) and the joint graph fitted
    that camera's noise exactly: its residuals fell to 1e-4 px, its robust scale to the
    floor, while the other camera's grew (a free dual360 rig, 6 frames, seed 50; with
    uniform weights a 1/k share leaks in).

    Parameters
    ----------
    model : KNNCorrection
        The camera's fitted correction (``uv_px_``, ``predict_without_self``).
    uv_px : ndarray, shape (N, 2)
        The camera's observations (raw px).

    Returns
    -------
    ndarray, shape (N, 2)
    """
    uv = np.ascontiguousarray(uv_px, dtype=float).reshape(-1, 2)
    corr = np.asarray(model.predict(uv), float)
    train = getattr(model, "uv_px_", None)
    if train is None or not hasattr(model, "predict_without_self") or not len(uv):
        return corr
    index: dict[bytes, int] = {}
    for k, row in enumerate(np.ascontiguousarray(train, dtype=float)):
        index.setdefault(row.tobytes(), k)
    at = np.array([index.get(row.tobytes(), -1) for row in uv])
    if (at >= 0).any():
        corr[at >= 0] = np.asarray(model.predict_without_self(), float)[at[at >= 0]]
    return corr


def start_sigma_px(calibs: dict[str, Calibration], ids: list[str]) -> dict[str, float]:
    """Each camera's robust scale (px) to start the joint adjustment from.

    Its own calibration's ``sigma_px``, unless that calibration had no redundancy (an
    RMS below :data:`MIN_SIGMA_PX`: its images fitted exactly, the scale at the floor
    while the pixels have noise); such a camera starts from the median scale of the
    cameras that had some. From the floor the joint stages' re-estimates creep (a
    60 deg pinhole of a mixed rig, free targets, 6 frames, calibrated alone on the
    only 2 of its images that shared targets: 0.011, 0.023, 0.031, 0.037 px in 4
    stages against 0.3 px of noise), and its cam_from_rig sigma was 5.6 times too
    small. When no camera had redundancy (noise-free data), each keeps its own.

    Parameters
    ----------
    calibs : dict of str -> Calibration
        Each camera's own calibration (``statistics["sigma_px"]``, ``["rms_px"]``).
    ids : list of str
        The cameras.

    Returns
    -------
    dict of str -> float
    """
    own = {c: float(calibs[c].statistics.get("sigma_px", 1.0)) for c in ids}
    exact = {c for c in ids if float(calibs[c].statistics.get("rms_px", 1.0)) < MIN_SIGMA_PX}
    others = [own[c] for c in ids if c not in exact]
    if not exact or not others:
        return own
    fill = float(np.median(others))
    return {c: (fill if c in exact else own[c]) for c in ids}


def _reselect_terms(
    reselect: dict,
    problems: dict[str, BundleProblem],
    joint_camera: dict[str, SphereCamera],
    build: Callable[[], gtsam.NonlinearFactorGraph],
    values: gtsam.Values,
    ids: list[str],
    say: Callable[[str], None],
) -> gtsam.Values | None:
    """Drop, for each camera of ``reselect``, the terms the joint graph does not support.

    The Wald test with a BIC penalty of the single camera
    (:func:`.calibrate.terms_to_drop`) on the joint marginal covariance of the camera's
    intrinsics, its degrees of freedom the redundancy of its observations in the joint
    graph. ``problems`` and ``joint_camera`` are updated in place.

    Returns
    -------
    gtsam.Values or None
        ``values`` with the reduced intrinsics vectors, or None when nothing is dropped
        (or the covariance is singular).
    """
    keys = {cid: intrinsics_key(ids.index(cid)) for cid in reselect}
    marginal = marginal_covariances(build(), values, list(keys.values()))
    if marginal is None:
        say("[rig] no covariance of the intrinsics: the term sets are kept")
        return None
    redundancy = rig_redundancy(problems, values)
    out = gtsam.Values(values)
    changed = False
    for cid, key in keys.items():
        p = problems[cid]
        names = list(p.intrinsics_names())
        theta = np.asarray(values.atVector(key), float)
        drop = terms_to_drop(
            theta,
            marginal[key],
            names,
            p.radial_names or (),
            p.brown_names,
            len(p.uv_px),
            float(np.sum(redundancy[cid])),
        )
        if not drop:
            continue
        keep = [k for k, n in enumerate(names) if n not in drop]
        radial = tuple(n for n in (p.radial_names or ()) if n not in drop)
        brown = tuple(n for n in p.brown_names if n not in drop)
        problems[cid] = replace(p, radial_names=radial, brown_names=brown)
        joint_camera[cid] = with_terms(joint_camera[cid], radial, brown)
        out.update(key, theta[keep])
        changed = True
        say(f"[rig] camera {cid}: terms the joint data do not support: {', '.join(drop)}")
    return out if changed else None


def _gtsam_pose(pose: Pose) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3(np.asarray(pose[0], float)), np.asarray(pose[1], float))


def _pose(p: gtsam.Pose3) -> Pose:
    return np.asarray(p.rotation().matrix()), np.asarray(p.translation())


def theta_of(camera: SphereCamera) -> tuple[np.ndarray, tuple[str, ...] | None, tuple[str, ...]]:
    """The intrinsics vector of ``camera`` in the graph's layout, its radial and Brown names
    (the radial mapping's fixed warp ``w`` is not in the vector: :func:`warp_of`)."""
    radial_names = (
        None if camera.radial is None else tuple(n for n in camera.radial if n != WARP_TERM)
    )
    brown_names = tuple(camera.brown)
    theta = [camera.xp, camera.yp, camera.c]
    theta += [camera.radial[n] for n in radial_names or ()]
    theta += [camera.brown[n] for n in brown_names]
    return np.asarray(theta, float), radial_names, brown_names


def camera_with_theta(camera: SphereCamera, theta: np.ndarray) -> SphereCamera:
    """``camera`` with the intrinsics ``theta`` (same layout as :func:`theta_of`)."""
    _, radial_names, brown_names = theta_of(camera)
    g = len(radial_names or ())
    radial = None
    if radial_names is not None:
        radial = dict(zip(radial_names, map(float, theta[3 : 3 + g])))
        if warp_of(camera) is not None:
            radial[WARP_TERM] = warp_of(camera)
    return replace(
        camera,
        xp=float(theta[0]),
        yp=float(theta[1]),
        c=float(theta[2]),
        radial=radial,
        brown=dict(zip(brown_names, map(float, theta[3 + g :]))),
    )


def with_terms(
    camera: SphereCamera, radial_names: tuple[str, ...], brown_names: tuple[str, ...]
) -> SphereCamera:
    """``camera`` with the radial terms ``radial_names`` and the Brown terms
    ``brown_names`` (in that order): its own values where it has them, 0 elsewhere; the
    warp kept. Only for a camera with a radial mapping."""
    radial = {n: float(camera.radial.get(n, 0.0)) for n in radial_names}
    if warp_of(camera) is not None:
        radial[WARP_TERM] = warp_of(camera)
    brown = {n: float(camera.brown.get(n, 0.0)) for n in brown_names}
    return replace(camera, radial=radial, brown=brown)


def warp_of(camera: SphereCamera) -> float | None:
    """The fixed warp ``w`` of ``camera``'s radial mapping, or None."""
    if camera.radial is None or WARP_TERM not in camera.radial:
        return None
    return float(camera.radial[WARP_TERM])


def cam_from_rig_covariance(rig_from_cam: gtsam.Pose3, cov: np.ndarray) -> np.ndarray:
    """Covariance of ``cam_from_rig`` from that of its inverse's right perturbation.

    ``rig_from_cam * exp([w, v])`` is ``exp(-[w, v]) * cam_from_rig``: to first order
    the rotation of ``cam_from_rig = (R, t)`` turns by ``-w`` (camera axes) and ``t``
    moves by ``[t]x w - v``.

    Returns
    -------
    ndarray, shape (6, 6)
        Covariance of ``[rotation (rad, camera axes), t (dataset units)]``.
    """
    t = -rig_from_cam.rotation().matrix().T @ rig_from_cam.translation()  # cam_from_rig t
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    J = np.block([[-np.eye(3), np.zeros((3, 3))], [tx, -np.eye(3)]])
    return J @ cov @ J.T


@dataclass
class JointRigResult:
    """Outcome of :func:`adjust_rig_jointly` (poses in the files' convention).

    Attributes
    ----------
    cam_from_rig : dict of str -> (R, t)
    rig_from_world : dict of str -> (R, t)
        Per frame id.
    cam_from_world : dict of str -> (R, t)
        Per image id (framed images: ``cam_from_rig * rig_from_world``).
    target_xyz : dict of str -> ndarray (3,)
    cameras : dict of str -> SphereCamera
        The jointly adjusted intrinsics, each with its camera's kNN correction.
    residuals_px : dict of str -> ndarray (N_c, 2)
        Raw-pixel residuals of each camera's observations (its calibration's order).
    weights : dict of str -> ndarray (N_c,)
        Final robust weights.
    sigma_px : dict of str -> float
        Final robust scale per camera (corrected coordinates).
    cam_from_rig_covariance : dict of str -> ndarray (6, 6) or None
        Marginal covariance of ``[rotation (rad, camera axes), t]`` of each camera but
        the first, times ``max(1, variance_factor)``; None when the system is singular.
    intrinsics_sigma : dict of str -> dict or None
    result : OptimizationResult
        Of the last stage; ``history`` spans every stage.
    stages : int
        Robust stages run.
    datum : str
        ``"control"`` or ``"free"`` (:class:`Datum`).
    variance_factor : float
        A-posteriori variance factor ``sum(w (e / sigma)^2) / redundancy``.
    redundancy : int
        ``2 N + 3 (weighted targets) + 7 (free network) - unknowns``.
    mean_redundancy : float
        ``redundancy / (2 N + 3 (weighted targets))``, the mean redundancy number
        (:func:`~gtsam_sphere.estimation.calibrate.mean_redundancy`).
    target_shifts : dict
        How far the joint adjustment moved the targets with a prior, in sigmas of it
        (:func:`~gtsam_sphere.estimation.calibrate.targets_off_prior_statistics`; empty
        without such targets).
    notes : list of str
        What the adjustment left out or could not compute (no covariance).
    undetermined_targets : list of str
        Targets without a sigma seen in fewer than two images once the outliers are set
        aside, or whose rays do not fix them (intersection sigma infinite or beyond the
        targets' extent, :func:`~gtsam_sphere.estimation.calibrate.unfixed_targets`);
        not in ``target_xyz``.
    undetermined_reasons : dict of str -> str
        Why, per undetermined target (``calibrate.LOST_TO_OUTLIERS_REASON`` or
        ``calibrate.UNFIXED_REASON``).
    target_precision : dict
        ``target`` (ids), ``intersection_sigma`` (dataset units, over every camera
        that sees the target, poses and lenses held: a lower bound) and ``weak`` (above
        ``weak_target_limit``, 2 % of the targets' extent).
    weak_target_limit : float
    max_incidence_deg : dict of str -> float
        Widest incidence angle (deg) of each camera's observations in the joint graph
        (the field its jointly adjusted mapping must not fold in).
    loss : str
        The last stage's loss: ``"huber"``, or ``"cauchy"`` when gross outliers were
        left (:data:`~gtsam_sphere.estimation.calibrate.CAUCHY_MIN_FRACTION`).
    unsettled_scales : list of str
        Cameras whose robust scale still changed by more than 5 % in the last of
        :data:`MAX_STAGES` robust stages, or fell to :data:`MIN_SIGMA_PX` from a start
        above 10 times it (their observations fitted exactly): their weights, and the
        precision computed with them, are not reliable.
    unestimated_scales : dict of str -> int
        Cameras whose robust scale the last stage could not estimate, with the number
        of their observations of local redundancy at least ``MIN_REDUNDANCY`` (fewer
        than :data:`MIN_REDUNDANT_OBSERVATIONS`: their targets rest on their own rays);
        their scale was held, and their fit cannot be checked.
    n_outliers : dict of str -> int
        Each camera's observations beyond 5 of its sigmas in the final graph and not
        consistent with their neighbours (:func:`~gtsam_sphere.estimation.correct.blunders`,
        the single camera's ``n_outliers``).
    """

    cam_from_rig: dict[str, Pose]
    rig_from_world: dict[str, Pose]
    cam_from_world: dict[str, Pose]
    target_xyz: dict[str, np.ndarray]
    cameras: dict[str, SphereCamera]
    residuals_px: dict[str, np.ndarray]
    weights: dict[str, np.ndarray]
    sigma_px: dict[str, float]
    cam_from_rig_covariance: dict[str, np.ndarray | None]
    intrinsics_sigma: dict[str, dict | None]
    result: OptimizationResult
    stages: int = 0
    datum: str = ""
    variance_factor: float = float("nan")
    redundancy: int = 0
    mean_redundancy: float = float("nan")
    target_shifts: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    unsettled_scales: list[str] = field(default_factory=list)
    n_outliers: dict[str, int] = field(default_factory=dict)
    unestimated_scales: dict[str, int] = field(default_factory=dict)
    undetermined_targets: list[str] = field(default_factory=list)
    max_incidence_deg: dict[str, float] = field(default_factory=dict)
    loss: str = "huber"
    undetermined_reasons: dict[str, str] = field(default_factory=dict)
    target_precision: dict = field(default_factory=dict)
    weak_target_limit: float = 0.0


def _weighted_ss(problems: dict, values: gtsam.Values, loss: Loss, threshold: float) -> float:
    """Sum over every camera of the robustly weighted squared standardised residuals."""
    total = 0.0
    for p in problems.values():
        r = np.linalg.norm(p.residuals_px(values), axis=1) / p.noise.sigma_px
        w, _ = robust_weight(r, loss, threshold)
        total += float(np.sum(w * r * r))
    return total


def precision_from_covariance(cov: np.ndarray, t: np.ndarray) -> dict:
    """Standard deviations of ``cam_from_rig`` from its covariance (:class:`JointRigResult`).

    Returns
    -------
    dict
        ``rotation_sigma_deg`` (the RMS length of the 3-D rotation error, deg),
        ``rotation_sigma_deg_axes`` (3,) (about the camera's axes), ``translation_sigma``
        (3,) (dataset units), ``baseline_sigma`` (of ``|t|``), ``covariance`` (6, 6).
    """
    var_rot = np.diag(cov)[:3]
    u = t / max(float(np.linalg.norm(t)), 1e-300)
    return {
        "rotation_sigma_deg": float(np.degrees(np.sqrt(np.sum(var_rot)))),
        "rotation_sigma_deg_axes": np.degrees(np.sqrt(var_rot)),
        "translation_sigma": np.sqrt(np.diag(cov)[3:]),
        "baseline_sigma": float(np.sqrt(u @ cov[3:, 3:] @ u)),
        "covariance": cov,
    }


def rig_target_covariances(
    problems: dict[str, BundleProblem],
    values: gtsam.Values,
    weights: dict[str, np.ndarray],
    held_intrinsics: set[str],
    held_extrinsics: bool,
    datum_xyz: np.ndarray | None = None,
    datum_points: np.ndarray | None = None,
) -> np.ndarray | None:
    """Marginal covariance of every target of the joint graph, (T, 3, 3) or None.

    :func:`~gtsam_sphere.estimation.graph.target_covariances` with the rig's
    camera-side unknowns: each frame's (or unframed image's) pose, each camera's
    ``rig_from_cam`` (but the first's) and intrinsics, from every camera's analytic
    Jacobians. ``weights`` (N_c,) per camera, 1 / px^2; ``held_intrinsics`` the cameras
    whose intrinsics are held, ``held_extrinsics`` when ``cam_from_rig`` is; the datum
    arguments as there (a free network's S-transform).
    """
    ids = list(problems)
    per_cam, pose_keys, ext_keys = [], set(), set()
    for cid in ids:
        p = problems[cid]
        if not p.blocks or len(p.uv_px) == 0:
            continue
        jacobians = p.observation_jacobians(values)
        J, model = jacobians
        n_model = model.n_theta
        n_th = 0 if cid in held_intrinsics else n_model
        pk = np.asarray(p.image_pose_keys, np.int64)[p.obs_image]
        ek = np.full(len(pk), -1, np.int64)
        if p.image_extrinsic_keys is not None and not held_extrinsics:
            ek = np.asarray(p.image_extrinsic_keys, np.int64)[p.obs_image]
        J_ext = J[:, :, 9 + n_model : 15 + n_model]
        if model.k_ext is None:
            J_ext = np.zeros((len(pk), 2, 6))
        per_cam.append((cid, p, J, n_th, pk, ek, J_ext, p.target_jacobians(values, jacobians)))
        pose_keys.update(pk.tolist())
        ext_keys.update(ek[ek >= 0].tolist())
    if not per_cam:
        return None
    column = {k: 6 * i for i, k in enumerate(sorted(pose_keys))}
    offset = 6 * len(column)
    for k in sorted(ext_keys):
        column[k] = offset
        offset += 6
    theta_at = {}
    for cid, _, _, n_th, _, _, _, _ in per_cam:
        theta_at[cid] = offset
        offset += n_th
    width = max(12 + n_th for _, _, _, n_th, _, _, _, _ in per_cam)
    J_t, J_c, cols, obs, w = [], [], [], [], []
    for cid, p, J, n_th, pk, ek, J_ext, J_target in per_cam:
        n = len(pk)
        c = np.full((n, width), -1, np.intp)
        jc = np.zeros((n, 2, width))
        c[:, 0:6] = np.array([column[k] for k in pk.tolist()])[:, None] + np.arange(6)
        jc[:, :, 0:6] = J[:, :, 0:6]
        c[:, 6 : 6 + n_th] = theta_at[cid] + np.arange(n_th)
        jc[:, :, 6 : 6 + n_th] = J[:, :, 9 : 9 + n_th]
        has = ek >= 0
        if has.any():
            starts = np.array([column.get(k, -1) for k in ek.tolist()])
            c[has, 6 + n_th : 12 + n_th] = starts[has, None] + np.arange(6)
            jc[has, :, 6 + n_th : 12 + n_th] = J_ext[has]
        J_t.append(J_target)
        J_c.append(jc)
        cols.append(c)
        obs.append(p.obs_target)
        w.append(np.asarray(weights[cid], float))
    return target_covariances(
        np.concatenate(J_t),
        np.concatenate(J_c),
        np.concatenate(cols),
        offset,
        np.concatenate(obs),
        np.concatenate(w),
        per_cam[0][1].target_sigma,
        datum_xyz,
        datum_points,
    )


def rig_redundancy(problems: dict[str, BundleProblem], values: gtsam.Values) -> dict:
    """Local redundancy (0 to 2) of every camera's observations, (N_c,) per camera.

    As :meth:`BundleProblem.observation_redundancy`, with the information of a target
    summed over every camera that sees it (the cameras' problems index the rig's
    targets alike), each observation weighted by its camera's current ``sigma_px``.
    """
    ids = list(problems)
    if not ids:
        return {}
    J = [problems[c].target_jacobians(values) for c in ids]
    sig = [np.full(len(problems[c].uv_px), problems[c].noise.sigma_px) for c in ids]
    red = observation_redundancy(
        np.concatenate(J),
        np.concatenate([problems[c].obs_target for c in ids]),
        np.concatenate(sig),
        problems[ids[0]].target_sigma,
    )
    bounds = np.cumsum([0] + [len(s) for s in sig])
    return {c: red[bounds[k] : bounds[k + 1]] for k, c in enumerate(ids)}


#: a camera's observations its own adjustment left out that the joint graph takes back:
#: targets it could not determine (``calibrate.without_undetermined_targets``) and the
#: images outside its largest connected group (:func:`.rig.largest_connected_part`)
HELD_FOR_THE_RIG = ("undetermined_observations", "joint_only_observations")


def _with_undetermined(extra: dict) -> dict:
    """A calibration's observations (``extra["observations"]``: ``image``, ``target``,
    ``uv_px``) followed by those it left out as not determined
    (``extra["undetermined_observations"]``) and those of its images that only the
    rig holds (``extra["joint_only_observations"]``, :func:`.rig.largest_connected_part`).
    """
    out = extra["observations"]
    for name in HELD_FOR_THE_RIG:
        more = extra.get(name)
        if not more or not len(more["image"]):
            continue
        out = {
            "image": list(out["image"]) + list(more["image"]),
            "target": list(out["target"]) + list(more["target"]),
            "uv_px": np.concatenate(
                [np.asarray(out["uv_px"], float).reshape(-1, 2), np.asarray(more["uv_px"], float)]
            ),
        }
    return out


def joint_images(calib: Calibration, frame_of: dict[str, str | None], frames) -> list[str]:
    """A camera's images in the joint graph: those it calibrated alone, then those only
    the rig holds whose frame is posed (in ``frames``), in order of first observation:
    images its own adjustment left out for too few determined observations
    (``extra["undetermined_observations"]``) and images outside its largest connected
    group (``extra["joint_only_observations"]``)."""
    out = list(calib.image_ids)
    seen = set(out)
    for name in HELD_FOR_THE_RIG:
        for iid in (calib.extra.get(name) or {}).get("image", []):
            if iid not in seen and frame_of.get(iid) in frames:
                seen.add(iid)
                out.append(iid)
    return out


def adjust_rig_jointly(
    rig: RigDataset,
    calibs: dict[str, Calibration],
    cam_from_rig: dict[str, Pose],
    rig_from_world: dict[str, Pose],
    target_xyz: dict[str, np.ndarray],
    optimizer: OptimizerOptions | None = None,
    say: Callable[[str], None] | None = None,
    loss_threshold: float = 2.45,
    points_per_factor: int = 8,
    fixed_intrinsics: dict[str, np.ndarray] | None = None,
    fixed_extrinsics: bool = False,
    knn_rounds: int = 0,
    seed: int = 0,
    reselect_terms: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] | None = None,
    reselect_if_misfit: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] | None = None,
) -> JointRigResult:
    """Adjust a rig's frames, extrinsics, intrinsics and targets in one graph.

    Parameters
    ----------
    rig : RigDataset
    calibs : dict of str -> Calibration
        Each camera's own calibration (model, kNN correction, kept observations in
        ``extra["observations"]``, ``sigma_px``, ``control_sigma``, image poses).
    cam_from_rig, rig_from_world, target_xyz :
        The starting values (the averaged ones of :mod:`.rig`); every frame of a
        calibrated image must be in ``rig_from_world``.
    optimizer : OptimizerOptions
    say : callable(str)
    loss_threshold : float
        Huber threshold in units of each camera's sigma.
    points_per_factor : int
    fixed_intrinsics : dict of str -> ndarray, optional
        Cameras whose intrinsics are held (a tight prior), as ``fixed_intrinsics``.
    fixed_extrinsics : bool
        Hold every ``cam_from_rig`` at its starting value (a tight prior): only the
        frames, the unframed images, the targets and the free intrinsics move (the
        oracle of a simulated rig, :mod:`gtsam_sphere.simulate.oracle`). Their
        covariance is then ~0 and not reported.
    knn_rounds : int
        Rounds of re-learning the kNN correction of each camera that has one from its
        residuals in the joint graph (:func:`.correct.train_correction`, the
        grey-box loop's step), each followed by the robust stages again; stops early
        when no camera's RMS (within 5 sigma) changes by 2%. 0 (default): the
        per-camera corrections are held.
    seed : int
        Seed of the kNN cross-validation.
    reselect_terms : dict of str -> (radial names, Brown names), optional
        Cameras whose own calibration saw part of their data only (a split or seeded
        camera, :mod:`.rig`), or a narrower field (``rig._joint_widens``): after the
        first robust stages the joint graph gives them these terms (the ones their own
        run started with, those it dropped at 0), adjusts once at the settled scales,
        drops those the joint data do not support (:func:`.calibrate.terms_to_drop` on
        the joint covariance) and runs the robust stages again. A term set chosen
        on 2 of a narrow camera's 6 images dropped every radial term its Brown lens
        needed, and the joint graph, holding that set, placed it 6.8 reported sigmas
        from its true ``cam_from_rig`` (a free mixed rig, 6 frames, seed 50).
    reselect_if_misfit : dict of str -> (radial names, Brown names), optional
        Cameras whose term set stands unless the joint graph shows it misfits (a camera
        seeded on approximate targets, :mod:`.rig`): those whose robust scale after the
        first robust stages exceeds :data:`MISFIT_SCALE_RATIO` times the largest of the
        other cameras', join ``reselect_terms`` (:func:`misfitting_cameras`).

    Returns
    -------
    JointRigResult
    """
    say = say or (lambda _line: None)
    optimizer = optimizer or OptimizerOptions()
    ids = rig.camera_ids
    frame_of = dict(zip(rig.image_ids, rig.image_frame))
    t_index = {tid: j for j, tid in enumerate(rig.target_ids)}
    frames = list(rig_from_world)
    f_index = {f: k for k, f in enumerate(frames)}

    # target priors: the dataset's sigma; exact targets get the cameras' control sigma
    sigma = np.asarray(rig.target_sigma, float).copy()
    control = [calibs[c].statistics.get("control_sigma") for c in ids]
    control = [float(s) for s in control if s is not None]
    if control:
        sigma = np.where(sigma == 0, float(np.median(control)), sigma)

    values = gtsam.Values()
    for f, k in f_index.items():
        values.insert(frame_key(k), _gtsam_pose(rig_from_world[f]).inverse())
    for c, cid in enumerate(ids):
        if c > 0:
            values.insert(extrinsics_key(c), _gtsam_pose(cam_from_rig[cid]).inverse())

    problems: dict[str, BundleProblem] = {}
    raw_uv: dict[str, np.ndarray] = {}
    kept: dict[str, np.ndarray] = {}
    all_targets, own_poses = [], []
    image_global = {iid: g for g, iid in enumerate(rig.image_ids)}
    # each camera's observations, with those its own calibration left out as not
    # determined (calibrate.without_undetermined_targets): another camera may see them
    obs_of = {cid: _with_undetermined(calibs[cid].extra) for cid in ids}
    images_of = {cid: joint_images(calibs[cid], frame_of, f_index) for cid in ids}
    # an image only the rig holds whose frame no other camera posed stays out
    posed = {cid: np.isin(obs_of[cid]["image"], images_of[cid]) for cid in ids}
    # targets without a sigma seen in fewer than two images (of any camera) are not
    # determined: their observations stay out of the graph
    undetermined = undetermined_targets(
        [image_global[i] for cid in ids for i, ok in zip(obs_of[cid]["image"], posed[cid]) if ok],
        [t_index[tg] for cid in ids for tg, ok in zip(obs_of[cid]["target"], posed[cid]) if ok],
        sigma,
    )
    start_sigma = start_sigma_px(calibs, ids)
    reselect_terms, reselect_if_misfit = (
        {
            cid: terms
            for cid, terms in (given or {}).items()
            if calibs[cid].camera.radial is not None
            and not (fixed_intrinsics and cid in fixed_intrinsics)
        }
        for given in (reselect_terms, reselect_if_misfit)
    )
    joint_camera = {cid: calibs[cid].camera for cid in ids}
    for c, cid in enumerate(ids):
        calib = calibs[cid]
        obs = obs_of[cid]
        local = {iid: k for k, iid in enumerate(images_of[cid])}
        obs_target = np.array([t_index[tg] for tg in obs["target"]], int)
        keep = ~undetermined[obs_target] & posed[cid]
        kept[cid] = keep
        obs_target = obs_target[keep]
        obs_image = np.array([local.get(i, -1) for i in obs["image"]], int)[keep]
        uv = np.asarray(obs["uv_px"], float).reshape(-1, 2)[keep]
        camera = joint_camera[cid]
        corr = np.zeros_like(uv)
        if camera.correction is not None and len(uv):
            corr = held_corrections(camera.correction, uv)
        pose_keys, ext_keys = [], []
        own_R = dict(zip(calib.image_ids, calib.cam_from_world_R))
        own_t = dict(zip(calib.image_ids, calib.cam_from_world_t))
        for iid in images_of[cid]:
            f = frame_of.get(iid)
            R, t = own_R.get(iid), own_t.get(iid)
            if f is None:
                key = pose_key(image_global[iid])
                own_poses.append(key)
                values.insert(key, _gtsam_pose((R, t)).inverse())
                pose_keys.append(key)
                ext_keys.append(-1)
            else:
                pose_keys.append(frame_key(f_index[f]))
                ext_keys.append(extrinsics_key(c) if c > 0 else -1)
        theta, radial_names, brown_names = theta_of(camera)
        values.insert(intrinsics_key(c), theta)
        problems[cid] = BundleProblem(
            obs_image=obs_image,
            obs_target=obs_target,
            uv_px=uv,
            target_xyz=np.asarray(rig.target_xyz, float),
            target_sigma=sigma,
            n_images=len(images_of[cid]),
            brown_names=brown_names,
            brown_scale_px=camera.brown_scale_px,
            noise=NoiseOptions(start_sigma[cid], Loss.HUBER, loss_threshold),
            points_per_factor=points_per_factor,
            corrections_px=corr,
            radial_names=radial_names,
            radial_warp=warp_of(camera),
            image_pose_keys=np.array(pose_keys, np.int64),
            image_extrinsic_keys=np.array(ext_keys, np.int64),
            intrinsics_key=intrinsics_key(c),
        )
        raw_uv[cid] = uv
        all_targets.append(obs_target)

    # priors and datum once for the whole rig (the single-camera graph's rules)
    obs_target = np.concatenate(all_targets)
    datum_problem = BundleProblem(
        obs_image=np.zeros(len(obs_target), int),
        obs_target=obs_target,
        uv_px=np.zeros((len(obs_target), 2)),
        target_xyz=np.asarray(rig.target_xyz, float),
        target_sigma=sigma,
        n_images=1,
    )
    free = datum_problem.free_targets
    xyz0 = np.asarray(rig.target_xyz, float).copy()
    for j in free:
        xyz0[j] = target_xyz.get(rig.target_ids[j], xyz0[j])
        values.insert(point_key(int(j)), np.asarray(xyz0[j], float))

    def build() -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        for p in problems.values():
            for factor in p.observation_factors():
                graph.add(factor)
        datum_problem.add_priors(graph)
        for c, cid in enumerate(ids):
            if fixed_intrinsics and cid in fixed_intrinsics:
                theta = np.asarray(fixed_intrinsics[cid], float)
                noise = gtsam.noiseModel.Isotropic.Sigma(len(theta), 1e-9)
                graph.add(gtsam.PriorFactorVector(intrinsics_key(c), theta, noise))
            if fixed_extrinsics and c > 0:
                graph.add(
                    gtsam.PriorFactorPose3(
                        extrinsics_key(c),
                        _gtsam_pose(cam_from_rig[cid]).inverse(),
                        gtsam.noiseModel.Isotropic.Sigma(6, 1e-9),
                    )
                )
        return graph

    ordering = make_ordering(
        [point_key(int(j)) for j in free],
        [frame_key(k) for k in range(len(frames))] + own_poses,
        [extrinsics_key(c) for c in range(1, len(ids))]
        + [intrinsics_key(c) for c in range(len(ids))],
    )
    notes: list[str] = []
    if undetermined.any():
        notes.append(
            f"{int(undetermined.sum())} targets without a sigma seen in one image only "
            "left out (not determined)"
        )
    say(
        f"joint rig adjustment: {len(frames)} frames, {len(own_poses)} unframed images, "
        f"{len(free)} free targets, {len(obs_target)} observations, datum "
        f"{datum_problem.datum.value}"
    )
    history: list[dict] = []
    result = None
    stage = 0

    unsettled: set[str] = set()
    held: dict[str, int] = {}

    alternated: dict[str, tuple[float, float]] = {}

    def robust_stages(start: gtsam.Values) -> OptimizationResult:
        nonlocal stage
        out = None
        unsettled.clear()
        alternated.clear()
        estimates: dict[str, list[float]] = {cid: [] for cid in problems}
        for _ in range(MAX_STAGES):
            stage += 1
            graph = build()
            out = optimize(
                graph, start if out is None else out.values, optimizer, ordering, say, "[rig] "
            )
            offset = history[-1]["iteration"] + 1 if history else 0
            history.extend(
                dict(h, iteration=h["iteration"] + offset, stage=stage) for h in out.history
            )
            unsettled.clear()
            held.clear()
            redundancy = rig_redundancy(problems, out.values)
            for cid, p in problems.items():
                r = np.linalg.norm(p.residuals_px(out.values), axis=1)
                red = redundancy[cid]
                usable = int(np.sum(np.isfinite(red) & (red >= MIN_REDUNDANCY)))
                old = p.noise.sigma_px
                if usable < MIN_REDUNDANT_OBSERVATIONS and len(r):
                    # its observations dominate their targets: too few carry the noise
                    # to scale it, and the plain median of the rest runs to the floor
                    held[cid] = usable
                    continue
                new = robust_sigma_px(r, MIN_SIGMA_PX, red)
                estimates[cid].append(new)
                if abs(new - old) > 0.05 * old:
                    two_ago = estimates[cid][-3] if len(estimates[cid]) >= 3 else None
                    if (
                        two_ago is not None
                        and abs(new - two_ago) <= ALTERNATION_RTOL * two_ago
                        and abs(new - old) <= ALTERNATION_SPAN * min(new, old)
                    ):
                        # a two-cycle: the reweighting alternates between two scales;
                        # the larger is kept (its weights the more cautious), after one
                        # more stage when the last one ran at the smaller
                        alternated[cid] = (min(new, old), max(new, old))
                        if new > old:
                            unsettled.add(cid)
                            p.noise = NoiseOptions(new, Loss.HUBER, loss_threshold)
                        continue
                    unsettled.add(cid)
                p.noise = NoiseOptions(new, Loss.HUBER, loss_threshold)
            changed = bool(unsettled)
            say(
                "[rig] robust scale per camera: "
                + ", ".join(f"{cid} {p.noise.sigma_px:.4f} px" for cid, p in problems.items())
            )
            if not changed:
                break
        return out

    def inlier_rms(p: BundleProblem, vals: gtsam.Values) -> float:
        r = np.linalg.norm(p.residuals_px(vals), axis=1)
        keep = r < 5.0 * p.noise.sigma_px
        return float(np.sqrt(np.mean(r[keep] ** 2))) if keep.any() else float("nan")

    result = robust_stages(values)
    misfit = misfitting_cameras(
        {cid: p.noise.sigma_px for cid, p in problems.items()}, reselect_if_misfit
    )
    for cid in misfit:
        reselect_terms[cid] = reselect_if_misfit[cid]
    reselect_terms = {
        cid: terms
        for cid, terms in reselect_terms.items()
        if len(problems[cid].uv_px) >= RESELECT_OBS_PER_TERM * (3 + len(terms[0]) + len(terms[1]))
    }
    for cid in misfit:
        say(
            f"[rig] camera {cid}: its robust scale in the joint graph, "
            f"{problems[cid].noise.sigma_px:.4f} px, is above {MISFIT_SCALE_RATIO:g} times "
            "the other cameras': its term set, chosen with its targets held only near "
            "their approximate coordinates, "
            + (
                "is chosen again"
                if cid in reselect_terms
                else "stands (too few observations to choose it again)"
            )
        )
    if reselect_terms:
        # the full term set, adjusted once at the scales just settled (re-estimated
        # with terms the data may not support, a camera's scale fell to the floor or
        # oscillated), then the Wald test, then the robust stages with what is kept
        expanded = gtsam.Values(result.values)
        for cid, (radial, brown) in reselect_terms.items():
            key = intrinsics_key(ids.index(cid))
            camera = camera_with_theta(joint_camera[cid], result.values.atVector(key))
            joint_camera[cid] = with_terms(camera, radial, brown)
            theta, radial_names, brown_names = theta_of(joint_camera[cid])
            problems[cid] = replace(
                problems[cid], radial_names=radial_names, brown_names=brown_names
            )
            expanded.update(key, theta)
        say(
            "[rig] the terms of "
            + ", ".join(reselect_terms)
            + " chosen again in the joint graph (their own calibration saw part of their data "
            "or of their field)"
        )
        stage += 1
        full = optimize(build(), expanded, optimizer, ordering, say, "[rig] ")
        offset = history[-1]["iteration"] + 1 if history else 0
        history.extend(
            dict(h, iteration=h["iteration"] + offset, stage=stage) for h in full.history
        )
        reduced = _reselect_terms(
            reselect_terms, problems, joint_camera, build, full.values, ids, say
        )
        result = robust_stages(full.values if reduced is None else reduced)
    models: dict[str, object] = {}
    learners = [cid for cid in ids if calibs[cid].camera.correction is not None]
    for rnd in range(1, int(knn_rounds) + 1 if learners else 1):
        before = {cid: inlier_rms(problems[cid], result.values) for cid in learners}
        for cid in learners:
            p = problems[cid]
            if len(p.uv_px) == 0:
                continue
            parametric = p.radial_names is not None or bool(p.brown_names)
            target = p.corrections_px + p.residuals_px(result.values)
            models[cid], p.corrections_px, _ = train_correction(
                p.uv_px, target, seed, 0 if parametric else None
            )
        result = robust_stages(result.values)
        after = {cid: inlier_rms(problems[cid], result.values) for cid in learners}
        say(
            f"[rig] kNN round {rnd} in the joint graph: RMS within 5 sigma "
            + ", ".join(f"{cid} {before[cid]:.4f} -> {after[cid]:.4f} px" for cid in learners)
        )
        if all(abs(after[c] - before[c]) <= 0.02 * before[c] for c in learners):
            break
    # gross outliers left: a last stage with Cauchy's redescending influence, from the
    # Huber solution (the single camera's rule, calibrate.adjust). Huber bounds a
    # blunder's pull but keeps it: with 3 % blunders of 30-300 px, a weighted ring of
    # four cameras, 8 frames, kept 14-28 mm check-point RMSE against 3-4 mm free
    loss = Loss.HUBER
    n_obs_all = sum(len(p.uv_px) for p in problems.values())
    n_gross = sum(
        int(np.sum(np.linalg.norm(p.residuals_px(result.values), axis=1) > 10 * p.noise.sigma_px))
        for p in problems.values()
    )
    huber_ss = None
    if n_gross and n_gross >= CAUCHY_MIN_FRACTION * n_obs_all:
        say(f"[rig] {n_gross} observations beyond 10 sigma: final stage with Cauchy")
        huber_ss = _weighted_ss(problems, result.values, Loss.HUBER, loss_threshold)
        loss = Loss.CAUCHY
        for p in problems.values():
            p.noise = NoiseOptions(p.noise.sigma_px, loss, loss_threshold)
        stage += 1
        last = optimize(build(), result.values, optimizer, ordering, say, "[rig] ")
        offset = history[-1]["iteration"] + 1 if history else 0
        history.extend(
            dict(h, iteration=h["iteration"] + offset, stage=stage) for h in last.history
        )
        result = last
    result.history = history
    final = result.values

    # precision: the final, robustly weighted graph at the solution, scaled by the
    # a-posteriori variance factor when it exceeds 1 (errors the model does not hold)
    graph = build()
    weighted_ss = _weighted_ss(problems, final, loss, loss_threshold)
    sig_free = sigma[free]
    n_priors = int(np.sum(np.isfinite(sig_free) & (sig_free > 0)))
    n_theta = sum(
        len(p.intrinsics_names())
        for cid, p in problems.items()
        if not (fixed_intrinsics and cid in fixed_intrinsics)
    )
    n_ext = 0 if fixed_extrinsics else len(ids) - 1
    n_unknowns = 6 * (len(frames) + len(own_poses) + n_ext) + 3 * len(free) + n_theta
    redundancy = (
        2 * len(obs_target) + 3 * n_priors + datum_problem.n_datum_constraints() - n_unknowns
    )
    variance_factor = weighted_ss / max(redundancy, 1)
    inflate = max(1.0, variance_factor)
    if huber_ss is not None:
        # the Cauchy stage takes the targets off the blunders' pull, but not always the
        # extrinsics (a weighted mixed rig of 6 frames, seed 7, 3 % blunders: 8.5 mm
        # off with Huber or Cauchy, 3.1 mm with the blunders removed; why is not known:
        # the per-camera stage the joint starts from, and holds the kNN field of, saw
        # them too); its own variance factor (0.54 there) would report 2.6 mm. The
        # precision keeps the Huber solution's inflation: pessimistic, not silent
        inflate = max(inflate, huber_ss / max(redundancy, 1))
    cov_ext: dict[str, np.ndarray | None] = dict.fromkeys(ids[1:])
    int_sigma: dict[str, dict | None] = dict.fromkeys(ids)
    wanted = [intrinsics_key(c) for c in range(len(ids))]
    if not fixed_extrinsics:
        wanted += [extrinsics_key(c) for c in range(1, len(ids))]
    marginal = marginal_covariances(graph, final, wanted)
    if marginal is None:
        notes.append("no covariance: the normal equations are singular")
    else:
        for c, cid in enumerate(ids):
            names = problems[cid].intrinsics_names()
            cov = inflate * marginal[intrinsics_key(c)]
            int_sigma[cid] = dict(zip(names, map(float, np.sqrt(np.diag(cov)))))
            if c > 0 and not fixed_extrinsics:
                cov = inflate * marginal[extrinsics_key(c)]
                cov_ext[cid] = cam_from_rig_covariance(final.atPose3(extrinsics_key(c)), cov)

    # targets without a sigma left on one ray once the outliers are set aside (the
    # single-camera rule, calibrate.targets_lost_to_outliers): not determined
    res_model_of = {cid: p.residuals_px(final) for cid, p in problems.items()}
    good_image, good_target, offset = [], [], 0
    J_all, w_all, w_of = [], [], {}
    n_outliers: dict[str, int] = {}
    for cid, p in problems.items():
        outlier = blunders(raw_uv[cid], res_model_of[cid], p.noise.sigma_px)
        n_outliers[cid] = int(outlier.sum())
        # an image per camera and image (two cameras of one frame see from two places)
        good_image.append(offset + p.obs_image[~outlier])
        good_target.append(p.obs_target[~outlier])
        offset += p.n_images
        r = np.linalg.norm(res_model_of[cid], axis=1) / p.noise.sigma_px
        w = robust_weight(r, loss, loss_threshold)[0] if len(r) else np.zeros(0)
        w_of[cid] = np.where(outlier, 0.0, w) / p.noise.sigma_px**2
        w_all.append(w_of[cid])
        J_all.append(p.target_jacobians(final))
    observed = np.bincount(obs_target, minlength=len(sigma)) > 0
    lost = undetermined_targets(np.concatenate(good_image), np.concatenate(good_target), sigma)
    lost &= observed
    reasons = dict.fromkeys(np.flatnonzero(lost).tolist(), LOST_TO_OUTLIERS_REASON)
    # each target's intersection sigma over every camera that sees it (poses and lenses
    # held; the single camera's rule, calibrate._result): rays that do not fix a target
    # (a stereo pair's two rays of one frame meeting 53 km away) leave it undetermined
    meet = intersection_sigma(np.concatenate(J_all), obs_target, np.concatenate(w_all), sigma)
    meet[np.isfinite(sigma) & (sigma == 0)] = 0.0
    xyz_solver = np.asarray(rig.target_xyz, float).copy()
    for j in free:
        xyz_solver[j] = final.atPoint3(point_key(int(j)))
    extent = targets_extent(xyz_solver[observed & ~lost])
    unfixed = unfixed_targets(meet, observed & ~lost & ~np.isfinite(sigma), extent)
    for j in np.flatnonzero(unfixed).tolist():
        reasons[j] = UNFIXED_REASON
    lost |= unfixed
    if lost.any():
        notes.append(
            f"{int(lost.sum())} targets without a sigma are not determined once the outliers "
            "are set aside (seen in fewer than two images, or rays that do not fix them): "
            "left out of the targets"
        )
    used = np.flatnonzero(observed & ~lost)
    # the full precision (poses, extrinsics and lenses estimated too), a free network's
    # in the datum of its similarity onto the approximate coordinates (below)
    datum_points = datum_sim = None
    if datum_problem.datum is Datum.FREE:
        # as the single-camera result: S-transformed onto the approximate coordinates,
        # a fit that targets drifted off along one ray cannot pull
        fit = free[~lost[free]] if np.sum(~lost[free]) >= 3 else free
        datum_sim, kept_fit = fit_similarity_trimmed(
            xyz_solver[fit], np.asarray(rig.target_xyz, float)[fit]
        )
        datum_points = fit[kept_fit]
    cov_t = rig_target_covariances(
        problems,
        final,
        w_of,
        set(fixed_intrinsics or ()),
        bool(fixed_extrinsics),
        xyz_solver,
        datum_points,
    )
    full = None
    if cov_t is not None:
        full = np.sqrt(np.maximum(np.linalg.eigvalsh(cov_t)[:, -1], 0.0))
        full[np.isfinite(sigma) & (sigma == 0)] = 0.0
    # targets that two rays place far from their approximate coordinates (the single
    # camera's rule, calibrate.unreliable_targets), in the approximate coordinates' datum
    to_datum = 1.0 if datum_sim is None else datum_sim.scale
    in_datum = xyz_solver.copy()
    if datum_sim is not None:
        in_datum[free] = datum_sim.apply(in_datum[free])
    misfit = np.linalg.norm(in_datum - np.asarray(rig.target_xyz, float), axis=1)
    good_image_all, good_target_all = np.concatenate(good_image), np.concatenate(good_target)
    unreliable, reference = unreliable_targets(
        good_image_all,
        good_target_all,
        np.ones(len(good_image_all), bool),
        observed & ~lost & ~np.isfinite(sigma),
        misfit,
        to_datum * (meet if full is None else full),
    )
    for j in np.flatnonzero(unreliable).tolist():
        reasons[j] = UNRELIABLE_REASON.format(
            misfit=misfit[j], reference=reference, units=rig.units
        )
    if unreliable.any():
        notes.append(
            f"{int(unreliable.sum())} targets seen in two images only are far from their "
            "approximate coordinates (two rays cannot tell a mislabel from the target): "
            "left out of the targets"
        )
    lost |= unreliable
    used = np.flatnonzero(observed & ~lost)
    weak_limit, weak = weak_targets(xyz_solver[used], (meet if full is None else full)[used])
    if weak.any():
        notes.append(
            f"{int(weak.sum())} of {len(used)} adjusted targets are weakly determined: "
            "sigma along the worst direction above 2 % of the targets' extent (rays that "
            "meet at small angles, or poses the network holds poorly; listed in "
            "target_precision)"
        )

    # results, in the files' convention
    xyz = xyz_solver.copy()
    rig_R = np.array([_pose(final.atPose3(frame_key(k)).inverse())[0] for k in range(len(frames))])
    rig_t = np.array([_pose(final.atPose3(frame_key(k)).inverse())[1] for k in range(len(frames))])
    ext = {ids[0]: (np.eye(3), np.zeros(3))}
    for c in range(1, len(ids)):
        ext[ids[c]] = _pose(final.atPose3(extrinsics_key(c)).inverse())
    own = {k: _pose(final.atPose3(k).inverse()) for k in own_poses}
    scale = 1.0
    if datum_sim is not None:
        sim = datum_sim
        xyz[free] = sim.apply(xyz[free])
        rig_R, rig_t = sim.apply_to_cam_from_world(rig_R.reshape(-1, 3, 3), rig_t.reshape(-1, 3))
        for k, (R, t) in own.items():
            R2, t2 = sim.apply_to_cam_from_world(R[None], t[None])
            own[k] = (R2[0], t2[0])
        scale = sim.scale
        meet = meet * scale
        full = None if full is None else full * scale
        weak_limit *= scale
        ext = {cid: (R, scale * t) for cid, (R, t) in ext.items()}
        cov_ext = {
            cid: None
            if cov is None
            else cov * np.repeat([1.0, scale], 3)[:, None] * np.repeat([1.0, scale], 3)[None]
            for cid, cov in cov_ext.items()
        }

    cameras, residuals, weights = {}, {}, {}
    max_incidence: dict[str, float] = {}
    cam_from_world: dict[str, Pose] = {}
    for c, cid in enumerate(ids):
        p = problems[cid]
        camera = camera_with_theta(joint_camera[cid], final.atVector(intrinsics_key(c)))
        if cid in models:  # re-learned in the joint graph, for every observation
            camera = replace(camera, correction=models[cid])
        cameras[cid] = camera
        res_model = res_model_of[cid]
        res = camera.pixel_residuals(raw_uv[cid], res_model) if len(res_model) else res_model
        keep = kept[cid]
        residuals[cid] = np.full((len(keep), 2), np.nan)
        residuals[cid][keep] = np.where(np.isfinite(res), res, res_model)
        r = np.linalg.norm(res_model, axis=1) / p.noise.sigma_px
        weights[cid] = np.zeros(len(keep))
        weights[cid][keep] = robust_weight(r, loss, loss_threshold)[0]
        for iid in images_of[cid]:
            f = frame_of.get(iid)
            if f is None:
                cam_from_world[iid] = own[pose_key(image_global[iid])]
            else:
                k = f_index[f]
                R_c, t_c = ext[cid]
                cam_from_world[iid] = (R_c @ rig_R[k], R_c @ rig_t[k] + t_c)
        # the field this camera's observations span in the joint graph
        if len(p.obs_target):
            poses = [cam_from_world[iid] for iid in images_of[cid]]
            R_i = np.array([R for R, _ in poses])[p.obs_image]
            t_i = np.array([t for _, t in poses])[p.obs_image]
            pc = np.einsum("nij,nj->ni", R_i, xyz[p.obs_target]) + t_i
            max_incidence[cid] = float(np.max(incidence_deg(pc)))
    for cid, (low, high) in alternated.items():
        notes.append(
            f"camera {cid}: its robust scale alternated between {low:.4f} and {high:.4f} px "
            "from stage to stage (two fixed points of the reweighting); the larger is kept"
        )
    # the targets with a prior the data moved furthest (calibrate.targets_off_prior)
    weighted = np.array(
        [j for j in free if np.isfinite(sigma[j]) and sigma[j] > 0 and not lost[j]], int
    )
    # rays that are not outliers, each camera's image apart (calibrate._result)
    seen_in = images_per_target(good_target_all, good_image_all, len(rig.target_ids))
    target_shifts = targets_off_prior_statistics(
        [rig.target_ids[j] for j in weighted],
        shift_over_sigma(xyz[weighted] - rig.target_xyz[weighted], sigma[weighted]),
        seen_in[weighted],
    )
    return JointRigResult(
        target_shifts=target_shifts,
        cam_from_rig=ext,
        rig_from_world={f: (rig_R[k], rig_t[k]) for f, k in f_index.items()},
        cam_from_world=cam_from_world,
        target_xyz={rig.target_ids[j]: xyz[j] for j in np.unique(obs_target) if not lost[j]},
        undetermined_targets=[rig.target_ids[j] for j in np.flatnonzero(lost)],
        undetermined_reasons={rig.target_ids[j]: why for j, why in sorted(reasons.items())},
        target_precision={
            "target": [rig.target_ids[j] for j in used],
            "intersection_sigma": meet[used],
            "weak": weak,
            **({} if full is None else {"sigma": full[used]}),
        },
        weak_target_limit=float(weak_limit),
        max_incidence_deg=max_incidence,
        loss=str(loss),
        cameras=cameras,
        residuals_px=residuals,
        weights=weights,
        sigma_px={cid: float(p.noise.sigma_px) for cid, p in problems.items()},
        cam_from_rig_covariance=cov_ext,
        intrinsics_sigma=int_sigma,
        result=result,
        stages=stage,
        datum=datum_problem.datum.value,
        variance_factor=float(variance_factor),
        redundancy=int(redundancy),
        mean_redundancy=mean_redundancy(redundancy, len(obs_target), n_priors),
        notes=notes,
        unestimated_scales=dict(held),
        n_outliers=n_outliers,
        unsettled_scales=[
            cid
            for cid, p in problems.items()
            if cid in unsettled
            or (p.noise.sigma_px <= 1.01 * MIN_SIGMA_PX and start_sigma[cid] > 10.0 * MIN_SIGMA_PX)
        ],
    )
