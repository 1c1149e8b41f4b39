"""Initial camera poses without prior knowledge of the lens (Chow et al. 2018, section 4).

The paper seeds its adjustment with P3P poses computed from surveyed (approximate) target
coordinates. Here the lens is unknown, so P3P runs on bearings from *hypothetical* radial
mappings with the principal point at the image centre ``((width-1)/2, (height-1)/2)``:

====================  ===================  ==================================
``mapping``           radius ``r(alpha)``  domain of ``alpha``
====================  ===================  ==================================
``"pinhole"``         ``f tan(alpha)``     [0, 90) deg
``"equidistant"``     ``f alpha``          [0, 180] deg (may look behind)
``"sphere"``          ``f sin(alpha)``     [0, 90] deg (front hemisphere)
====================  ===================  ==================================

Every mapping has ``dr/dalpha = f`` on the axis, so ``f_px`` is comparable across kinds.

Strategy
--------
1. Coarse search: for each kind, a geometric grid of ``f`` (ratio ``1.15`` between
   neighbours, ~60 hypotheses in all) spanning diagonal fields of view of 40 deg up to
   160 (pinhole), 360 (equidistant; also 360 deg on a circle of 0.4 times the short
   side: circular fisheyes) or 180 deg (sphere; down to an image circle of 0.4 times
   the short side). Each hypothesis runs :func:`~gtsam_sphere.p3p.ransac_pose`
   (no refinement, 64 samples) on the 4 images with most observations with a loose
   threshold ``3 * threshold_rad``, scored by the MSAC cost ``sum(min(err^2, thr^2))``
   (inliers first, then their errors) twice: over all observations, and over the
   central ones only (radius below a quarter of the short side, where a few percent of
   focal error cannot spoil mappings that are steep at the rim, like the sphere's near
   90 deg). The best ``f`` of each criterion is a candidate.
2. Scan: 13 focal lengths 2.3 % apart around each candidate, same 4 images, threshold
   ``2 * threshold_rad``, all observations.
3. Zoom, for candidates whose scan cost is within 1.5 times the best: 5 focal lengths
   0.6 % apart plus a parabolic step, with pose refinement and ``threshold_rad``, on up
   to 8 *scoring images*. The lowest cost over kinds and focal lengths wins. Every
   evaluation uses the same random seeds (common random numbers) so costs compare
   hypotheses, not luck.
4. All images run with the chosen hypothesis and the final threshold.

Threshold choice: ``max(threshold_rad, threshold_px / f_px)`` with defaults 0.01 rad and
4 px. Approximate targets with 1 cm isotropic noise seen from 2-4 m move by
0.0025-0.005 rad (1 sigma), so 0.01 rad keeps 86-99 % of them; 4 px is the pixel-noise
floor for short focal lengths. Blunders of tens of pixels are rejected when they exceed
the threshold; the later robust adjustment deals with the rest.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .errors import InitialisationError
from .p3p import angular_errors_rad, ransac_pose

__all__ = ["MAPPINGS", "InitialisationResult", "bearings_from_pixels", "initialize_poses"]

MAPPINGS: tuple[str, ...] = ("pinhole", "equidistant", "sphere")

_GRID_RATIO = 1.15  # neighbouring coarse focal hypotheses differ by this factor
_MAX_FOV_DEG = {"pinhole": 160.0, "equidistant": 360.0, "sphere": 180.0}
_MIN_FOV_DEG = 40.0


@dataclass
class InitialisationResult:
    """Poses from :func:`initialize_poses`.

    Attributes
    ----------
    cam_from_world_R : (M, 3, 3) rotations, NaN for images that failed.
    cam_from_world_t : (M, 3) translations, metres, NaN for images that failed.
    ok : (M,) bool, image initialised.
    inlier_mask : (N,) bool per observation (False for observations of failed images).
    mapping : chosen hypothesis kind, one of :data:`MAPPINGS`.
    f_px : chosen focal scale, px (``dr/dalpha`` on the axis).
    failures : image index -> human-readable reason.
    threshold_rad : angular inlier threshold of the final pass, radians.
    scores : (mapping, f_px) -> MSAC cost (rad^2) of every hypothesis evaluated.
    """

    cam_from_world_R: np.ndarray
    cam_from_world_t: np.ndarray
    ok: np.ndarray
    inlier_mask: np.ndarray
    mapping: str
    f_px: float
    failures: dict[int, str]
    threshold_rad: float = float("nan")
    scores: dict[tuple[str, float], float] = field(default_factory=dict)


def _alpha_from_radius(r_px: np.ndarray, mapping: str, f_px: float) -> np.ndarray:
    """Incidence angle (rad) of image radius ``r_px``; NaN outside the mapping's domain."""
    rho = np.asarray(r_px, dtype=float) / f_px
    if mapping == "pinhole":
        return np.arctan(rho)
    if mapping == "equidistant":
        return np.where(rho <= np.pi, rho, np.nan)
    if mapping == "sphere":
        with np.errstate(invalid="ignore"):
            return np.where(rho <= 1.0, np.arcsin(np.minimum(rho, 1.0)), np.nan)
    raise ValueError(f"unknown mapping {mapping!r}; expected one of {MAPPINGS}")


