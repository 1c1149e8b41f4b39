"""Factor graph of the spherical bundle adjustment with self-calibration.

Variables (``docs/conventions.md``):

- ``x{i}``: ``Pose3`` ``world_from_cam`` of image ``i`` (GTSAM's camera-pose
  convention; the files store its inverse ``cam_from_world``);
- ``l{j}``: ``Point3`` of target ``j`` when it is not exact control;
- ``k0``: intrinsics vector ``[xp, yp, c, *brown]`` (px, px, px, dimensionless).

Observations are grouped into :class:`ObservationBlock` factors, each a
``gtsam.CustomFactor``: free targets in tiles of a few targets by a few
images seeing them, exact-control targets per image. The blocks of one graph
are evaluated together, in one vectorised numpy pass per ``Values``, by the
package's one factor engine (:mod:`~gtsam_sphere.estimation.engine`). Robust weighting stays per
observation: each observation's 2-vector residual is weighted by the
M-estimator on its own norm, exactly as ``gtsam.noiseModel.Robust`` would do
for a single-observation factor (IRLS weights ``sqrt(w)`` on the linear system,
``rho`` in the cost).

The measurements a block holds are the *corrected* pixels; rewriting the
corrections means building new blocks, which costs milliseconds
(:meth:`BundleProblem.build`).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import gtsam
import numpy as np

from ..core._compat import StrEnum
from ..core.errors import DatasetError
from ..core.robust import Loss as Loss  # re-exported: the loss of NoiseOptions
from ..core.robust import robust_sigma_px as robust_sigma_px  # re-exported
from .engine import BundleMeasurement, FactorEngine, ProjectionModel, Whitener


def pose_key(i: int) -> int:
    """GTSAM key of image ``i``'s ``world_from_cam`` pose."""
    return gtsam.symbol("x", i)


def point_key(j: int) -> int:
    """GTSAM key of target ``j``."""
    return gtsam.symbol("l", j)


INTRINSICS_KEY = gtsam.symbol("k", 0)


def intrinsics_key(c: int) -> int:
    """GTSAM key of camera ``c``'s intrinsics in a rig graph (``k0`` is ``INTRINSICS_KEY``)."""
    return gtsam.symbol("k", c)


def frame_key(f: int) -> int:
    """GTSAM key of rig frame ``f``'s ``world_from_rig`` pose (a rig graph)."""
    return gtsam.symbol("f", f)


