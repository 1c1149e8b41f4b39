"""Factor graph of the spherical bundle adjustment with self-calibration.

Variables (``docs/conventions.md``):

- ``x{i}``: ``Pose3`` ``world_from_cam`` of image ``i`` (GTSAM's camera-pose
  convention; the files store its inverse ``cam_from_world``);
- ``l{j}``: ``Point3`` of target ``j`` when it is not exact control;
- ``k0``: intrinsics vector ``[xp, yp, c, *brown]`` (px, px, px, dimensionless).

Observations are grouped into :class:`ObservationBlock` factors, each a
``gtsam.CustomFactor`` that evaluates all its observations in one vectorised
numpy call: free targets are grouped a few points per factor (all images
seeing them), exact-control targets per image. Robust weighting stays per
observation: each observation's 2-vector residual is weighted by the
M-estimator on its own norm, exactly as ``gtsam.noiseModel.Robust`` would do
for a single-observation factor (IRLS weights ``sqrt(w)`` on the linear system,
``rho`` in the cost).

The measurements a block holds are the *corrected* pixels; rewriting the
corrections means building new blocks, which costs milliseconds
(:meth:`BundleProblem.build`).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import gtsam
import numpy as np

from .camera import sphere_residual
from .geometry import skew


def pose_key(i: int) -> int:
    """GTSAM key of image ``i``'s ``world_from_cam`` pose."""
    return gtsam.symbol("x", i)


def point_key(j: int) -> int:
    """GTSAM key of target ``j``."""
    return gtsam.symbol("l", j)


INTRINSICS_KEY = gtsam.symbol("k", 0)


class Loss(enum.StrEnum):
    """Robust M-estimators, applied per observation to the whitened residual norm."""

    L2 = "l2"
    HUBER = "huber"
    CAUCHY = "cauchy"
    TUKEY = "tukey"
    GEMAN_MCCLURE = "geman-mcclure"


def robust_weight(r: np.ndarray, loss: Loss | str, k: float) -> tuple[np.ndarray, np.ndarray]:
    """IRLS weight ``w(r)`` and cost ``rho(r)`` of whitened residual norms ``r`` (N,).

    ``rho(r) = r^2 / 2`` near zero for every loss, so costs compare with L2.
    """
    loss = Loss(loss)
    r = np.asarray(r, float)
    if loss is Loss.L2:
        return np.ones_like(r), 0.5 * r * r
    if loss is Loss.HUBER:
        big = r > k
        w = np.where(big, k / np.maximum(r, 1e-300), 1.0)
        rho = np.where(big, k * r - 0.5 * k * k, 0.5 * r * r)
        return w, rho
    if loss is Loss.CAUCHY:
        q = (r / k) ** 2
        return 1.0 / (1.0 + q), 0.5 * k * k * np.log1p(q)
    if loss is Loss.TUKEY:
        q = np.minimum((r / k) ** 2, 1.0)
        return (1.0 - q) ** 2 * (r <= k), k * k / 6.0 * (1.0 - (1.0 - q) ** 3)
    if loss is Loss.GEMAN_MCCLURE:
        d = k * k + r * r
        return k**4 / d**2, 0.5 * k * k * r * r / d
    raise ValueError(f"unknown loss {loss!r}")


@dataclass
class NoiseOptions:
    """Measurement noise and robust loss.

    Attributes
    ----------
    sigma_px : float
        Standard deviation of an image coordinate (px).
    loss : Loss
        M-estimator applied to each observation's whitened residual norm.
    loss_threshold : float
        Threshold ``k`` in units of ``sigma_px``; 2.45 is the 95% quantile of
        the norm of a 2-D standard normal, so 5% of clean observations are
        mildly down-weighted.
    """

    sigma_px: float = 1.0
    loss: Loss = Loss.HUBER
    loss_threshold: float = 2.45