def bearings_from_pixels(
    uv_px: np.ndarray, mapping: str, f_px: float, principal_point_px
) -> np.ndarray:
    """Unproject pixels to unit rays with a generic radial mapping.

    Parameters
    ----------
    uv_px : (N, 2) array
        Pixel coordinates (u right, v down, (0, 0) the centre of the top-left pixel).
    mapping : {"pinhole", "equidistant", "sphere"}
        ``r = f tan(alpha)``, ``r = f alpha`` or ``r = f sin(alpha)`` (front hemisphere),
        with ``alpha`` the angle between the ray and the optical axis (+z).
    f_px : float
        Focal scale, px.
    principal_point_px : (2,) array-like
        Principal point (u, v), px.

    Returns
    -------
    (N, 3) array
        Unit rays in the camera frame (x right, y down, z forward); they point behind the
        camera (z < 0) for equidistant radii beyond ``f * pi / 2``. Rows are NaN for
        pixels outside the mapping's domain (``r > f`` for "sphere", ``r > pi f`` for
        "equidistant") or non-finite input.
    """
    if not np.isfinite(f_px) or f_px <= 0:
        raise ValueError(f"f_px must be a positive finite number, got {f_px!r}")
    uv = np.asarray(uv_px, dtype=float).reshape(-1, 2)
    pp = np.asarray(principal_point_px, dtype=float).reshape(2)
    d = uv - pp
    r = np.hypot(d[:, 0], d[:, 1])
    alpha = _alpha_from_radius(r, mapping, f_px)
    safe_r = np.where(r > 0, r, 1.0)
    sin_a = np.sin(alpha)
    rays = np.empty((uv.shape[0], 3))
    rays[:, 0] = np.where(r > 0, sin_a * d[:, 0] / safe_r, 0.0)
    rays[:, 1] = np.where(r > 0, sin_a * d[:, 1] / safe_r, 0.0)
    rays[:, 2] = np.cos(alpha)
    rays[~np.isfinite(alpha)] = np.nan
    return rays


def _focal_grid(mapping: str, width: int, height: int) -> np.ndarray:
    """Coarse focal hypotheses (px) for one mapping, geometric with ratio ``_GRID_RATIO``."""
    r_max = np.hypot((width - 1) / 2.0, (height - 1) / 2.0)

    def f_of_fov(fov_deg: float) -> float:
        half = np.radians(fov_deg) / 2.0
        if mapping == "pinhole":
            return r_max / np.tan(half)
        if mapping == "equidistant":
            return r_max / half
        return r_max / np.sin(min(half, np.pi / 2))

    f_hi = f_of_fov(_MIN_FOV_DEG)
    f_lo = f_of_fov(_MAX_FOV_DEG[mapping])
    if mapping == "sphere":  # circular orthographic image inside the frame
        f_lo = min(f_lo, 0.4 * min(width, height))
    if mapping == "equidistant":  # circular fisheye: 360 deg on a circle inside the frame
        f_lo = min(f_lo, 0.4 * min(width, height) / np.pi)
    n = int(np.ceil(np.log(f_hi / f_lo) / np.log(_GRID_RATIO))) + 1
    return np.geomspace(f_lo, f_hi, n)