def extrinsics_key(c: int) -> int:
    """GTSAM key of camera ``c``'s ``rig_from_cam`` pose (a rig graph)."""
    return gtsam.symbol("e", c)


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

    The bundle graph's use of the one factor engine
    (:class:`~gtsam_sphere.estimation.engine.FactorEngine`, with a
    :class:`~gtsam_sphere.estimation.engine.ProjectionModel` whose measurement is
    :class:`~gtsam_sphere.estimation.engine.BundleMeasurement`: the intrinsics a
    variable). Blocks built together (:meth:`share_evaluation`, as
    :class:`BundleProblem` does) share one engine: the first callback at a given
    ``Values`` evaluates all their observations whose variables changed in one
    numpy pass and the others read their part of it (exactly: a stored result
    serves a block only at bit-identical variables). A block on its own has an
    engine of its own.

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
    radial_names : tuple of str or None
        Radial-mapping coefficients in the intrinsics vector; None: sphere mapping.
    extrinsic_keys : list of int, optional
        Keys of ``rig_from_cam`` poses (a rig graph): an observation with one has
        ``world_from_cam = pose * extrinsic``, its pose key then holding the frame's
        ``world_from_rig``.
    extrinsic_local : ndarray of int, shape (n,), optional
        Index into ``extrinsic_keys`` per observation, -1 (default) for none.
    intrinsics_key : int
        Key of the intrinsics vector (one per camera in a rig graph).
    radial_warp : float or None
        The radial mapping's fixed warp ``w`` (:func:`~gtsam_sphere.core.camera.radial_g`).
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
        radial_names: tuple[str, ...] | None = None,
        extrinsic_keys=(),
        extrinsic_local=None,
        intrinsics_key: int = INTRINSICS_KEY,
        radial_warp: float | None = None,
    ):
        self.radial_names = None if radial_names is None else tuple(radial_names)
        self.radial_warp = None if radial_warp is None else float(radial_warp)
        self.pose_keys = [int(k) for k in pose_keys]
        self.point_keys = [int(k) for k in point_keys]
        self.pose_local = np.asarray(pose_local, int)
        self.point_local = np.asarray(point_local, int)
        self.free = self.point_local >= 0
        self.fixed_xyz = np.asarray(fixed_xyz, float)
        self.uv_px = np.asarray(uv_px, float)
        self.brown_names = tuple(brown_names)
        self.brown_scale_px = float(brown_scale_px)
        self.noise = noise
        self.n = len(self.uv_px)
        self.extrinsic_keys = [int(k) for k in extrinsic_keys]
        if extrinsic_local is None:
            extrinsic_local = np.full(self.n, -1)
        self.extrinsic_local = np.asarray(extrinsic_local, int)
        self.composed = self.extrinsic_local >= 0
        self.intrinsics_key = int(intrinsics_key)
        self.keys = self.point_keys + self.pose_keys + self.extrinsic_keys + [self.intrinsics_key]
        self._engine: FactorEngine | None = None
        self._index = 0

    def _model_id(self) -> tuple:
        return (
            self.brown_names,
            self.brown_scale_px,
            self.noise,
            self.radial_names,
            self.intrinsics_key,
            self.radial_warp,
        )

    @staticmethod
    def share_evaluation(blocks: list[ObservationBlock]) -> None:
        """Evaluate ``blocks`` together from now on: one engine, one numpy pass per ``Values``.

        The blocks must share the measurement model, noise options and intrinsics key.
        """
        if not blocks:
            return
        model_id = blocks[0]._model_id()
        if any(b._model_id() != model_id for b in blocks):
            raise ValueError("blocks sharing an evaluation must share model, noise, intrinsics")
        first = blocks[0]
        measurement = BundleMeasurement(
            np.concatenate([b.uv_px for b in blocks]),
            first.brown_names,
            first.brown_scale_px,
            first.radial_names,
            first.radial_warp,
        )
        extrinsics = any(b.extrinsic_keys for b in blocks)
        fixed = None  # every point a variable
        if not all(b.free.all() for b in blocks):
            fixed = np.concatenate([b.fixed_xyz for b in blocks])
        model = ProjectionModel(measurement, fixed, extrinsics)
        specs = []
        for b in blocks:
            keys = [b.pose_keys, b.point_keys, [b.intrinsics_key]]
            local = [b.pose_local, b.point_local, np.zeros(b.n, np.intp)]
            if extrinsics:
                keys.append(b.extrinsic_keys)
                local.append(b.extrinsic_local)
            specs.append((keys, local))
        noise = first.noise
        whitener = Whitener.isotropic(noise.sigma_px, noise.loss, noise.loss_threshold)
        engine = FactorEngine.from_blocks(model, specs, whitener)
        for i, b in enumerate(blocks):
            b._engine, b._index = engine, i

    def engine(self) -> tuple[FactorEngine, int]:
        """The engine evaluating this block and the block's index in it."""
        if self._engine is None:
            ObservationBlock.share_evaluation([self])
        return self._engine, self._index

    def factor(self) -> gtsam.CustomFactor:
        """The ``gtsam.CustomFactor`` (unit noise: whitening is done inside)."""
        engine, i = self.engine()
        return engine.factor(i)

    def state(self, values: gtsam.Values):
        """Camera-frame points (n, 3), rotations ``R_wc`` (n, 3, 3) and theta (K,) at ``values``.

        Composed with GTSAM's own ``Pose3`` products (a reference for the engine's).
        """
        T = np.array([values.atPose3(k).matrix() for k in self.pose_keys])[self.pose_local]
        if self.extrinsic_keys:
            E = np.array([values.atPose3(k).matrix() for k in self.extrinsic_keys])
            T[self.composed] = T[self.composed] @ E[self.extrinsic_local[self.composed]]
        R = T[:, :3, :3]
        t = T[:, :3, 3]
        pw = self.fixed_xyz.copy()
        if self.point_keys:
            P = np.array([values.atPoint3(k) for k in self.point_keys])
            pw[self.free] = P[self.point_local[self.free]]
        pc = np.einsum("nji,nj->ni", R, pw - t)
        return pc, R, values.atVector(self.intrinsics_key)

    def residuals_px(self, values: gtsam.Values) -> np.ndarray:
        """Unweighted residuals ``measured - predicted`` (n, 2) px."""
        engine, i = self.engine()
        return engine.residuals_px(values, i)

    def evaluate(self, this, values: gtsam.Values, H):
        """CustomFactor callback: whitened, robustly weighted error (2n,).

        With ``H`` None (cost evaluation) the returned vector has squared norm
        ``2 * sum(rho)``; with ``H`` a list (linearisation) it is the IRLS
        system ``sqrt(w) * e / sigma`` and ``H`` receives the matching
        Jacobian blocks, Fortran-ordered, one per key.
        """
        engine, i = self.engine()
        return np.array(engine.callback(i)(this, values, H), copy=True)


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


class Datum(StrEnum):
    """How the network's datum is defined."""

    CONTROL = "control"  # exact (sigma 0) or weighted control points
    FREE = "free"  # approximate coordinates only: minimal constraints + S-transform