class ObservationBlock:
    """A vectorised group of observations behind one ``gtsam.CustomFactor``.

    Parameters
    ----------
    pose_keys : list of int
        Keys of the ``world_from_cam`` poses this block touches.
    point_keys : list of int
        Keys of the free targets this block touches (may be empty).
    pose_local : ndarray of int, shape (n,)
        Index into ``pose_keys`` per observation.
    point_local : ndarray of int, shape (n,)
        Index into ``point_keys``, or -1 for exact control points.
    fixed_xyz : ndarray, shape (n, 3)
        World coordinates used where ``point_local == -1``.
    uv_px : ndarray, shape (n, 2)
        Corrected measurements (px).
    brown_names : tuple of str
    brown_scale_px : float
    noise : NoiseOptions
    """

    def __init__(
        self,
        pose_keys,
        point_keys,
        pose_local,
        point_local,
        fixed_xyz,
        uv_px,
        brown_names,
        brown_scale_px,
        noise: NoiseOptions,
    ):
        self.pose_keys = list(pose_keys)
        self.point_keys = list(point_keys)
        self.pose_local = np.asarray(pose_local, int)
        self.point_local = np.asarray(point_local, int)
        self.free = self.point_local >= 0
        self.fixed_xyz = np.asarray(fixed_xyz, float)
        self.uv_px = np.asarray(uv_px, float)
        self.brown_names = tuple(brown_names)
        self.brown_scale_px = float(brown_scale_px)
        self.noise = noise
        self.n = len(self.uv_px)
        self.keys = self.point_keys + self.pose_keys + [INTRINSICS_KEY]
        self._rows = np.arange(self.n)

    def factor(self) -> gtsam.CustomFactor:
        """The ``gtsam.CustomFactor`` (unit noise: whitening is done inside)."""
        model = gtsam.noiseModel.Unit.Create(2 * self.n)
        return gtsam.CustomFactor(model, self.keys, self.evaluate)

    def state(self, values: gtsam.Values):
        """Camera-frame points (n,3), rotations R_wc (n,3,3) and theta from ``values``."""
        T = np.array([values.atPose3(k).matrix() for k in self.pose_keys])
        R = T[self.pose_local, :3, :3]
        t = T[self.pose_local, :3, 3]
        pw = self.fixed_xyz.copy()
        if self.point_keys:
            P = np.array([values.atPoint3(k) for k in self.point_keys])
            pw[self.free] = P[self.point_local[self.free]]
        pc = np.einsum("nji,nj->ni", R, pw - t)
        return pc, R, values.atVector(INTRINSICS_KEY)

    def residuals_px(self, values: gtsam.Values) -> np.ndarray:
        """Unweighted residuals ``measured - predicted`` (n, 2) px."""
        pc, _, theta = self.state(values)
        return sphere_residual(theta, self.brown_names, self.brown_scale_px, self.uv_px, pc)

    def evaluate(self, this, values: gtsam.Values, H):
        """CustomFactor callback: whitened, robustly weighted error (2n,).

        With ``H`` None (cost evaluation) the returned vector has squared norm
        ``2 * sum(rho)``; with ``H`` a list (linearisation) it is the IRLS
        system ``sqrt(w) * e / sigma`` and ``H`` receives the matching
        Jacobian blocks, Fortran-ordered, one per key.
        """
        pc, R, theta = self.state(values)
        sigma = self.noise.sigma_px
        k = self.noise.loss_threshold
        if H is None:
            e = sphere_residual(theta, self.brown_names, self.brown_scale_px, self.uv_px, pc)
            r = np.sqrt((e * e).sum(1)) / sigma
            _, rho = robust_weight(r, self.noise.loss, k)
            with np.errstate(invalid="ignore", divide="ignore"):
                scale = np.where(r > 0, np.sqrt(2.0 * rho) / r, 1.0) / sigma
            return (e * scale[:, None]).ravel()
        e, J_theta, J_pc = sphere_residual(
            theta, self.brown_names, self.brown_scale_px, self.uv_px, pc, jacobians=True
        )
        r = np.sqrt((e * e).sum(1)) / sigma
        w, _ = robust_weight(r, self.noise.loss, k)
        scale = np.sqrt(w) / sigma
        J_pc = J_pc * scale[:, None, None]
        n = self.n
        # pose: d(pc)/d(omega) = [pc]x, d(pc)/d(v) = -I (right perturbation of world_from_cam)
        J_pose = np.concatenate([J_pc @ skew(pc), -J_pc], axis=2)
        blocks = np.zeros((n, 2, len(self.pose_keys), 6))
        blocks[self._rows, :, self.pose_local, :] = J_pose
        out = []
        if self.point_keys:
            J_pt = np.einsum("nab,ncb->nac", J_pc, R)  # J_pc @ R_wc^T
            pblocks = np.zeros((n, 2, len(self.point_keys), 3))
            f = self.free
            pblocks[self._rows[f], :, self.point_local[f], :] = J_pt[f]
            for q in range(len(self.point_keys)):
                out.append(np.asfortranarray(pblocks[:, :, q, :].reshape(2 * n, 3)))
        for q in range(len(self.pose_keys)):
            out.append(np.asfortranarray(blocks[:, :, q, :].reshape(2 * n, 6)))
        out.append(np.asfortranarray((J_theta * scale[:, None, None]).reshape(2 * n, -1)))
        for q, block in enumerate(out):
            H[q] = block
        return (e * scale[:, None]).ravel()