def _g(mapping: str, alpha: np.ndarray) -> np.ndarray:
    """Radius per unit focal length, ``r / f``, at incidence ``alpha`` (rad)."""
    if mapping == "pinhole":
        return np.where(alpha < np.radians(85.0), np.tan(np.minimum(alpha, 1.5)), np.nan)
    if mapping == "equidistant":
        return alpha
    return np.where(alpha <= np.pi / 2, np.sin(alpha), np.nan)


class _Problem:
    """Observations grouped by image, with per-hypothesis RANSAC evaluation."""

    def __init__(self, uv, obs_image, obs_target, target_xyz, width, height, n_images):
        self.uv = uv
        self.points = target_xyz[obs_target]
        self.pp = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
        self.radius = np.hypot(*(uv - self.pp).T)
        order = np.argsort(obs_image, kind="stable")
        counts = np.bincount(obs_image, minlength=n_images)
        self.obs_of_image = np.split(order, np.cumsum(counts)[:-1])
        self.counts = counts
        r_central = 0.25 * min(width, height)
        self.central_of_image = [i[self.radius[i] <= r_central] for i in self.obs_of_image]

    def run(
        self,
        image,
        mapping,
        f_px,
        thr,
        seed,
        max_iterations,
        min_inliers,
        refine=True,
        central=False,
    ):
        """RANSAC pose of one image under one hypothesis; returns (PoseResult, MSAC cost)."""
        idx = (self.central_of_image if central else self.obs_of_image)[image]
        rays = bearings_from_pixels(self.uv[idx], mapping, f_px, self.pp)
        res = ransac_pose(
            rays,
            self.points[idx],
            thr,
            np.random.default_rng(seed),
            max_iterations=max_iterations,
            min_inliers=min_inliers,
            refine=refine,
        )
        if np.all(np.isfinite(res.R)):
            err = np.nan_to_num(angular_errors_rad(rays, self.points[idx], res.R, res.t), nan=9.0)
            cost = float(np.minimum(err * err, thr * thr).sum())
        else:
            cost = idx.size * thr * thr
        return res, cost

    def cost(self, images, seeds, mapping, f_px, thr, max_iterations, refine=True, central=False):
        """Total MSAC cost of a hypothesis over ``images`` (rad^2)."""
        total = 0.0
        for image, seed in zip(images, seeds, strict=True):
            total += self.run(image, mapping, f_px, thr, seed, max_iterations, 4, refine, central)[
                1
            ]
        return total


def _focal_scan(problem, images, seeds, mapping, f0, thr):
    """Stage one of the focal search: 13 values of ``log f`` over one coarse step either
    side of ``f0`` (2.3 % apart), no pose refinement, threshold ``2 thr``.

    Returns ``(f_px, cost)`` of the best value.
    """
    half = np.log(_GRID_RATIO)
    xs = np.log(f0) + np.linspace(-half, half, 13)
    cs = [problem.cost(images, seeds, mapping, np.exp(x), 2.0 * thr, 64, False) for x in xs]
    j = int(np.argmin(cs))
    return float(np.exp(xs[j])), float(cs[j])


def _focal_zoom(problem, images, seeds, mapping, f0, thr):
    """Stage two: 5 values 0.6 % apart around ``f0`` with refinement and ``thr``, then a
    parabolic step in ``log f``. Returns ``(f_px, cost)``."""
    h = np.log(_GRID_RATIO) / 24.0
    x2 = np.log(f0) + h * np.arange(-2, 3)
    c2 = [problem.cost(images, seeds, mapping, np.exp(x), thr, 300) for x in x2]
    j = int(np.argmin(c2))
    xs, cs = list(x2), list(c2)
    if 0 < j < len(c2) - 1:
        y0, y1, y2 = c2[j - 1], c2[j], c2[j + 1]
        den = y0 - 2 * y1 + y2
        if den > 0:
            x_new = x2[j] + 0.5 * h * (y0 - y2) / den
            xs.append(x_new)
            cs.append(problem.cost(images, seeds, mapping, np.exp(x_new), thr, 300))
    k = int(np.argmin(cs))
    return float(np.exp(xs[k])), float(cs[k])