def observation_redundancy(
    J: np.ndarray, obs_target: np.ndarray, sigma_px: np.ndarray, target_sigma: np.ndarray
) -> np.ndarray:
    """Local redundancy numbers of the observations from the targets they share.

    The redundancy number of a 2-D observation is the trace of its 2 x 2 block of
    ``I - H`` (``H`` the hat matrix of the weighted adjustment): the expected squared
    residual norm over ``sigma^2``, 2 for an observation of a known point, 0 for one
    that alone determines what it observes. Here ``H`` is taken block by block over
    the targets (the poses and intrinsics, each determined by many observations,
    absorb little of any one): for target ``j`` with information
    ``N_j = sum_k J_k^T J_k / s_k^2 + I / sigma_j^2`` (its prior, when it has one),
    observation ``k`` has ``h_k = tr(J_k N_j^+ J_k^T) / s_k^2``. A target seen in one
    image with a loose prior gives ``h ~ 2`` (its residual tells nothing of the noise);
    a target seen in ``m`` images with no prior ``h ~ 3 / m``.

    Parameters
    ----------
    J : ndarray, shape (N, 2, 3)
        Derivative of each predicted pixel by its target (px per dataset unit;
        zero for exact targets): :meth:`BundleProblem.target_jacobians`.
    obs_target : ndarray of int, shape (N,)
    sigma_px : ndarray, shape (N,)
        Image noise of each observation, px.
    target_sigma : ndarray, shape (T,)
        Prior sigma of the targets (dataset units; 0 exact, NaN none).

    Returns
    -------
    ndarray, shape (N,)
        ``2 - h_k``, clipped to [0, 2].
    """
    J = np.asarray(J, float)
    obs_target = np.asarray(obs_target, np.intp)
    w = 1.0 / np.square(np.asarray(sigma_px, float))
    info = target_information(J, obs_target, w, target_sigma)
    used = np.unique(obs_target)
    cov = np.zeros_like(info)
    cov[used] = np.linalg.pinv(info[used], hermitian=True)
    h = w * np.einsum("nki,nij,nkj->n", J, cov[obs_target], J)
    return np.clip(2.0 - h, 0.0, 2.0)


#: :func:`target_covariances` works on dense arrays: computed up to this many pose and
#: intrinsic unknowns, and this many (target x unknown) entries
FULL_PRECISION_MAX_UNKNOWNS = 1000
FULL_PRECISION_MAX_ENTRIES = 6_000_000