class NormalOffsetFactor:
    """1-D datum constraint ``n . (p - p0) / sigma`` on a ``Point3``."""

    def __init__(self, key: int, normal: np.ndarray, p0: np.ndarray, sigma: float):
        self.key, self.normal, self.p0, self.sigma = key, np.asarray(normal), np.asarray(p0), sigma

    def factor(self) -> gtsam.CustomFactor:
        """The ``gtsam.CustomFactor``."""
        return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(1), [self.key], self.evaluate)

    def evaluate(self, this, values, H):
        """CustomFactor callback."""
        p = values.atPoint3(self.key)
        if H is not None:
            H[0] = np.asfortranarray(self.normal[None, :] / self.sigma)
        return np.array([self.normal @ (p - self.p0) / self.sigma])


class Datum(enum.StrEnum):
    """How the network's datum is defined."""

    CONTROL = "control"  # exact (sigma 0) or weighted control points
    FREE = "free"  # approximate coordinates only: minimal constraints + S-transform


def choose_minimal_constraint_points(xyz: np.ndarray) -> tuple[int, int, int]:
    """Three well-spread points (indices into ``xyz`` (T,3)) for a minimal datum."""
    centroid = xyz.mean(0)
    a = int(np.argmax(np.linalg.norm(xyz - centroid, axis=1)))
    b = int(np.argmax(np.linalg.norm(xyz - xyz[a], axis=1)))
    ab = xyz[b] - xyz[a]
    ab /= np.linalg.norm(ab)
    d = xyz - xyz[a]
    off = np.linalg.norm(d - np.outer(d @ ab, ab), axis=1)
    c = int(np.argmax(off))
    return a, b, c