def _check_inputs(uv_px, obs_image, obs_target, target_xyz, width, height, n_images):
    uv = np.asarray(uv_px, dtype=float)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"uv_px must have shape (N, 2), got {uv.shape}")
    n = uv.shape[0]
    img = np.asarray(obs_image)
    tgt = np.asarray(obs_target)
    xyz = np.asarray(target_xyz, dtype=float)
    for name, arr in (("obs_image", img), ("obs_target", tgt)):
        if arr.shape != (n,):
            raise ValueError(f"{name} must have shape ({n},) like uv_px, got {arr.shape}")
        if n and not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(f"{name} must hold integers, got dtype {arr.dtype}")
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"target_xyz must have shape (T, 3), got {xyz.shape}")
    if int(width) <= 0 or int(height) <= 0:
        raise ValueError(f"width and height must be positive, got {width} x {height}")
    if int(n_images) <= 0:
        raise ValueError(f"n_images must be positive, got {n_images}")
    if n and (img.min() < 0 or img.max() >= n_images):
        raise ValueError(
            f"obs_image values must lie in [0, {n_images}), got {img.min()}..{img.max()}"
        )
    if n and (tgt.min() < 0 or tgt.max() >= xyz.shape[0]):
        raise ValueError(
            f"obs_target values must lie in [0, {xyz.shape[0]}), got {tgt.min()}..{tgt.max()}"
        )
    return uv, img.astype(np.int64), tgt.astype(np.int64), xyz