def target_covariances(
    J_target: np.ndarray,
    J_camera: np.ndarray,
    camera_columns: np.ndarray,
    n_camera_unknowns: int,
    obs_target: np.ndarray,
    weight: np.ndarray,
    target_sigma: np.ndarray,
    datum_xyz: np.ndarray | None = None,
    datum_points: np.ndarray | None = None,
) -> np.ndarray | None:
    """Marginal covariance of every target, poses and intrinsics included, (T, 3, 3).

    :func:`intersection_sigma` holds the poses and the lens; here they are estimated
    with the targets. With the targets eliminated first (their normal blocks ``N_j``,
    :func:`target_information`), the reduced system of the camera-side unknowns (poses,
    a rig's frames and extrinsics, intrinsics) is ``S = C - sum_j W_j N_j^+ W_j^T``
    (``W_j`` the target-camera blocks) and each target's covariance
    ``N_j^+ + A_j S^+ A_j^T`` with ``A_j = N_j^+ W_j^T``. With ``datum_points``, a free
    network: the covariance is S-transformed onto the datum of a similarity fitted over
    those targets (equal weights), the datum of
    :func:`~gtsam_sphere.core.geometry.fit_similarity_trimmed` onto the approximate
    coordinates; ``S^+`` (on the Jacobi-scaled system) leaves out the network's
    7-parameter defect, which the transform removes from every generalised inverse
    alike.

    Parameters
    ----------
    J_target : ndarray, shape (N, 2, 3)
        Derivative of each pixel by its target (zero for exact targets), px per unit.
    J_camera : ndarray, shape (N, 2, K)
        By the observation's camera-side unknowns (pose ``[omega, v]``, right
        perturbation; intrinsics; ...), in the order of ``camera_columns``.
    camera_columns : ndarray of int, shape (N, K)
        Column of each in the reduced system, ``0 .. n_camera_unknowns - 1``; -1 for
        none (its Jacobian is ignored). :func:`pose_and_intrinsics_columns` lays out a
        single camera's.
    n_camera_unknowns : int
    obs_target : ndarray of int, shape (N,)
    weight : ndarray, shape (N,)
        1 / px^2 (robust weight / sigma^2; 0 leaves the observation out).
    target_sigma : ndarray, shape (T,)
        Prior sigma of the targets (0 exact, NaN none).
    datum_xyz : ndarray, shape (T, 3), optional
        The adjusted targets (source frame of the datum fit).
    datum_points : ndarray of int, optional
        The targets the free network's similarity is fitted over (at least 3).

    Returns
    -------
    ndarray, shape (T, 3, 3) or None
        Dataset units^2 (zero for targets not observed or exact). None above
        :data:`FULL_PRECISION_MAX_UNKNOWNS` or :data:`FULL_PRECISION_MAX_ENTRIES`.
    """
    obs_target = np.asarray(obs_target, np.intp)
    w = np.asarray(weight, float)
    n, n_t, n_c = len(obs_target), len(target_sigma), int(n_camera_unknowns)
    if n == 0 or n_c > FULL_PRECISION_MAX_UNKNOWNS or 3 * n_t * n_c > FULL_PRECISION_MAX_ENTRIES:
        return None
    cols = np.asarray(camera_columns, np.intp)
    Jc = np.where((cols >= 0)[:, None, :], np.asarray(J_camera, float), 0.0)
    cols = np.where(cols >= 0, cols, n_c)  # a spare column, dropped below
    info = target_information(J_target, obs_target, w, target_sigma)
    cov = np.zeros_like(info)
    used = np.unique(obs_target)
    cov[used] = np.linalg.pinv(info[used], hermitian=True)
    # W_j^T (T, 3, n_c) and C (n_c, n_c), accumulated from each observation's blocks
    Wt = np.zeros((n_t, n_c + 1, 3))
    np.add.at(Wt, (obs_target[:, None], cols), np.einsum("n,nka,nki->nai", w, Jc, J_target))
    Wt = Wt[:, :n_c].transpose(0, 2, 1)
    C = np.zeros((n_c + 1, n_c + 1))
    np.add.at(C, (cols[:, :, None], cols[:, None, :]), np.einsum("n,nka,nkb->nab", w, Jc, Jc))
    C = C[:n_c, :n_c]
    A = np.einsum("tij,tjc->tic", cov, Wt)  # N_j^+ W_j^T
    S = C - Wt.reshape(3 * n_t, n_c).T @ A.reshape(3 * n_t, n_c)
    # Jacobi scaling by the information before the targets are eliminated: an unknown
    # the targets' own shifts absorb keeps only round-off in S, of either sign, and its
    # eigenvalue is dropped below (scaled by S's own diagonal, clamped at 1e-300, such
    # round-off overflowed: a free ring4 rig of 4 frames, seed 5)
    diag = np.diag(C)
    d = np.sqrt(np.where(diag > 0.0, diag, 1.0))
    ev, V = np.linalg.eigh(S / np.outer(d, d))
    keep = ev > 1e-10 * max(float(ev.max()), 1e-300)
    S_inv = (V[:, keep] / ev[keep]) @ V[:, keep].T / np.outer(d, d)
    if datum_points is None:
        AS = np.einsum("tic,cd->tid", A, S_inv)
        return cov + np.einsum("tid,tjd->tij", AS, A)
    # S-transform onto the fit over F: dx' = dx - G_j M sum_{i in F} G_i^T dx_i
    F = np.asarray(datum_points, np.intp)
    x = np.asarray(datum_xyz, float) - np.asarray(datum_xyz, float)[F].mean(axis=0)
    G = np.zeros((n_t, 3, 7))
    G[:, :, 0:3] = np.eye(3)
    G[:, 0, 4], G[:, 0, 5] = x[:, 2], -x[:, 1]  # -[x]x: the small rotation's columns
    G[:, 1, 3], G[:, 1, 5] = -x[:, 2], x[:, 0]
    G[:, 2, 3], G[:, 2, 4] = x[:, 1], -x[:, 0]
    G[:, :, 6] = x
    M = np.linalg.pinv(np.einsum("fia,fib->ab", G[F], G[F]))
    GM = np.einsum("tia,ab->tib", G, M)
    inF = np.zeros(n_t, bool)
    inF[F] = True
    # (S A)_j = A_j - G_j M sum_F G_i^T A_i
    SA = A - np.einsum("tia,ac->tic", GM, np.einsum("fia,fic->ac", G[F], A[F]))
    # diagonal blocks of S D S^T (D = the N_j^+ blocks)
    GtDG = np.einsum("fia,fij,fjb->ab", G[F], cov[F], G[F])
    KD = np.where(inF[:, None, None], np.einsum("tia,tja,tjk->tik", GM, G, cov), 0.0)
    SDS = cov - KD - KD.transpose(0, 2, 1) + np.einsum("tia,ab,tjb->tij", GM, GtDG, GM)
    ASA = np.einsum("tic,cd,tjd->tij", SA, S_inv, SA)
    return SDS + ASA


def pose_and_intrinsics_columns(obs_pose: np.ndarray, n_theta: int) -> tuple[np.ndarray, int]:
    """:func:`target_covariances`' layout for one camera: 6 columns per pose, then the
    intrinsics. ``obs_pose`` (N,) indexes the poses 0 .. P-1; returns the columns (N,
    6 + n_theta) and the number of unknowns ``6 P + n_theta``."""
    obs_pose = np.asarray(obs_pose, np.intp)
    n_pose = int(obs_pose.max()) + 1 if len(obs_pose) else 0
    cols = np.concatenate(
        [
            6 * obs_pose[:, None] + np.arange(6),
            np.broadcast_to(6 * n_pose + np.arange(n_theta), (len(obs_pose), n_theta)),
        ],
        axis=1,
    )
    return cols, 6 * n_pose + int(n_theta)


