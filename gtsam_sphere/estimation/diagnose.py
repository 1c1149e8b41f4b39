"""Degeneracy checks on a calibration's geometry, before and right after initialisation.

A self-calibrating bundle adjustment needs a network that determines the
intrinsics: several images, targets seen from more than one position, either
3D targets or varied views of a plane, and one connected block of images (or
enough control in each block). :func:`check_geometry` looks for the classic
failures and returns one :class:`Problem` per finding, naming the images or
targets concerned and what to capture next; :func:`raise_if_degenerate`
turns the fatal ones into a :class:`DegenerateGeometryError` (a
:class:`~gtsam_sphere.core.errors.InputError`, so the command line exits 2).

The checks are pure functions of the dataset (and, for the pose-dependent
ones, of the initial ``cam_from_world`` poses); nothing is adjusted.

=========================  =====  ===========================================
code                       poses  fatal when
=========================  =====  ===========================================
``single-image``           no     0 usable images; 1 image with free (no
                                  sigma) targets or coplanar targets
``degenerate-targets``     no     the observed targets coincide or are collinear
``few-points``             no     never (images skipped or likely to fail);
                                  fatal if no image has enough points
``skipped-images``         no     never (images left out for other reasons)
``disconnected-network``   no     a group of images sharing no target with the
                                  others is not held by 3 non-collinear targets
                                  with a sigma (always, in a free network)
``undetermined-targets``   no     never (free targets seen in one image only: left
                                  out of the adjustment)
``no-baseline``            yes    the camera centres' spread is below
                                  ``min_baseline_ratio`` of the distance to the
                                  targets and some observed target is free
``planar-narrow-view``     yes    coplanar targets, every incidence below half
                                  of ``narrow_fov_deg`` and every view within
                                  ``min_tilt_deg`` of the plane's normal
=========================  =====  ===========================================
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core._compat import StrEnum
from ..core.errors import DegenerateGeometryError
from ..io.dataset import Dataset

logger = logging.getLogger(__name__)

__all__ = [
    "DegenerateGeometryError",
    "Problem",
    "ProblemCode",
    "check_geometry",
    "image_groups",
    "raise_if_degenerate",
    "undetermined_targets",
]


class ProblemCode(StrEnum):
    """Kinds of geometric weakness found by :func:`check_geometry`."""

    SINGLE_IMAGE = "single-image"
    DEGENERATE_TARGETS = "degenerate-targets"
    FEW_POINTS = "few-points"
    SKIPPED_IMAGES = "skipped-images"
    DISCONNECTED = "disconnected-network"
    UNDETERMINED_TARGETS = "undetermined-targets"
    NO_BASELINE = "no-baseline"
    PLANAR_NARROW = "planar-narrow-view"


@dataclass(frozen=True)
class Problem:
    """One finding of :func:`check_geometry`.

    Attributes
    ----------
    code : ProblemCode
    message : str
        What is wrong, naming the images or targets concerned.
    advice : str
        What to capture (or change in the dataset) to fix it.
    fatal : bool
        True when the adjustment cannot determine the intrinsics (or the
        network) at all; False for a weakness worth a warning.
    items : tuple of str
        Ids of the images or targets concerned (all of them; the message
        lists the first few).
    """

    code: ProblemCode
    message: str
    advice: str
    fatal: bool
    items: tuple[str, ...] = ()

    def __str__(self) -> str:
        return f"[{self.code}] {self.message} -> {self.advice}"


def _names(ids: Sequence[str], limit: int = 6) -> str:
    """``'A', 'B', 'C'`` or ``'A', 'B', ... (+12 more)`` for messages."""
    shown = ", ".join(repr(i) for i in ids[:limit])
    return shown if len(ids) <= limit else f"{shown}, ... (+{len(ids) - limit} more)"


def _singular_values(xyz: np.ndarray) -> np.ndarray:
    """Singular values (3,) of points (K, 3) about their centroid (zeros for K < 2)."""
    if len(xyz) < 2:
        return np.zeros(3)
    s = np.linalg.svd(xyz - xyz.mean(0), compute_uv=False)
    return np.pad(s, (0, 3 - len(s)))


def _non_collinear(xyz: np.ndarray, tol: float = 1e-6) -> bool:
    """True for at least 3 points (K, 3) that do not lie on one line."""
    s = _singular_values(xyz)
    return len(xyz) >= 3 and s[0] > 0 and s[1] > tol * s[0]


def _poses(cam_from_world: Any, n_images: int) -> tuple[np.ndarray, np.ndarray]:
    """``(R (M,3,3), t (M,3))`` from the accepted pose arguments, validated."""
    if hasattr(cam_from_world, "cam_from_world_R"):
        R, t = cam_from_world.cam_from_world_R, cam_from_world.cam_from_world_t
    elif isinstance(cam_from_world, (tuple, list)) and len(cam_from_world) == 2:
        R, t = cam_from_world
    else:
        Rt = np.asarray(cam_from_world, float)
        if Rt.ndim != 3 or Rt.shape[1:] != (3, 4):
            raise ValueError(
                "cam_from_world must be (R (M,3,3), t (M,3)), an (M,3,4) array [R|t] or an "
                f"object with cam_from_world_R / cam_from_world_t; got shape {Rt.shape}"
            )
        R, t = Rt[:, :, :3], Rt[:, :, 3]
    R = np.asarray(R, float)
    t = np.asarray(t, float)
    if R.shape != (n_images, 3, 3) or t.shape != (n_images, 3):
        raise ValueError(
            f"cam_from_world must have shapes ({n_images}, 3, 3) and ({n_images}, 3) for the "
            f"dataset's {n_images} images, got {R.shape} and {t.shape}"
        )
    return R, t


def image_groups(dataset: Dataset) -> list[np.ndarray]:
    """Groups of images connected through shared targets that are variables.

    Images and targets form a bipartite graph (one edge per observation);
    exact control targets (``sigma == 0``) are constants of the adjustment and
    do not link the images that see them.

    Parameters
    ----------
    dataset : Dataset

    Returns
    -------
    list of ndarray of int
        Image indices (into ``dataset.image_ids``) of each connected group,
        largest group first (ties: lowest first image).
    """
    n_img = len(dataset.image_ids)
    parent = np.arange(n_img + len(dataset.target_ids))

    def find(a: int) -> int:
        root = a
        while parent[root] != root:
            root = parent[root]
        while parent[a] != root:  # path compression
            parent[a], a = root, parent[a]
        return int(root)

    linking = ~(dataset.target_sigma == 0)
    for i, j in zip(dataset.obs_image, dataset.obs_target):
        if linking[j]:
            a, b = find(int(i)), find(n_img + int(j))
            if a != b:
                parent[max(a, b)] = min(a, b)
    roots = np.array([find(i) for i in range(n_img)], int)
    groups = [np.flatnonzero(roots == r) for r in np.unique(roots)]
    return sorted(groups, key=lambda g: (-len(g), int(g[0])))


def undetermined_targets(
    obs_image: np.ndarray, obs_target: np.ndarray, target_sigma: np.ndarray
) -> np.ndarray:
    """Targets without a sigma seen in fewer than two images: no depth along the ray.

    Parameters
    ----------
    obs_image, obs_target : ndarray of int, shape (N,)
        Image and target index of each observation (an image may observe a target twice:
        it counts once).
    target_sigma : ndarray, shape (T,)
        NaN (or inf) where a target has no sigma.

    Returns
    -------
    ndarray of bool, shape (T,)
    """
    sigma = np.asarray(target_sigma, float)
    pairs = np.unique(
        np.stack([np.asarray(obs_image, int), np.asarray(obs_target, int)], 1).reshape(-1, 2),
        axis=0,
    )
    n_views = np.bincount(pairs[:, 1], minlength=len(sigma))
    return ~np.isfinite(sigma) & (n_views < 2)


def check_geometry(
    dataset: Dataset,
    cam_from_world: Any = None,
    *,
    min_points_per_image: int = 6,
    min_baseline_ratio: float = 0.02,
    planar_tolerance: float = 0.01,
    narrow_fov_deg: float = 60.0,
    min_tilt_deg: float = 15.0,
    weighted_anchor: bool = True,
) -> list[Problem]:
    """Find the geometric degeneracies of a calibration dataset.

    Parameters
    ----------
    dataset : Dataset
        A validated dataset (``dataset.skipped_images`` lists images already
        left out).
    cam_from_world : optional
        Poses of ``dataset``'s images, ``p_cam = R @ p_world + t``: a pair
        ``(R (M,3,3), t (M,3))``, an ``(M, 3, 4)`` array ``[R | t]`` or an object
        with ``cam_from_world_R`` / ``cam_from_world_t`` (the
        :class:`~gtsam_sphere.estimation.calibrate.Initialisation`). Rows with NaN are
        ignored. Without poses the baseline and planar checks are not run.
    min_points_per_image : int
        Images with fewer observations are reported (``few-points``); 6 is
        what the initialisation needs.
    min_baseline_ratio : float
        ``no-baseline`` when the largest distance of a camera centre from
        their mean is below this fraction of the median camera-target
        distance (0.02 is a triangulation angle of about 1 degree).
    planar_tolerance : float
        Targets are coplanar when their relief (third singular value of the
        centred coordinates) is below this fraction of their extent (first).
    narrow_fov_deg : float
        Full field of view (degrees) below which, with coplanar targets and
        no tilted view, the principal distance cannot be told from the
        distance to the plane.
    min_tilt_deg : float
        A view is tilted when its optical axis is at least this far (degrees)
        from the plane's normal.
    weighted_anchor : bool
        True: a group of images sharing no target with the others is held in
        the world frame by 3 non-collinear weighted targets (``sigma > 0``), a
        warning. False: only exact control (``sigma == 0``) holds a group; any
        other split is fatal.

    Returns
    -------
    list of Problem
        Fatal problems first, in the order of the table in the module
        docstring; empty for a healthy network.

    Raises
    ------
    ValueError
        ``cam_from_world`` does not match the dataset's images.
    """
    problems: list[Problem] = []
    ids = list(dataset.image_ids)
    n_img = len(ids)
    n_obs_img = np.bincount(dataset.obs_image, minlength=n_img) if n_img else np.zeros(0, int)
    used = np.unique(dataset.obs_target)
    xyz_used = dataset.target_xyz[used]
    sigma = dataset.target_sigma
    free_used = used[np.isnan(sigma[used])]
    extent = _singular_values(xyz_used)
    coplanar = bool(extent[0] > 0 and extent[2] <= planar_tolerance * extent[0])

    # -- images -----------------------------------------------------------------------------
    few_skipped = [i for i, r in dataset.skipped_images if "usable observations" in r]
    other_skipped = [(i, r) for i, r in dataset.skipped_images if "usable observations" not in r]
    usable = np.flatnonzero(n_obs_img >= min_points_per_image)
    few_kept = [ids[i] for i in range(n_img) if n_obs_img[i] < min_points_per_image]
    if n_img == 0:
        problems.append(
            Problem(
                ProblemCode.SINGLE_IMAGE,
                "no usable image is left",
                f"capture images that each see at least {min_points_per_image} targets, "
                "from several positions",
                True,
            )
        )
    elif len(usable) == 0:
        problems.append(
            Problem(
                ProblemCode.FEW_POINTS,
                f"no image has {min_points_per_image} or more observations (largest: "
                f"{int(n_obs_img.max())}, in {ids[int(np.argmax(n_obs_img))]!r})",
                f"frame at least {min_points_per_image} targets in every image "
                "(move back, or add targets)",
                True,
                tuple(ids),
            )
        )
    elif len(usable) == 1:
        only = int(usable[0])
        seen = np.unique(dataset.obs_target[dataset.obs_image == only])
        n_free = int(np.isnan(sigma[seen]).sum())
        s = _singular_values(dataset.target_xyz[seen])
        why = []
        if n_free:
            why.append(f"{n_free} of its targets have no sigma and cannot be triangulated")
        if s[0] > 0 and s[2] <= planar_tolerance * s[0]:
            why.append("its targets are coplanar")
        problems.append(
            Problem(
                ProblemCode.SINGLE_IMAGE,
                f"only one usable image ({ids[only]!r})"
                + (": " + " and ".join(why) if why else ": the intrinsics rest on one resection"),
                "capture more images (10 or more) from different positions and orientations, "
                "covering the whole frame",
                bool(why),
                (ids[only],),
            )
        )
    if len(usable) and (few_skipped or few_kept):
        parts = []
        if few_skipped:
            parts.append(f"{len(few_skipped)} skipped by the loader ({_names(few_skipped)})")
        if few_kept:
            parts.append(
                f"{len(few_kept)} kept with fewer than {min_points_per_image} observations, "
                f"which the initialisation will likely leave out ({_names(few_kept)})"
            )
        problems.append(
            Problem(
                ProblemCode.FEW_POINTS,
                "images with too few usable points: " + "; ".join(parts),
                f"frame at least {min_points_per_image} targets inside each image",
                False,
                tuple(few_skipped + few_kept),
            )
        )
    if other_skipped:
        detail = "; ".join(f"{i!r}: {r}" for i, r in other_skipped[:3])
        more = f" (+{len(other_skipped) - 3} more)" if len(other_skipped) > 3 else ""
        problems.append(
            Problem(
                ProblemCode.SKIPPED_IMAGES,
                f"{len(other_skipped)} images left out: {detail}{more}",
                "check these images' observations (mislabelled targets, blunders)",
                False,
                tuple(i for i, _ in other_skipped),
            )
        )

    # -- targets ----------------------------------------------------------------------------
    tids = dataset.target_ids
    if n_img and (len(used) < 3 or not _non_collinear(xyz_used)):
        kind = "coincide" if extent[0] == 0 or len(used) < 2 else "lie on one line"
        problems.append(
            Problem(
                ProblemCode.DEGENERATE_TARGETS,
                f"the {len(used)} observed targets {kind} ({_names([tids[j] for j in used])})",
                "observe targets spread over an area or volume (a board, walls and floor); "
                "check the targets' xyz",
                True,
                tuple(tids[j] for j in used),
            )
        )

    # -- connectivity -----------------------------------------------------------------------
    groups = image_groups(dataset) if n_img > 1 else []
    if len(groups) > 1:
        weak, unanchored = [], []
        for g in groups:
            seen = np.unique(dataset.obs_target[np.isin(dataset.obs_image, g)])
            exact = seen[sigma[seen] == 0]
            weighted = seen[np.isfinite(sigma[seen])]
            if _non_collinear(dataset.target_xyz[exact]):
                continue
            if weighted_anchor and _non_collinear(dataset.target_xyz[weighted]):
                weak.append(g)
            else:
                unanchored.append(g)
        if unanchored or weak:
            desc = "; ".join(
                f"group {k + 1}: {len(g)} image{'s' if len(g) > 1 else ''} "
                f"({_names([ids[i] for i in g], 4)})"
                for k, g in enumerate(groups[:6])
            )
            more = f"; +{len(groups) - 6} more groups" if len(groups) > 6 else ""
            if unanchored:
                free_net = not np.isfinite(sigma[used]).any()
                held = "no target has a sigma (free network), so" if free_net else "some"
                problems.append(
                    Problem(
                        ProblemCode.DISCONNECTED,
                        f"the images form {len(groups)} groups that share no target "
                        f"({desc}{more}); {held} groups are not held in the world frame by "
                        "3 non-collinear control targets",
                        "capture images that overlap, seeing targets of several groups, give "
                        "at least 3 non-collinear targets in every group a sigma, or leave the "
                        "smaller groups out",
                        True,
                        tuple(ids[i] for g in unanchored for i in g),
                    )
                )
            else:
                problems.append(
                    Problem(
                        ProblemCode.DISCONNECTED,
                        f"the images form {len(groups)} groups that share no target "
                        f"({desc}{more}); they are tied together only through the targets' "
                        "approximate coordinates (sigma)",
                        "capture images that overlap, seeing targets of several groups",
                        False,
                        tuple(ids[i] for g in weak for i in g),
                    )
                )

    if n_img > 1 and len(free_used):
        undetermined = undetermined_targets(dataset.obs_image, dataset.obs_target, sigma)
        once = [tids[j] for j in free_used if undetermined[j]]
        if once:
            problems.append(
                Problem(
                    ProblemCode.UNDETERMINED_TARGETS,
                    f"{len(once)} targets without a sigma are seen in one image only, so their "
                    f"coordinates are not determined ({_names(once)}): their observations "
                    "are left out of the adjustment",
                    "capture more images so that every target is seen from at least two "
                    "positions, or give these targets a sigma",
                    False,
                    tuple(once),
                )
            )

    # -- pose-dependent checks --------------------------------------------------------------
    if cam_from_world is not None and n_img:
        R, t = _poses(cam_from_world, n_img)
        problems += _pose_checks(
            dataset,
            R,
            t,
            free_used,
            coplanar,
            min_baseline_ratio=min_baseline_ratio,
            narrow_fov_deg=narrow_fov_deg,
            min_tilt_deg=min_tilt_deg,
        )
    return sorted(problems, key=lambda p: not p.fatal)


def _pose_checks(
    dataset: Dataset,
    R: np.ndarray,
    t: np.ndarray,
    free_used: np.ndarray,
    coplanar: bool,
    *,
    min_baseline_ratio: float,
    narrow_fov_deg: float,
    min_tilt_deg: float,
) -> list[Problem]:
    """``no-baseline`` and ``planar-narrow-view`` from poses R (M,3,3), t (M,3)."""
    problems: list[Problem] = []
    ids = dataset.image_ids
    ok = np.all(np.isfinite(R), axis=(1, 2)) & np.all(np.isfinite(t), axis=1)
    obs = ok[dataset.obs_image]
    if ok.sum() < 1 or not obs.any():
        return problems
    centres = -np.einsum("mji,mj->mi", R, t)  # C = -R^T t
    xyz = dataset.target_xyz[dataset.obs_target[obs]]
    dist = np.linalg.norm(xyz - centres[dataset.obs_image[obs]], axis=1)
    scale = float(np.median(dist))
    good = np.flatnonzero(ok)
    if len(good) >= 2 and scale > 0:
        c = centres[good]
        spread = float(np.max(np.linalg.norm(c - c.mean(0), axis=1)))
        if spread < min_baseline_ratio * scale:
            units = dataset.units
            problems.append(
                Problem(
                    ProblemCode.NO_BASELINE,
                    f"all {len(good)} images ({_names([ids[i] for i in good], 4)}) were taken "
                    "from one position: the camera centres "
                    f"lie within {spread:.3g} {units} of their mean, {100 * spread / scale:.2g}% "
                    f"of the median distance to the targets ({scale:.3g} {units})"
                    + (
                        f"; the {len(free_used)} targets without a sigma cannot be triangulated"
                        if len(free_used)
                        else ""
                    ),
                    "move the camera between images (a baseline of 10-20% of the distance to "
                    "the targets or more), or give every target a sigma",
                    bool(len(free_used)),
                    tuple(ids[i] for i in good),
                )
            )

    if coplanar:
        used = np.unique(dataset.obs_target)
        pts = dataset.target_xyz[used]
        normal = np.linalg.svd(pts - pts.mean(0))[2][2]
        pc = np.einsum("nij,nj->ni", R[dataset.obs_image[obs]], xyz) + t[dataset.obs_image[obs]]
        alpha = np.degrees(np.arctan2(np.hypot(pc[:, 0], pc[:, 1]), pc[:, 2]))
        axes = R[good, 2, :]  # optical axes in the world frame
        tilt = np.degrees(np.arccos(np.clip(np.abs(axes @ normal), 0.0, 1.0)))
        if np.max(alpha) < narrow_fov_deg / 2 and np.max(tilt) < min_tilt_deg:
            problems.append(
                Problem(
                    ProblemCode.PLANAR_NARROW,
                    f"the targets are coplanar, the field of view used is narrow (largest "
                    f"incidence {np.max(alpha):.1f} deg) and every view "
                    f"({_names([ids[i] for i in good], 4)}) is within {np.max(tilt):.1f} deg "
                    "of the plane's normal: the principal distance cannot be told from the "
                    "distance to the plane",
                    f"tilt the camera by {max(2 * min_tilt_deg, 30):.0f}-45 deg relative to "
                    "the plane in several directions, fill the frame's corners, or add targets "
                    "off the plane",
                    True,
                    tuple(ids[i] for i in good),
                )
            )
    return problems


def raise_if_degenerate(
    problems: Sequence[Problem], warn: Callable[[str], None] | None = None
) -> list[Problem]:
    """Raise for the fatal problems; pass the others to ``warn`` or the logger.

    Parameters
    ----------
    problems : sequence of Problem
        Output of :func:`check_geometry`.
    warn : callable(str), optional
        Receives one line per non-fatal problem (``"warning: [code] message ->
        advice"``). Default: each is a warning of the ``gtsam_sphere.estimation.diagnose``
        logger (``"[code] message -> advice"``).

    Returns
    -------
    list of Problem
        The non-fatal problems (when nothing was raised).

    Raises
    ------
    DegenerateGeometryError
        If any problem is fatal; its message holds every fatal message and its
        advice, on one line.
    """
    fatal = [p for p in problems if p.fatal]
    if fatal:
        raise DegenerateGeometryError(fatal)
    rest = [p for p in problems if not p.fatal]
    for p in rest:
        if warn is not None:
            warn(f"warning: {p}")
        else:
            logger.warning("%s", p)
    return rest