def initialize_poses(
    uv_px: np.ndarray,
    obs_image: np.ndarray,
    obs_target: np.ndarray,
    target_xyz: np.ndarray,
    width: int,
    height: int,
    n_images: int,
    *,
    rng: np.random.Generator | None = None,
    progress: Callable[[str], None] | None = None,
    min_inliers: int = 6,
    threshold_rad: float = 0.01,
    threshold_px: float = 4.0,
    n_scoring_images: int = 8,
    n_coarse_images: int = 4,
    mappings: tuple[str, ...] = MAPPINGS,
) -> InitialisationResult:
    """Initial cam_from_world poses of every image, with the lens mapping unknown.

    Parameters
    ----------
    uv_px : (N, 2) array
        Observed pixels (u right, v down, (0, 0) the centre of the top-left pixel).
    obs_image : (N,) int array
        Image index of each observation, in ``[0, n_images)``.
    obs_target : (N,) int array
        Target index of each observation, row of ``target_xyz``.
    target_xyz : (T, 3) array
        Approximate world coordinates of the targets, metres (noise and a few percent of
        blunders in the observations are tolerated).
    width, height : int
        Image size, px; the principal point is assumed at ``((width-1)/2, (height-1)/2)``.
    n_images : int
        Number of images ``M``.
    rng : numpy.random.Generator, optional
        Randomness for RANSAC (default: a fixed seed, so results are reproducible).
    progress : callable(str), optional
        Receives progress messages.
    min_inliers : int
        An image is initialised when its pose has at least this many inliers.
    threshold_rad, threshold_px : float
        Final angular inlier threshold is ``max(threshold_rad, threshold_px / f_px)``
        (see the module docstring for the rationale).
    n_scoring_images, n_coarse_images : int
        Images (those with most observations) used to rank lens hypotheses in the fine
        and the coarse search.
    mappings : tuple of str
        Mapping kinds to try, subset of :data:`MAPPINGS`.

    Returns
    -------
    InitialisationResult
        Poses (NaN for failed images), per-observation inliers, the chosen ``mapping`` and
        ``f_px``, and ``failures`` with a reason for every image not initialised.

    Raises
    ------
    ValueError
        On malformed input, or when no image can be initialised (the message gives the
        reasons).
    """
    uv, img, tgt, xyz = _check_inputs(
        uv_px, obs_image, obs_target, target_xyz, width, height, n_images
    )
    for m in mappings:
        if m not in MAPPINGS:
            raise ValueError(f"unknown mapping {m!r}; expected a subset of {MAPPINGS}")
    rng = np.random.default_rng(0) if rng is None else rng
    say = progress if progress is not None else (lambda _msg: None)
    n_images = int(n_images)
    min_inliers = max(int(min_inliers), 4)
    problem = _Problem(uv, img, tgt, xyz, int(width), int(height), n_images)
    counts = problem.counts

    failures: dict[int, str] = {}
    for i in range(n_images):
        if counts[i] < min_inliers:
            failures[i] = (
                "no observations"
                if counts[i] == 0
                else f"only {counts[i]} observation{'s' if counts[i] != 1 else ''} "
                f"(need at least {min_inliers})"
            )
    eligible = np.flatnonzero(counts >= min_inliers)
    if eligible.size == 0:
        raise InitialisationError(
            f"no image can be initialised: every one of the {n_images} images has fewer "
            f"than {min_inliers} observations (counts: {counts.tolist()})"
        )

    scoring = eligible[np.argsort(-counts[eligible], kind="stable")][:n_scoring_images]
    seeds = rng.integers(0, 2**63 - 1, size=scoring.size)
    scores: dict[tuple[str, float], float] = {}

    # 1. coarse search. Two criteria per kind: the cost on all observations, and on the
    # central ones only (r < a quarter of the short side, where every kind has
    # dr/dalpha ~ f and a few percent of focal error cannot spoil the fit, which matters
    # for mappings that are steep at the rim like the sphere's near 90 deg).
    coarse_thr = 3.0 * threshold_rad
    coarse_images = scoring[:n_coarse_images]
    coarse_seeds = seeds[: coarse_images.size]
    candidates: dict[str, list[float]] = {}
    for m in mappings:
        grid = _focal_grid(m, int(width), int(height))
        cands = []
        for central in (False, True):
            costs = [
                problem.cost(
                    coarse_images, coarse_seeds, m, f, coarse_thr, 64, False, central=central
                )
                for f in grid
            ]
            j = int(np.argmin(costs))
            if not cands or abs(np.log(grid[j] / cands[0])) > 1.5 * np.log(_GRID_RATIO):
                cands.append(float(grid[j]))
        candidates[m] = cands
        say(f"coarse: {m:11s} f candidates {', '.join(f'{c:.1f}' for c in cands)} px")

    # 2. 1-D focal search around every candidate (scan on the coarse images), then a
    # zoom with pose refinement on all scoring images for the promising ones; the lowest
    # MSAC cost over kinds wins.
    scanned = []
    for m in mappings:
        for f0 in candidates[m]:
            f_s, c_s = _focal_scan(problem, coarse_images, coarse_seeds, m, f0, threshold_rad)
            scanned.append((c_s, m, f_s))
            say(f"scan:   {m:11s} f = {f_s:.1f} px (cost {c_s:.4g})")
    best_scan = min(c for c, _, _ in scanned)
    best = (np.inf, "", np.nan)
    for c_s, m, f_s in sorted(scanned):
        if c_s > 1.5 * best_scan:
            continue
        f_m, c_m = _focal_zoom(problem, scoring, seeds, m, f_s, threshold_rad)
        scores[(m, f_m)] = c_m
        say(f"zoom:   {m:11s} f = {f_m:.1f} px (cost {c_m:.4g})")
        if c_m < best[0]:
            best = (c_m, m, f_m)
    _, mapping, f_px = best
    say(f"chosen mapping: {mapping}, f = {f_px:.1f} px")

    # 3. all images with the chosen hypothesis
    thr = max(threshold_rad, threshold_px / f_px)
    rot = np.full((n_images, 3, 3), np.nan)
    trans = np.full((n_images, 3), np.nan)
    ok = np.zeros(n_images, bool)
    inlier_mask = np.zeros(uv.shape[0], bool)
    image_seeds = rng.integers(0, 2**63 - 1, size=n_images)
    for i in eligible:
        res, _ = problem.run(i, mapping, f_px, thr, image_seeds[i], 1000, min_inliers)
        if res.success:
            ok[i] = True
            rot[i], trans[i] = res.R, res.t
            inlier_mask[problem.obs_of_image[i]] = res.inlier_mask
        else:
            failures[int(i)] = res.reason or "RANSAC failed"
    say(f"initialised {int(ok.sum())} of {n_images} images ({len(failures)} failed)")
    if not ok.any():
        detail = "; ".join(f"image {k}: {v}" for k, v in sorted(failures.items())[:10])
        raise InitialisationError(
            f"no image could be initialised with the best lens hypothesis "
            f"({mapping}, f = {f_px:.1f} px): {detail}"
        )
    return InitialisationResult(
        cam_from_world_R=rot,
        cam_from_world_t=trans,
        ok=ok,
        inlier_mask=inlier_mask,
        mapping=mapping,
        f_px=f_px,
        failures=dict(sorted(failures.items())),
        threshold_rad=thr,
        scores=scores,
    )