def target_information(
    J: np.ndarray, obs_target: np.ndarray, weight: np.ndarray, target_sigma: np.ndarray
) -> np.ndarray:
    """Information of each target with the poses and intrinsics held, (T, 3, 3).

    ``N_j = sum_k w_k J_k^T J_k + I / sigma_j^2`` (the prior term where the target has a
    sigma): the normal-equation block of target ``j`` alone.

    Parameters
    ----------
    J : ndarray, shape (N, 2, 3)
        Derivative of each predicted pixel by its target, px per dataset unit
        (:meth:`BundleProblem.target_jacobians`; zero for exact targets).
    obs_target : ndarray of int, shape (N,)
    weight : ndarray, shape (N,)
        Weight of each observation, 1 / px^2 (robust weight / sigma_px^2; 0 leaves it
        out).
    target_sigma : ndarray, shape (T,)
        Prior sigma of the targets (dataset units; 0 exact, NaN none).

    Returns
    -------
    ndarray, shape (T, 3, 3)
        In 1 / dataset unit^2.
    """
    J = np.asarray(J, float)
    w = np.asarray(weight, float)
    info = np.zeros((len(target_sigma), 3, 3))
    np.add.at(
        info, np.asarray(obs_target, np.intp), w[:, None, None] * np.einsum("nki,nkj->nij", J, J)
    )
    sig = np.asarray(target_sigma, float)
    has_prior = np.isfinite(sig) & (sig > 0)
    prior = np.zeros(len(sig))
    prior[has_prior] = 1.0 / np.square(sig[has_prior])
    return info + prior[:, None, None] * np.eye(3)


def intersection_sigma(
    J: np.ndarray, obs_target: np.ndarray, weight: np.ndarray, target_sigma: np.ndarray
) -> np.ndarray:
    """Standard deviation of each target along its worst direction, poses and lens held.

    ``1 / sqrt(smallest eigenvalue of N_j)`` (:func:`target_information`): how well the
    target's rays (and its prior) fix it where they meet. Two rays at angle ``g`` from
    distance ``d`` through a lens of scale ``f`` px with noise ``s`` px give
    ``(d / f) s / sqrt(1 - cos g)``: large where the rays meet at small angles (the
    depth of a target seen from close stations). The poses' and the lens's own
    uncertainty come on top: a lower bound of the full marginal sigma.

    Parameters
    ----------
    J, obs_target, weight, target_sigma
        As :func:`target_information`.

    Returns
    -------
    ndarray, shape (T,)
        Dataset units; NaN for targets not observed or exact (``target_sigma`` 0), inf
        where the information is singular (one ray).
    """
    info = target_information(J, obs_target, weight, target_sigma)
    out = np.full(len(info), np.nan)
    sig = np.asarray(target_sigma, float)
    used = np.unique(np.asarray(obs_target, np.intp))
    used = used[~(np.isfinite(sig[used]) & (sig[used] == 0))]
    low = np.linalg.eigvalsh(info[used])[:, 0]
    scale = np.maximum(np.abs(info[used]).max(axis=(1, 2)), 1e-300)
    out[used] = np.where(low > 1e-12 * scale, 1.0 / np.sqrt(np.maximum(low, 1e-300)), np.inf)
    return out


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


#: images per observation block of free targets (see :func:`_tile_observations`)
IMAGES_PER_FACTOR = 8
#: the blocks' observations and variables by a digest of what they depend on
#: (:meth:`BundleProblem._structure`), oldest first
_STRUCTURES: dict[bytes, tuple[list, list]] = {}
_STRUCTURES_KEPT = 8


def _group_targets(seen: list[np.ndarray], n_images: int, size: int) -> list[list[int]]:
    """Greedy partition of targets into groups of at most ``size`` seen by similar images.

    ``seen[j]`` holds the images seeing target ``j``. Seeds are taken in order;
    a group grows by the remaining target whose images have the largest
    Jaccard index with the group's (ties: lowest index) and stops at ``size``
    targets or when no remaining target shares an image with the group.
    """
    n = len(seen)
    holders = [[] for _ in range(n_images)]  # targets seen by each image
    for j, images in enumerate(seen):
        for i in images.tolist():
            holders[i].append(j)
    holders = [np.asarray(h, np.intp) for h in holders]
    count = np.array([len(x) for x in seen])
    left = np.ones(n, bool)
    inter = np.zeros(n)  # images each target shares with the group being grown
    groups = []
    for seed in range(n):
        if not left[seed]:
            continue
        group, union, j = [], set(), seed
        while True:
            group.append(j)
            left[j] = False
            for i in seen[j].tolist():
                if i not in union:
                    union.add(i)
                    inter[holders[i]] += 1
            if len(group) >= size:
                break
            score = np.where(left & (inter > 0), inter / (count + len(union) - inter), -1.0)
            j = int(np.argmax(score))
            if score[j] <= 0:
                break
        for i in union:
            inter[holders[i]] -= 1
        groups.append(group)
    return groups


