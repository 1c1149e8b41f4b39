"""The calibration pipeline: data -> init -> graph -> optimize -> (correct) -> result.

:func:`adjust` runs one robust bundle adjustment with self-calibration on a
:class:`~gtsam_sphere.estimation.graph.BundleProblem`; :func:`calibrate` runs the whole
job on a :class:`~gtsam_sphere.io.dataset.Dataset`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace

import gtsam
import numpy as np

from ..core._compat import StrEnum
from ..core.camera import (
    ALPHA0_RAD,
    DEFAULT_MODEL,
    PA_TERMS,
    WARP_TERM,
    Model,
    SphereCamera,
    has_radial_brown,
    parse_brown_terms,
    radial_g,
    radial_terms,
    radial_warp,
)
from ..core.errors import DegenerateGeometryError, GtsamSphereError
from ..core.geometry import fit_similarity_trimmed, incidence_deg
from ..core.robust import MAD_RELATIVE_SE, MAD_TO_SIGMA, Loss, robust_sigma_px, robust_weight
from ..io.calibration import Calibration
from ..io.dataset import Dataset
from .diagnose import (
    ProblemCode,
    check_geometry,
    image_groups,
    raise_if_degenerate,
    undetermined_targets,
)
from .graph import (
    INTRINSICS_KEY,
    BundleProblem,
    Datum,
    NoiseOptions,
    intersection_sigma,
    point_key,
    pose_key,
)
from .optimize import (
    OptimizationResult,
    OptimizerKind,
    OptimizerOptions,
    make_ordering,
    marginal_covariances,
    optimize,
)

logger = logging.getLogger(__name__)

#: Brown terms of the brown models unless told otherwise
BROWN_DEFAULT_TERMS = ("k1", "k2", "k3", "p1", "p2")
#: non-radial terms of the radial models unless told otherwise: decentering and affinity
RADIAL_DEFAULT_TERMS = ("p1", "p2", "a1", "a2")

#: floor of the estimated image noise (px): no detector measures better, and below it
#: perfect (simulated) data whitens residuals at the projection's numerical noise, so LM
#: stalls and the covariance looks singular (seen at 1e-4 px; 0.001 px took 194 iterations)
MIN_SIGMA_PX = 0.005
CONTROL_SIGMA_AUTO = "auto"
# Exact targets (sigma 0) are estimated with this fraction of their extent as the prior
# sigma by default: 0.2 mm on a 20 cm printed board (boards are curled and mis-scaled by
# a few tenths of a millimetre; any sigma from 0.1 to 2 mm gave the same held-out error
# on fish_1, README "Printed boards").
CONTROL_SIGMA_RELATIVE = 1e-3


@dataclass
class CalibrationOptions:
    """Options of :func:`calibrate` (and of ``gtsam-sphere calibrate``).

    Attributes
    ----------
    model : Model
        ``sphere`` (IOP only), ``brown`` (IOP + ``brown_terms``), ``radial``
        (a radial mapping + the non-radial ``brown_terms``), each ``+knn``.
    brown_terms : tuple of str or None
        Brown additional parameters (Eq. 5). ``None`` picks the model's
        default: k1,k2,k3,p1,p2 for ``brown``; decentering and affinity
        p1,p2,a1,a2 for ``radial`` (which only takes the non-radial terms).
    radial_terms : int
        Most coefficients ``g3, g5, ...`` of the radial mapping (0-6); with
        ``select_terms`` those the data cannot support are dropped.
    optimizer : OptimizerKind
    loss : Loss
    loss_threshold : float
        In units of ``sigma_px``.
    sigma_px : float or None
        Image-coordinate standard deviation; ``None`` estimates it from the
        residuals (robust MAD) and adjusts again.
    max_iterations : int
    points_per_factor : int
    seed : int
        Seed of every random choice (RANSAC, cross-validation).
    control_sigma : float, "auto" or None
        Standard deviation, in the dataset's units (metres by default), given to the
        targets the dataset marks as exactly known (``sigma: 0``, e.g. the corners of a
        printed board), so that the adjustment estimates their coordinates around the
        nominal ones: the board's real shape (a curled or badly printed board), as the
        data contract allows. ``"auto"`` (default): ``CONTROL_SIGMA_RELATIVE`` (1e-3)
        times the diagonal of the exact targets' bounding box (0.2 mm for a 20 cm
        board, 9 mm for a 9 m room); ``None`` keeps them exact. On the real chessboard
        data in ``../shared/data`` 0.1-2 mm lowers the held-out RMS by 40-60%; see the
        README.
    select_terms : bool
        For the radial models, and the Brown models whose terms are decentering and
        affinity only (the sphere fallback's), drop the radial and decentering/affinity
        terms the data cannot support (:func:`select_terms`); False keeps every term.
    """

    model: Model = DEFAULT_MODEL
    brown_terms: tuple[str, ...] | None = None
    optimizer: OptimizerKind = OptimizerKind.LM
    loss: Loss = Loss.HUBER
    loss_threshold: float = 2.45
    sigma_px: float | None = None
    max_iterations: int = 100
    points_per_factor: int = 8
    seed: int = 0
    knn: dict = field(default_factory=dict)
    fixed_intrinsics: tuple[float, ...] | None = None
    covariance: bool = True
    radial_terms: int = 6
    control_sigma: float | str | None = "auto"
    select_terms: bool = True

    def __post_init__(self):
        self.model = Model(self.model)
        if self.control_sigma != CONTROL_SIGMA_AUTO and self.control_sigma is not None:
            try:
                value = float(self.control_sigma)
            except (TypeError, ValueError):
                value = float("nan")
            if not (np.isfinite(value) and value > 0):
                raise ValueError(
                    "control_sigma must be a positive number, 'auto' or None, got "
                    f"{self.control_sigma!r}"
                )
            self.control_sigma = value
        self.optimizer = OptimizerKind(self.optimizer)
        self.loss = Loss(self.loss)
        if isinstance(self.brown_terms, str):
            self.brown_terms = parse_brown_terms(self.brown_terms)
        if self.brown_terms is None:
            radial = self.model.uses_radial
            self.brown_terms = RADIAL_DEFAULT_TERMS if radial else BROWN_DEFAULT_TERMS
        self.brown_terms = tuple(self.brown_terms)
        if self.model.uses_radial and has_radial_brown(self.brown_terms):
            raise ValueError(
                f"model {self.model} estimates the radial mapping g; radial Brown terms "
                f"{[t for t in self.brown_terms if t.startswith('k')]} would duplicate it: "
                "choose among p1, p2, a1, a2"
            )


@dataclass
class Adjustment:
    """State after one adjustment of a :class:`BundleProblem`.

    Attributes
    ----------
    values : gtsam.Values
    residuals_px : ndarray, shape (N, 2)
        ``measured (corrected) - predicted``.
    weights : ndarray, shape (N,)
        Robust weight per observation.
    result : OptimizationResult
    """

    values: gtsam.Values
    residuals_px: np.ndarray
    weights: np.ndarray
    result: OptimizationResult
    sigma_px: float
    loss: str = ""
    #: the smallest robust scale any of its stages estimated (px; NaN when none did)
    min_sigma_px: float = float("nan")


def initial_values(
    problem: BundleProblem,
    world_from_cam: list[gtsam.Pose3],
    theta: np.ndarray,
    target_xyz: np.ndarray | None = None,
) -> gtsam.Values:
    """Values for the problem's variables: poses, free targets, intrinsics."""
    xyz = problem.target_xyz if target_xyz is None else target_xyz
    values = gtsam.Values()
    for i in np.unique(problem.obs_image):
        values.insert(pose_key(int(i)), world_from_cam[int(i)])
    for t in problem.free_targets:
        values.insert(point_key(int(t)), np.asarray(xyz[t], float))
    values.insert(INTRINSICS_KEY, np.asarray(theta, float))
    return values


#: the final Cauchy stage of :func:`adjust` runs when at least this fraction of the
#: observations lie beyond 10 sigma of the Huber solution
CAUCHY_MIN_FRACTION = 0.005

#: a robust stage of :func:`adjust` holds out the targets without a sigma that only
#: observations beyond this many sigmas tie to a second image (:func:`held_out_targets`)
GROSS_SIGMA = 10.0
#: ... and beyond this many pixels: a camera fitted exactly (a rig camera's group of two
#: images, its scale at the 0.005 px floor) has no blunders to tell at 10 sigma
GROSS_MIN_PX = 1.0


def held_out_targets(problem: BundleProblem, values: gtsam.Values) -> np.ndarray:
    """Targets a robust stage must hold out: free, and determined only by gross rays.

    A target without a sigma seen in two images, one of them through a blunder, sits on
    the good image's ray at a depth only the blunder fixes. Robust stages let it slide
    along that ray toward wherever the blunder's residual is least; when that is the
    good camera's own centre, it creeps there by a fraction of its distance per
    iteration (the step is damped by a curvature that grows as the inverse square of its
    depth) and, within a micrometre, any step carries it through the centre, where its
    projection jumps. Zoo stress 3201 s32 (a 289 deg field-of-view room, 2 % blunders):
    the final Cauchy stage crawled 14 iterations at 2e-5 of the cost each, target T0068
    ended 1.6e-7 m from a camera centre, LM then found no step at any damping (a step of
    1e-6 raised the cost by 45, a tenth of it), the run stalled and the calibration was
    not trusted at 0.98x the family oracle's 3D error; every kNN round after it stalled at
    its first iteration. Such targets are left out of the adjusted targets afterwards
    (:func:`targets_lost_to_outliers`); this keeps them out of the stage too.

    Gross: beyond :data:`GROSS_SIGMA` sigmas and :data:`GROSS_MIN_PX` (a free rig's
    camera fitted exactly on two images held out targets at 0.05 px, and its rig lost
    its trust; ``tests/test_rig_trust.py``).

    Parameters
    ----------
    problem : BundleProblem
        Built (its residuals are evaluated); its ``noise.sigma_px`` is the scale.
    values : gtsam.Values
        The stage's start.

    Returns
    -------
    ndarray of bool, shape (N,)
        The observations of those targets (all False for a rig camera's problem, whose
        poses are not one per image, and for a network whose datum such a target is).
    """
    n = len(problem.uv_px)
    none = np.zeros(n, bool)
    if n == 0 or problem.image_pose_keys is not None or problem.image_extrinsic_keys is not None:
        return none
    r = np.linalg.norm(problem.residuals_px(values), axis=1)
    gross = ~(r <= max(GROSS_SIGMA * problem.noise.sigma_px, GROSS_MIN_PX))
    if not gross.any():
        return none
    sigma = np.asarray(problem.target_sigma, float)
    lost = undetermined_targets(problem.obs_image[~gross], problem.obs_target[~gross], sigma)
    seen = undetermined_targets(problem.obs_image, problem.obs_target, sigma)
    lost &= ~seen  # seen in two images or more, one of them only through gross rays
    datum = getattr(problem, "datum_targets", None) or ()
    if not lost.any() or lost[list(datum)].any():
        return none
    return lost[problem.obs_target]


def adjust(
    problem: BundleProblem,
    values: gtsam.Values,
    optimizer: OptimizerOptions,
    progress: Callable[[str], None] | None = None,
    estimate_sigma: bool = True,
    label: str = "",
    max_stages: int = 6,
    first_stage_mask: np.ndarray | None = None,
    warm: bool = False,
    after_stage: Callable[[gtsam.Values, np.ndarray, float], bool | None] | None = None,
    first_stage_all: bool = True,
) -> Adjustment:
    """Robust adjustment, optionally estimating ``sigma_px`` from the residuals.

    With ``estimate_sigma`` the scale starts at the robust scale of the
    initial residuals and is re-estimated (``median(|e|) / sqrt(2 ln 2)`` of the
    residuals standardised by their redundancy numbers,
    :meth:`BundleProblem.observation_redundancy`: a target seen in one image absorbs
    its own residual, and a camera whose targets were mostly seen once, the narrow
    camera of a rig, saw its scale collapse to the floor) after each adjustment until
    it changes by less than 5% (graduated robustness), at most ``max_stages``
    adjustments. The first stage is plain
    least squares; ``first_stage_mask`` (N,) bool restricts it to the
    observations the initialisation's RANSAC found consistent, so blunders
    cannot pull it (the robust stages then see every observation). It also runs on
    every observation, and the start with the lower truncated cost in raw pixels wins
    (:func:`_truncated_costs`), unless ``first_stage_all`` is False: the mask then comes
    from a converged robust adjustment of the same observations (:func:`readjust`),
    whose rejects are gross by its own residuals, and least squares on every
    observation only wanders (a 105 deg field-of-view object with 2 % blunders: 11 s
    for that start against 0.3 s without them, in each of three target-prior rounds,
    for a start that then lost).

    ``warm``: ``values`` is a converged robust adjustment of this problem with a
    slightly changed measurement (a kNN round's new corrections), and
    ``problem.noise.sigma_px`` its scale. There is then no poor start for a first
    least-squares stage to protect: the robust stages start from that scale, and stop
    as soon as it changes by less than 5% (one stage, usually).

    ``after_stage(values, r_px, sigma_px)``: called after every robust stage but the
    last (not after the first, least-squares, stage: its state can be far from the
    robust one) with its values, the residual norms (N,) px and the new scale
    estimate; it may raise to abandon the adjustment (the fold probe of
    :func:`calibrate`) or return True to end it there with that stage's state and no
    further stage (the warp probe: that state only starts another adjustment).

    Returns
    -------
    Adjustment
    """
    ordering = make_ordering(
        [point_key(int(t)) for t in problem.free_targets],
        [pose_key(int(i)) for i in np.unique(problem.obs_image)],
        [INTRINSICS_KEY],
    )
    if estimate_sigma and not warm:
        # graduated robustness: start from the scale of the initial residuals, so a poor
        # start is not frozen by tiny robust weights, then shrink to the estimated noise
        problem.build()
        r0 = np.linalg.norm(problem.residuals_px(values), axis=1)
        sigma = robust_sigma_px(r0, problem.noise.sigma_px)
        problem.noise = NoiseOptions(sigma, problem.noise.loss, problem.noise.loss_threshold)
        if first_stage_mask is not None and len(first_stage_mask) == len(r0):
            # RANSAC's verdict, plus what the start already predicts well (RANSAC's lens
            # hypotheses cannot see past 90 deg for the sphere, for instance)
            first_stage_mask = np.asarray(first_stage_mask, bool) | (r0 < 3.0 * np.median(r0))
    loss = problem.noise.loss
    history: list[dict] = []
    result = None
    stopped = False
    estimated: list[float] = []  # the robust scale of each stage
    for stage in range(1, max_stages + 1):
        # stage 1 in plain least squares: robust weights computed at a poor start can hold
        # a wrong minimum (observed with a 300 deg lens); later stages are robust
        first_l2 = estimate_sigma and not warm and stage == 1 and len(problem.uv_px) > 0
        problem.noise = NoiseOptions(
            problem.noise.sigma_px, Loss.L2 if first_l2 else loss, problem.noise.loss_threshold
        )
        graph = problem.build()
        start = values if result is None else result.values
        sub = _inlier_problem(problem, first_stage_mask) if first_l2 else None
        if sub is not None and not first_stage_all:
            if progress:
                n_out = len(problem.uv_px) - len(sub.uv_px)
                progress(f"{label}stage 1 without {n_out} observations beyond 5 sigma")
            result = _optimize_subset(sub, start, optimizer, progress, label)
            sub = None
        elif first_l2:
            result = optimize(graph, start, optimizer, ordering, progress, label)
        else:
            result = _robust_stage(problem, graph, start, optimizer, ordering, progress, label)
        if sub is not None:
            # least squares breaks down with one blunder, so stage 1 also runs without the
            # observations RANSAC rejected, and the start with the lower truncated cost
            # over *every* observation wins (_truncated_costs; 10% blunders: only the
            # second survives; a 300 deg sphere lens: the first, as RANSAC's hypotheses
            # stop at 90 deg)
            if progress:
                n_out = len(problem.uv_px) - len(sub.uv_px)
                progress(f"{label}stage 1 again without {n_out} observations RANSAC rejected")
            alt = _optimize_subset(sub, start, optimizer, progress, label)
            costs = _truncated_costs(problem, [result.values, alt.values])
            if progress:
                progress(
                    f"{label}truncated cost of stage 1 with all / without rejected: "
                    f"{costs[0]:.4e} / {costs[1]:.4e}"
                )
            if costs[1] < costs[0]:
                result = alt
        offset = history[-1]["iteration"] + 1 if history else 0
        history += [dict(h, iteration=h["iteration"] + offset, stage=stage) for h in result.history]
        if not estimate_sigma:
            break
        r = np.linalg.norm(problem.residuals_px(result.values), axis=1)
        old = problem.noise.sigma_px
        # standardised by each observation's redundancy: the residuals of targets seen
        # in one image (absorbed by the target) would otherwise pull the scale to zero
        redundancy = problem.observation_redundancy(result.values, old)
        sigma = robust_sigma_px(r, MIN_SIGMA_PX, redundancy)
        estimated.append(sigma)
        if progress:
            progress(f"{label}robust scale estimate sigma = {sigma:.4f} px (was {old:.4f})")
        problem.noise = NoiseOptions(sigma, loss, problem.noise.loss_threshold)
        if abs(sigma - old) <= 0.05 * old and (stage > 1 or warm):
            break
        if after_stage is not None and 1 < stage < max_stages:
            if after_stage(result.values, r, sigma):
                stopped = True
                break
    if estimate_sigma and loss is Loss.HUBER and not stopped:
        # Huber bounds a blunder's influence but does not remove it: with gross outliers
        # present, a last stage with Cauchy's redescending influence (from the Huber
        # solution, so no wrong minimum) lets them pull no more (10% blunders: 3D error
        # 1.31x the clean run with Huber alone, 0.96x with this stage). A handful
        # (below CAUCHY_MIN_FRACTION) pulls the Huber solution by next to nothing, and
        # the stage is not free: IRLS with Cauchy's weights converges linearly (a 340 deg
        # lens's 18 rim observations in 9,546: 70-100 iterations per adjustment, and the
        # last kNN round stopped at the iteration limit: not trusted)
        r = np.linalg.norm(problem.residuals_px(result.values), axis=1)
        n_out = int(np.sum(r > 10.0 * problem.noise.sigma_px))
        if n_out and n_out >= CAUCHY_MIN_FRACTION * len(r):
            if progress:
                progress(f"{label}{n_out} observations beyond 10 sigma: final stage with Cauchy")
            problem.noise = NoiseOptions(
                problem.noise.sigma_px, Loss.CAUCHY, problem.noise.loss_threshold
            )
            stage += 1
            graph = problem.build()
            result = _robust_stage(
                problem, graph, result.values, optimizer, ordering, progress, label
            )
            offset = history[-1]["iteration"] + 1
            history += [
                dict(h, iteration=h["iteration"] + offset, stage=stage) for h in result.history
            ]
    problem.build()
    result.history = history
    res = problem.residuals_px(result.values)
    r = np.linalg.norm(res, axis=1) / problem.noise.sigma_px
    w, _ = robust_weight(r, problem.noise.loss, problem.noise.loss_threshold)
    used = str(loss) if problem.noise.loss is loss else f"{loss}, then {problem.noise.loss}"
    # the next adjustment of this problem starts again from the caller's loss
    problem.noise = NoiseOptions(problem.noise.sigma_px, loss, problem.noise.loss_threshold)
    return Adjustment(
        result.values,
        res,
        w,
        result,
        problem.noise.sigma_px,
        used,
        min(estimated) if estimated else float("nan"),
    )


#: :func:`_truncated_costs` caps each squared residual at this many (common) sigmas
STAGE_ONE_CAP = 3.0


def _truncated_costs(problem: BundleProblem, candidates: list[gtsam.Values]) -> list[float]:
    """Truncated least-squares cost (px^2) of every observation at each of ``candidates``:
    ``sum(min(r^2, (STAGE_ONE_CAP sigma)^2))`` (:attr:`Loss.TRUNCATED`) with one scale
    for all, the smallest of their median-based scales.

    It ranks the two starts of :func:`adjust`'s first stage (with every observation, and
    without those RANSAC rejected). A blunder costs the same wherever it lands, so a
    start is not rewarded for bending toward blunders; a valid observation that RANSAC
    rejected (beyond 90 deg for a 300 deg sphere lens) still counts where one start
    fits it. Huber's cost with each start's own scale did reward the bend: on boards
    with 2-5 % blunders, where the poses and a flexible mapping can follow them, the
    start with every observation won (5.7e3 against 7.0e3 for a 114 deg pinhole board
    with 2 %) and the calibration wandered into a wrong, untrusted solution; the other
    start gives 0.95x the oracle's 3D error.

    The residuals are raw pixels (:func:`raw_residuals_px`). In corrected coordinates
    (the adjustment's metric before :func:`~gtsam_sphere.core.camera.sphere_residual`
    undid decentering and affinity), least squares pulled by blunders inflated the
    affinity ``a1`` until the corrected residuals of half the images were half the
    noise (a 105 deg field-of-view object, 2 % blunders, the second target-prior
    round: ``a1`` 0.59, principal point 500 px off, median residual 0.43 against the
    truth's 0.59 px), that start won, the robust stages slid on to sigma 0.2 px and
    the calibration ended untrusted at 45x the oracle's 3D error.
    """
    r = [np.linalg.norm(raw_residuals_px(problem, v), axis=1) for v in candidates]
    sigma = min(robust_sigma_px(ri, 1e-9) for ri in r)
    # rho = min(r / sigma, cap)^2 / 2 in sigmas; 2 sigma^2 rho is the cost in px^2
    rho = [robust_weight(ri / sigma, Loss.TRUNCATED, STAGE_ONE_CAP)[1] for ri in r]
    return [float(2.0 * sigma**2 * np.sum(x)) for x in rho]


def raw_residuals_px(problem: BundleProblem, values: gtsam.Values) -> np.ndarray:
    """Residuals (N, 2) in raw pixels at ``values``: the adjustment's residuals mapped
    by :meth:`SphereCamera.pixel_residuals` (the same with the radial mapping, whose
    Brown terms ``p1 p2 a1 a2`` the residual already undoes; the radial ``k1-k3`` of
    the Brown model mapped by ``(I - d brown / d uv)^-1``; unchanged where that map is
    singular).

    Raw pixels are the scale the noise has, and compare solutions fairly: in corrected
    coordinates a solution can shrink its cost by shrinking the metric.
    """
    e = problem.residuals_px(values)
    if not has_radial_brown(problem.brown_names):
        return e  # the residual is already in raw pixels (to first order)
    key = problem.intrinsics_key
    theta = values.atVector(key) if values.exists(key) else problem.fixed_intrinsics
    size = int(np.ceil(2.0 * problem.brown_scale_px))
    camera = camera_from_theta(problem, np.asarray(theta, float), size, size)
    raw = camera.pixel_residuals(problem.corrected_uv_px, e)
    return np.where(np.isfinite(raw), raw, e)


def _inlier_problem(problem: BundleProblem, mask: np.ndarray | None) -> BundleProblem | None:
    """The problem restricted to ``mask`` (N,) observations, or None if not usable."""
    if mask is None or len(mask) != len(problem.uv_px) or mask.all():
        return None
    keep = np.asarray(mask, bool)
    images = np.unique(problem.obs_image)
    if not np.array_equal(np.unique(problem.obs_image[keep]), images):
        return None  # an image would lose every observation
    try:
        return replace(
            problem,
            obs_image=problem.obs_image[keep],
            obs_target=problem.obs_target[keep],
            uv_px=problem.uv_px[keep],
            corrections_px=problem.corrections_px[keep],
        )
    except ValueError:  # e.g. the control targets left no datum
        return None


def _optimize_subset(sub: BundleProblem, start: gtsam.Values, optimizer, progress, label):
    """Optimise the restricted problem ``sub`` from ``start``; the result's values hold
    every variable of ``start`` (unchanged where ``sub`` has none)."""
    sub_values, sub_ordering = _sub_values(sub, start)
    out = optimize(sub.build(), sub_values, optimizer, sub_ordering, progress, label)
    merged = gtsam.Values(start)
    merged.update(out.values)
    out.values = merged
    return out


def _robust_stage(
    problem: BundleProblem,
    graph: gtsam.NonlinearFactorGraph,
    start: gtsam.Values,
    optimizer: OptimizerOptions,
    ordering,
    progress,
    label: str,
):
    """One robust stage of :func:`adjust` on ``graph`` (``problem`` built), holding out the
    targets :func:`held_out_targets` names: they follow their good image's pose, at the
    depth along its ray they had."""
    hold = held_out_targets(problem, start)
    sub = _inlier_problem(problem, ~hold) if hold.any() else None
    sub_graph = None
    if sub is not None:
        sub_graph = sub.build()
        if getattr(sub, "datum_targets", None) != getattr(problem, "datum_targets", None):
            sub = None  # another datum: the held targets would not follow it
    if sub is None:
        return optimize(graph, start, optimizer, ordering, progress, label)
    held = np.unique(problem.obs_target[hold])
    if progress:
        progress(
            f"{label}{len(held)} targets without a sigma that only observations beyond "
            f"{GROSS_SIGMA:g} sigma tie to a second image held out of this stage"
        )
    sub_values, sub_ordering = _sub_values(sub, start)
    out = optimize(sub_graph, sub_values, optimizer, sub_ordering, progress, label)
    merged = gtsam.Values(start)
    merged.update(out.values)
    r = np.linalg.norm(problem.residuals_px(start), axis=1)
    good = []
    for t in held:
        rows = np.flatnonzero(problem.obs_target == t)
        good.append(rows[np.argmin(r[rows])])
        key = pose_key(int(problem.obs_image[good[-1]]))
        cam = start.atPose3(key).transformTo(start.atPoint3(point_key(int(t))))
        merged.update(point_key(int(t)), merged.atPose3(key).transformFrom(cam))
    _onto_rays(problem, merged, held, np.array(good))
    out.values = merged
    return out


def _onto_rays(problem: BundleProblem, values: gtsam.Values, targets, rows) -> None:
    """Move free ``targets`` (k,) across observation ``rows`` (k,)'s rays until those
    observations fit, in place: Gauss-Newton steps of least norm, which are normal to
    the ray (a step along it changes nothing) and so keep each target's depth."""
    keys = [point_key(int(t)) for t in targets]
    for _ in range(3):
        points = np.array([values.atPoint3(k) for k in keys])
        e0 = problem.residuals_px(values)[rows]
        step_m = 1e-6 * np.maximum(np.linalg.norm(points, axis=1), 1e-3)
        J = np.empty((len(keys), 2, 3))
        for a in range(3):
            trial = gtsam.Values(values)
            for k, p, h in zip(keys, points, step_m):
                trial.update(k, p + h * np.eye(3)[a])
            J[:, :, a] = (problem.residuals_px(trial)[rows] - e0) / step_m[:, None]
        for k, p, Jk, ek in zip(keys, points, J, e0):
            values.update(k, p - np.linalg.pinv(Jk) @ ek)


def _sub_values(sub: BundleProblem, values: gtsam.Values):
    """Values and elimination ordering of a restricted problem's variables."""
    out = gtsam.Values()
    points = [point_key(int(t)) for t in sub.free_targets]
    poses = [pose_key(int(i)) for i in np.unique(sub.obs_image)]
    for k in points:
        out.insert(k, values.atPoint3(k))
    for k in poses:
        out.insert(k, values.atPose3(k))
    out.insert(INTRINSICS_KEY, values.atVector(INTRINSICS_KEY))
    return out, make_ordering(points, poses, [INTRINSICS_KEY])


def repair_poses(
    problem: BundleProblem,
    adj: Adjustment,
    dataset: Dataset,
    rng: np.random.Generator,
    say: Callable[[str], None],
    max_rounds: int = 2,
) -> list[int]:
    """Re-resect images whose pose converged to a wrong minimum, in ``adj.values``.

    An image is suspect when the median of its residual norms exceeds
    ``5 * sigma``: a wrong initial pose (P3P ambiguity, mislabelled targets)
    that the adjustment could not leave. Its pose is recomputed by P3P +
    RANSAC on bearings from the now-calibrated camera and the adjusted
    targets; the caller adjusts again. Returns the image indices changed.
    """
    from ..core.p3p import ransac_pose

    theta = adj.values.atVector(INTRINSICS_KEY)
    camera = camera_from_theta(problem, theta, dataset.width, dataset.height)
    r = np.linalg.norm(adj.residuals_px, axis=1)
    xyz = adjusted_target_xyz(problem, adj.values)
    changed = []
    threshold = 5.0 * adj.sigma_px
    for i in np.unique(problem.obs_image):
        m = problem.obs_image == i
        if np.median(r[m]) <= threshold:
            continue
        uv = problem.corrected_uv_px[m]
        rays = camera.unproject(uv)
        ok = np.all(np.isfinite(rays), axis=1)
        if ok.sum() < 4:
            continue
        thr_rad = max(3.0 * threshold / camera.c, 1e-3)
        points = xyz[problem.obs_target[m]][ok]
        best = ransac_pose(rays[ok], points, thr_rad, rng)
        # a lens that folds images two rays at a pixel: both compete, as in the
        # initialisation, and that pose is kept when it explains more observations (the
        # front ray alone left stress 3301 s34's images 7-9 m off, 17-25 of ~51 inliers)
        back = folded_rays(camera, uv[ok], rays[ok], threshold)
        if np.isfinite(back).all(axis=1).any():
            # its own generator, derived from the image: the caller's draws stay as
            # they were without the fold
            both = ransac_pose(
                np.vstack([rays[ok], back]),
                np.vstack([points, points]),
                thr_rad,
                np.random.default_rng([int(i), len(points)]),
            )
            n = int(ok.sum())
            if both.success and (
                not best.success
                or np.sum(both.inlier_mask[:n] | both.inlier_mask[n:]) > best.n_inliers
            ):
                best = both
        if not best.success:
            say(
                f"  image {dataset.image_ids[i]}: residuals {np.median(r[m]):.1f} px, "
                f"re-resection failed ({best.reason})"
            )
            continue
        old = adj.values.atPose3(pose_key(int(i)))
        new = gtsam.Pose3(gtsam.Rot3(best.R), gtsam.Point3(*best.t)).inverse()
        adj.values.update(pose_key(int(i)), new)
        res_new = problem.residuals_px(adj.values)[m]
        if np.median(np.linalg.norm(res_new, axis=1)) < np.median(r[m]):
            changed.append(int(i))
            say(
                f"  image {dataset.image_ids[i]}: median residual {np.median(r[m]):.1f} px, "
                f"re-resected ({best.n_inliers} of {m.sum()} inliers)"
            )
        else:
            adj.values.update(pose_key(int(i)), old)
    return changed


#: :func:`folded_rays` searches the incidences 0-180 deg at this step (deg)
FOLD_SEARCH_STEP_DEG = 0.25


def folded_rays(
    camera: SphereCamera, uv_px: np.ndarray, front: np.ndarray, tolerance_px: float
) -> np.ndarray:
    """The other ray a folding lens images at each pixel, or NaN where there is none.

    A lens whose image radius turns back inside its field (the sphere mapping past
    90 deg, a radial mapping fitted to one, an orthographic lens past 180 deg) images
    two rays at a pixel: :meth:`~gtsam_sphere.core.camera.SphereCamera.unproject` gives
    the front one. The other is searched along the front ray's azimuth over the
    incidences 0-180 deg (steps of :data:`FOLD_SEARCH_STEP_DEG`), at least 1 deg from
    the front ray's, projecting within ``tolerance_px`` of the pixel.

    Parameters
    ----------
    camera : SphereCamera
    uv_px : ndarray, shape (N, 2)
        Pixels, as ``camera`` unprojects them.
    front : ndarray, shape (N, 3)
        ``camera.unproject(uv_px)`` (unit rays, camera frame).
    tolerance_px : float

    Returns
    -------
    ndarray, shape (N, 3)
        Unit rays in the camera frame; NaN rows where no other ray projects there.
    """
    uv_px = np.asarray(uv_px, float)
    front = np.asarray(front, float)
    n = len(uv_px)
    out = np.full((n, 3), np.nan)
    if n == 0:
        return out
    alpha = np.radians(np.arange(FOLD_SEARCH_STEP_DEG, 180.0, FOLD_SEARCH_STEP_DEG))
    phi = np.arctan2(front[:, 1], front[:, 0])
    a0 = np.arccos(np.clip(front[:, 2], -1.0, 1.0))
    sa = np.sin(alpha)[None, :]
    ca = np.broadcast_to(np.cos(alpha)[None, :], (n, len(alpha)))
    grid = np.stack([sa * np.cos(phi)[:, None], sa * np.sin(phi)[:, None], ca], axis=-1)
    with np.errstate(invalid="ignore", over="ignore"):
        uv = camera.project(grid.reshape(-1, 3), valid_only=False).reshape(n, len(alpha), 2)
        d = np.linalg.norm(uv - uv_px[:, None, :], axis=2)
    d[~np.isfinite(d)] = np.inf
    d[np.abs(alpha[None, :] - a0[:, None]) < np.radians(1.0)] = np.inf
    j = np.argmin(d, axis=1)
    hit = d[np.arange(n), j] <= tolerance_px
    out[hit] = grid[np.flatnonzero(hit), j[hit]]
    return out


def camera_from_theta(
    problem: BundleProblem, theta: np.ndarray, width: int, height: int, correction=None
) -> SphereCamera:
    """The :class:`SphereCamera` of intrinsics laid out as ``problem.intrinsics_names()``."""
    names = problem.intrinsics_names()
    vals = dict(zip(names, map(float, theta)))
    radial = None
    if problem.radial_names is not None:
        radial = {n: vals[n] for n in problem.radial_names}
        if problem.radial_warp is not None:
            radial[WARP_TERM] = float(problem.radial_warp)
    return SphereCamera(
        width=width,
        height=height,
        xp=vals["xp_px"],
        yp=vals["yp_px"],
        c=vals["c_px"],
        brown={n: vals[n] for n in problem.brown_names},
        brown_scale_px=problem.brown_scale_px,
        correction=correction,
        radial=radial,
    )


def initial_radial(
    uv_px: np.ndarray,
    points_cam: np.ndarray,
    principal_point_px: np.ndarray,
    n_terms: int,
    warp_w: float = 0.0,
    max_coefficient: float | None = None,
) -> np.ndarray:
    """Initial ``[c, g3, g5, ...]`` of the radial mapping from initial poses.

    Linear least squares of ``|uv - pp| = c * g(alpha)`` over the observations
    (N,2), (N,3), reweighted twice with Huber weights against poor initial
    poses; falls back to equidistant (``g = alpha``) when the fit is not
    usable. With a warp ``warp_w`` (not 0) the polynomial's variable is
    ``k beta(alpha)`` (:func:`~gtsam_sphere.core.camera.radial_g`). The highest terms
    are dropped (started at 0) until every coefficient is at most ``max_coefficient``
    in magnitude (default :data:`RADIAL_START_MAX`).
    """
    bound = RADIAL_START_MAX if max_coefficient is None else float(max_coefficient)
    r = np.linalg.norm(uv_px - principal_point_px, axis=1)
    norm = np.linalg.norm(points_cam, axis=1)
    alpha = np.arccos(np.clip(points_cam[:, 2] / np.where(norm > 0, norm, 1.0), -1, 1))
    ok = np.isfinite(alpha) & np.isfinite(r) & (norm > 0)
    k = float(np.exp(warp_w)) if warp_w != 0.0 else 1.0
    # g = h(phi) / k, phi = k beta (radial_g): fit h in phi, then c = c_h * k
    beta = alpha[ok] if warp_w == 0.0 else k * radial_warp(alpha[ok], warp_w)
    for n in range(n_terms, -1, -1):
        # the fewest terms dropped that keep every coefficient sane: over a narrow range
        # of phi the high powers are tiny and their coefficients huge (seed 5 case 05 of
        # the zoo, a 150 deg pinhole with w = -1.39: g up to -7.9e8 on a 58 % consistent
        # start; the adjustment then crawled and the term selection broke the fit)
        cg = _fit_radial(r[ok], beta, n)
        if n == 0 or np.all(np.abs(cg[1:]) <= bound):
            break
    cg = np.concatenate([cg, np.zeros(n_terms - n)])
    return np.concatenate([[cg[0] * k], cg[1:]])


#: largest magnitude of a radial coefficient :func:`initial_radial` starts from
RADIAL_START_MAX = 1e3
#: ... and from the initial poses (RANSAC's, of an approximate lens): the polynomial's
#: variable spans [0, 2] (:func:`~gtsam_sphere.core.camera.radial_g`), where a mapping
#: has coefficients of order one. Where the observations start far off the axis, the
#: fit of every term trades them off with ``c``: a 292 deg double-sphere board seen from
#: 33 deg (``bench_lens_zoo.py --stress 40 --seed 3103 --shapes`` s11) fitted six terms
#: with ``c`` = 2.5 px and g up to 175, about as well as four with ``c`` = 40 px and g
#: up to 1.4 (1.99 against 2.07 px RMS); from the six every stage crawled to its cap
#: (142 s of CPU), from the four 19 s. The re-warped start of :func:`select_warp` fits
#: adjusted geometry and keeps the looser bound
RADIAL_FIRST_START_MAX = 10.0


#: warps :func:`warp_following_lens` tries (``k = exp(w)`` from 0.22 to 2.7)
LENS_WARPS = tuple(round(float(w), 2) for w in np.arange(-1.5, 1.001, 0.25))
#: the radial mapping's polynomial misses the initial lens by more than this (px RMS at
#: the observed incidences) before :func:`warp_following_lens` changes its warp ...
LENS_MISFIT_PX = 0.05
#: ... and another warp follows it at most this fraction of that misfit
LENS_MISFIT_GAIN = 0.5


def _lens_fit(alpha: np.ndarray, radius_px: np.ndarray, n_terms: int, w: float):
    """``(rms_px, [c, g3, ...])`` of the least-squares fit of ``radius_px = c g(alpha)``
    (:func:`~gtsam_sphere.core.camera.radial_g`) with ``n_terms`` odd terms in the warp
    ``w``, (M,), (M,); the coefficients are None without a positive scale ``c``."""
    k = math.exp(w)
    beta = alpha if w == 0.0 else k * radial_warp(alpha, w)
    A = _radial_design(beta, n_terms)
    x = np.linalg.lstsq(A, radius_px, rcond=None)[0]
    rms = float(np.sqrt(np.mean((A @ x - radius_px) ** 2)))
    if not x[0] > 0:  # no positive scale: not a lens
        return rms, None
    # g = h(phi) / k with phi = k beta(alpha) (radial_g): c = c_h k
    return rms, np.concatenate([[x[0] * k], x[1:] / x[0]])


def warp_following_lens(
    alpha_rad: np.ndarray, radius_px: np.ndarray, n_terms: int, warp_w: float = 0.0
) -> tuple[float, float, float, np.ndarray] | None:
    """The warp of the radial mapping's variable whose ``n_terms`` odd terms follow the
    initial lens, when the current one's cannot.

    The initial lens family (stereographic, equisolid, ...: a noise-free curve) is
    fitted as ``c * g(alpha)`` (:func:`~gtsam_sphere.core.camera.radial_g`) at the
    observations' incidences for each warp of :data:`LENS_WARPS`. When the warp
    ``warp_w`` misses it by more than :data:`LENS_MISFIT_PX` RMS and another follows it
    within :data:`LENS_MISFIT_GAIN` of that, with coefficients below
    :data:`RADIAL_START_MAX`, that warp is returned. The warp chosen after the first
    adjustment (:func:`select_warp`) scores the pixels, whose noise hides a misfit of a
    tenth of a pixel; such a misfit is systematic and the poses absorb it: a 322 deg
    stereographic lens (f = 32 px, 1 px noise, a board: stress seed 1129 case s14 of
    ``bench_lens_zoo.py``) kept ``w = 0``, whose six terms miss the lens by 0.118 px,
    and ended at 1.31x the oracle's 3D error; ``w = 0.5`` (0.023 px): 1.03x. Over the
    200 cases of two zoo lists and two stress draws only that one changes. The mapping
    then starts from this fit (``cg``), not from the initial poses' (:func:`initial_radial`):
    from theirs that case's first stage took 100 iterations (13.7 s in all), from the
    lens's 4 (6.2 s), to the same result.

    Parameters
    ----------
    alpha_rad : ndarray, shape (M,)
        Incidence angles (rad) of the observations the initial poses explain.
    radius_px : ndarray, shape (M,)
        The initial lens's image radius (px) at them (NaN outside its domain: left out).
    n_terms : int
        Odd terms of the radial mapping.
    warp_w : float
        The current warp (0: none).

    Returns
    -------
    (w, misfit_px, current_misfit_px, cg) or None
        The warp, the misfits (px RMS) of its fit and of the current warp's, and the
        fit's ``[c, g3, ...]`` (c in px); None when the current warp stays (fewer
        than ``4 (n_terms + 1)`` usable rows, a misfit within :data:`LENS_MISFIT_PX`, or
        no warp that gains enough).
    """
    alpha = np.asarray(alpha_rad, float)
    radius = np.asarray(radius_px, float)
    ok = np.isfinite(alpha) & np.isfinite(radius) & (alpha > 1e-3)
    if ok.sum() < 4 * (n_terms + 1):
        return None
    alpha, radius = alpha[ok], radius[ok]
    current, _ = _lens_fit(alpha, radius, n_terms, warp_w)
    if current <= LENS_MISFIT_PX:
        return None
    best = None
    for w in LENS_WARPS:
        rms, cg = _lens_fit(alpha, radius, n_terms, w)
        sane = cg is not None and np.all(np.abs(cg[1:]) <= RADIAL_START_MAX)
        if sane and (best is None or rms < best[1]):
            best = (float(w), rms, cg)
    if best is None or best[0] == warp_w or best[1] > LENS_MISFIT_GAIN * current:
        return None
    return best[0], best[1], current, best[2]


def _radial_design(beta: np.ndarray, n_terms: int) -> np.ndarray:
    """(M, 1 + n_terms) columns of ``r = c beta + c A0 sum g_i (beta / A0)^(2i+3)`` in
    ``(c, c g3, ...)`` at the (warped) incidences ``beta`` (M,) rad."""
    t = beta / ALPHA0_RAD
    return np.column_stack([beta] + [ALPHA0_RAD * t ** (2 * i + 3) for i in range(n_terms)])


def _fit_radial(r: np.ndarray, beta: np.ndarray, n_terms: int) -> np.ndarray:
    """``[c, g3, ...]`` of ``r = c * (beta + A0 sum g_i (beta / A0)^(2i+3))`` (M,), (M,)."""
    A = _radial_design(beta, n_terms)
    w = np.ones(len(r))
    c_eq = float(np.sum(r * beta) / max(np.sum(beta**2), 1e-12))
    fallback = np.concatenate([[c_eq], np.zeros(n_terms)])
    if len(r) < 2 * (n_terms + 1):
        return fallback
    x = fallback
    for _ in range(3):
        sw = np.sqrt(w)
        x = np.linalg.lstsq(A * sw[:, None], r * sw, rcond=None)[0]
        res = np.abs(A @ x - r)
        k = 2.0 * MAD_TO_SIGMA * max(float(np.median(res)), 1e-9)
        w, _ = robust_weight(res, Loss.HUBER, k)
    if not np.all(np.isfinite(x)) or x[0] <= 0:
        return fallback
    return np.concatenate([[x[0]], x[1:] / x[0]])


def initial_principal_distance(
    uv_px: np.ndarray, points_cam: np.ndarray, principal_point_px: np.ndarray
) -> float:
    """Least-squares ``c`` of ``uv - pp = c * P[:2] / |P|`` over observations (N,2), (N,3)."""
    s = points_cam[:, :2] / np.linalg.norm(points_cam, axis=1)[:, None]
    xbar = uv_px - principal_point_px
    ok = np.all(np.isfinite(s), axis=1)
    return float((xbar[ok] * s[ok]).sum() / max((s[ok] * s[ok]).sum(), 1e-12))


def _poses_from_values(values: gtsam.Values, n_images: int):
    R = np.empty((n_images, 3, 3))
    t = np.empty((n_images, 3))
    for i in range(n_images):
        cam_from_world = values.atPose3(pose_key(i)).inverse()
        R[i] = cam_from_world.rotation().matrix()
        t[i] = cam_from_world.translation()
    return R, t


@dataclass
class Initialisation:
    """Initial state shared by several calibrations of the same dataset.

    Attributes
    ----------
    dataset : Dataset
        The dataset without the images that could not be initialised.
    cam_from_world_R : ndarray, shape (M, 3, 3)
    cam_from_world_t : ndarray, shape (M, 3)
    n_input_images : int
    mapping : str
    f_px : float
    inlier_mask : ndarray of bool, shape (N,) or None
        Per observation of ``dataset``: consistent with its image's RANSAC pose.
    principal_point_px : ndarray, shape (2,) or None
        The initialisation's principal point (the image centre, or the centre of the
        disc the observations fill, refitted with the poses); None: the image centre.
    warp_w : float
        The initial lens's warp (:class:`~.initialize.LensHypothesis`); not 0: the radial
        mapping gets the warp term ``w`` starting there.
    folded : bool
        The initial lens is the folded orthographic one (``f sin a`` up to 180 deg), whose
        image no increasing radial mapping can follow.
    lens_radius_px : callable or None
        The initial lens family's image radius (px) at incidence (rad), ``(N,) -> (N,)``,
        NaN outside its domain (:meth:`~.initialize.LensHypothesis.radius_px`); None for
        a refitted polynomial (the radial mapping follows it in its own warp) or a
        start from elsewhere. :func:`warp_following_lens` reads it.
    alternatives : list of Initialisation
        Other initial lenses of a lens that left many observations inconsistent (its
        other warps, :class:`~.initialize.InitialisationResult`), most consistent
        first: :func:`calibrate` starts again from the first when its result cannot be
        trusted.
    folded_alternative : callable or None
        Returns the :class:`Initialisation` of the folded orthographic lens the search
        scored beside the chosen (fitted) one, posed on demand: :func:`calibrate` tries
        the sphere model from it when the result cannot be trusted otherwise.
    """

    dataset: Dataset
    cam_from_world_R: np.ndarray
    cam_from_world_t: np.ndarray
    n_input_images: int
    mapping: str
    f_px: float
    inlier_mask: np.ndarray | None = None
    principal_point_px: np.ndarray | None = None
    warp_w: float = 0.0
    folded: bool = False
    lens_radius_px: Callable[[np.ndarray], np.ndarray] | None = None
    alternatives: list[Initialisation] = field(default_factory=list)
    folded_alternative: Callable[[], Initialisation] | None = None
    #: radial reference calibrations adjusted from this start, by their options' text
    #: (:func:`_check_against_reference`: models compared from one initialisation,
    #: ``analysis.compare``'s eight, share one)
    references: dict[str, Calibration] = field(default_factory=dict, repr=False, compare=False)


def initialise(
    dataset: Dataset, seed: int = 0, progress: Callable[[str], None] | None = None
) -> Initialisation:
    """Initial poses by P3P + RANSAC with the lens unknown (see :mod:`.initialize`).

    Images that cannot be initialised are removed and reported in
    ``dataset.skipped_images``.
    """
    from .initialize import initialize_poses

    say = progress or (lambda _line: None)
    say(f"initialising {len(dataset.image_ids)} images (P3P + RANSAC, lens unknown)")
    init = initialize_poses(
        dataset.uv_px,
        dataset.obs_image,
        dataset.obs_target,
        dataset.target_xyz,
        dataset.width,
        dataset.height,
        len(dataset.image_ids),
        rng=np.random.default_rng(seed),
        progress=say,
    )
    say(f"initial lens: {init.lens.describe()} (family {init.mapping}, f = {init.f_px:.1f} px)")
    chosen = _initialisation_of(dataset, init, say)
    chosen.alternatives = [
        _initialisation_of(dataset, alt, lambda _line: None) for alt in init.alternatives
    ]
    if init.pose_folded is not None:
        pose_folded = init.pose_folded
        chosen.folded_alternative = lambda: _initialisation_of(
            dataset, pose_folded(), lambda _line: None
        )
    return chosen


def _initialisation_of(dataset: Dataset, init, say: Callable[[str], None]) -> Initialisation:
    """The :class:`Initialisation` of an :class:`~.initialize.InitialisationResult`:
    its poses, lens and consistent observations, without the images it failed on."""
    n_input_images = len(dataset.image_ids)
    R, t = init.cam_from_world_R, init.cam_from_world_t
    inliers = np.asarray(init.inlier_mask, bool)[init.ok[dataset.obs_image]]
    say(f"RANSAC: {int((~inliers).sum())} of {len(inliers)} observations inconsistent")
    if not np.all(init.ok):
        for i, why in sorted(init.failures.items()):
            say(f"  image {dataset.image_ids[i]} not initialised: {why}")
        reasons = {i: f"initialisation failed: {why}" for i, why in init.failures.items()}
        R, t = R[init.ok], t[init.ok]
        dataset = dataset.subset_images(init.ok, reasons)
    return Initialisation(
        dataset,
        R,
        t,
        n_input_images,
        init.mapping,
        float(init.f_px),
        inliers,
        init.principal_point_px.copy(),
        float(init.lens.warp_w),
        bool(init.lens.folded),
        None if init.lens.mapping == "fitted" or init.lens.folded else init.lens.radius_px,
    )


def resolve_control_sigma(dataset: Dataset, control_sigma: float | str | None) -> float | None:
    """The standard deviation (dataset units) the exact targets get, or None (kept exact).

    ``"auto"`` is ``CONTROL_SIGMA_RELATIVE`` times the diagonal of the bounding box of
    the targets with ``sigma == 0`` (None when fewer than two exist or they coincide).
    """
    if control_sigma != CONTROL_SIGMA_AUTO:
        return None if control_sigma is None else float(control_sigma)
    exact = dataset.target_xyz[dataset.target_sigma == 0]
    if exact.shape[0] < 2:
        return None
    diagonal = float(np.linalg.norm(exact.max(axis=0) - exact.min(axis=0)))
    return CONTROL_SIGMA_RELATIVE * diagonal if diagonal > 0 else None


def with_control_sigma(
    dataset: Dataset, control_sigma: float | None, say: Callable[[str], None] | None = None
) -> Dataset:
    """``dataset`` with its exact targets (``sigma == 0``) given ``control_sigma``.

    Parameters
    ----------
    dataset : Dataset
    control_sigma : float or None
        Standard deviation in the dataset's units (see :func:`resolve_control_sigma` for
        ``"auto"``); ``None`` returns ``dataset`` itself.
    say : callable(str), optional
        Told how many targets changed.

    Returns
    -------
    Dataset
        A copy whose ``target_sigma`` (T,) has ``control_sigma`` where it had 0.
    """
    if control_sigma is None:
        return dataset
    exact = dataset.target_sigma == 0
    if say is not None and exact.any():
        say(
            f"{int(exact.sum())} exact targets estimated with sigma {control_sigma:g} "
            f"{dataset.units} around their nominal coordinates (control_sigma)"
        )
    sigma = np.where(exact, float(control_sigma), dataset.target_sigma)
    return replace(dataset, target_sigma=sigma)


#: an image left with fewer observations of determined targets is not adjusted
MIN_DETERMINED_OBSERVATIONS = 4

#: the reason recorded for each observation :func:`without_undetermined_targets` leaves out
UNDETERMINED_REASON = "target without a sigma seen in one image only: not determined"


def without_undetermined_targets(
    dataset: Dataset, say: Callable[[str], None] | None = None
) -> tuple[Dataset, np.ndarray, np.ndarray]:
    """``dataset`` without the observations of targets the adjustment cannot determine.

    A target without a sigma (approximate coordinates only) seen in one image only has
    no depth along its ray: its observation has no redundancy (it says nothing about
    the lens) and leaves the normal equations singular, which read as "some intrinsics
    are not determined" (free networks of 10-25 images, where half of the room's
    targets are seen once: ``bench_lens_zoo.py --stress 40 --seed 212 --targets`` s09,
    s11, s29). Their observations are left out and recorded in ``dropped``; an image
    left with fewer than :data:`MIN_DETERMINED_OBSERVATIONS` goes to
    ``skipped_images``, which may leave other targets seen once: repeated until stable.
    The rig's joint adjustment, where another camera may see the target, takes them
    back (:mod:`.rig_joint`).

    Parameters
    ----------
    dataset : Dataset
    say : callable(str), optional
        Told what was left out.

    Returns
    -------
    dataset : Dataset
        The rest (``dataset`` itself when nothing is left out).
    keep_obs : ndarray of bool, shape (N,)
        The input's observations kept.
    keep_img : ndarray of bool, shape (M,)
        The input's images kept.
    """
    keep_obs = np.ones(dataset.n_observations, bool)
    keep_img = np.ones(len(dataset.image_ids), bool)
    if np.isfinite(dataset.target_sigma).all():
        return dataset, keep_obs, keep_img
    while True:
        undetermined = undetermined_targets(
            dataset.obs_image[keep_obs], dataset.obs_target[keep_obs], dataset.target_sigma
        )
        weak = keep_obs & undetermined[dataset.obs_target]
        keep_obs &= ~weak
        n_left = np.bincount(dataset.obs_image[keep_obs], minlength=len(dataset.image_ids))
        few = keep_img & (n_left < MIN_DETERMINED_OBSERVATIONS)
        keep_img &= ~few
        keep_obs &= keep_img[dataset.obs_image]
        if not weak.any() and not few.any():
            break
    if keep_obs.all():
        return dataset, keep_obs, keep_img
    # left out one by one in the images kept; the images removed go whole (below)
    left_out = ~keep_obs & keep_img[dataset.obs_image]
    out = dataset.subset_observations(~left_out, UNDETERMINED_REASON)
    n_targets = len(np.unique(dataset.obs_target[left_out]))
    if not keep_img.all():
        out = out.subset_images(
            keep_img,
            dict.fromkeys(
                np.flatnonzero(~keep_img).tolist(),
                f"fewer than {MIN_DETERMINED_OBSERVATIONS} observations of targets whose "
                "coordinates are determined",
            ),
        )
    if say is not None:
        gone = f"; images with too few left: {int((~keep_img).sum())}" if not keep_img.all() else ""
        say(
            f"{int(left_out.sum())} observations of {n_targets} targets without a sigma "
            f"seen in one image only left out (their coordinates are not determined){gone}"
        )
    return out, keep_obs, keep_img


UNFIXED_REASON = (
    "target without a sigma whose rays, outliers set aside, do not fix its position "
    "(parallel, meeting at so small an angle that its sigma exceeds the targets' extent, "
    "or weighted down to nothing): its adjusted coordinates are not determined"
)
LOST_TO_OUTLIERS_REASON = (
    "target without a sigma seen in fewer than two images once the outliers are set aside: "
    "its adjusted coordinates are not determined"
)

#: the words that end :data:`UNRELIABLE_REASON` (how a listed target is told unreliable)
UNRELIABLE_TAG = "not reliable"
UNRELIABLE_REASON = (
    "target without a sigma seen in two images only (one redundant observation: a "
    "mislabelled ray cannot be told from a good one), {misfit:.4g} {units} from its "
    "approximate coordinates where the targets seen in three or more images are "
    "{reference:.4g} {units} (median): " + UNRELIABLE_TAG
)


def targets_lost_to_outliers(dataset: Dataset, outlier: np.ndarray) -> np.ndarray:
    """Targets without a sigma that only outliers made look determined.

    :func:`without_undetermined_targets` leaves out the targets seen in one image before
    the adjustment. A target seen in two whose second ray is a blunder is kept, and the
    robust adjustment then sets that ray aside: the target is free along the other and
    drifts (zoo stress 214 s32, a free room of 8 images: six targets 0.5-6 km away,
    whose least-squares S-transform onto the approximate coordinates shrank the whole
    network 2000 times). Those targets are left out of the adjusted targets and listed
    with :data:`LOST_TO_OUTLIERS_REASON`; their observations stay in the file.

    Parameters
    ----------
    dataset : Dataset
        The adjusted observations.
    outlier : ndarray of bool, shape (N,)
        The observations classified as blunders.

    Returns
    -------
    ndarray of bool, shape (T,)
        Observed targets without a sigma seen in fewer than two images by the other
        observations.
    """
    outlier = np.asarray(outlier, bool)
    if not outlier.any():
        return np.zeros(len(dataset.target_ids), bool)
    good = ~outlier
    lost = undetermined_targets(
        dataset.obs_image[good], dataset.obs_target[good], dataset.target_sigma
    )
    lost &= np.bincount(dataset.obs_target, minlength=len(dataset.target_ids)) > 0
    # exact targets are not variables (sigma 0 is finite): never lost
    return lost


#: :func:`unreliable_targets`: a target seen in two images is not reliable when its
#: adjusted position is farther from its approximate coordinates than this many times the
#: median distance of the targets seen in three or more (plus 3 of its own sigma)
UNRELIABLE_MISFIT_FACTOR = 5.0


def unreliable_targets(
    obs_image: np.ndarray,
    obs_target: np.ndarray,
    good: np.ndarray,
    judge: np.ndarray,
    misfit: np.ndarray,
    sigma: np.ndarray | None = None,
) -> tuple[np.ndarray, float]:
    """Targets whose position rests on two rays and disagrees with its approximate
    coordinates: reliability (redundancy), not precision.

    A target without a sigma seen in two images has one redundant observation: a ray
    that is a blunder along the other's epipolar line leaves no residual, and when both
    are (two mislabels) the rays meet anywhere. Zoo stress 2912 s15 (a 160 deg room,
    5 % blunders): target T0156, seen twice and both times mislabelled, met 3.16 m off
    with small residuals; its precision was fine, and the similarity of the check points
    spread it over every other (92x the oracle's 3D error, trusted). A target seen in
    three or more images can be told from its blunders; one seen in two cannot, and
    when it also lands far from its approximate coordinates (compared with how far the
    targets seen in three or more land from theirs) nothing says which is wrong.

    Parameters
    ----------
    obs_image, obs_target : ndarray of int, shape (N,)
        Image and target index of each observation.
    good : ndarray of bool, shape (N,)
        The observations that are not blunders.
    judge : ndarray of bool, shape (T,)
        The targets to judge: variables without a sigma, determined.
    misfit : ndarray, shape (T,)
        Distance (dataset units) from each adjusted target, in the datum of the
        approximate coordinates, to its approximate coordinates.
    sigma : ndarray, shape (T,), optional
        Each target's sigma along its worst direction (dataset units), added 3 times
        to the limit (a target that two rays fix poorly may legitimately move).

    Returns
    -------
    unreliable : ndarray of bool, shape (T,)
    reference : float
        Median misfit of the judged targets seen in three or more images (NaN when
        fewer than 3 such targets: nothing is judged then).
    """
    judge = np.asarray(judge, bool)
    misfit = np.asarray(misfit, float)
    good = np.asarray(good, bool)
    n_targets = len(judge)
    stride = int(np.max(obs_image, initial=0)) + 1  # one code per (target, image) pair
    pairs = np.unique(np.asarray(obs_target)[good] * stride + np.asarray(obs_image)[good])
    n_images = np.bincount(pairs // stride, minlength=n_targets)
    reference = judge & (n_images >= 3) & np.isfinite(misfit)
    out = np.zeros(n_targets, bool)
    if reference.sum() < 3:
        return out, float("nan")
    median = float(np.median(misfit[reference]))
    limit = UNRELIABLE_MISFIT_FACTOR * median
    if sigma is not None:
        sig = np.asarray(sigma, float)
        limit = limit + 3.0 * np.where(np.isfinite(sig), sig, 0.0)
    with np.errstate(invalid="ignore"):
        out = judge & (n_images == 2) & np.isfinite(misfit) & (misfit > limit)
    return out, median


#: :func:`weak_targets`: a target whose sigma (worst direction) exceeds this fraction of
#: the targets' extent is weakly determined
WEAK_TARGET_FRACTION = 0.02


def targets_extent(xyz: np.ndarray) -> float:
    """Size of a set of targets (T, 3): the diagonal of the box of their 5th to 95th
    percentiles per axis (dataset units; a few targets that flew off do not count)."""
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    if len(xyz) == 0:
        return 0.0
    return float(np.linalg.norm(np.percentile(xyz, 95, axis=0) - np.percentile(xyz, 5, axis=0)))


def unfixed_targets(meet_sigma: np.ndarray, judge: np.ndarray, extent: float) -> np.ndarray:
    """Targets whose rays do not fix them: intersection sigma infinite, or beyond the
    extent of the network.

    Two rays meeting at a tiny angle give a finite sigma at the point where they meet,
    however far: a free stereo rig of 6 frames (``simulate_rig("stereo", 6, seed=9)``,
    every sigma removed) put a target seen by the two cameras of one frame, 12 cm
    apart, 53 km away in a 7 m room, and it was trusted. A target that could be
    anywhere in the network is not determined.

    Parameters
    ----------
    meet_sigma : ndarray, shape (T,)
        :func:`~gtsam_sphere.estimation.graph.intersection_sigma` (dataset units; NaN or
        0 for exact targets and targets not observed).
    judge : ndarray of bool, shape (T,)
        The targets to judge (those without a sigma).
    extent : float
        :func:`targets_extent` of the observed targets, in the units of ``meet_sigma``.

    Returns
    -------
    ndarray of bool, shape (T,)
    """
    sig = np.asarray(meet_sigma, float)
    judge = np.asarray(judge, bool)
    out = judge & np.isposinf(sig)
    if extent > 0:
        out |= judge & np.isfinite(sig) & (sig > extent)
    return out


def weak_targets(xyz: np.ndarray, meet_sigma: np.ndarray) -> tuple[float, np.ndarray]:
    """Targets the adjustment determines poorly, relative to the size of the network.

    Parameters
    ----------
    xyz : ndarray, shape (T, 3)
        Adjusted coordinates (dataset units).
    meet_sigma : ndarray, shape (T,)
        Each target's sigma along its worst direction (dataset units; NaN or 0 for
        exact targets): the full one (:meth:`BundleProblem.target_covariances`), or
        where that is not computed the intersection sigma
        (:func:`~gtsam_sphere.estimation.graph.intersection_sigma`, a lower bound).

    Returns
    -------
    limit : float
        :data:`WEAK_TARGET_FRACTION` of the extent (the 5-95 percentile box's
        diagonal) of the targets, dataset units.
    weak : ndarray of bool, shape (T,)
        ``meet_sigma > limit``.
    """
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    if len(xyz) == 0:
        return 0.0, np.zeros(0, bool)
    limit = WEAK_TARGET_FRACTION * targets_extent(xyz)
    sig = np.asarray(meet_sigma, float)
    return limit, np.isfinite(sig) & (sig > limit) | np.isposinf(sig)


class _FoldsEarly(Exception):
    """A radial run stopped early: the lens folds like a sphere (the message says how).

    ``sigma_px``: the robust scale of the radial adjustment where the fold was seen
    (px), None when the initial lens itself folds (no adjustment ran)."""

    def __init__(self, init: Initialisation, why: str, sigma_px: float | None = None):
        super().__init__(why)
        self.init = init
        self.sigma_px = sigma_px


class _FitsWorse(Exception):
    """A run stopped after its first adjustment: its robust scale ``sigma_px`` (px) is
    above the limit it was given (another model already fits clearly better)."""

    def __init__(self, sigma_px: float):
        super().__init__(f"robust sigma {sigma_px:.3f} px")
        self.sigma_px = sigma_px


def _folds_like_a_sphere_deg(fold_deg: float, seen_deg: float) -> bool:
    """:func:`_folds_like_a_sphere`'s test on the fold and the widest ray (degrees)."""
    return fold_deg < seen_deg and 80.0 <= fold_deg <= 100.0 and seen_deg > 90.0


def _fold_of_adjusted_mapping(
    problem: BundleProblem,
    values: gtsam.Values,
    r_px: np.ndarray,
    sigma_px: float,
    dataset: Dataset,
) -> tuple[float, float]:
    """Where the adjusted radial mapping of ``values`` folds and the widest ray whose
    residual ``r_px`` (N,) is within 3 ``sigma_px`` (degrees)."""
    theta = np.asarray(values.atVector(INTRINSICS_KEY), float)
    cam = camera_from_theta(problem, theta, dataset.width, dataset.height)
    inc = incidence_deg(adjusted_points_cam(problem, values))
    inlier = np.asarray(r_px) < 3.0 * sigma_px
    seen = inc[inlier] if inlier.any() else inc
    return float(np.degrees(cam.max_alpha_rad())), float(np.max(seen))


def _fold_probe(problem: BundleProblem, init: Initialisation, dataset: Dataset, when: str):
    """``after_stage`` hook of :func:`adjust` (and the check after it): raise
    :class:`_FoldsEarly` when the adjusted radial mapping folds like a sphere."""

    def probe(values: gtsam.Values, r_px: np.ndarray, sigma_px: float) -> None:
        fold_deg, seen_deg = _fold_of_adjusted_mapping(problem, values, r_px, sigma_px, dataset)
        if _folds_like_a_sphere_deg(fold_deg, seen_deg):
            raise _FoldsEarly(
                init,
                f"{when}'s mapping folds at {fold_deg:.1f} deg, rays seen to {seen_deg:.1f} deg",
                sigma_px,
            )

    return probe


@dataclass
class _StageProbe:
    """``after_stage`` hook of the first adjustment: the fold probe (may raise), then,
    with ``warp``, the warp probe: True (end the adjustment there, ``fired``) when
    another warp already fits the geometry clearly better (:func:`_better_warp`), as
    :func:`select_warp` re-warps and adjusts again from that state anyway."""

    fold: Callable[[gtsam.Values, np.ndarray, float], None] | None
    warp: bool
    problem: BundleProblem
    say: Callable[[str], None]
    fired: bool = False

    def __call__(self, values: gtsam.Values, r_px: np.ndarray, sigma_px: float) -> bool:
        if self.fold is not None:
            self.fold(values, r_px, sigma_px)
        if not self.warp:
            return False
        choice = _better_warp(self.problem, values, r_px, sigma_px)
        if choice is not None:
            self.say(
                f"warp w = {choice[0]:.2f} already fits better than the current one "
                f"({choice[1]:.3f} px vs {choice[2]:.3f} px): first adjustment ends here"
            )
            self.fired = True
        return self.fired


def _calibrate_once(
    dataset: Dataset,
    options: CalibrationOptions | None = None,
    progress: Callable[[str], None] | None = None,
    init: Initialisation | None = None,
    fold_probe: bool = False,
    station_sigma: bool = False,
    first_sigma_limit_px: float | None = None,
) -> tuple[Calibration, Initialisation]:
    """One calibration run (see :func:`calibrate`); returns it and its initialisation.

    ``fold_probe``: raise :class:`_FoldsEarly` when the initial lens is the folded
    orthographic one, or when the first adjustment's radial mapping already folds like a
    sphere (the rest of the radial run would only end in the same fold, and
    :func:`calibrate` then tries the sphere model first).

    ``first_sigma_limit_px``: raise :class:`_FitsWorse` when the first adjustment's
    robust sigma (px) is above it (the rest of the run would not be kept).

    ``station_sigma``: also the standard deviation of each image's camera centre (the
    square root of the trace of its position covariance, dataset units) from the
    marginal covariance, in ``calib.extra["station_sigma"]`` (M,) (absent when the
    system is singular)."""
    options = options or CalibrationOptions()
    say = progress or (lambda _line: None)
    rng = np.random.default_rng(options.seed)
    control_sigma = resolve_control_sigma(dataset, options.control_sigma)
    exact_targets = dataset.target_sigma == 0
    dataset = with_control_sigma(dataset, control_sigma, say)
    geometry = check_geometry(dataset)
    raise_if_degenerate(geometry)  # warnings to the logger
    if init is None:
        init = initialise(dataset, options.seed, say)
    if fold_probe and init.folded and options.fixed_intrinsics is None:
        raise _FoldsEarly(init, "the initial lens is the folded orthographic one")
    full = with_control_sigma(init.dataset, control_sigma)
    dataset, keep_obs, keep_img = without_undetermined_targets(full, say)
    init_R, init_t = init.cam_from_world_R[keep_img], init.cam_from_world_t[keep_img]
    inlier_mask = None if init.inlier_mask is None else np.asarray(init.inlier_mask)[keep_obs]
    posed = check_geometry(dataset, (init_R, init_t))
    geometry += raise_if_degenerate([p for p in posed if p not in geometry])
    n_input_images = init.n_input_images

    pp = np.array([(dataset.width - 1) / 2.0, (dataset.height - 1) / 2.0])
    if init.principal_point_px is not None:
        pp = np.asarray(init.principal_point_px, float)
    pc = np.einsum("nij,nj->ni", init_R[dataset.obs_image], dataset.target_xyz[dataset.obs_target])
    pc += init_t[dataset.obs_image]
    c0 = initial_principal_distance(dataset.uv_px, pc, pp)
    say(f"initial principal distance c = {c0:.1f} px")

    brown_names = options.brown_terms if options.model.uses_brown else ()
    radial_names = None
    if options.model.uses_radial:
        radial_names = radial_terms(options.radial_terms)
        brown_names = options.brown_terms
    warp_w = init.warp_w if radial_names is not None and init.warp_w != 0.0 else None
    if warp_w is not None:
        say(f"radial mapping with a warp (the initial lens squeezes its rim): w = {warp_w:.3f}")
    lens_cg = None  # the radial mapping's start when it follows the initial lens
    if radial_names is not None and init.lens_radius_px is not None and inlier_mask is not None:
        alpha = np.radians(incidence_deg(pc))
        rows = np.asarray(inlier_mask, bool) & (np.linalg.norm(pc, axis=1) > 0)
        follows = warp_following_lens(
            alpha[rows], init.lens_radius_px(alpha[rows]), len(radial_names), warp_w or 0.0
        )
        if follows is not None:
            w_new, misfit_new, misfit_old, lens_cg = follows
            say(
                f"radial mapping with the warp w = {w_new:.2f}: its {len(radial_names)} terms "
                f"follow the initial lens ({init.mapping}, f = {init.f_px:.1f} px) at the "
                f"observed incidences to {misfit_new:.3f} px RMS, against {misfit_old:.3f} px "
                f"with w = {warp_w or 0.0:.2f}"
            )
            warp_w = w_new if w_new != 0.0 else None
    problem = BundleProblem(
        obs_image=dataset.obs_image,
        obs_target=dataset.obs_target,
        uv_px=dataset.uv_px,
        target_xyz=dataset.target_xyz,
        target_sigma=dataset.target_sigma,
        n_images=len(dataset.image_ids),
        brown_names=tuple(brown_names),
        brown_scale_px=0.5 * max(dataset.width, dataset.height),
        noise=NoiseOptions(options.sigma_px or 1.0, options.loss, options.loss_threshold),
        points_per_factor=options.points_per_factor,
        fixed_intrinsics=None
        if options.fixed_intrinsics is None
        else np.asarray(options.fixed_intrinsics, float),
        radial_names=radial_names,
        radial_warp=warp_w,
    )
    world_from_cam = [
        gtsam.Pose3(gtsam.Rot3(R), gtsam.Point3(*t)).inverse() for R, t in zip(init_R, init_t)
    ]
    if radial_names is None:
        theta0 = np.concatenate([pp, [c0], np.zeros(len(brown_names))])
    else:
        # the observations RANSAC found consistent with the initial poses: the others
        # (40 % on a hard 3D object) would bend the polynomial
        fit_rows = np.ones(len(pc), bool)
        if inlier_mask is not None and inlier_mask.sum() >= 4 * (len(radial_names) + 1):
            fit_rows = np.asarray(inlier_mask, bool)
        cg = lens_cg
        if cg is None:
            cg = initial_radial(
                dataset.uv_px[fit_rows],
                pc[fit_rows],
                pp,
                len(radial_names),
                warp_w or 0.0,
                RADIAL_FIRST_START_MAX,
            )
        say(f"initial radial mapping: c = {cg[0]:.1f} px, g = {np.round(cg[1:], 4).tolist()}")
        theta0 = np.concatenate([pp, cg, np.zeros(len(brown_names))])
    if problem.fixed_intrinsics is not None:
        theta0 = problem.fixed_intrinsics.copy()
    values = initial_values(problem, world_from_cam, theta0)
    opt = OptimizerOptions(options.optimizer, options.max_iterations)
    say(
        f"adjusting: {len(dataset.image_ids)} images, {len(problem.free_targets)} free targets, "
        f"{dataset.n_observations} observations, datum {problem.datum.value}"
    )
    probing = fold_probe and radial_names is not None and problem.fixed_intrinsics is None
    # the probe also runs between the first adjustment's noise stages: a mapping that
    # folds like a sphere spends them crawling (seed 3 case 33 of the zoo, a 250 deg
    # orthographic lens: three Huber stages of 100 iterations each, 5.7 s of 9.8)
    stage_probe = _StageProbe(
        _fold_probe(problem, init, dataset, "a first-adjustment stage") if probing else None,
        problem.fixed_intrinsics is None and options.model.uses_radial,
        problem,
        say,
    )
    adj = adjust(
        problem,
        values,
        opt,
        say,
        estimate_sigma=options.sigma_px is None,
        first_stage_mask=inlier_mask,
        after_stage=stage_probe,
    )
    # the smallest scale its stages reached: a fit that then drifts away grows from it
    stage_sigma_px = adj.min_sigma_px
    reverted_warps: dict[float, Adjustment] = {}
    if stage_probe.fired:
        # the first adjustment stopped for a better warp: take it before anything else
        # adjusts this problem again
        problem, adj = select_warp(problem, adj, opt, say, options.sigma_px is None, reverted_warps)
    first_sigma_px = adj.sigma_px
    if first_sigma_limit_px is not None and first_sigma_px > first_sigma_limit_px:
        raise _FitsWorse(first_sigma_px)
    repaired = repair_poses(problem, adj, dataset, rng, say)
    if repaired:
        adj = readjust(problem, adj, opt, say, options.sigma_px is None)
    if probing:
        r_px = np.linalg.norm(adj.residuals_px, axis=1)
        _fold_probe(problem, init, dataset, "the first adjustment")(adj.values, r_px, adj.sigma_px)
    if control_sigma is not None and options.control_sigma == CONTROL_SIGMA_AUTO:
        problem, adj, control_sigma = refine_control_sigma(
            problem, adj, exact_targets, control_sigma, opt, say, options.sigma_px is None
        )
    if problem.fixed_intrinsics is None and options.model.uses_radial:
        problem, adj = select_warp(problem, adj, opt, say, options.sigma_px is None, reverted_warps)
    if options.select_terms and problem.fixed_intrinsics is None and _selects_terms(problem):
        problem, adj = select_terms(problem, adj, opt, say, options.sigma_px is None)
    history = adj.result.history
    correction = None
    knn_stable, knn_rounds = True, 0
    if options.model.uses_knn:
        from .correct import grey_box_loop

        adj, correction, history, knn_stable, knn_rounds = grey_box_loop(
            problem, adj, opt, options, say, adjust
        )

    cov_theta = None
    if options.covariance and problem.fixed_intrinsics is None:
        say("computing the precision of the intrinsics (marginal covariance)")
        cov_theta = intrinsics_covariance(problem, adj.values)
    calib = _result(dataset, problem, adj, correction, history, options, n_input_images)
    if station_sigma:
        keys = problem.image_keys()[0]
        cov = marginal_covariances(problem.build(), adj.values, keys)
        if cov is not None:
            # the pose is world_from_cam: its translation block (body axes) is the
            # camera centre's; the trace does not depend on the axes
            calib.extra["station_sigma"] = np.sqrt([np.trace(cov[k][3:, 3:]) for k in keys])
    left_out = ~keep_obs
    if left_out.any():
        # kept for the rig's joint adjustment, where another camera may determine them
        # (with those of the images left with too few: the rig's frames can pose them)
        calib.statistics["n_undetermined_observations"] = int(left_out.sum())
        calib.extra["undetermined_observations"] = {
            "image": [full.image_ids[i] for i in full.obs_image[left_out]],
            "target": [full.target_ids[j] for j in full.obs_target[left_out]],
            "uv_px": full.uv_px[left_out],
        }
    if control_sigma is not None:
        calib.statistics["control_sigma"] = control_sigma
        calib.statistics["control_sigma_mode"] = (
            "auto" if options.control_sigma == CONTROL_SIGMA_AUTO else "given"
        )
    if np.isfinite(stage_sigma_px):
        calib.statistics["first_stage_sigma_px"] = float(stage_sigma_px)
    findings = distrust_reasons(calib, cov_theta, options, problem, knn_stable, first_sigma_px)
    calib.statistics["distrust"] = [text for _, text in findings]
    calib.statistics["distrust_codes"] = [str(code) for code, _ in findings]
    calib.statistics["trusted"] = not findings
    calib.statistics["first_sigma_px"] = float(first_sigma_px)
    if options.model.uses_knn:
        calib.statistics["knn_rounds"] = int(knn_rounds)
    calib.extra["geometry_warnings"] = [
        {"code": str(p.code), "message": p.message, "advice": p.advice} for p in geometry
    ]
    names = problem.intrinsics_names()
    calib.statistics["intrinsics_names"] = names
    if cov_theta is not None:
        calib.statistics["intrinsics_sigma"] = dict(
            zip(names, map(float, np.sqrt(np.diag(cov_theta))))
        )
        calib.statistics["intrinsics_covariance"] = cov_theta
    return calib, init


def _folds_like_a_sphere(calib: Calibration) -> bool:
    """The radial mapping stops increasing inside the observed field, near 90 degrees,
    with rays observed past 90 degrees: what a lens that folds (an orthographic lens
    past 180 deg) looks like. A fold anywhere else is a model that does not fit, and
    the sphere model would only hide it behind large kNN corrections (a 150 deg
    pinhole lens "calibrated" by sphere+knn: trusted, 94x the oracle's error)."""
    cam = calib.camera
    if cam.radial is None:
        return False
    fold_deg = float(np.degrees(cam.max_alpha_rad()))
    seen_deg = float(calib.statistics["max_incidence_deg"])
    return _folds_like_a_sphere_deg(fold_deg, seen_deg)


#: an alternative initial lens's trusted calibration replaces an untrusted first one only
#: when its final robust sigma is at most this many times the first's: zoo stress 2912
#: s37 (a 330 deg double-sphere lens, 0.1 px noise, a board never seen within 63 deg of
#: the axis) was refused in warp w = 1 for a fold at 14 deg, where nothing was observed;
#: the alternative in w = 0 followed the lens so much worse (sigma 0.41 against 0.15 px)
#: that k = 3 neighbours learned the rest, and it was trusted at 3.6x the oracle's 3D error
ALTERNATIVE_SIGMA_LIMIT = 1.5


def _from_another_initial_lens(
    dataset: Dataset,
    options: CalibrationOptions,
    progress: Callable[[str], None] | None,
    init: Initialisation,
    calib: Calibration,
) -> Calibration:
    """A calibration that cannot be trusted, started from a lens that left many
    observations inconsistent: calibrate again from the initialisation's first
    alternative (:attr:`Initialisation.alternatives`) and keep that if it can be
    trusted (``statistics.initial_lens_fallback`` says so) and fits within
    :data:`ALTERNATIVE_SIGMA_LIMIT` of ``calib``'s robust sigma, else ``calib``
    (``statistics.initial_lens_fallback_refused`` says why, when the alternative was
    trusted but fit worse).

    Such a lens (zoo case 05: a 150 deg pinhole with strong Brown terms in a small
    circle, 55-65 % of the observations consistent) is chaotic: a change in the last
    digits of the initial poses can decide between trusted at 0.3x the oracle's 3D
    error and not trusted at 30-60x, and one of its other warps then often succeeds.
    """
    say = progress or (lambda _line: None)
    alt = init.alternatives[0]
    why = "; ".join(calib.statistics["distrust"])
    say(
        f"not trusted ({why}) from an initial lens that left "
        f"{int(np.sum(~np.asarray(init.inlier_mask, bool)))} observations inconsistent: "
        f"calibrating again from its alternative with warp w = {alt.warp_w:.1f} "
        f"({int(np.sum(alt.inlier_mask))} consistent)"
    )
    again, _ = _calibrate_once(dataset, options, progress, alt)
    if not again.statistics["trusted"]:
        say("not trusted from the alternative either: the first result is kept")
        return calib
    sigma_first, sigma_again = calib.statistics["sigma_px"], again.statistics["sigma_px"]
    if sigma_again > ALTERNATIVE_SIGMA_LIMIT * sigma_first:
        refused = (
            f"the alternative with warp w = {alt.warp_w:g} was trusted but follows the lens "
            f"worse: sigma {sigma_again:.4f} px against {sigma_first:.4f} px of the first "
            f"(more than {ALTERNATIVE_SIGMA_LIMIT:g}x)"
        )
        say(f"{refused}: the first result is kept")
        calib.statistics["initial_lens_fallback_refused"] = refused
        return calib
    again.statistics["initial_lens_fallback"] = (
        f"warp w = {init.warp_w:g} -> {alt.warp_w:g}: the first calibration was not trusted ({why})"
    )
    return again


#: the reason recorded for each image :func:`connected_images` leaves out
DISCONNECTED_REASON = (
    "shares no target with the images calibrated (its group of images is not held in the "
    "world frame by 3 non-collinear targets with a sigma)"
)


def connected_images(dataset: Dataset, error: DegenerateGeometryError) -> Dataset | None:
    """The images that can be adjusted together when the only fatal problem is that the
    images form groups sharing no target (``disconnected-network``).

    The groups held in the world frame (each by 3 non-collinear targets with a sigma)
    are kept; in a free network (no group held) the largest group (ties: the lowest
    first image). The others go to ``skipped_images`` with :data:`DISCONNECTED_REASON`.
    A free room of 8 images where one image, or a pair, saw only targets no other image
    saw (zoo stress 215 s20, 216 s20) was refused whole before; the diagnosis itself
    advises leaving the smaller groups out. A rig does not take this path: its joint
    adjustment holds a camera's other groups through their frames
    (:func:`.rig.largest_connected_part`).

    Parameters
    ----------
    dataset : Dataset
    error : DegenerateGeometryError
        The refusal of its calibration.

    Returns
    -------
    Dataset or None
        The images kept, or None when ``error`` has another fatal problem (or nothing
        would be left out).
    """
    problems = list(error.problems)
    if not problems or any(p.code is not ProblemCode.DISCONNECTED for p in problems):
        return None
    unheld = {i for p in problems for i in p.items}
    keep = np.array([i not in unheld for i in dataset.image_ids], bool)
    if not keep.any():
        groups = image_groups(dataset)
        if len(groups) < 2:
            return None
        keep[groups[0]] = True
    if keep.all():
        return None
    reasons = dict.fromkeys(np.flatnonzero(~keep).tolist(), DISCONNECTED_REASON)
    return dataset.subset_images(keep, reasons)


def calibrate(
    dataset: Dataset,
    options: CalibrationOptions | None = None,
    progress: Callable[[str], None] | None = None,
    init: Initialisation | None = None,
    *,
    keep_connected: bool = True,
) -> Calibration:
    """Calibrate the camera of ``dataset``: initialise, adjust, (learn corrections).

    Parameters
    ----------
    dataset : Dataset
        A validated ``dataset@1``.
    options : CalibrationOptions
    progress : callable(str), optional
        Receives progress lines (the CLI prints them on standard error).
    init : Initialisation, optional
        Reuse an initialisation (:func:`initialise`) of the same dataset.
    keep_connected : bool
        When the images form groups that share no target and that is the only reason
        to refuse the dataset, calibrate the images that can be adjusted together
        (:func:`connected_images`) and list the others in ``skipped_images`` with a
        logged warning (default); False raises (a rig's cameras: the joint adjustment
        holds their other groups).

    Returns
    -------
    Calibration
        Adjusted poses (``cam_from_world``), targets and the camera model,
        with statistics. For a free network (no target sigma) the result is
        S-transformed onto the approximate coordinates (inner-constraint
        datum: the approximations fix the datum and nothing else). When a
        radial model's mapping folds inside the observed field (a lens that
        folds, like an orthographic one past 180 deg) the sphere model is
        tried from the same initialisation and kept if it can be trusted
        (``statistics.model_fallback`` says so). When a result cannot be trusted and
        the initial lens left many observations inconsistent, the calibration starts
        again from the initialisation's best other lens and keeps that if it can be
        trusted (``statistics.initial_lens_fallback``).
    """
    if keep_connected:
        try:
            return calibrate(dataset, options, progress, init, keep_connected=False)
        except DegenerateGeometryError as error:
            part = connected_images(dataset, error)
            if part is None:
                raise
            n_out = len(dataset.image_ids) - len(part.image_ids)
            logger.warning(
                "the images form groups that share no target (%s): calibrating the %d "
                "images that can be adjusted together; %d left out (listed in "
                "skipped_images)",
                " ".join(str(error).split())[:300],
                len(part.image_ids),
                n_out,
            )
            if progress:
                progress(
                    f"the images form groups that share no target: {n_out} left out, "
                    f"{len(part.image_ids)} calibrated"
                )
            calib = calibrate(part, options, progress, None, keep_connected=False)
            calib.statistics["n_images_input"] = len(dataset.image_ids)
            return calib
    options = options or CalibrationOptions()
    say = progress or (lambda _line: None)
    fallback_options = sphere_fallback_options(options)
    fallback = fallback_options.model  # sphere(+knn), or brown(+knn) with a1 a2

    def sphere_instead(
        reason: str, init: Initialisation, radial_sigma_px: float | None
    ) -> Calibration | None:
        # a lens whose image folds (an orthographic lens past 180 deg: rays behind the
        # camera land inside the disc again) has no increasing radial mapping; the
        # sphere model holds it. Kept only if it can be trusted and fits about as well
        # as the radial mapping did where it was seen folding.
        terms = fallback_options.brown_terms if fallback.uses_brown else ()
        say(
            f"the radial mapping cannot follow this lens ({reason}): calibrating with the "
            f"sphere model{' (with ' + ', '.join(terms) + ')' if terms else ''} (a lens "
            "that folds, e.g. orthographic past 180 deg)"
        )
        # stopped after its first adjustment when that already fits clearly worse: the
        # rest (kNN rounds, covariance) would not be kept (10 of 16 s of a 262 deg sphere
        # lens seen on both sides of its fold, beyond a 4000x3000 sensor)
        limit = None if radial_sigma_px is None else SPHERE_FIT_RATIO * radial_sigma_px
        try:
            alt, _ = _calibrate_once(
                dataset, fallback_options, progress, init, first_sigma_limit_px=limit
            )
        except _FitsWorse as worse:
            say(
                f"the sphere model {sphere_fits_worse(worse.sigma_px, radial_sigma_px)}: the "
                f"{options.model} model after all"
            )
            return None
        why = "is not trusted" if not alt.statistics["trusted"] else ""
        why = why or sphere_fits_worse(alt.statistics["first_sigma_px"], radial_sigma_px)
        why = why or sphere_learns_a_misfit(alt.statistics.get("knn_rounds", 0))
        if why:
            say(f"the sphere model {why}: the {options.model} model after all")
            return None
        alt.statistics["model_fallback"] = f"{options.model} -> {alt.model}: {reason}"
        return alt

    radial = options.model.uses_radial
    try:
        calib, init = _calibrate_once(dataset, options, progress, init, fold_probe=radial)
    except _FoldsEarly as early:
        # the fold showed early (the initial lens, or the first adjustment): the sphere
        # model first, the whole radial run only if it cannot be trusted (seed 3 case 33
        # of the zoo, a 250 deg orthographic lens, ran both in full: 5.7x the median time)
        calib = sphere_instead(str(early), early.init, early.sigma_px)
        if calib is None:
            calib, _ = _calibrate_once(dataset, options, progress, early.init)
    else:
        if radial and not calib.statistics["trusted"] and _folds_like_a_sphere(calib):
            reason = "the radial mapping folded inside the observed field"
            calib = sphere_instead(reason, init, calib.statistics["first_sigma_px"]) or calib
        if not calib.statistics["trusted"] and init.alternatives:
            calib = _from_another_initial_lens(dataset, options, progress, init, calib)
        st = calib.statistics
        many_outliers = st.get("n_outliers", 0) > OUTLIER_SHARE * max(
            st.get("n_observations", 0), 1
        )
        if radial and many_outliers and init.folded_alternative is not None:
            # the search scored a folded lens beside the fitted one it chose; an odd
            # polynomial cannot follow a fold, and seen through one the geometry is wrong
            # and many observations disagree with it (a 322 deg orthographic object whose
            # sensor had a1 = 0.016: the fitted lens won the search, 18 % of the
            # observations ended beyond 5 sigma, 69x the oracle's 3D error)
            why = "; ".join(calib.statistics["distrust"])
            reason = f"the radial result is not trusted ({why}) and the lens may fold"
            folded = init.folded_alternative()
            calib = sphere_instead(reason, folded, calib.statistics["first_sigma_px"]) or calib
    if not radial and options.fixed_intrinsics is None and calib.statistics["trusted"]:
        _check_against_reference(dataset, options, say, init, calib)
    _warn_about_targets(calib)
    for reason in calib.statistics["distrust"]:
        logger.warning("do not trust this result: %s", reason)
    return calib


def _warn_about_targets(calib: Calibration) -> None:
    """Log the targets the result leaves out (not determined) and the weak ones, once,
    for the calibration returned (not for a run it replaced or a reference run)."""
    lost = getattr(calib, "extra", {}).get("undetermined_targets", [])
    doubtful = [entry for entry in lost if entry["reason"].endswith(UNRELIABLE_TAG)]
    lost = [entry for entry in lost if not entry["reason"].endswith(UNRELIABLE_TAG)]
    if doubtful:
        names = ", ".join(e["id"] for e in doubtful[:5]) + (", ..." if len(doubtful) > 5 else "")
        logger.warning(
            "%d targets seen in two images only are far from their approximate coordinates "
            "(%s): two rays cannot tell a mislabel from the target; left out of the "
            "adjusted targets (listed in undetermined_targets); check their labels or "
            "capture them in more images",
            len(doubtful),
            names,
        )
    if lost:
        names = ", ".join(entry["id"] for entry in lost[:5]) + (", ..." if len(lost) > 5 else "")
        logger.warning(
            "%d targets without a sigma are not determined once the outliers are set aside "
            "(%s): seen in fewer than two images, or rays that do not fix them; left out of "
            "the adjusted targets (listed in undetermined_targets)",
            len(lost),
            names,
        )
    n_weak = calib.statistics.get("n_targets_weak", 0)
    if n_weak:
        logger.warning(
            "%d of %d adjusted targets are weakly determined: sigma along the worst "
            "direction above %.4g %s, %g %% of the targets' extent (rays that meet at "
            "small angles, or poses the network holds poorly; listed in "
            "target_precision)",
            n_weak,
            len(calib.target_ids),
            calib.statistics["weak_target_limit"],
            calib.units,
            100 * WEAK_TARGET_FRACTION,
        )


#: a model the user chose (``sphere``, ``brown``, each ``+knn``) is not trusted when its
#: median residual exceeds this factor times a plain radial adjustment's from the same
#: start (:func:`fits_worse_than_reference`)
REFERENCE_FIT_RATIO = 1.2


def median_scale_px(residuals_px: np.ndarray) -> float:
    """Robust scale (px) of 2-D residuals (N, 2): their median norm / ``sqrt(2 ln 2)``."""
    return robust_sigma_px(np.linalg.norm(np.asarray(residuals_px, float), axis=1))


def fits_worse_than_reference(model: str, scale_px: float, reference_px: float) -> str:
    """Why a chosen model does not follow the lens ("" when it fits about as well as
    the reference).

    The reference is the radial mapping (``radial``: no kNN correction, every term
    kept) adjusted from the same initialisation. A model that follows the lens ends,
    with its kNN rounds, at most a few percent above it; one that does not leaves the
    misfit in the residuals or in a kNN field that trades off with the geometry. Zoo
    seeds 0-1 with ``--model sphere+knn`` (the paper's model; session 21): on boards and
    3D objects it was trusted at 10-380x the oracle's 3D error; those this rule catches
    had residuals 1.3-31x the reference's (the others, at 1.16x, are caught by
    :func:`stations_differ_from_reference`), while the rooms where it ended within 1.7x
    of the oracle were at 0.90-1.13x, one at 1.22x (1.48x the oracle, no longer
    trusted); ``--model sphere`` on a 180 deg equidistant board ended at 7.7 px against
    0.30 px, trusted at 296x.

    Parameters
    ----------
    model : str
        The chosen model's name (for the message).
    scale_px, reference_px : float
        Robust residual scales (px, :func:`median_scale_px`) of the chosen model's
        result and of the reference adjustment.

    Returns
    -------
    str
    """
    if not np.isfinite(reference_px) or scale_px <= REFERENCE_FIT_RATIO * reference_px:
        return ""
    return (
        f"the {model} model does not follow this lens: its residuals ({scale_px:.3f} px, "
        f"median scale) are {scale_px / reference_px:.2f} times those of a radial mapping "
        f"adjusted from the same start without corrections ({reference_px:.3f} px); the "
        f"default model ({DEFAULT_MODEL}) follows it"
    )


def _check_against_reference(
    dataset: Dataset,
    options: CalibrationOptions,
    say: Callable[[str], None],
    init: Initialisation,
    calib: Calibration,
) -> None:
    """Compare a chosen ``sphere``/``brown`` model's result with a radial reference.

    The reference is the radial mapping with every term and no kNN, adjusted from
    ``init`` with the marginal covariance of its poses (shared by the calibrations of
    one initialisation, :attr:`Initialisation.references`). Adds to ``calib``'s
    statistics (in place) ``scale_px``, ``reference_scale_px``,
    ``station_shift_vs_reference``, ``reference_trusted``, and the reasons of
    :func:`fits_worse_than_reference` and :func:`stations_differ_from_reference` to its
    distrust. A reference that cannot be adjusted is logged as a warning: no
    comparison."""
    say(f"checking the {options.model} model against a radial mapping from the same start")
    ref_options = replace(
        options,
        model=Model.RADIAL,
        brown_terms=None,
        select_terms=False,
        covariance=False,
        sigma_px=None,
    )
    key = repr(ref_options)
    if key not in init.references:
        try:
            init.references[key], _ = _calibrate_once(
                dataset, ref_options, None, init, station_sigma=True
            )
        except (GtsamSphereError, np.linalg.LinAlgError, RuntimeError) as exc:
            logger.warning(
                "the %s model could not be checked: the reference radial adjustment failed (%s)",
                options.model,
                exc,
            )
            return
    ref = init.references[key]
    st = calib.statistics
    st["reference_trusted"] = bool(ref.statistics["trusted"])
    scale = median_scale_px(calib.extra["observations"]["residual_px"])
    reference = median_scale_px(ref.extra["observations"]["residual_px"])
    st["reference_scale_px"] = reference
    st["scale_px"] = scale
    shift = station_shift(calib, ref)
    if shift is not None:
        st["station_shift_vs_reference"] = shift
    reasons = [
        (code, why)
        for code, why in (
            (
                Distrust.REFERENCE_FIT,
                fits_worse_than_reference(str(options.model), scale, reference),
            ),
            (
                Distrust.REFERENCE_STATIONS,
                stations_differ_from_reference(str(options.model), shift),
            ),
        )
        if why
    ]
    say(
        f"median residual scale {scale:.3f} px, the radial reference's {reference:.3f} px"
        + ("" if shift is None else f"; camera centres {shift:.2f} sigma from the reference's")
        + (": not trusted" if reasons else "")
    )
    if reasons:
        st["distrust"].extend(why for _, why in reasons)
        st.setdefault("distrust_codes", []).extend(str(code) for code, _ in reasons)
        st["trusted"] = False


def station_shift(calib: Calibration, reference: Calibration) -> float | None:
    """RMS distance between the camera centres of ``calib`` and of ``reference`` over
    the images both posed, in units of the reference's RMS station sigma
    (``reference.extra["station_sigma"]``); None without it or a common image."""
    sigma = reference.extra.get("station_sigma")
    if sigma is None:
        return None
    ref = {
        i: (-R.T @ t, s)
        for i, R, t, s in zip(
            reference.image_ids, reference.cam_from_world_R, reference.cam_from_world_t, sigma
        )
    }
    d2, s2 = [], []
    for i, R, t in zip(calib.image_ids, calib.cam_from_world_R, calib.cam_from_world_t):
        if i in ref:
            centre, s = ref[i]
            d2.append(float(np.sum((-R.T @ t - centre) ** 2)))
            s2.append(float(s) ** 2)
    if not d2 or not np.isfinite(s2).all() or np.mean(s2) <= 0:
        return None
    return float(np.sqrt(np.mean(d2) / np.mean(s2)))


#: a model the user chose is not trusted when its camera centres lie further than this
#: many (RMS) station sigmas from the radial reference's (:func:`stations_differ_from_reference`)
STATION_SHIFT_LIMIT = 5.0


def stations_differ_from_reference(model: str, shift: float | None) -> str:
    """Why a chosen model's geometry is not the lens's ("" when its camera centres lie
    within :data:`STATION_SHIFT_LIMIT` station sigmas of the reference's, or ``shift``
    is None).

    A kNN field can follow a misfit of the model in the image and still move the
    cameras: the field trades off with ``c`` and the distances to the targets.
    ``shift`` is :func:`station_shift` against the radial reference of
    :func:`_check_against_reference`.
    """
    if shift is None or shift <= STATION_SHIFT_LIMIT:
        return ""
    return (
        f"the {model} model moves the cameras: their centres lie {shift:.1f} sigma (RMS) "
        "from those of a radial mapping adjusted from the same start; its correction "
        f"trades off with the geometry (the default model, {DEFAULT_MODEL}, follows this lens)"
    )


def sphere_fallback_options(options: CalibrationOptions) -> CalibrationOptions:
    """The options of the sphere model that stands in for a radial mapping seen folding.

    The sphere mapping (``+knn`` when the options learn a correction), with the
    options' affinity terms (``a1, a2``, of the radial model's defaults) as Brown
    terms, so that the fallback models a sensor's affinity as the radial model would
    (term selection drops them when the data do not support them). Without them, a 203
    deg orthographic board whose sensor had ``a1 = 0.015`` (draw s06 of ``--stress 40
    --seed 209 --defects``) was trusted at 4.9x the oracle's 3D error, its principal
    point 8 px off: the kNN rounds had learned the affinity (1.07x with them). The
    decentering pair is left to the kNN rounds: on a folded lens it trades off with the
    principal point (zoo seed 0 case 35, a 360 deg orthographic object with a moving
    pupil and an error field, kept ``p1, p2`` and ended 2.1 px off, 0.26 px without).

    Parameters
    ----------
    options : CalibrationOptions

    Returns
    -------
    CalibrationOptions
        ``sphere``/``sphere+knn`` without ``a1, a2`` among the options' terms, else
        ``brown``/``brown+knn`` with them.
    """
    pa = tuple(t for t in options.brown_terms if t in ("a1", "a2"))  # see above
    if not pa:
        model = Model.SPHERE_KNN if options.model.uses_knn else Model.SPHERE
        return replace(options, model=model, brown_terms=())
    model = Model.BROWN_KNN if options.model.uses_knn else Model.BROWN
    return replace(options, model=model, brown_terms=pa)


#: the sphere model replaces a radial mapping seen folding only if its first
#: adjustment's robust sigma is at most this factor times the radial adjustment's there
SPHERE_FIT_RATIO = 1.5


def sphere_fits_worse(sphere_sigma_px: float, radial_sigma_px: float | None) -> str:
    """Why the sphere model fits a lens clearly worse than the radial mapping seen
    folding on it ("" when it does not, or ``radial_sigma_px`` is None).

    Both are robust scales (px) of a first adjustment of the same data from the same
    initialisation: the sphere model's, and the radial adjustment's where its mapping
    was seen folding (or its first adjustment's). A lens that does fold (an
    orthographic lens past 180 deg) fits the sphere model at least as well (a 250 deg
    orthographic room: 0.294 px against 0.329 px). A lens whose rim is only squeezed
    near a fold beyond the field (a 215 deg catadioptric lens, unified ``xi`` 2.17, on
    a 240 px circle with 1 px noise and 2 % blunders) can make an early radial stage
    fold too, and the sphere model then fits at 2.65 px against 1.01 px: its kNN
    rounds learned the misfit as a 2 px "field", trusted at 20x the oracle's 3D error.

    Parameters
    ----------
    sphere_sigma_px : float
        The sphere model's first adjustment's robust sigma (px).
    radial_sigma_px : float or None
        The radial adjustment's (px).

    Returns
    -------
    str
    """
    if radial_sigma_px is None or sphere_sigma_px <= SPHERE_FIT_RATIO * radial_sigma_px:
        return ""
    return (
        f"fits worse than the radial mapping where it folded (robust sigma "
        f"{sphere_sigma_px:.3f} px against {radial_sigma_px:.3f} px)"
    )


#: the sphere model standing in for a lens that folds is kept only if its kNN loop
#: settles within this many rounds
FALLBACK_KNN_ROUNDS = 8


def sphere_learns_a_misfit(knn_rounds: int) -> str:
    """Why the kNN loop of the sphere model that stands in for a lens seen folding says
    the model does not follow the lens ("" when it settled within
    :data:`FALLBACK_KNN_ROUNDS` rounds).

    A lens that folds is the sphere model's own: over zoo seeds 0-7 and 80 random draws
    beyond them (session 17), the 38 calibrations kept on that model settled in 2-4
    rounds, error fields and moving pupils included. Where the fold was an early radial
    stage's mistake (a 98 deg double-sphere lens on a board with 5 % blunders: its
    adjusted geometry saw rays at 96 deg), the sphere model fits about as well as that
    stage (1.19 against 0.98 px, within :data:`SPHERE_FIT_RATIO`), and the kNN rounds
    then learn the misfit as a 1 px "field" over 13 rounds: trusted at 48x the oracle's
    3D error with ``c`` 15 % off. (The paper's own ``sphere+knn``, chosen by the user
    for a lens that does not fold, learns a field of hundreds of px over 10-20 rounds:
    that is what this rule refuses for a fallback.)

    Parameters
    ----------
    knn_rounds : int
        ``statistics.knn_rounds`` of the sphere model's calibration (0 without kNN).

    Returns
    -------
    str
    """
    if knn_rounds <= FALLBACK_KNN_ROUNDS:
        return ""
    return (
        f"needed {knn_rounds} kNN rounds (a lens that folds settles in a few): its "
        "correction learned a misfit"
    )


def readjust(
    problem: BundleProblem,
    adj: Adjustment,
    optimizer: OptimizerOptions,
    say: Callable[[str], None],
    estimate_sigma: bool = True,
    values: gtsam.Values | None = None,
    warm: bool = False,
) -> Adjustment:
    """Adjust ``problem`` again from ``adj``'s state (or ``values``), its first stage on
    the observations ``adj`` left within 5 sigma (after a pose repair, a new target
    prior or fewer intrinsics). ``warm``: the start is ``adj``'s converged robust
    solution barely changed (terms the data do not support dropped): robust stages
    from ``adj``'s scale, no least-squares stage (:func:`adjust`)."""
    consistent = np.linalg.norm(adj.residuals_px, axis=1) < 5.0 * adj.sigma_px
    start = gtsam.Values(adj.values) if values is None else values
    if warm:
        problem.noise = NoiseOptions(adj.sigma_px, problem.noise.loss, problem.noise.loss_threshold)
    return adjust(
        problem,
        start,
        optimizer,
        say,
        estimate_sigma=estimate_sigma,
        first_stage_mask=None if warm else consistent,
        warm=warm,
        first_stage_all=False,
    )


def refine_control_sigma(
    problem: BundleProblem,
    adj: Adjustment,
    exact: np.ndarray,
    control_sigma: float,
    optimizer: OptimizerOptions,
    say: Callable[[str], None],
    estimate_sigma: bool = True,
) -> tuple[BundleProblem, Adjustment, float]:
    """Match the automatic shape prior of the exact targets to the shape the data show.

    The automatic prior (1e-3 of the object's extent) is a guess. Once adjusted, the
    targets' shifts from their nominal coordinates tell how far from its design the
    object really is: a curled printed board moves its corners by a few tenths of a
    millimetre, a perfect object only by the noise. The prior becomes the RMS of the
    shifts per coordinate (a variance-component estimate that takes the prior's
    redundancy as complete), clipped to [1/20, 3] times the previous value, and the
    problem is adjusted again while it changes by more than a factor 1.5 (at most 3
    times: a perfect object tends to exact, a warped one to its warp). A needlessly
    loose prior on a perfect object weakens the network (a simulated cube corner:
    1.35x the oracle's camera-station error with 0.6 mm, 1.13x held exact).

    Parameters
    ----------
    problem, adj : the adjusted problem.
    exact : (T,) bool, targets the dataset marked exact (``sigma == 0``).
    control_sigma : the prior sigma they got (dataset units).

    Returns
    -------
    (problem, adjustment, sigma)
    """
    idx = [int(t) for t in problem.free_targets if exact[int(t)]]
    if len(idx) < 4:
        return problem, adj, control_sigma
    for _ in range(3):
        xyz = np.array([adj.values.atPoint3(point_key(t)) for t in idx])
        rms = float(np.sqrt(np.mean((xyz - problem.target_xyz[idx]) ** 2)))
        sigma = float(np.clip(rms, control_sigma / 20.0, 3.0 * control_sigma))
        if not np.isfinite(sigma) or max(sigma / control_sigma, control_sigma / sigma) < 1.5:
            break
        say(
            f"exact targets moved {rms:.3g} RMS per coordinate with a prior of "
            f"{control_sigma:.3g}: prior set to {sigma:.3g}, adjusting again"
        )
        target_sigma = problem.target_sigma.copy()
        target_sigma[exact] = sigma
        problem = replace(problem, target_sigma=target_sigma)
        adj = readjust(problem, adj, optimizer, say, estimate_sigma)
        control_sigma = sigma
    return problem, adj, control_sigma


def adjusted_target_xyz(problem: BundleProblem, values: gtsam.Values) -> np.ndarray:
    """World coordinates of every target (T, 3): the adjusted ones where free, else nominal."""
    xyz = np.array(problem.target_xyz, float, copy=True)
    for j in problem.free_targets:
        xyz[j] = values.atPoint3(point_key(int(j)))
    return xyz


def adjusted_points_cam(problem: BundleProblem, values: gtsam.Values) -> np.ndarray:
    """Every observed target in its camera's frame (N, 3), metres: the adjusted poses
    (``cam_from_world``) applied to :func:`adjusted_target_xyz`."""
    R, t = _poses_from_values(values, problem.n_images)
    xyz = adjusted_target_xyz(problem, values)
    pc = np.einsum("nij,nj->ni", R[problem.obs_image], xyz[problem.obs_target])
    return pc + t[problem.obs_image]


#: a calibration whose final robust sigma exceeds this factor times its first
#: adjustment's is not trusted
SIGMA_GROWTH = 3.0
#: :func:`select_terms` keeps the terms when the reduced model's robust sigma exceeds
#: this factor times the full one's (the dropped terms were not zero after all). Not
#: near 1: with few observations per unknown the full model's sigma is the optimistic
#: one (a rig's narrow pinhole alone, 167 observations of 136 targets mostly seen once:
#: 0.164 px with every term, 0.245 px reduced, and the reduced model's poses are the
#: right ones, within 0.37 deg against 1.54 deg; 1.05 here kept the overfit)
TERMS_SIGMA_GAIN = 2.0
#: log-warps :func:`select_warp` compares (``k = exp(w)`` from 0.2 to 5)
WARP_GRID = tuple(round(float(w), 2) for w in np.arange(-1.6, 1.601, 0.05))
#: a warp replaces the current one only if its radial fit's robust residual is
#: below this fraction of the current warp's
WARP_GAIN = 0.8
#: the warps are scored with the mapping's own terms too when the best one-term fit's
#: robust residual exceeds this many sigma (the one term cannot follow the shape)
WARP_TERMS_GATE = 5.0
#: rows (evenly spread in incidence) of that scoring
WARP_TERMS_ROWS = 2000


def _warp_scores(r_px: np.ndarray, alpha: np.ndarray, warps, n_terms: int = 1) -> np.ndarray:
    """Robust residual (px) of the radial fit ``r = c (beta + g3 ... )`` with ``n_terms``
    terms per warp."""
    scores = []
    for w in warps:
        beta = alpha if w == 0.0 else math.exp(w) * radial_warp(alpha, w)
        cg = _fit_radial(r_px, beta, n_terms)
        pred = cg[0] * radial_g(beta, cg[1:])
        scores.append(MAD_TO_SIGMA * float(np.median(np.abs(pred - r_px))))
    return np.asarray(scores)


def _better_warp(
    problem: BundleProblem, values: gtsam.Values, r_px: np.ndarray, sigma_px: float
) -> tuple[float, float, float, np.ndarray] | None:
    """The warp of :data:`WARP_GRID` whose radial fit to the geometry at ``values``, with
    one term or else with the mapping's terms, has a robust residual below
    :data:`WARP_GAIN` times the current warp's.

    ``r_px`` (N,) are the residual norms at ``values`` and ``sigma_px`` their scale:
    the observations within 3 sigma are fitted.

    Returns
    -------
    (w, best_px, current_px, keep) or None
        The warp, the two fits' robust residuals (px) and the (N,) bool rows fitted;
        None when the current warp stays (or fewer than 20 rows are usable).
    """
    theta = np.asarray(values.atVector(INTRINSICS_KEY), float)
    pc = adjusted_points_cam(problem, values)
    norm = np.linalg.norm(pc, axis=1)
    alpha = np.arccos(np.clip(pc[:, 2] / np.where(norm > 0, norm, 1.0), -1.0, 1.0))
    r = np.linalg.norm(problem.corrected_uv_px - theta[:2], axis=1)
    keep = np.asarray(r_px) < 3.0 * sigma_px
    keep &= np.isfinite(alpha) & np.isfinite(r) & (norm > 0) & (alpha > 1e-3)
    if keep.sum() < 20:
        return None
    current = float(problem.radial_warp or 0.0)
    warps = sorted(set(WARP_GRID) | {current})
    # one term first: the warp that makes the shape simple (a 170 deg fov lens on a
    # board: w = 0.6, then two terms, 0.93x the oracle; left at w = 0 its six terms
    # bend to follow it, 1.35x). Then, only where one term cannot follow the shape at
    # all (its best fit beyond WARP_TERMS_GATE sigma: 33 sigma for a 340 deg
    # stereographic lens, 1.0-1.4 sigma for the zoo's others), the mapping's own
    # terms: one term ranks the warps by the first few tens of degrees, and that lens
    # kept w = 0, whose six terms left c 13 % off, 1.48x the oracle's 3D error; six
    # terms pick w = 0.25: 1.00x. On at most WARP_TERMS_ROWS rows spread evenly in
    # incidence: six terms for 65 warps cost 3 s on 7,000 observations.
    rows = np.flatnonzero(keep)
    scores = _warp_scores(r[rows], alpha[rows], warps)
    choice = _warp_winner(scores, warps, current)
    n_terms = len(problem.radial_names or ())
    if choice is None and n_terms > 1 and float(np.min(scores)) > WARP_TERMS_GATE * sigma_px:
        if len(rows) > WARP_TERMS_ROWS:
            by_alpha = rows[np.argsort(alpha[rows], kind="stable")]
            rows = by_alpha[np.linspace(0, len(rows) - 1, WARP_TERMS_ROWS).astype(int)]
        scores = _warp_scores(r[rows], alpha[rows], warps, n_terms)
        choice = _warp_winner(scores, warps, current, _terms_gain(len(rows)))
    return None if choice is None else (*choice, keep)


def _terms_gain(n_rows: int) -> float:
    """:data:`WARP_GAIN` of the scoring with the mapping's terms on ``n_rows`` rows: a
    warp wins when its residual is two standard errors of a MAD below the current
    one's (0.948 on 2,000 rows).

    Those fits reach the noise, which both residuals share, so a real gain in shape is a
    small fraction of the residual: a 340 deg stereographic room (seed 8 case 27 of the
    zoo) scored 0.304 px against 0.331 px for ``w = 0`` (0.92); with the one-term gain
    0.8 it kept ``w = 0``, 1.10x the oracle's 3D error; with this gain 0.76x.
    """
    return 1.0 - 2.0 * MAD_RELATIVE_SE / math.sqrt(max(n_rows, 1))


def _warp_winner(scores: np.ndarray, warps: list, current: float, gain: float = WARP_GAIN):
    """``(w, best_px, current_px)`` of the best-scoring warp when it scores below
    ``gain`` times the ``current`` one, else None."""
    best = int(np.argmin(scores))
    now = float(scores[warps.index(current)])
    if warps[best] == current or scores[best] >= gain * now:
        return None
    return float(warps[best]), float(scores[best]), now


def select_warp(
    problem: BundleProblem,
    adj: Adjustment,
    optimizer: OptimizerOptions,
    say: Callable[[str], None],
    estimate_sigma: bool = True,
    reverted: dict[float, Adjustment] | None = None,
) -> tuple[BundleProblem, Adjustment]:
    """Choose the radial mapping's warp from the adjusted geometry (radial models).

    The initial lens family fixes the warp ``w`` of the radial mapping's variable
    (:func:`~gtsam_sphere.core.camera.radial_warp`): 0 (equidistant) for most
    families. The polynomial terms can follow any smooth mapping, but a poorly
    matched warp needs many of them and they trade off with the poses: a simulated
    170 deg field-of-view lens (omega 1.5, true ``w`` 0.62) seen on a board had 1.35x
    the oracle's camera-station error with ``w = 0`` and six terms, 0.86x with its
    own warp and none. With the adjusted poses and targets, the image radius of
    every observation is fitted as ``c * g(alpha)`` for each warp of
    :data:`WARP_GRID`, with one term and, when no warp wins that way, with the
    mapping's own terms (:func:`_better_warp`); when the best fit's robust residual is below
    :data:`WARP_GAIN` times the current warp's, the mapping is re-initialised with
    that warp (all its terms refitted) and adjusted again, and kept only if the new
    adjustment's robust sigma is not worse than the old one.

    ``reverted`` (filled here) maps each warp reverted to the adjustment it was tried
    from: the same warp from the same adjustment is not tried again (the calibration
    asks twice when the first adjustment stopped early for a warp; zoo seed 9 case 05,
    a 150 deg pinhole with strong Brown terms, readjusted the same reverted warp twice,
    34 s of 148).

    Returns
    -------
    (problem, adjustment)
        The re-warped ones, or the inputs.
    """
    choice = _better_warp(
        problem, adj.values, np.linalg.norm(adj.residuals_px, axis=1), adj.sigma_px
    )
    if choice is None:
        return problem, adj
    w, best, now, keep = choice
    if reverted is not None and reverted.get(w) is adj:
        say(f"warp w = {w:.2f} was tried from this adjustment and reverted: not again")
        return problem, adj
    current = float(problem.radial_warp or 0.0)
    theta = np.asarray(adj.values.atVector(INTRINSICS_KEY), float)
    names = list(problem.intrinsics_names())
    pc = adjusted_points_cam(problem, adj.values)
    pp = theta[:2]
    uv = problem.corrected_uv_px
    cg = initial_radial(uv[keep], pc[keep], pp, len(problem.radial_names), w)
    rewarped = replace(problem, radial_warp=None if w == 0.0 else w)
    new_theta = theta.copy()
    new_theta[names.index("c_px")] = cg[0]
    for k, name in enumerate(problem.radial_names):
        new_theta[names.index(name)] = cg[1 + k]
    values = gtsam.Values(adj.values)
    values.update(INTRINSICS_KEY, new_theta)
    say(
        f"radial mapping: warp w = {w:.2f} fits the adjusted geometry better than "
        f"w = {current:.2f} (radial fit residual {best:.3f} px vs "
        f"{now:.3f} px); adjusting with it"
    )
    new = readjust(rewarped, adj, optimizer, say, estimate_sigma, values)
    why = rewarp_rejected(new.result.status, new.sigma_px, adj.sigma_px)
    if why:
        say(f"warp w = {w:.2f}: {why} (sigma {new.sigma_px:.4f} px): reverted")
        if reverted is not None:
            reverted[w] = adj
        return problem, adj
    return rewarped, new


def rewarp_rejected(status, new_sigma_px: float, old_sigma_px: float) -> str:
    """Why the re-warped adjustment of :func:`select_warp` is not kept ("" to keep it).

    Kept when it converged with a robust sigma at most 2 % above the old one, or when
    it stopped unconverged, at its iteration limit or stalled (no step lowered the cost
    at any damping), but not diverged, with a sigma already 2 % below the old one: the
    stages after it go on from there. (A 340 deg stereographic lens of the zoo, seed 1
    case 27, reached sigma 0.316 px with its own warp against 0.379 px without, at the
    limit of 100 iterations; reverting it left 1.44x the oracle's 3D error, keeping it
    1.04x. A 170 deg sphere lens on a board, seed 1 case 31, started with a poor warp
    stalled at sigma 0.498 px with a better one against 1.011 px: reverted, the
    calibration was not trusted; kept, 1.04x and trusted.)

    Parameters
    ----------
    status : str or LMStatus
        The adjustment's status (``"converged"``, ``"max-iterations"`` /
        ``"max_iterations"``, ``"stalled: ..."``, ``"diverged"``).
    new_sigma_px, old_sigma_px : float
        Robust sigma (px) of the re-warped and of the current adjustment.

    Returns
    -------
    str
        The reason, or "" when the re-warped adjustment is kept.
    """
    status = str(status).replace("-", "_")
    if status == "converged":
        return "" if new_sigma_px <= 1.02 * old_sigma_px else "no better"
    if status == "max_iterations" or status.startswith("stalled"):
        return "" if new_sigma_px < 0.98 * old_sigma_px else "not converged and not better"
    return f"not converged ({status})"


def _selects_terms(problem: BundleProblem) -> bool:
    """Term selection applies to the radial mapping, and to the sphere mapping with
    decentering and affinity terms only (no radial Brown terms): the sphere fallback."""
    if problem.radial_names is not None:
        return True
    brown = problem.brown_names
    return bool(brown) and all(t in PA_TERMS for t in brown)


def likelihood_ratio(wald: float, dof: float) -> float:
    """The likelihood-ratio statistic ``r ln(1 + W / r)`` of dropped terms whose Wald
    statistic ``W`` was computed with a sigma estimated from ``r`` degrees of freedom.

    Equal to ``W`` when ``r`` is large (every room and board of the lens zoo: ``r`` in
    the thousands); smaller where the sigma itself is uncertain. The Wald statistic
    takes the estimated sigma as exact: a rig's narrow pinhole, 6 frames and 105 of 136
    targets seen once (``r`` = 32), had its sigma at 0.16 px for 0.3 px of noise, and
    the decentering pair passed with an increment of 14.2 against a penalty of 11.6
    (10.3 here), poses 1.0 deg off against 0.42 deg without it.

    Parameters
    ----------
    wald : float
        ``W`` (``inf`` stays ``inf``).
    dof : float
        ``r``; not positive: ``wald`` unchanged.

    Returns
    -------
    float
    """
    if dof <= 0.0 or not np.isfinite(wald):
        return float(wald)
    return float(dof * np.log1p(wald / dof))


def terms_to_drop(
    theta: np.ndarray,
    cov: np.ndarray,
    names: list[str],
    radial_names: tuple[str, ...],
    brown_names: tuple[str, ...],
    n_observations: int,
    dof: float,
) -> list[str]:
    """The terms :func:`select_terms` drops, from the intrinsics and their covariance.

    The radial order ``k`` with the smallest ``L(S_k) + k ln(2 N)`` (``S_k`` the radial
    terms above order ``k``, ``L`` the :func:`likelihood_ratio` of their Wald statistic;
    ties go to fewer terms), then each of the pairs ``(p1, p2)``, ``(a1, a2)`` present
    while its own increment ``L(S + G) - L(S)`` stays below ``|G| ln(2 N)``.

    Parameters
    ----------
    theta : ndarray, shape (K,)
        The intrinsics, in the order of ``names``.
    cov : ndarray, shape (K, K)
        Their covariance.
    names : list of str, length K
    radial_names : tuple of str
        The radial terms ``g3, g5, ...`` in increasing order.
    brown_names : tuple of str
        The Brown terms among ``names``.
    n_observations : int
        ``N`` (2-D observations).
    dof : float
        The degrees of freedom of the sigma ``cov`` was computed with.

    Returns
    -------
    list of str
        The radial terms dropped, highest order first, then the pairs.
    """
    penalty = float(np.log(2.0 * max(n_observations, 1)))

    def stat(subset: list[str]) -> float:
        k = [names.index(n) for n in subset]
        if not k:
            return 0.0
        try:
            w = float(theta[k] @ np.linalg.solve(cov[np.ix_(k, k)], theta[k]))
        except np.linalg.LinAlgError:
            return np.inf
        return likelihood_ratio(w, dof)

    radial = list(radial_names)
    bic = [stat(radial[k:]) + k * penalty for k in range(len(radial) + 1)]
    order = min(range(len(radial) + 1), key=lambda k: (bic[k], k))
    drop = radial[order:][::-1]
    s_drop = bic[order] - order * penalty  # L(drop)
    for pair in (("p1", "p2"), ("a1", "a2")):
        group = [n for n in pair if n in brown_names]
        if not group:
            continue
        s_new = stat(drop + group)
        if s_new - s_drop < penalty * len(group):
            drop += group
            s_drop = s_new
    return drop


def select_terms(
    problem: BundleProblem,
    adj: Adjustment,
    optimizer: OptimizerOptions,
    say: Callable[[str], None],
    estimate_sigma: bool = True,
) -> tuple[BundleProblem, Adjustment]:
    """Drop the radial and decentering/affinity terms the data cannot support.

    Every added intrinsic costs accuracy where the geometry is weak (a planar board:
    p1, p2, a1, a2 and the high radial terms trade off with the poses; on a simulated
    90 deg equidistant lens seen on a board, the default 4 + 4 terms gave 1.35x the
    oracle's camera-station error, ``xp, yp, c`` alone 1.02x). A BIC choice on the Wald
    statistic ``W = theta_S^T Cov_SS^-1 theta_S`` of the set ``S`` of dropped terms
    (``~ chi^2(|S|)`` when they are zero), used as its likelihood ratio with the sigma
    estimated (:func:`likelihood_ratio`): the radial order with the smallest BIC, then
    the pairs ``(p1, p2)`` and ``(a1, a2)`` on their own increments
    (:func:`terms_to_drop`). (Until session 19 the pairs were tested like the radial
    terms: the radial terms dropped before lent their unused allowance, and a
    decentering pair with ``W = 62`` against 17 went after six radial terms with ``W =
    3.4``: a 268 deg equidistant board whose sensor had ``p1, p2`` of 1.5e-4 ended at
    1.96x the oracle's 3D error, 1.21x now. Until session 20 the radial terms were
    dropped from the highest order down while ``W(S + g) < (|S| + 1) ln(2 N)``: the
    first order the full model beats, not the best one, so noise in the high terms lent
    its allowance to ``g3``: a 238 deg field-of-view board of 8 images, BIC 25.2 without
    radial terms against 11.4 with ``g3``, lost ``g3`` and ended trusted at 2.2x the
    oracle's 3D error (``bench_lens_zoo.py --stress 40 --seed 211 --targets`` s12),
    0.95x now; the best order with ``W`` itself made a rig's narrow pinhole keep ``g5, p1,
    p2`` on a sigma 3x too optimistic, poses 1.0 deg off, see :func:`likelihood_ratio`.)
    A term whose effect is real is kept (``W`` grows
    with the data); what the kept model misses is the kNN stage's to learn. When
    something is dropped the reduced problem is adjusted again from the current values.

    Returns
    -------
    (problem, adjustment)
        The reduced ones, or the inputs when nothing is dropped or the covariance is
        singular.
    """
    cov = intrinsics_covariance(problem, adj.values)
    if cov is None or not np.all(np.isfinite(cov)):
        return problem, adj
    names = list(problem.intrinsics_names())
    theta = np.asarray(adj.values.atVector(INTRINSICS_KEY), float)
    # the degrees of freedom the robust sigma came from: the observations' redundancy
    # numbers (an upper bound: the block-wise numbers leave out what the poses and
    # intrinsics absorb)
    dof = float(np.sum(problem.observation_redundancy(adj.values, problem.noise.sigma_px)))
    drop = terms_to_drop(
        theta, cov, names, problem.radial_names or (), problem.brown_names,
        len(problem.obs_image), dof,
    )  # fmt: skip
    if not drop:
        return problem, adj
    keep = [n for n in names if n not in drop]
    reduced = replace(
        problem,
        radial_names=None
        if problem.radial_names is None
        else tuple(n for n in problem.radial_names if n not in drop),
        brown_names=tuple(n for n in problem.brown_names if n not in drop),
    )
    values = gtsam.Values(adj.values)
    values.update(INTRINSICS_KEY, theta[[names.index(n) for n in keep]])
    say(
        f"terms the data do not support (Wald test, BIC penalty): {', '.join(drop)}; "
        "adjusting without them"
    )
    # warm: the dropped terms were indistinguishable from zero (the Wald test), so the
    # start is next to the reduced model's solution
    new = readjust(reduced, adj, optimizer, say, estimate_sigma, values, warm=True)
    if estimate_sigma and new.sigma_px > TERMS_SIGMA_GAIN * adj.sigma_px:
        # the test trusts the covariance: with a wild polynomial (coefficients of 1e8
        # with larger sigmas, after a poor start) it passes terms the fit needs (seed 5
        # case 05 of the zoo: sigma 1.02 -> 19.6 px, and the kNN rounds then learned a
        # 10 px "field", trusted at 50x the oracle's 3D error)
        say(
            f"without {', '.join(drop)} the robust sigma is {new.sigma_px:.4f} px against "
            f"{adj.sigma_px:.4f} px: kept"
        )
        return problem, adj
    return reduced, new


#: a calibration with more of its observations beyond 5 sigma is not trusted: real data
#: 0.1-2.4 %, the zoo's blunders up to 5 %; a 322 deg orthographic object seen through
#: a fitted polynomial 18 % (20 % was the limit: trusted at 69x the oracle's 3D error)
OUTLIER_SHARE = 0.1


class Distrust(StrEnum):
    """Kinds of reason not to trust a calibration (``statistics.distrust_codes``, one per
    ``statistics.distrust`` entry): see :func:`distrust_reasons` and
    :func:`_check_against_reference`."""

    NOT_CONVERGED = "not-converged"
    SINGULAR = "singular"
    FOLD = "fold"
    OUTLIERS = "outliers"
    KNN_UNSTABLE = "knn-unstable"
    SIGMA_GROWTH = "sigma-growth"
    IMPRECISE = "imprecise"
    LOW_REDUNDANCY = "low-redundancy"
    TARGETS_OFF_PRIOR = "targets-off-prior"
    REFERENCE_FIT = "reference-fit"
    REFERENCE_STATIONS = "reference-stations"


#: a fold between two observed incidence angles this far apart (degrees) lies where the
#: mapping is extrapolated, and :func:`fold_reason` says so
FOLD_GAP_DEG = 10.0


def fold_reason(fold_deg: float, seen_deg: float, incidence_deg) -> str:
    """Why a radial mapping that folds at ``fold_deg`` inside the field seen up to
    ``seen_deg`` is not trusted, naming the gap in the observations it lies in, if any.

    A 322 deg stereographic lens that saw its board only beyond 60 deg off the axis
    (``bench_lens_zoo.py --stress 40 --seed 213 --targets --defects`` s19) fitted the
    periphery well (0.83x the oracle's 3D error) while its polynomial folded at 38 deg,
    where no target was: the centre of the image is extrapolated, and "fewer terms"
    was not the advice to give.

    Parameters
    ----------
    fold_deg : float
        Where the mapping stops increasing (degrees).
    seen_deg : float
        The widest observed incidence (degrees).
    incidence_deg : array_like, shape (N,)
        The observations' incidence angles (degrees).

    Returns
    -------
    str
    """
    inc = np.asarray(incidence_deg, float).ravel()
    inc = inc[np.isfinite(inc)]
    below, above = inc[inc <= fold_deg], inc[inc > fold_deg]
    lo = float(below.max()) if below.size else 0.0
    hi = float(above.min()) if above.size else float(seen_deg)
    if inc.size and hi - lo >= FOLD_GAP_DEG:
        gap = f"below {hi:.0f} deg" if not below.size else f"between {lo:.0f} and {hi:.0f} deg"
        return (
            f"the radial mapping folds at {fold_deg:.1f} deg, where no target was observed "
            f"(none {gap} off the axis; the field seen reaches {seen_deg:.1f} deg): the "
            "mapping there is extrapolated; capture views with the target there"
            + (" (near the image centre)" if not below.size else "")
        )
    return (
        f"the radial mapping folds at {fold_deg:.1f} deg, inside the observed field "
        f"({seen_deg:.1f} deg): fewer --radial-terms, or --model sphere if the lens itself "
        "folds (an orthographic lens past 180 deg)"
    )


def fold_off_sensor(camera, n_azimuths: int = 72) -> bool:
    """Whether the rays at the radial mapping's fold all image off the sensor.

    A lens that folds (a sphere lens past 180 deg: ``r = c sin(alpha)``) whose fold
    lies beyond the sensor's corners images no ray near the fold, so no target can be
    observed there; the rays seen beyond the fold come back onto the image. A 262 deg
    sphere lens on a 4000x3000 sensor (``bench_lens_zoo.py --stress 40 --seed 225
    --targets --defects`` s06) saw its targets up to 58 deg and again from 122 to
    131 deg, folded at 89.8 deg some 3000 px from the principal point against
    corners within 2660 px, and was distrusted for the gap at 0.64x the oracle's 3D
    error.

    Parameters
    ----------
    camera : SphereCamera
        With a radial mapping.
    n_azimuths : int
        Rays at the fold angle tried around the axis.

    Returns
    -------
    bool
        True when every ray at the fold projects outside ``[-0.5, width - 0.5] x
        [-0.5, height - 0.5]`` (pixels); False when one lands on the sensor or does
        not project.
    """
    alpha = camera.max_alpha_rad()
    if alpha >= math.pi:
        return False
    az = np.linspace(0.0, 2.0 * math.pi, n_azimuths, endpoint=False)
    rays = np.stack(
        [
            math.sin(alpha) * np.cos(az),
            math.sin(alpha) * np.sin(az),
            np.full_like(az, math.cos(alpha)),
        ],
        axis=1,
    )
    uv = camera.project(rays, valid_only=False)
    if not np.all(np.isfinite(uv)):
        return False
    return not bool(camera.inside_image(uv).any())


#: a calibration whose principal point's sigma (the larger of ``xp``'s and ``yp``'s,
#: seen from the principal distance) exceeds this angle is not trusted: the optical
#: axis is then unknown to several degrees (zoo stress 3002 s04: 7 images, 180
#: observations of a free room at 1.5 px, 2.55 deg, the principal point 151 px off,
#: trusted at 6.3x the oracle's 3D error; the next largest of 80 stress cases was 1.07
#: deg, at 1.00x)
PRINCIPAL_POINT_SIGMA_LIMIT_DEG = 2.0


def principal_point_sigma_deg(sx_px: float, sy_px: float, c_px: float) -> float:
    """The principal point's sigma as an angle (deg): the larger of ``sx_px`` and
    ``sy_px`` (px) seen from the principal distance ``c_px`` (px)."""
    return float(np.degrees(np.arctan2(max(sx_px, sy_px), c_px)))


def imprecise_principal_point(cov_theta, names, c_px: float) -> str:
    """Why the principal point is too poorly determined to trust ("" when it is not).

    Parameters
    ----------
    cov_theta : ndarray, shape (K, K), or None
        Covariance of the intrinsics (px^2 for ``xp_px``, ``yp_px``).
    names : sequence of str, length K
        Their names (:meth:`BundleProblem.intrinsics_names`).
    c_px : float
        Principal distance (px).

    Returns
    -------
    str
        The reason, naming the sigmas (px) and the angle (deg) against
        :data:`PRINCIPAL_POINT_SIGMA_LIMIT_DEG`.
    """
    names = list(names)
    if cov_theta is None or "xp_px" not in names or "yp_px" not in names or not c_px > 0:
        return ""
    cov = np.asarray(cov_theta, float)
    sx, sy = (
        float(np.sqrt(max(cov[k, k], 0.0))) for k in (names.index("xp_px"), names.index("yp_px"))
    )
    angle_deg = principal_point_sigma_deg(sx, sy, c_px)
    if not angle_deg > PRINCIPAL_POINT_SIGMA_LIMIT_DEG:
        return ""
    return (
        f"the principal point is poorly determined: sigma {sx:.1f} / {sy:.1f} px (x / y), "
        f"{angle_deg:.2f} deg of the field (limit {PRINCIPAL_POINT_SIGMA_LIMIT_DEG:g} deg); "
        "capture more images, with the target across the whole field and at several "
        "distances and tilts"
    )


#: a calibration whose mean redundancy number (the redundancy over the number of
#: equations, observations and target priors) is below this is not trusted. The
#: redundancy number of an equation is the share of its error its residual shows; the
#: rest moves the estimate (Förstner 1987, "Reliability analysis of parameter
#: estimation in linear models"). Below a quarter, three quarters of a blunder or a
#: model error go into the parameters unseen, and the precision the adjustment reports
#: describes a fit that could absorb them: zoo stress 2912 s13 (120 observations of 50
#: free targets in 5 images: 0.20) was trusted at 2.9x the oracle's 3D error with its
#: principal point 47 px off at a sigma of 12 px, and stress 3002 s04 (0.24) at 6.3x;
#: the next lowest of 181 zoo and stress cases was 0.43 (at 1.02x). Not higher: free
#: rooms of 6 and 10 images at 0.31 and 0.32 matched the oracle (a 5-image room at 0.29
#: was 2.9x: the mean does not separate them)
MIN_MEAN_REDUNDANCY = 0.25


def mean_redundancy(redundancy: float, n_observations: int, n_priors: int) -> float:
    """Mean redundancy number: ``redundancy / (2 n_observations + 3 n_priors)`` (the
    equations of the 2-D observations and of the 3-D target priors); NaN without any."""
    n_equations = 2 * int(n_observations) + 3 * int(n_priors)
    return float(redundancy) / n_equations if n_equations > 0 else float("nan")


def low_redundancy(statistics: dict) -> str:
    """Why the adjustment controls its observations too poorly to trust ("" when not).

    Parameters
    ----------
    statistics : dict
        A calibration's statistics: ``mean_redundancy`` (absent: nothing judged),
        ``redundancy``, ``n_observations``.

    Returns
    -------
    str
        The reason, naming the redundancy and its mean against
        :data:`MIN_MEAN_REDUNDANCY`.
    """
    mean = statistics.get("mean_redundancy")
    if mean is None or not mean < MIN_MEAN_REDUNDANCY:
        return ""
    return (
        f"the observations barely over-determine the geometry: redundancy "
        f"{statistics['redundancy']} for {statistics['n_observations']} observations "
        f"(mean redundancy number {mean:.2f}, limit {MIN_MEAN_REDUNDANCY:.2f}), so a "
        "blunder or a model error goes mostly into the estimate unseen and the reported "
        "precision is optimistic; capture more images, each target in three or more"
    )


#: a target whose adjusted coordinates moved further than this many sigmas of its prior
#: (the dataset's sigma, or the shape prior of an exact target,
#: :attr:`BundleProblem.target_sigma`) from its stated ones disagrees with the images: the
#: shift of a consistent target is below it with probability 1 - 1.4e-5 (chi with 3
#: degrees of freedom; the shift's own sigma is below the prior's)
TARGET_SHIFT_LIMIT_SIGMA = 5.0
#: this many targets beyond :data:`TARGET_SHIFT_LIMIT_SIGMA` make the calibration
#: untrusted (:func:`targets_off_prior`); fewer are a logged warning naming them (one
#: wrong coordinate, or a target that only blunders reached). A 297 deg double-sphere
#: lens of f = 15 px on 640x480 (``bench_rig.py --random 2 --seed 7 --only r01``), whose
#: image radius grows from 31 px at 90 deg to 285 px at 146 deg, fits its rim through
#: the radial mapping only to a few px, where a pixel is a few thousandths of a radian:
#: 9 of its 370 surveyed targets (1 cm) moved 5.1-7.3 sigma, the rig's cam_from_rig
#: ended 4.4 sigma off and the check points 1.8x the oracle's error, trusted. Over 65
#: zoo and stress calibrations with weighted targets: at most one target beyond 5 sigma
#: (a room with 2 % blunders, 7.7 sigma, 1.00x the oracle)
MIN_TARGETS_OFF_PRIOR = 3


def shift_over_sigma(shift: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Each target's shift from its stated coordinates in sigmas of its prior.

    Parameters
    ----------
    shift : ndarray, shape (T, 3)
        Adjusted minus stated coordinates (dataset units).
    sigma : ndarray, shape (T,)
        The prior's sigma per axis (dataset units, > 0).

    Returns
    -------
    ndarray, shape (T,)
        ``|shift| / sigma``.
    """
    shift = np.asarray(shift, float).reshape(-1, 3)
    sigma = np.asarray(sigma, float).reshape(-1)
    if len(shift) != len(sigma):
        raise ValueError(f"shift has {len(shift)} rows and sigma {len(sigma)}")
    return np.linalg.norm(shift, axis=1) / sigma


def images_per_target(obs_target: np.ndarray, obs_image: np.ndarray, n_targets: int) -> np.ndarray:
    """How many distinct images observe each target.

    Parameters
    ----------
    obs_target, obs_image : ndarray of int, shape (N,)
        Each observation's target and image index.
    n_targets : int

    Returns
    -------
    ndarray of int, shape (n_targets,)
    """
    obs_target = np.asarray(obs_target, int).reshape(-1)
    obs_image = np.asarray(obs_image, int).reshape(-1)
    if len(obs_target) != len(obs_image):
        raise ValueError(f"obs_target has {len(obs_target)} entries and obs_image {len(obs_image)}")
    if len(obs_target) == 0:
        return np.zeros(n_targets, int)
    pairs = np.unique(np.stack([obs_target, obs_image], axis=1), axis=0)
    return np.bincount(pairs[:, 0], minlength=n_targets)


def targets_off_prior_statistics(
    target_ids: list[str], shift_sigma: np.ndarray, n_images: np.ndarray | None = None
) -> dict:
    """The statistics :func:`targets_off_prior` judges: ``target_shift_max_sigma``,
    ``n_targets_off_prior`` (targets seen in two images or more, beyond
    :data:`TARGET_SHIFT_LIMIT_SIGMA`) and ``targets_off_prior`` (their ids, the furthest
    first, at most 20), and ``targets_off_prior_one_image`` (those seen in one image
    only, outliers set aside: the error of that one observation, a blunder, goes into
    the target rather than the lens, and the target moves; the stress draw 210's s04, a
    46 deg pinhole room of 161 observations with 2 % blunders: three blunders each moved
    a target seen once 7.4-14.3 sigma, the lens matched the oracle; stress 3301 s07: three
    targets seen in two images, one ray a blunder, the adjustment kept the blunder and
    set the good ray aside, 6.8-13.6 sigma, the lens 1.01x the oracle).

    Parameters
    ----------
    target_ids : list of str, length T
    shift_sigma : ndarray, shape (T,)
        :func:`shift_over_sigma` of those targets.
    n_images : ndarray of int, shape (T,), optional
        How many images see each through a ray that is not an outlier
        (:func:`images_per_target`); default: two or more.
    """
    shift_sigma = np.asarray(shift_sigma, float)
    if len(shift_sigma) == 0:
        return {}
    n_images = np.full(len(shift_sigma), 2) if n_images is None else np.asarray(n_images)
    beyond = shift_sigma > TARGET_SHIFT_LIMIT_SIGMA

    def named(mask: np.ndarray) -> list[dict]:
        idx = np.flatnonzero(mask)
        idx = idx[np.argsort(-shift_sigma[idx])]
        return [{"id": target_ids[j], "shift_sigma": float(shift_sigma[j])} for j in idx[:20]]

    return {
        "target_shift_max_sigma": float(np.max(shift_sigma)),
        "n_targets_off_prior": int(np.sum(beyond & (n_images >= 2))),
        "targets_off_prior": named(beyond & (n_images >= 2)),
        "targets_off_prior_one_image": named(beyond & (n_images < 2)),
    }


def targets_off_prior(statistics: dict, warn: bool = True) -> str:
    """Why the images and the stated target coordinates disagree too much to trust the
    result ("" when not): at least :data:`MIN_TARGETS_OFF_PRIOR` targets moved beyond
    :data:`TARGET_SHIFT_LIMIT_SIGMA` sigmas of their priors. Fewer are logged as a
    warning naming them (``warn``).

    Parameters
    ----------
    statistics : dict
        ``n_targets_off_prior`` (absent: nothing judged), ``targets_off_prior`` and
        ``target_shift_max_sigma`` (:func:`targets_off_prior_statistics`).
    warn : bool
        Log the warning for one or two targets.

    Returns
    -------
    str
        The reason, naming the furthest targets and their shifts in sigmas.
    """
    single = statistics.get("targets_off_prior_one_image") or []
    if single and warn:
        logger.warning(
            "%d target(s) seen in one image only (outliers set aside) moved beyond %.0f "
            "sigma of their stated coordinates (in sigmas: %s): a blunder in that image "
            "moves its target, not the lens; check those observations",
            len(single),
            TARGET_SHIFT_LIMIT_SIGMA,
            ", ".join(f"{t['id']} ({t['shift_sigma']:.1f})" for t in single[:5]),
        )
    n = statistics.get("n_targets_off_prior")
    if not n:
        return ""
    named = ", ".join(
        f"{t['id']} ({t['shift_sigma']:.1f})" for t in statistics["targets_off_prior"][:5]
    )
    more = f" and {n - 5} more" if n > 5 else ""
    if n < MIN_TARGETS_OFF_PRIOR:
        if warn:
            logger.warning(
                "%d target(s) moved beyond %.0f sigma of their stated coordinates (in "
                "sigmas: %s): check their coordinates and their observations",
                n,
                TARGET_SHIFT_LIMIT_SIGMA,
                named,
            )
        return ""
    return (
        f"{n} targets moved beyond {TARGET_SHIFT_LIMIT_SIGMA:.0f} sigma of their stated "
        f"coordinates (in sigmas: {named}{more}): the images disagree with them, either "
        "their coordinates or sigmas are wrong, or the lens model does not follow the "
        "observations that moved them (a lens whose image grows steeply at its rim, "
        "where a pixel is a tiny angle); check those targets, and compare the residuals "
        "by incidence angle"
    )


def distrust_reasons(
    calib: Calibration,
    cov_theta,
    options,
    problem: BundleProblem,
    knn_stable: bool = True,
    first_sigma_px: float | None = None,
) -> list[tuple[Distrust, str]]:
    """Why a calibration should not be trusted (empty when it can be), each reason with
    its kind (:class:`Distrust`).

    Not converged (iteration cap, divergence, stalled); singular normal
    equations (an intrinsic parameter not determined by the data); a radial
    mapping that stops increasing inside the observed field (it would fold the
    image); more than :data:`OUTLIER_SHARE` of the observations beyond 5 sigma; a kNN
    loop that ran out of rounds (``knn_stable`` False); a principal point whose sigma
    exceeds :data:`PRINCIPAL_POINT_SIGMA_LIMIT_DEG` (:func:`imprecise_principal_point`);
    a mean redundancy number below :data:`MIN_MEAN_REDUNDANCY` (:func:`low_redundancy`);
    an estimated robust sigma above :data:`SIGMA_GROWTH` times ``first_sigma_px``, the
    first adjustment's (px).
    """
    st = calib.statistics
    out = []
    if not st["converged"]:
        detail = f": {st['status_message']}" if st.get("status_message") else ""
        out.append(
            (Distrust.NOT_CONVERGED, f"the optimiser did not converge ({st['status']}{detail})")
        )
    if options.covariance and problem.fixed_intrinsics is None and cov_theta is None:
        out.append(
            (
                Distrust.SINGULAR,
                "the normal equations are singular: some intrinsics are not determined",
            )
        )
    cam = calib.camera
    fold_deg = float(np.degrees(cam.max_alpha_rad()))
    if cam.radial is not None and fold_deg < st["max_incidence_deg"] and fold_off_sensor(cam):
        # a lens that folds (a sphere lens past 180 deg) seen on both sides of its fold
        logger.info(
            "the radial mapping folds at %.1f deg, where the image of every ray lies off "
            "the sensor: the rays seen beyond it (to %.1f deg) come back onto the image",
            fold_deg,
            st["max_incidence_deg"],
        )
    elif cam.radial is not None and fold_deg < st["max_incidence_deg"]:
        incidence = calib.extra.get("observations", {}).get("incidence_deg")
        out.append(
            (
                Distrust.FOLD,
                fold_reason(
                    float(np.degrees(cam.max_alpha_rad())),
                    st["max_incidence_deg"],
                    [] if incidence is None else incidence,
                ),
            )
        )
    if st["n_outliers"] > OUTLIER_SHARE * max(st["n_observations"], 1):
        out.append(
            (
                Distrust.OUTLIERS,
                f"{st['n_outliers']} of {st['n_observations']} observations are beyond 5 sigma",
            )
        )
    if not knn_stable:
        # the default lens models leave a small, smooth field the loop settles on in 2-3
        # rounds; a field still moving after all of them is learning the misfit of a
        # wrong geometry (seed 4 case 05 of the zoo, a 150 deg pinhole posed 56 px off
        # its principal point: 25 rounds, trusted at 31x the oracle's 3D error)
        out.append(
            (
                Distrust.KNN_UNSTABLE,
                "the kNN correction did not become stable (CV and adjustment RMS) within "
                "its rounds (options.knn max_rounds)",
            )
        )
    if problem.fixed_intrinsics is None:
        why = imprecise_principal_point(cov_theta, problem.intrinsics_names(), cam.c)
        if why:
            out.append((Distrust.IMPRECISE, why))
    why = low_redundancy(st)
    if why:
        out.append((Distrust.LOW_REDUNDANCY, why))
    why = targets_off_prior(st)
    if why:
        out.append((Distrust.TARGETS_OFF_PRIOR, why))
    stage = st.get("first_stage_sigma_px")
    if options.sigma_px is None and stage and st["sigma_px"] > SIGMA_GROWTH * stage:
        # the first adjustment's own stages drifted: its robust scale grew from the
        # smallest a stage reached (stress 3201 s06, a 332 deg sphere lens on a 3D object,
        # 0.1 px: 0.17 px after the first stage, then Huber stages let the 22 % the
        # initialisation could not explain pull the lens to c = 4,714 px (true 528) and
        # a 7 deg field at 9.9 px; trusted at 10.9x the known-family adjustment's 3D
        # error)
        out.append(
            (
                Distrust.SIGMA_GROWTH,
                f"the final robust sigma ({st['sigma_px']:.3f} px) is "
                f"{st['sigma_px'] / stage:.1f} times the smallest a stage of the first "
                f"adjustment reached ({stage:.3f} px): the adjustment moved away from the "
                "geometry its first stage fitted",
            )
        )
    growth = st["sigma_px"] / first_sigma_px if first_sigma_px else 0.0
    if options.sigma_px is None and growth > SIGMA_GROWTH:
        # every later step (warp, terms, shape prior, kNN) is kept only when it fits at
        # least about as well: a final scale far above the first adjustment's means one
        # of them broke the fit (seed 5 case 05 before RADIAL_START_MAX: 1.02 -> 26.9 px)
        out.append(
            (
                Distrust.SIGMA_GROWTH,
                f"the final robust sigma ({st['sigma_px']:.3f} px) is {growth:.1f} times the "
                f"first adjustment's ({first_sigma_px:.3f} px)",
            )
        )
    return out


def intrinsics_covariance(problem: BundleProblem, values: gtsam.Values) -> np.ndarray | None:
    """Covariance (K, K) of the intrinsics from ``gtsam.Marginals`` (px^2 / dimensionless).

    The graph is whitened with the estimated ``sigma_px`` and robust weights,
    so this is the a-posteriori precision. ``None`` if the system is singular.
    """
    cov = marginal_covariances(problem.build(), values, [INTRINSICS_KEY])
    return None if cov is None else cov[INTRINSICS_KEY]


def intrinsics_sigma(problem: BundleProblem, values: gtsam.Values) -> np.ndarray | None:
    """Standard deviations (K,) of the intrinsics, see :func:`intrinsics_covariance`."""
    cov = intrinsics_covariance(problem, values)
    return None if cov is None else np.sqrt(np.diag(cov))


def classify_outliers(
    camera: SphereCamera,
    dataset: Dataset,
    R: np.ndarray,
    t: np.ndarray,
    xyz: np.ndarray,
    residuals_px: np.ndarray,
    index: np.ndarray,
) -> list[dict]:
    """List outlying observations with their likely cause.

    An outlier whose pixel lies close to where *another* target of the
    dataset projects in the same image (closer than a third of its own
    residual and than ``10 px + 1%`` of it) is reported as a mislabelled
    target (``"mislabelled"``, with the target it matches); the others as
    ``"gross offset"``.

    Parameters
    ----------
    camera : SphereCamera
    dataset : Dataset
    R, t : ndarray, shapes (M, 3, 3) and (M, 3)
        Adjusted ``cam_from_world`` per image.
    xyz : ndarray, shape (T, 3)
        Adjusted target coordinates (world frame).
    residuals_px : ndarray, shape (N, 2)
    index : ndarray of int
        Observations to list.

    Returns
    -------
    list of dict
        ``image``, ``target``, ``uv_px``, ``residual_px``, ``residual_norm_px``,
        ``cause`` and, for mislabelled ones, ``matches_target`` and
        ``distance_px`` to its projection. Largest residual first.
    """
    out = []
    r_norm = np.linalg.norm(residuals_px, axis=1)
    # A target's exact pixel (the learned correction inverted, ~30 kNN queries) lies
    # within the correction's bound of its pixel without the correction (uv = w +
    # learned(uv)): only the targets that could match are projected exactly. Every
    # target exactly per outlier took 17.7 of ov_plane_train's 25 s (165 outliers in 18
    # images); the tabulated correction instead (session 12) 0.77 s of a small room's
    # 5.7 s and 16 s of a 340 deg room's 40 s (a rough correction: a fine table).
    bound = math.inf
    if camera.correction is not None and hasattr(camera.correction, "prediction_bound_px"):
        bound = camera.correction.prediction_bound_px()
    parametric = replace(camera, correction=None)
    # per image: camera-frame points, pixels without the correction, exact pixels and
    # which of them are computed
    pixels: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
    for o in index[np.argsort(-r_norm[index])]:
        i = int(dataset.obs_image[o])
        uv = dataset.uv_px[o]
        if i not in pixels:
            pc_i = xyz @ R[i].T + t[i]
            with np.errstate(invalid="ignore"):
                w = parametric.project(pc_i, exact=True, valid_only=False)
            done = np.full(len(w), camera.correction is None)
            pixels[i] = pc_i, w, w.copy(), done
        pc, w, exact_uv, done = pixels[i]
        limit = min(r_norm[o] / 3.0, 10.0 + 0.01 * r_norm[o])
        if math.isinf(bound):  # no bound: every target is a candidate
            near = np.ones(len(w), bool)
        else:
            with np.errstate(invalid="ignore"):
                near = np.linalg.norm(w - uv, axis=1) < limit + bound
        near[dataset.obs_target[o]] = False
        todo = np.flatnonzero(near & ~done)
        if todo.size:
            with np.errstate(invalid="ignore"):
                exact_uv[todo] = camera.project(pc[todo], exact=True, valid_only=False)
            done[todo] = True
        d = np.full(len(pc), np.inf)
        d[near] = np.nan_to_num(np.linalg.norm(exact_uv[near] - uv, axis=1), nan=np.inf)
        j = int(np.argmin(d))
        entry = {
            "image": dataset.image_ids[i],
            "target": dataset.target_ids[dataset.obs_target[o]],
            "uv_px": uv,
            "residual_px": residuals_px[o],
            "residual_norm_px": float(r_norm[o]),
            "cause": "gross offset",
        }
        if np.isfinite(d[j]) and d[j] < min(r_norm[o] / 3.0, 10.0 + 0.01 * r_norm[o]):
            entry.update(
                cause="mislabelled", matches_target=dataset.target_ids[j], distance_px=float(d[j])
            )
        out.append(entry)
    return out


def _result(dataset, problem, adj, correction, history, options, n_input_images) -> Calibration:
    values = adj.values
    theta = values.atVector(INTRINSICS_KEY)
    camera = camera_from_theta(problem, theta, dataset.width, dataset.height, correction)
    R, t = _poses_from_values(values, len(dataset.image_ids))
    xyz = adjusted_target_xyz(problem, values)
    # the adjustment's residuals keep the radial Brown terms' corrected coordinates
    # (core.camera.sphere_residual); statistics and files report raw pixels (OpenCV's
    # definition); sigma, weights and outliers stay in the adjustment's own coordinates
    res_model = adj.residuals_px
    res = camera.pixel_residuals(dataset.uv_px, res_model, exact=True)
    res = np.where(np.isfinite(res), res, res_model)
    r_model = np.linalg.norm(res_model, axis=1)
    r_norm = np.linalg.norm(res, axis=1)
    sigma = adj.sigma_px
    whitened2 = (r_model / sigma) ** 2
    # a blunder is gross relative to its neighbours, not only to the global sigma: a
    # residual beyond 5 sigma that its image neighbours share (a lens or board error the
    # model does not hold, large at the border of a wide lens) is systematic, reported
    # as such and not listed as an outlier
    from .correct import blunders

    outlier = blunders(dataset.uv_px, res_model, sigma)
    systematic = (r_model > 5.0 * sigma) & ~outlier
    # each target's precision where its rays meet (poses and lens held), outliers out
    weight = np.where(outlier, 0.0, adj.weights) / sigma**2
    meet_sigma = intersection_sigma(
        problem.target_jacobians(values), dataset.obs_target, weight, dataset.target_sigma
    )
    meet_sigma[dataset.target_sigma == 0] = 0.0  # exact: held
    lost_reason = dict.fromkeys(
        np.flatnonzero(targets_lost_to_outliers(dataset, outlier)).tolist(),
        LOST_TO_OUTLIERS_REASON,
    )
    seen = np.bincount(dataset.obs_target, minlength=len(dataset.target_ids)) > 0
    no_sigma = np.zeros(len(dataset.target_ids), bool)
    no_sigma[problem.free_targets] = True
    no_sigma &= ~np.isfinite(problem.target_sigma)
    settled = seen & ~np.isin(np.arange(len(no_sigma)), list(lost_reason))
    extent = targets_extent(xyz[settled])
    for j in np.flatnonzero(unfixed_targets(meet_sigma, settled & no_sigma, extent)).tolist():
        lost_reason.setdefault(j, UNFIXED_REASON)
    lost = np.zeros(len(dataset.target_ids), bool)
    lost[list(lost_reason)] = True
    scale = 1.0
    datum_points = None
    if problem.datum is Datum.FREE:
        free = problem.free_targets
        fit = free[~lost[free]] if np.sum(~lost[free]) >= 3 else free
        sim, kept = fit_similarity_trimmed(xyz[fit], dataset.target_xyz[fit])
        datum_points = fit[kept]
        scale = sim.scale
    # each target's full precision, poses and lens estimated with it (a free network's
    # in the datum of its similarity onto the approximate coordinates)
    cov = problem.target_covariances(values, weight, xyz, datum_points)
    full_sigma = None
    if cov is not None:
        full_sigma = scale * np.sqrt(np.maximum(np.linalg.eigvalsh(cov)[:, -1], 0.0))
        full_sigma[dataset.target_sigma == 0] = 0.0
        full_sigma[lost] = np.inf
    if problem.datum is Datum.FREE:
        xyz[free] = sim.apply(xyz[free])
        R, t = sim.apply_to_cam_from_world(R, t)
        meet_sigma *= sim.scale
    # targets that two rays place far from their approximate coordinates: one redundant
    # observation cannot tell a mislabel from a target (unreliable_targets)
    misfit = np.linalg.norm(xyz - dataset.target_xyz, axis=1)
    unreliable, reference = unreliable_targets(
        dataset.obs_image,
        dataset.obs_target,
        ~outlier,
        seen & no_sigma & ~lost,
        misfit,
        meet_sigma if full_sigma is None else full_sigma,
    )
    for j in np.flatnonzero(unreliable).tolist():
        lost_reason[j] = UNRELIABLE_REASON.format(
            misfit=misfit[j], reference=reference, units=dataset.units
        )
    lost |= unreliable
    if full_sigma is not None:
        full_sigma[unreliable] = np.inf
    observed = np.unique(dataset.obs_target)
    used_targets = observed[~lost[observed]]
    weak_limit, weak = weak_targets(
        xyz[used_targets], (meet_sigma if full_sigma is None else full_sigma)[used_targets]
    )
    pc = np.einsum("nij,nj->ni", R[dataset.obs_image], xyz[dataset.obs_target])
    pc += t[dataset.obs_image]
    inc = incidence_deg(pc)
    n_obs = dataset.n_observations
    n_priors = int(
        np.sum(
            np.isfinite(problem.target_sigma[problem.free_targets])
            & (problem.target_sigma[problem.free_targets] > 0)
        )
    )
    redundancy = 2 * n_obs + 3 * n_priors + problem.n_datum_constraints() - problem.n_unknowns()
    # the field the data support (SphereCamera.valid_alpha_rad): the widest observation
    # that is not a blunder
    seen = inc[~outlier] if (~outlier).any() else inc
    camera.observed_alpha_rad = float(np.radians(np.max(seen)))
    # beyond the loss threshold: Huber's weight < 1 there; Cauchy's weight < 1/2
    down = np.flatnonzero(r_model > problem.noise.loss_threshold * sigma)
    down = down[np.argsort(-r_model[down])]
    n_rejected = dataset.n_input_observations - n_obs
    statistics = {
        "rms_px": float(np.sqrt(np.mean(r_norm**2))),
        "rms_px_without_outliers": float(np.sqrt(np.mean(r_norm[~outlier] ** 2))),
        "rms_px_corrected": float(np.sqrt(np.mean(r_model**2))),
        "n_observations": int(n_obs),
        "n_rejected": int(n_rejected),
        "n_images": len(dataset.image_ids),
        "n_images_skipped": len(dataset.skipped_images),
        "n_images_input": n_input_images + 0,
        "n_targets": int(len(used_targets)),
        "n_targets_undetermined": int(lost.sum()),
        "n_targets_unreliable": int(unreliable.sum()),
        "n_targets_weak": int(weak.sum()),
        "weak_target_limit": float(weak_limit),
        "n_downweighted": int(len(down)),
        "n_outliers": int(outlier.sum()),
        "n_systematic": int(systematic.sum()),
        "sigma_px": float(sigma),
        "loss": adj.loss or str(problem.noise.loss),
        "loss_threshold": float(problem.noise.loss_threshold),
        "weighted_sum_squares": float(np.sum(adj.weights * whitened2)),
        "cost": float(history[-1]["cost"]),
        "redundancy": int(redundancy),
        "mean_redundancy": mean_redundancy(redundancy, n_obs, n_priors),
        "variance_factor": float(np.sum(adj.weights * whitened2) / max(redundancy, 1)),
        "max_incidence_deg": float(np.max(inc)),
        "fov_deg": float(2 * np.max(inc)),
        "n_beyond_90deg": int(np.sum(inc > 90.0)),
        "iterations": int(history[-1]["iteration"]),
        "status": str(adj.result.status.value),
        "converged": bool(adj.result.converged),
        "datum": problem.datum.value,
    }
    if adj.result.message:
        statistics["status_message"] = adj.result.message
    weighted = problem.free_targets[
        np.isfinite(problem.target_sigma[problem.free_targets])
        & (problem.target_sigma[problem.free_targets] > 0)
    ]
    shift = xyz[weighted] - dataset.target_xyz[weighted]
    if len(weighted):
        # how far the data moved the targets that had a sigma (control points, or a
        # printed board with control_sigma): its real shape, in the dataset's units
        statistics["target_shift_rms"] = float(np.sqrt(np.mean(np.sum(shift**2, axis=1))))
        statistics["target_shift_max"] = float(np.max(np.linalg.norm(shift, axis=1)))
        statistics.update(
            targets_off_prior_statistics(
                [dataset.target_ids[j] for j in weighted],
                shift_over_sigma(shift, problem.target_sigma[weighted]),
                # images whose ray is not an outlier: a target seen in two, one ray a
                # blunder, is held by the other ray alone, and a blunder kept in its
                # place moves it (stress 3301 s07: three such targets 6.8-13.6 sigma
                # off, the lens 1.01x the oracle's 3D error, not trusted)
                images_per_target(
                    dataset.obs_target[~outlier],
                    dataset.obs_image[~outlier],
                    len(dataset.target_ids),
                )[weighted],
            )
        )
    ids = dataset.image_ids
    tids = dataset.target_ids
    extra = {
        "downweighted": [
            {
                "image": ids[dataset.obs_image[o]],
                "target": tids[dataset.obs_target[o]],
                "residual_px": res[o],
                "weight": float(adj.weights[o]),
                "outlier": bool(outlier[o]),
            }
            for o in down
        ],
        "outliers": classify_outliers(camera, dataset, R, t, xyz, res, np.flatnonzero(outlier)),
        "skipped_images": [{"id": i, "reason": why} for i, why in dataset.skipped_images],
        "target_precision": {
            "target": [tids[j] for j in used_targets],
            "intersection_sigma": meet_sigma[used_targets],
            "weak": weak,
            **({} if full_sigma is None else {"sigma": full_sigma[used_targets]}),
        },
        "undetermined_targets": [
            {
                "id": tids[j],
                "reason": lost_reason[j],
                "n_observations": int(np.sum(dataset.obs_target == j)),
            }
            for j in sorted(lost_reason)
        ],
        "dropped_observations": [
            {"image": i, "target": tg, "reason": why} for i, tg, why in dataset.dropped
        ],
        # wall-clock seconds stay out of the file: same input and seed, same bytes
        "history": [{k: v for k, v in h.items() if k != "seconds"} for h in history],
        "observations": {
            "image": [ids[i] for i in dataset.obs_image],
            "target": [tids[j] for j in dataset.obs_target],
            "uv_px": dataset.uv_px,
            "residual_px": res,
            "weight": adj.weights,
            "incidence_deg": inc,
        },
        "target_shifts": {
            "target": [tids[j] for j in weighted],
            "nominal_xyz": dataset.target_xyz[weighted],
            "shift": shift,
        },
        "options": {
            k: (str(v) if not isinstance(v, (int, float, dict, tuple, list)) else v)
            for k, v in asdict(options).items()
        },
    }
    if dataset.source:
        extra["source"] = str(dataset.source)
    model = options.model
    if model.uses_brown and not problem.brown_names:  # term selection dropped them all
        model = Model.SPHERE_KNN if model.uses_knn else Model.SPHERE
    return Calibration(
        model=str(model),
        camera=camera,
        image_ids=list(ids),
        cam_from_world_R=R,
        cam_from_world_t=t,
        target_ids=[tids[j] for j in used_targets],
        target_xyz=xyz[used_targets],
        statistics=statistics,
        units=dataset.units,
        extra=extra,
    )