@dataclass
class BundleProblem:
    """Everything needed to (re)build the bundle-adjustment graph.

    Attributes
    ----------
    obs_image, obs_target : ndarray of int, shape (N,)
    uv_px : ndarray, shape (N, 2)
        Raw measurements.
    corrections_px : ndarray, shape (N, 2)
        Learned corrections subtracted from ``uv_px`` before adjustment.
    target_xyz, target_sigma : ndarray, shape (T, 3) and (T,)
        Approximate coordinates and their sigma (0 exact, NaN absent).
    brown_names : tuple of str
    brown_scale_px : float
    noise : NoiseOptions
    points_per_factor : int
        Free targets per :class:`ObservationBlock`.
    """

    obs_image: np.ndarray
    obs_target: np.ndarray
    uv_px: np.ndarray
    target_xyz: np.ndarray
    target_sigma: np.ndarray
    n_images: int
    brown_names: tuple[str, ...] = ()
    brown_scale_px: float = 1000.0
    noise: NoiseOptions = field(default_factory=NoiseOptions)
    points_per_factor: int = 4
    corrections_px: np.ndarray | None = None
    datum_sigma_scale: float = 1e-3
    fixed_intrinsics: np.ndarray | None = None

    def __post_init__(self):
        if self.corrections_px is None:
            self.corrections_px = np.zeros_like(self.uv_px)
        sig = self.target_sigma
        used = np.unique(self.obs_target)
        self.fixed = np.zeros(len(sig), bool)
        self.fixed[used] = sig[used] == 0
        self.free_targets = used[~self.fixed[used]]
        ctrl = used[np.isfinite(sig[used])]
        if len(ctrl) == 0:
            self.datum = Datum.FREE
        else:
            pts = self.target_xyz[ctrl]
            spread = np.linalg.svd(pts - pts.mean(0), compute_uv=False) if len(ctrl) >= 3 else 0
            if len(ctrl) < 3 or spread[1] < 1e-6 * max(spread[0], 1e-12):
                raise ValueError(
                    f"the targets with a sigma ({len(ctrl)} observed) do not define a datum: "
                    "give sigma to at least 3 non-collinear targets, or to none (free network)"
                )
            self.datum = Datum.CONTROL
        self.blocks: list[ObservationBlock] = []
        self.block_obs: list[np.ndarray] = []

    @property
    def corrected_uv_px(self) -> np.ndarray:
        """Measurements minus learned corrections, (N, 2) px."""
        return self.uv_px - self.corrections_px

    def _groups(self) -> list[np.ndarray]:
        """Observation indices of each block: exact control per image, then free
        targets ``points_per_factor`` at a time, ordered by the first image seeing them."""
        fixed_obs = self.fixed[self.obs_target]
        groups = [
            np.flatnonzero(fixed_obs & (self.obs_image == i))
            for i in np.unique(self.obs_image[fixed_obs])
        ]
        free_idx = np.flatnonzero(~fixed_obs)
        if len(free_idx):
            by_target: dict[int, list[int]] = {}
            for o in free_idx:
                by_target.setdefault(int(self.obs_target[o]), []).append(int(o))
            order = sorted(by_target, key=lambda t: (self.obs_image[by_target[t]].min(), t))
            G = max(1, int(self.points_per_factor))
            for a in range(0, len(order), G):
                groups.append(np.array([o for t in order[a : a + G] for o in by_target[t]]))
        return groups

    def _make_blocks(self) -> list[ObservationBlock]:
        uv = self.corrected_uv_px
        blocks = []
        for idx in self.block_obs:
            images = np.unique(self.obs_image[idx])
            tgt = self.obs_target[idx]
            free = ~self.fixed[tgt]
            points = np.unique(tgt[free])
            point_local = np.full(len(idx), -1)
            point_local[free] = np.searchsorted(points, tgt[free])
            blocks.append(
                ObservationBlock(
                    [pose_key(i) for i in images],
                    [point_key(t) for t in points],
                    np.searchsorted(images, self.obs_image[idx]),
                    point_local,
                    self.target_xyz[tgt],
                    uv[idx],
                    self.brown_names,
                    self.brown_scale_px,
                    self.noise,
                )
            )
        return blocks

    def build(self) -> gtsam.NonlinearFactorGraph:
        """Build the graph: observation blocks, target priors and the datum."""
        self.block_obs = self._groups()
        self.blocks = self._make_blocks()
        graph = gtsam.NonlinearFactorGraph()
        for b in self.blocks:
            graph.add(b.factor())
        sig = self.target_sigma
        for t in self.free_targets:
            if np.isfinite(sig[t]) and sig[t] > 0:
                graph.add(
                    gtsam.PriorFactorPoint3(
                        point_key(t),
                        self.target_xyz[t],
                        gtsam.noiseModel.Isotropic.Sigma(3, sig[t]),
                    )
                )
        if self.fixed_intrinsics is not None:
            theta = np.asarray(self.fixed_intrinsics, float)
            noise = gtsam.noiseModel.Isotropic.Sigma(len(theta), 1e-9)
            graph.add(gtsam.PriorFactorVector(INTRINSICS_KEY, theta, noise))
        if self.datum is Datum.FREE:
            xyz = self.target_xyz[self.free_targets]
            extent = float(np.linalg.norm(xyz.max(0) - xyz.min(0))) or 1.0
            sd = self.datum_sigma_scale * extent
            a, b, c = choose_minimal_constraint_points(xyz)
            ta, tb, tc = self.free_targets[[a, b, c]]
            self.datum_targets = (int(ta), int(tb), int(tc))
            for t in (ta, tb):
                graph.add(
                    gtsam.PriorFactorPoint3(
                        point_key(t), self.target_xyz[t], gtsam.noiseModel.Isotropic.Sigma(3, sd)
                    )
                )
            normal = np.cross(xyz[b] - xyz[a], xyz[c] - xyz[a])
            normal /= np.linalg.norm(normal)
            self._datum_factor = NormalOffsetFactor(point_key(tc), normal, self.target_xyz[tc], sd)
            graph.add(self._datum_factor.factor())
        return graph

    def n_datum_constraints(self) -> int:
        """Constraints that only fix the datum (7 for a free network, else 0)."""
        return 7 if self.datum is Datum.FREE else 0

    def residuals_px(self, values: gtsam.Values) -> np.ndarray:
        """Residuals ``measured - predicted`` (N, 2) px, in observation order."""
        out = np.empty((len(self.uv_px), 2))
        for block, idx in zip(self.blocks, self.block_obs):
            out[idx] = block.residuals_px(values)
        return out

    def n_unknowns(self) -> int:
        """Number of estimated parameters (6 per pose, 3 per free target, intrinsics)."""
        n_theta = 0 if self.fixed_intrinsics is not None else 3 + len(self.brown_names)
        return 6 * len(np.unique(self.obs_image)) + 3 * len(self.free_targets) + n_theta

    def intrinsics_names(self) -> list[str]:
        """Names of the intrinsics vector's entries."""
        return ["xp_px", "yp_px", "c_px", *self.brown_names]