def _group_images(masks: list[int], size: int) -> list[list[int]]:
    """Partition images into ``ceil(n / size)`` groups of balanced size.

    ``masks[k]`` is the bit mask of the targets image ``k`` sees. Seeds are
    taken in order; a group grows by the remaining image whose mask has the
    largest Jaccard index with the group's (ties: first in order).
    """
    n_groups = -(-len(masks) // size)
    cap = -(-len(masks) // n_groups)
    left = list(range(len(masks)))
    groups = []
    while left:
        seed = left.pop(0)
        group, union = [seed], masks[seed]
        while left and len(group) < cap:
            best, best_score = left[0], -1.0
            for k in left:
                score = (masks[k] & union).bit_count() / (masks[k] | union).bit_count()
                if score > best_score:
                    best, best_score = k, score
            left.remove(best)
            group.append(best)
            union |= masks[best]
        groups.append(group)
    return groups


def _tile_observations(
    target: np.ndarray, image: np.ndarray, targets_per_tile: int, images_per_tile: int
) -> list[np.ndarray]:
    """Partition observations (target and image of each) into tiles.

    The targets are grouped (at most ``targets_per_tile``) by similar sets of
    images, seeded in the order of the first image seeing them; each group's
    images are split into balanced groups (at most ``images_per_tile``) seeing
    similar subsets of the group; a tile is a target group times an image group.

    Why: a ``CustomFactor``'s Jacobian is dense per key, so a tile of ``T``
    targets and ``I`` images carries ``2 (3 T + 6 I + n_theta)`` numbers per
    observation (small tiles), while the per-factor costs (callback, checks,
    one copy per key) are shared by its observations (well-filled tiles).
    A target's observations stay in its group's tiles, so the elimination
    (targets first) meets each group once, as one clique.

    Returns
    -------
    list of ndarray of int
        Observation indices of each tile.
    """
    targets, t_of = np.unique(target, return_inverse=True)
    n_images = int(image.max()) + 1
    by_target = np.argsort(t_of, kind="stable")
    bounds = np.searchsorted(t_of[by_target], np.arange(len(targets) + 1))
    pairs = np.unique(t_of * n_images + image)  # (target, image) sorted
    pair_t, pair_i = np.divmod(pairs, n_images)
    pair_bounds = np.searchsorted(pair_t, np.arange(len(targets) + 1))
    seen = [pair_i[pair_bounds[j] : pair_bounds[j + 1]] for j in range(len(targets))]
    order = np.argsort(pair_i[pair_bounds[:-1]], kind="stable")  # by first image
    tiles = []
    for group in _group_targets([seen[j] for j in order], n_images, targets_per_tile):
        members = [int(order[g]) for g in group]
        obs = np.concatenate([by_target[bounds[j] : bounds[j + 1]] for j in members])
        masks: dict[int, int] = {}
        for bit, j in enumerate(members):
            for i in seen[j].tolist():
                masks[i] = masks.get(i, 0) | (1 << bit)
        if len(masks) <= images_per_tile:
            tiles.append(np.sort(obs))
            continue
        images = sorted(masks, key=lambda i: (-masks[i].bit_count(), i))
        tile_of = np.zeros(n_images, np.intp)
        split = _group_images([masks[i] for i in images], images_per_tile)
        for t, members_i in enumerate(split):
            tile_of[[images[k] for k in members_i]] = t
        tile = tile_of[image[obs]]
        tiles += [np.sort(obs[tile == t]) for t in range(len(split))]
    return tiles


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
        At most this many free targets per :class:`ObservationBlock` (a tile of
        targets by at most ``IMAGES_PER_FACTOR`` images, :func:`_tile_observations`).
    radial_names : tuple of str or None
        Radial-mapping coefficients estimated (``Model.RADIAL``); None: sphere mapping.
    image_pose_keys : ndarray of int, shape (n_images,), optional
        Key of each image's pose variable; default ``pose_key(i)``. In a rig graph a
        framed image's key is its frame's ``world_from_rig``
        (:func:`frame_key`).
    image_extrinsic_keys : ndarray of int, shape (n_images,), optional
        Key of each image's ``rig_from_cam`` (:func:`extrinsics_key`), composed after
        its pose, or -1 for none (default: none).
    intrinsics_key : int
        Key of the intrinsics vector.
    radial_warp : float or None
        Fixed warp ``w`` of the radial mapping (from the initialisation); None: none.
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
    points_per_factor: int = 8
    corrections_px: np.ndarray | None = None
    datum_sigma_scale: float = 1e-3
    fixed_intrinsics: np.ndarray | None = None
    radial_names: tuple[str, ...] | None = None
    radial_warp: float | None = None
    image_pose_keys: np.ndarray | None = None
    image_extrinsic_keys: np.ndarray | None = None
    intrinsics_key: int = INTRINSICS_KEY

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
                raise DatasetError(
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
        """Observation indices of each block.

        Exact control: one block per image (its variables are the pose and the
        intrinsics, so nothing is zero-padded). Free targets: tiles of
        :func:`_tile_observations`, at most ``points_per_factor`` targets by
        ``IMAGES_PER_FACTOR`` images. Cached (:meth:`_structure`).
        """
        return [g.copy() for g in self._structure()[0]]

    def _structure(self) -> tuple[list[np.ndarray], list[tuple]]:
        """The blocks' observations (:meth:`_tile_groups`) and variables (:meth:`_layout`).

        Both depend only on which target each image sees, the fixed targets, the image
        keys and ``points_per_factor``: a problem rebuilt for a new noise scale, loss or
        correction (every robust stage, every kNN round), or a copy of it with other
        intrinsics or target sigmas (``dataclasses.replace``), reuses them. They are kept
        by a digest of those inputs, the last :data:`_STRUCTURES_KEPT`.
        """
        image_pose, image_ext = self.image_keys()
        fingerprint = hashlib.sha256(
            b"".join(
                np.ascontiguousarray(a).tobytes()
                for a in (self.obs_image, self.obs_target, self.fixed, image_pose, image_ext)
            )
            + str(int(self.points_per_factor)).encode()
        ).digest()
        cached = _STRUCTURES.get(fingerprint)
        if cached is None:
            groups = self._tile_groups()
            cached = (groups, self._layout(groups, image_pose, image_ext))
            while len(_STRUCTURES) >= _STRUCTURES_KEPT:
                del _STRUCTURES[next(iter(_STRUCTURES))]  # the oldest
            _STRUCTURES[fingerprint] = cached
        return cached

    def _layout(self, groups, image_pose: np.ndarray, image_ext: np.ndarray) -> list[tuple]:
        """Per block: pose keys, point keys, their local indices, extrinsic keys and
        local indices, and the target of each observation."""
        out = []
        for idx in groups:
            obs_pose = image_pose[self.obs_image[idx]]
            obs_ext = image_ext[self.obs_image[idx]]
            poses = np.unique(obs_pose)
            exts = np.unique(obs_ext[obs_ext >= 0])
            ext_local = np.where(obs_ext >= 0, np.searchsorted(exts, obs_ext), -1)
            tgt = self.obs_target[idx]
            free = ~self.fixed[tgt]
            points = np.unique(tgt[free])
            point_local = np.full(len(idx), -1)
            point_local[free] = np.searchsorted(points, tgt[free])
            pose_local = np.searchsorted(poses, obs_pose)
            point_keys = [point_key(t) for t in points]
            out.append(
                (poses.tolist(), point_keys, pose_local, point_local, exts.tolist(), ext_local, tgt)
            )
        return out

    def _tile_groups(self) -> list[np.ndarray]:
        """:meth:`_groups` computed (not cached)."""
        fixed_obs = self.fixed[self.obs_target]
        groups = [
            np.flatnonzero(fixed_obs & (self.obs_image == i))
            for i in np.unique(self.obs_image[fixed_obs])
        ]
        free_idx = np.flatnonzero(~fixed_obs)
        if len(free_idx):
            G = max(1, int(self.points_per_factor))
            tiles = _tile_observations(
                self.obs_target[free_idx], self.obs_image[free_idx], G, IMAGES_PER_FACTOR
            )
            groups += [free_idx[t] for t in tiles]
        return groups

    def image_keys(self) -> tuple[np.ndarray, np.ndarray]:
        """Pose key and extrinsic key (-1: none) of every image, (n_images,) each."""
        poses = self.image_pose_keys
        if poses is None:
            poses = np.array([pose_key(i) for i in range(self.n_images)], np.int64)
        ext = self.image_extrinsic_keys
        if ext is None:
            ext = np.full(self.n_images, -1, np.int64)
        return np.asarray(poses, np.int64), np.asarray(ext, np.int64)

    def _make_blocks(self) -> list[ObservationBlock]:
        uv = self.corrected_uv_px
        groups, layout = self._structure()
        blocks = []
        for idx, (poses, points, pose_local, point_local, exts, ext_local, tgt) in zip(
            groups, layout
        ):
            blocks.append(
                ObservationBlock(
                    poses,
                    points,
                    pose_local,
                    point_local,
                    self.target_xyz[tgt],
                    uv[idx],
                    self.brown_names,
                    self.brown_scale_px,
                    self.noise,
                    self.radial_names,
                    exts,
                    ext_local,
                    self.intrinsics_key,
                    radial_warp=self.radial_warp,
                )
            )
        ObservationBlock.share_evaluation(blocks)
        return blocks

    def observation_factors(self) -> list[gtsam.CustomFactor]:
        """(Re)build the observation blocks (``self.blocks``) and return their factors."""
        self.block_obs = self._groups()
        self.blocks = self._make_blocks()
        return [b.factor() for b in self.blocks]

    def build(self) -> gtsam.NonlinearFactorGraph:
        """Build the graph: observation blocks, target priors and the datum."""
        graph = gtsam.NonlinearFactorGraph()
        for f in self.observation_factors():
            graph.add(f)
        self.add_priors(graph)
        return graph

    def add_priors(self, graph: gtsam.NonlinearFactorGraph) -> None:
        """Add the target priors, the datum and a fixed-intrinsics prior to ``graph``."""
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
            graph.add(gtsam.PriorFactorVector(self.intrinsics_key, theta, noise))
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

    def n_datum_constraints(self) -> int:
        """Constraints that only fix the datum (7 for a free network, else 0)."""
        return 7 if self.datum is Datum.FREE else 0

    def residuals_px(self, values: gtsam.Values) -> np.ndarray:
        """Residuals ``measured - predicted`` (N, 2) px, in observation order."""
        out = np.empty((len(self.uv_px), 2))
        for block, idx in zip(self.blocks, self.block_obs):
            out[idx] = block.residuals_px(values)
        return out

    def target_jacobians(self, values: gtsam.Values, jacobians=None) -> np.ndarray:
        """Derivative of each observation's predicted pixel by its target, (N, 2, 3).

        Analytic, from the factor engine's Jacobian (the world-point columns of
        :meth:`~gtsam_sphere.estimation.engine.ProjectionModel.jacobian`, unweighted), in
        px per dataset unit; zero for exact targets (not variables). The blocks must be
        built. ``jacobians``: :meth:`observation_jacobians` at ``values`` when already
        evaluated. :meth:`target_jacobians_numerical` is the central-difference reference.
        """
        if len(self.free_targets) == 0 or not self.blocks:
            return np.zeros((len(self.uv_px), 2, 3))
        J, model = jacobians if jacobians is not None else self.observation_jacobians(values)
        out = -J[:, :, model.point_columns]  # d(predicted) / d(point)
        out[self.fixed[self.obs_target]] = 0.0
        return out

    def target_jacobians_numerical(self, values: gtsam.Values) -> np.ndarray:
        """:meth:`target_jacobians` by central differences (the reference of the tests).

        Step ``1e-6`` of the free targets' extent, every free target moved at once (an
        observation sees one target): six evaluations of the residuals.
        """
        J = np.zeros((len(self.uv_px), 2, 3))
        free = self.free_targets
        if len(free) == 0:
            return J
        xyz = np.array([values.atPoint3(point_key(int(t))) for t in free])
        extent = float(np.linalg.norm(xyz.max(0) - xyz.min(0))) or 1.0
        step = 1e-6 * extent
        moved = gtsam.Values(values)
        for a in range(3):
            res = []
            for sign in (1.0, -1.0):
                for t, p in zip(free, xyz):
                    q = p.copy()
                    q[a] += sign * step
                    moved.update(point_key(int(t)), q)
                res.append(self.residuals_px(moved))
            # residuals are measured - predicted
            J[:, :, a] = -(res[0] - res[1]) / (2.0 * step)
        J[self.fixed[self.obs_target]] = 0.0
        return np.nan_to_num(J)

    def observation_redundancy(self, values: gtsam.Values, sigma_px: float) -> np.ndarray:
        """Local redundancy number (0 to 2) of each observation, (N,) (see
        :func:`observation_redundancy`), at ``values`` with the image noise ``sigma_px``."""
        return observation_redundancy(
            self.target_jacobians(values),
            self.obs_target,
            np.full(len(self.uv_px), float(sigma_px)),
            self.target_sigma,
        )

    def observation_jacobians(self, values: gtsam.Values):
        """Every observation's Jacobian at ``values``, in this problem's order.

        The factor engine's analytic ``d(measured - predicted) / dx`` (unweighted; NaN
        set to 0) with the columns of its
        :class:`~gtsam_sphere.estimation.engine.ProjectionModel`: the pose (6), the
        point (3), the intrinsics (``model.n_theta``) and, for a rig, ``rig_from_cam``
        (6). The blocks must be built.

        Returns
        -------
        J : ndarray, shape (N, 2, columns)
        model : ProjectionModel
        """
        engine, _ = self.blocks[0].engine()
        _, J_e = engine.jacobians_px(values)  # (2, columns, n), engine order
        J = np.zeros((len(self.uv_px), 2, J_e.shape[1]))
        J[np.concatenate(self.block_obs)] = J_e.transpose(2, 0, 1)
        return np.nan_to_num(J), engine.model

    def target_covariances(
        self,
        values: gtsam.Values,
        weight: np.ndarray,
        datum_xyz: np.ndarray | None = None,
        datum_points: np.ndarray | None = None,
    ) -> np.ndarray | None:
        """Marginal covariance of every target at ``values``, (T, 3, 3) or None.

        :func:`target_covariances` with this problem's Jacobians (the factor engine's,
        analytic; the blocks must be built), ``weight`` (N,) 1 / px^2 and its target
        priors; the intrinsics held when they are fixed. ``datum_xyz`` (T, 3) and
        ``datum_points``: a free network's similarity datum (the adjusted targets, and
        those the similarity is fitted over). None where the
        system is too large (:data:`FULL_PRECISION_MAX_UNKNOWNS`), for a rig's
        extrinsic poses, or without observations.
        """
        if not self.blocks or len(self.uv_px) == 0:
            return None
        jacobians = self.observation_jacobians(values)
        J, model = jacobians
        if model.k_ext is not None:
            return None
        n_theta = 0 if self.fixed_intrinsics is not None else model.n_theta
        images = np.unique(self.obs_image)
        cols, n_c = pose_and_intrinsics_columns(np.searchsorted(images, self.obs_image), n_theta)
        return target_covariances(
            self.target_jacobians(values, jacobians),
            np.concatenate([J[:, :, 0:6], J[:, :, 9 : 9 + n_theta]], axis=2),
            cols,
            n_c,
            self.obs_target,
            weight,
            self.target_sigma,
            datum_xyz,
            datum_points,
        )

    def n_unknowns(self) -> int:
        """Number of estimated parameters (6 per pose, 3 per free target, intrinsics)."""
        n_theta = 0 if self.fixed_intrinsics is not None else len(self.intrinsics_names())
        return 6 * len(np.unique(self.obs_image)) + 3 * len(self.free_targets) + n_theta

    def intrinsics_names(self) -> list[str]:
        """Names of the intrinsics vector's entries."""
        return ["xp_px", "yp_px", "c_px", *(self.radial_names or ()), *self.brown_names]
