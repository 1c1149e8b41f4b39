"""The one vectorised factor engine: observations behind ``gtsam.CustomFactor`` blocks.

Every pixel factor of the package runs here (issue 14): the bundle graph's
observation blocks (:class:`~gtsam_sphere.estimation.graph.ObservationBlock`,
intrinsics a variable, optional rig extrinsics) and the frozen-calibration
blocks for users' graphs (:class:`~gtsam_sphere.estimation.external.ProjectionBlocks`).
What differs between them is the *model* (:class:`ProjectionModel` with a
:class:`BundleMeasurement` or a :class:`FrozenMeasurement`) and the noise
(:class:`Whitener`); the engine (:class:`FactorEngine`) does the rest:

- **one shared evaluation**: the blocks of a set are evaluated together, every
  block whose variables changed in one numpy pass, the others read their rows;
- **one exact-cache rule**: a stored result serves a block only if the ``Values``
  a callback receives holds, for every key of that block, bit for bit the numbers
  the result was computed from (a block's result depends on nothing else); on a
  miss the engine evaluates the whole set (a batch step: most blocks changed) or
  the block alone (an incremental solver relinearising a few blocks, until their
  time exceeds that of one full pass);
- **trusted passes**: inside a pass of :func:`~gtsam_sphere.estimation.optimize.
  levenberg_marquardt` (:class:`TrustedPass`), the ``Values`` does not change, so
  one full pass validates every block without reading its variables again;
- **one Jacobian hand-off**: a persistent buffer holds every block's zero-padded,
  Fortran-ordered Jacobian blocks (zeros written once, non-zeros by one scatter per
  pass); a callback copies its blocks into a ``gtsam.JacobianVector`` shared by the
  blocks of its shape and hands it over in one C++ copy (``H[:] = native``);
- **one whitening**: any 2-D Gaussian ``gtsam.noiseModel`` (or the bundle's
  isotropic ``sigma_px``) and any M-estimator per observation, through
  :mod:`gtsam_sphere.core.robust`, exactly as a single-observation factor with a
  ``gtsam.noiseModel.Robust`` would be weighted (cost ``rho(r)``, IRLS weight
  ``sqrt(w(r))`` on the linear system).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

import gtsam
import numpy as np

from ..core.robust import Loss, robust_weight, whitening_scale

__all__ = [
    "BundleMeasurement",
    "FactorEngine",
    "FrozenMeasurement",
    "Kind",
    "ProjectionModel",
    "TrustedPass",
    "Whitener",
]

#: ``Values.extract(keys)`` (GTSAM 4.3's Python)
_VALUES_EXTRACT = hasattr(gtsam.Values, "extract")


# --------------------------------------------------------------------------- noise


class Whitener:
    """Per-observation whitening and robust weighting of 2-D residuals.

    Either an isotropic ``sigma`` (px) with a :class:`~gtsam_sphere.core.robust.Loss`
    (:meth:`isotropic`, the bundle graph's noise) or any 2-D GTSAM noise model
    (:meth:`from_noise_model`): a Gaussian base model (square-root information
    ``sqrt_info``) and, inside ``Robust``, an M-estimator acting on the whitened
    norm ``r``. Huber, Cauchy, Tukey and Geman-McClure are vectorised
    (:func:`~gtsam_sphere.core.robust.robust_weight`, their parameter read back
    from the estimator and checked against its own ``weight``/``loss``); any other
    estimator is called per observation.

    Attributes
    ----------
    sqrt_info : ndarray, shape (2, 2)
        Square-root information of the base model (1/px).
    sigma : float or None
        The isotropic sigma (px) when the base model is isotropic, else None.
    loss : Loss or None
        Vectorised loss (None: the estimator ``mest`` is called per observation).
    k : float
        Its threshold, in units of the whitened norm.
    """

    _KINDS = (
        ("Huber", Loss.HUBER),
        ("Cauchy", Loss.CAUCHY),
        ("Tukey", Loss.TUKEY),
        ("GemanMcClure", Loss.GEMAN_MCCLURE),
    )

    def __init__(self, sqrt_info: np.ndarray, sigma: float | None, loss, k: float, mest=None):
        self.sqrt_info = np.asarray(sqrt_info, float)
        self.sigma = None if sigma is None else float(sigma)
        self.loss = None if loss is None else Loss(loss)
        self.k = float(k)
        self.mest = mest

    @classmethod
    def isotropic(cls, sigma_px: float, loss: Loss | str, k: float) -> Whitener:
        """Isotropic noise ``sigma_px`` (px) and loss ``loss`` with threshold ``k`` (sigmas)."""
        return cls(np.eye(2) / float(sigma_px), sigma_px, loss, k)

    @classmethod
    def from_noise_model(cls, noise_model) -> Whitener:
        """The whitening of a 2-D ``gtsam.noiseModel`` (Gaussian, optionally in ``Robust``)."""
        if not isinstance(noise_model, gtsam.noiseModel.Base):
            raise TypeError(f"expected a gtsam.noiseModel, got {type(noise_model).__name__}")
        if noise_model.dim() != 2:
            raise ValueError(f"the noise model must be 2-dimensional, got {noise_model.dim()}")
        base, mest = noise_model, None
        if isinstance(noise_model, gtsam.noiseModel.Robust):
            base, mest = noise_model.noise(), noise_model.robust()
        if not isinstance(base, gtsam.noiseModel.Gaussian) or base.isConstrained():
            raise ValueError(
                f"unsupported noise model {type(base).__name__}: use a Gaussian model "
                "(Unit, Isotropic, Diagonal, Gaussian), optionally inside Robust"
            )
        sqrt_info = np.asarray(base.Whiten(np.eye(2)), float)
        sigma = float(base.sigma()) if isinstance(base, gtsam.noiseModel.Isotropic) else None
        loss, k = None, 0.0
        if mest is None or isinstance(mest, gtsam.noiseModel.mEstimator.Null):
            loss = Loss.L2
        else:
            for name, kind in cls._KINDS:
                if isinstance(mest, getattr(gtsam.noiseModel.mEstimator, name)):
                    found = _mestimator_parameter(mest, kind)
                    if found is not None:
                        loss, k = kind, found
                    break
        return cls(sqrt_info, sigma, loss, k, mest)

    def weights(self, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """IRLS weights ``w(r)`` and costs ``rho(r)`` of whitened norms ``r`` (n,)."""
        if self.loss is not None:
            return robust_weight(r, self.loss, self.k)
        w = np.array([self.mest.weight(float(x)) for x in r])
        rho = np.array([self.mest.loss(float(x)) for x in r])
        return w, rho

    def norms(self, e_px: np.ndarray) -> np.ndarray:
        """Whitened norms ``|sqrt_info @ e|`` (n,) of residuals ``e_px`` (n, 2) px."""
        if self.sigma is not None:
            return np.sqrt((e_px * e_px).sum(1)) / self.sigma
        e = e_px @ self.sqrt_info.T
        return np.sqrt((e * e).sum(1))

    def weigh(self, e_px: np.ndarray, linear: bool):
        """Cost residuals, IRLS residuals and the left factor of the Jacobians.

        Parameters
        ----------
        e_px : ndarray, shape (n, 2)
            Residuals (px).
        linear : bool
            Also the IRLS residuals and the Jacobians' left factor.

        Returns
        -------
        e_cost : ndarray, shape (n, 2)
            Squared norm ``2 rho(r)`` per observation.
        e_lin : ndarray, shape (n, 2) or None
            ``sqrt(w(r)) sqrt_info e``.
        left : ndarray, shape (n,) or (n, 2, 2), or None
            ``sqrt(w) / sigma`` (isotropic) or ``sqrt(w) sqrt_info``: the whitened,
            weighted Jacobian of an observation is ``left @ d e / d x``.
        """
        if self.sigma is not None:  # isotropic: the bundle graph's arithmetic, bit for bit
            sigma = self.sigma
            r = np.sqrt((e_px * e_px).sum(1)) / sigma
            w, rho = self.weights(r)
            e_cost = e_px * (whitening_scale(r, rho) / sigma)[:, None]
            if not linear:
                return e_cost, None, None
            scale = np.sqrt(w) / sigma
            return e_cost, e_px * scale[:, None], scale
        S = self.sqrt_info
        e = e_px @ S.T
        r = np.sqrt((e * e).sum(1))
        w, rho = self.weights(r)
        e_cost = e * whitening_scale(r, rho)[:, None]
        if not linear:
            return e_cost, None, None
        sw = np.sqrt(w)
        return e_cost, e * sw[:, None], sw[:, None, None] * S


def _mestimator_parameter(m, loss: Loss) -> float | None:
    """Threshold of GTSAM M-estimator ``m`` read back from its functions; None if they
    disagree with :func:`gtsam_sphere.core.robust.robust_weight` (then it is called per
    observation)."""
    big = 1e6
    if loss is Loss.HUBER:
        k = m.weight(big) * big
    elif loss is Loss.CAUCHY:
        w = m.weight(1.0)
        k = math.sqrt(w / (1.0 - w)) if 0.0 < w < 1.0 else float("nan")
    else:  # Tukey: loss(inf) = k^2 / 6; Geman-McClure: loss(inf) = k^2 / 2
        k = math.sqrt((6.0 if loss is Loss.TUKEY else 2.0) * m.loss(big))
    if not (math.isfinite(k) and k > 0):
        return None
    probe = np.array([0.05, 0.3, 0.9, 1.7, 3.1, 7.0, 25.0]) * k
    w, rho = robust_weight(probe, loss, k)
    w_ref = np.array([m.weight(float(r)) for r in probe])
    rho_ref = np.array([m.loss(float(r)) for r in probe])
    ok = np.allclose(w, w_ref, rtol=1e-9, atol=1e-12) and np.allclose(
        rho, rho_ref, rtol=1e-9, atol=1e-12
    )
    return float(k) if ok else None


def check_keys(keys, n: int, name: str) -> np.ndarray:
    """GTSAM keys of ``n`` observations as a (n,) uint64 array (a scalar is repeated).

    Raises ``ValueError`` naming ``name`` and the shape it got when they do not fit.
    """
    arr = np.asarray(keys, dtype=np.uint64).reshape(-1)
    if arr.size == 1 and n != 1:
        arr = np.full(n, arr[0], dtype=np.uint64)
    if arr.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},) like uv_px, got {arr.shape}")
    return arr


def apply_left(J: np.ndarray, left: np.ndarray, out: np.ndarray) -> None:
    """``out[:, :, n] = left_n @ J[:, :, n]``: weigh the Jacobian rows of observations.

    Parameters
    ----------
    J : ndarray, shape (2, c, n)
        ``d e / d x`` per observation (px per unit of ``x``), rows ``u``, ``v``.
    left : ndarray, shape (n,) or (n, 2, 2)
        A scale per observation or a 2x2 factor (:meth:`Whitener.weigh`, 1/px).
    out : ndarray, shape (2, c, n)
        Receives the whitened, weighted Jacobian (dimensionless per unit of ``x``).
    """
    if left.ndim == 1:
        np.multiply(J, left, out=out)
    else:
        out[...] = np.einsum("nab,bcn->acn", left, J)


# --------------------------------------------------------------------------- variables


@dataclass(frozen=True)
class Kind:
    """A kind of variable: how it is read from a ``gtsam.Values`` and its sizes.

    Attributes
    ----------
    name : str
        ``"pose3"`` (stored as the 16 numbers of ``Pose3.matrix()``, row-major;
        tangent ``[omega, v]``), ``"point3"`` or ``"vector"``.
    width : int
        Numbers stored per variable.
    dim : int
        Tangent dimension (Jacobian columns).
    """

    name: str
    width: int
    dim: int

    def key_bytes(self, values: gtsam.Values, key: int) -> bytes:
        """The stored numbers of ``key`` in ``values``, as bytes (the cache's signature)."""
        if self.name == "pose3":
            return values.atPose3(key).matrix().tobytes()
        if self.name == "point3":
            return np.asarray(values.atPoint3(key), float).tobytes()
        return np.asarray(values.atVector(key), float).tobytes()

    def read(self, values: gtsam.Values, keys: list[int], have=None) -> np.ndarray:
        """Rows (len(keys), width) of ``keys`` (sorted) in ``values``; NaN rows if absent.

        ``have``: (len(keys),) bool, the keys present in ``values`` when known.
        """
        out = np.full((len(keys), self.width), np.nan)
        if not keys:
            return out
        if self.name == "vector":
            for i, k in enumerate(keys):
                if values.exists(k):
                    v = np.asarray(values.atVector(k), float)
                    if v.shape != (self.width,):
                        raise ValueError(f"vector key {k} holds {v.shape}, expected {self.width}")
                    out[i] = v
            return out
        if not _VALUES_EXTRACT:
            for i, k in enumerate(keys):
                if values.exists(k):
                    out[i] = np.frombuffer(self.key_bytes(values, k), float)
            return out
        if have is None:
            have = slice(None)
            try:
                sub = values.extract(keys)
            except RuntimeError:  # some keys are absent: extract those present
                have = _present(values, np.asarray(keys, np.uint64))
                sub = values.extract(np.asarray(keys, np.uint64)[have].tolist())
        else:
            sub = values.extract(np.asarray(keys, np.uint64)[have].tolist())
        if self.name == "pose3":
            rows = gtsam.utilities.extractPose3(sub)
        else:
            rows = gtsam.utilities.extractPoint3(sub)
        if rows.shape[0] != sub.size():
            raise TypeError("pose keys must hold Pose3 values and target keys Point3 values")
        if self.name == "point3":
            out[have] = np.asarray(rows, float).reshape(-1, 3)
            return out
        T = np.empty((rows.shape[0], 16))
        T[:, _POSE_COLUMNS] = rows
        T[:, 12:] = (0.0, 0.0, 0.0, 1.0)
        out[have] = T
        return out


def _present(values: gtsam.Values, keys: np.ndarray) -> np.ndarray:
    """Which of ``keys`` (uint64, any order) ``values`` holds, (len(keys),) bool."""
    held = np.asarray(values.keys(), np.uint64)  # sorted
    if not len(held):
        return np.zeros(len(keys), bool)
    at = np.minimum(np.searchsorted(held, keys), len(held) - 1)
    return held[at] == keys


#: where ``extractPose3``'s row ``[R (by rows), t]`` goes in ``Pose3.matrix().ravel()``
_POSE_COLUMNS = [0, 1, 2, 4, 5, 6, 8, 9, 10, 3, 7, 11]

POSE3 = Kind("pose3", 16, 6)
POINT3 = Kind("point3", 3, 3)


def vector_kind(dim: int) -> Kind:
    """The kind of a ``dim``-vector variable."""
    return Kind("vector", int(dim), int(dim))


# --------------------------------------------------------------------------- models


class BundleMeasurement:
    """The calibration's measurement model with the intrinsics a variable (bundle graph).

    ``e = sphere_residual(theta, ...)``, see
    :func:`~gtsam_sphere.core.camera.sphere_residual`.

    Parameters
    ----------
    uv_px : ndarray, shape (N, 2)
        Corrected measurements (px).
    brown_names : tuple of str
    brown_scale_px : float
    radial_names : tuple of str or None
    radial_warp : float or None
    """

    def __init__(self, uv_px, brown_names, brown_scale_px, radial_names, radial_warp):
        self.uv_px = np.asarray(uv_px, float)
        self.brown_names = tuple(brown_names)
        self.brown_scale_px = float(brown_scale_px)
        self.radial_names = None if radial_names is None else tuple(radial_names)
        self.radial_warp = None if radial_warp is None else float(radial_warp)
        self.n_theta = 3 + len(self.radial_names or ()) + len(self.brown_names)

    def __call__(self, pc: np.ndarray, theta, rows, jacobians: bool):
        """``e`` (m, 2) px and, with ``jacobians``, ``de/dtheta`` (m, 2, K), ``de/dpc``."""
        from ..core.camera import sphere_residual

        out = sphere_residual(
            theta,
            self.brown_names,
            self.brown_scale_px,
            self.uv_px[rows],
            pc.T,
            jacobians=jacobians,
            radial_names=self.radial_names,
            warp=self.radial_warp,
        )
        return out if jacobians else (out, None, None)


class FrozenMeasurement:
    """A frozen calibration's measurement model: ``e = M (ideal_px - camera.ideal_from_points(P))``.

    ``M`` is the calibration's residual metric at each measurement
    (:meth:`~gtsam_sphere.core.camera.SphereCamera.measurement_metric`, constant per
    observation): the residual is weighed as in the adjustment that made the
    calibration, so its ``sigma_px`` applies unchanged.

    Parameters
    ----------
    camera : SphereCamera
    ideal_px : ndarray, shape (N, 2)
        Corrected measurements ``camera.ideal_from_pixels(uv)`` (px).
    metric : ndarray, shape (N, 2, 2), or None
        ``M`` per observation; None: the identity.
    """

    n_theta = 0

    def __init__(self, camera, ideal_px, metric=None):
        self.camera = camera
        self.ideal_px = np.asarray(ideal_px, float)
        self.metric = None if metric is None else np.asarray(metric, float)

    def __call__(self, pc: np.ndarray, theta, rows, jacobians: bool):
        """``e`` (m, 2) px and, with ``jacobians``, None and ``de/dpc`` (m, 2, 3)."""
        M = None if self.metric is None else self.metric[rows]
        if not jacobians:
            e = self.ideal_px[rows] - self.camera.ideal_from_points(pc.T)
            return (e if M is None else np.einsum("nij,nj->ni", M, e)), None, None
        pred, J = self.camera.ideal_from_points(pc.T, jacobians=True)
        e = self.ideal_px[rows] - pred
        if M is None:
            return e, None, -J
        return np.einsum("nij,nj->ni", M, e), None, -np.einsum("nij,njk->nik", M, J)


class ProjectionModel:
    """Observations of points by posed cameras: the residual and Jacobians the engine runs.

    Variables (kinds, in this order; the Jacobian's columns follow it): the pose
    ``A`` of each observation (``Pose3``, ``world_from_cam``, or the frame's
    ``world_from_rig`` when the observation has an extrinsic pose), its point
    (``Point3``, world; index -1: the fixed ``fixed_xyz``), the intrinsics vector
    (bundle only, one key per set) and the ``rig_from_cam`` pose ``B`` (when
    ``extrinsics``; index -1: none). The camera-frame point is ``pc = B^-1 A^-1 p``;
    the measurement (:class:`BundleMeasurement` or :class:`FrozenMeasurement`)
    turns it into the residual (px).

    Right perturbations ``A exp(dA)``, ``B exp(dB)`` with ``q = A^-1 p`` give
    ``d pc / d omega_B = [pc]x``, ``d pc / d v_B = -I`` and ``d pc / d dA = R_B^T
    (d q / d dA)`` with ``d q / d omega_A = [q]x``, ``d q / d v_A = -I`` (the chain
    rule through ``d(A B) / d dA = Ad(B^-1)``), ``d q / d p = R_A^T``.

    Parameters
    ----------
    measurement : BundleMeasurement or FrozenMeasurement
    fixed_xyz : ndarray, shape (N, 3) or None
        World points of the observations without a point variable.
    extrinsics : bool
        Whether the set has ``rig_from_cam`` variables (a fourth kind).
    """

    def __init__(self, measurement, fixed_xyz=None, extrinsics: bool = False):
        self.measurement = measurement
        self.n_theta = measurement.n_theta
        kinds = [POSE3, POINT3]
        if self.n_theta:
            kinds.append(vector_kind(self.n_theta))
        self.k_ext = len(kinds) if extrinsics else None
        if extrinsics:
            kinds.append(POSE3)
        self.kinds = tuple(kinds)
        # a factor's keys: points, poses, extrinsic poses, intrinsics
        order = [1, 0] + ([self.k_ext] if extrinsics else []) + ([2] if self.n_theta else [])
        self.key_order = tuple(order)
        self.fixed_xyz = None if fixed_xyz is None else np.asarray(fixed_xyz, float).T.copy()
        self.columns = 9 + self.n_theta + (6 if extrinsics else 0)
        #: the Jacobian's columns of the world point (:meth:`jacobian`)
        self.point_columns = slice(6, 9)

    def residual(self, tables, index, rows, jacobians: bool):
        """Residuals (m, 2) px of observations ``rows`` and what :meth:`jacobian` needs.

        Parameters
        ----------
        tables : list of ndarray
            Per kind, the variables (n_k, width) indexed by ``index``.
        index : list of ndarray of int, shape (m,)
            Per kind, each observation's row in ``tables`` (-1: none).
        rows : slice or ndarray of int
            The observations (for their measurements and fixed points).
        jacobians : bool

        Returns
        -------
        e_px : ndarray, shape (m, 2)
            ``measured - predicted`` (px).
        ctx : tuple
            What :meth:`jacobian` needs.
        """
        T = tables[0].T[:, index[0]]  # (16, m), rows of Pose3.matrix()
        R = T[[0, 1, 2, 4, 5, 6, 8, 9, 10]].reshape(3, 3, -1)  # R[i, j] = (R_A)_ij
        t = T[[3, 7, 11]]
        pi = index[1]
        if self.fixed_xyz is None:
            pw = np.ascontiguousarray(tables[1].T)[:, pi]
        else:
            pw = self.fixed_xyz[:, rows].copy()
            free = pi >= 0
            if free.any():
                pw[:, free] = tables[1].T[:, pi[free]]
        d = pw - t
        q = R[0] * d[0] + R[1] * d[1] + R[2] * d[2]  # R_A^T (p - t_A)
        pc, Rb = q, None
        if self.k_ext is not None:
            E = np.vstack([tables[self.k_ext], _IDENTITY_MATRIX]).T[:, index[self.k_ext]]
            Rb = E[[0, 1, 2, 4, 5, 6, 8, 9, 10]].reshape(3, 3, -1)
            db = q - E[[3, 7, 11]]
            pc = Rb[0] * db[0] + Rb[1] * db[1] + Rb[2] * db[2]  # R_B^T (q - t_B)
        theta = None
        if self.n_theta:
            theta = tables[2][index[2][0]] if len(index[2]) else tables[2][0]
        e, J_theta, J_pc = self.measurement(pc, theta, rows, jacobians)
        return e, (R, q, pc, Rb, J_theta, J_pc)

    def jacobian(self, ctx, left: np.ndarray) -> np.ndarray:
        """Whitened, weighted Jacobian of the residuals :meth:`residual` computed.

        Parameters
        ----------
        ctx : tuple
            The second output of :meth:`residual` (with ``jacobians``).
        left : ndarray, shape (m,) or (m, 2, 2)
            :meth:`Whitener.weigh`'s left factor.

        Returns
        -------
        J : ndarray, shape (2, columns, m)
            Rows ``u``, ``v``; columns ``[omega, v]`` of ``A`` (rad, m), the point (m),
            theta (its units), ``[omega, v]`` of ``B``; observation last.
        """
        R, q, pc, Rb, J_theta, J_pc = ctx
        J = np.empty((2, self.columns, pc.shape[1]))  # [row u/v, column, observation]
        Jc = J[:, 3:6]
        apply_left(J_pc.transpose(1, 2, 0), left, Jc)  # weighted d(e)/d(pc)
        if Rb is not None:
            c0 = 9 + self.n_theta
            _rows_cross(Jc, pc, J[:, c0 : c0 + 3])  # d(e)/d(omega_B) = J_pc [pc]x
            np.negative(Jc, out=J[:, c0 + 3 : c0 + 6])  # d(e)/d(v_B) = -J_pc
            # d(e)/d(q) = J_pc R_B^T, in place of d(e)/d(pc) (the identity if no B)
            Jc[...] = np.einsum("akn,jkn->ajn", Jc, Rb)
        # d(e)/d(omega) = J_q [q]x: row by row, the cross product (row x q)
        _rows_cross(Jc, q, J[:, 0:3])
        # d(e)/d(p_world) = J_q R_A^T
        Jp = J[:, 6:9]
        np.multiply(Jc[:, 0, None], R[:, 0], out=Jp)
        Jp += Jc[:, 1, None] * R[:, 1]
        Jp += Jc[:, 2, None] * R[:, 2]
        np.negative(Jc, out=Jc)  # d(q)/d(v) = -I
        if self.n_theta:
            apply_left(J_theta.transpose(1, 2, 0), left, J[:, 9 : 9 + self.n_theta])
        return J


#: ``Pose3.matrix().ravel()`` of the identity (an observation without extrinsic pose)
_IDENTITY_MATRIX = np.eye(4).ravel()[None]


def _rows_cross(J: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:
    """``out[a, :, n] = J[a, :, n] x p[:, n]``: ``J [p]x`` of rows ``J`` (2, 3, n), ``p`` (3, n)."""
    px, py, pz = p
    np.multiply(J[:, 1], pz, out=out[:, 0])
    out[:, 0] -= J[:, 2] * py
    np.multiply(J[:, 2], px, out=out[:, 1])
    out[:, 1] -= J[:, 0] * pz
    np.multiply(J[:, 0], py, out=out[:, 2])
    out[:, 2] -= J[:, 1] * px


# --------------------------------------------------------------------------- trusted passes

#: (values, token, jacobians) while a pass over a Values nobody modifies is under way
_TRUSTED: tuple | None = None


class TrustedPass:
    """Context for the passes (linearisations, evaluations) of a graph at ``values``.

    The promise: ``values`` is not modified from the construction of this object
    on, so a cache validated in one of its passes serves every later one. With
    ``jacobians``, an evaluation may also compute the Jacobians (a linearisation
    at the same values is expected next).

    Parameters
    ----------
    values : gtsam.Values
    jacobians : bool
    """

    def __init__(self, values: gtsam.Values, jacobians: bool = False) -> None:
        self.values = values
        self.token = object()
        self.jacobians = jacobians

    def __enter__(self):
        global _TRUSTED
        _TRUSTED = (self.values, self.token, self.jacobians)
        return self.values

    def __exit__(self, *exc) -> None:
        global _TRUSTED
        _TRUSTED = None


# --------------------------------------------------------------------------- the engine


@dataclass
class _Block:
    """One CustomFactor: observations ``start:end`` (engine order) and its layout."""

    start: int
    end: int
    index: int  # in the engine
    shape: tuple  # (2m, cols...): blocks of one shape share a gtsam.JacobianVector
    offset: int  # of its first view in the buffer
    size: int  # numbers of its views
    e_cost: np.ndarray  # (2m,) view of the cost residuals
    e_lin: np.ndarray  # (2m,) view of the IRLS residuals
    keys: list | None = None  # its factor keys, once asked for
    views: list | None = None  # (2m, cols) Fortran views of the buffer, one per factor key
    native: gtsam.JacobianVector | None = None  # that of its shape
    copies: list | None = None  # (view of native, view of the buffer) per factor key


class FactorEngine:
    """Observations of one model, cut into blocks, one ``gtsam.CustomFactor`` each.

    Parameters
    ----------
    model : ProjectionModel
        ``kinds``, ``key_order``, ``columns``, ``residual`` and ``jacobian``; its
        per-observation data (measurements, fixed points) in block order: block ``g``
        holds observations ``sum(sizes[:g]) : sum(sizes[:g + 1])``.
    sizes : array_like of int, shape (G,)
        Observations per block.
    counts : array_like of int, shape (G, K)
        Keys per block and kind (``K = len(model.kinds)``).
    keys : list of array_like of int, K of them
        Per kind, every block's keys (any order within a block), concatenated in
        block order (``counts[:, q].sum()`` each).
    local : list of array_like of int, K of them, each shape (N,)
        Per kind, each observation's slot among its block's keys of that kind, -1
        for none (a fixed point, no extrinsic pose). :meth:`from_blocks` builds these
        arrays from a list of blocks.
    whitener : Whitener

    Attributes
    ----------
    stats : dict
        ``hits`` (callbacks served from the cache), ``single`` (blocks evaluated
        alone), ``full_passes``.
    """

    def __init__(self, model, sizes, counts, keys, local, whitener: Whitener):
        self.model = model
        self.whitener = whitener
        kinds = model.kinds
        self.kinds = kinds
        nk = len(kinds)
        sizes = np.asarray(sizes, np.intp).reshape(-1)
        G = len(sizes)
        counts = np.asarray(counts, np.intp).reshape(G, nk)
        keys = [np.asarray(k, np.int64).reshape(-1) for k in keys]
        local = [np.asarray(loc, np.intp).reshape(-1) for loc in local]
        self.n = n = int(sizes.sum())
        starts = np.r_[0, np.cumsum(sizes)].astype(np.intp)
        self._start = starts
        self._block_of = np.repeat(np.arange(G), sizes)
        k_in_block = np.arange(n) - starts[self._block_of]  # observation's row in its block
        key_start = np.vstack([np.zeros((1, nk), np.intp), np.cumsum(counts, 0)])  # (G+1, nk)
        self._key_start = key_start
        self._cat = keys
        self._local = local
        self.keys, self.obs = [], []  # set-level sorted keys; (n,) row of each observation's
        for q in range(nk):
            uniq = np.unique(keys[q])
            self.keys.append(uniq.tolist())
            row = np.searchsorted(uniq, keys[q])
            loc = local[q]
            at = np.where(loc >= 0, key_start[self._block_of, q] + loc, 0)
            obs = np.where(loc >= 0, row[at], -1) if len(row) else np.full(n, -1)
            self.obs.append(obs.astype(np.intp))
        self._n_keys = sum(len(k) for k in self.keys)
        # the buffer: per block, per factor key (kinds in key_order, keys in the order
        # given) a (2m, dim) Fortran-ordered block, blocks and keys one after the other
        order = list(model.key_order)
        self._order = order
        dims = np.array([kinds[q].dim for q in order], np.intp)
        per_block = (2 * sizes)[:, None] * (counts[:, order] * dims)  # numbers per kind
        block_size = per_block.sum(1)
        block_off = np.r_[0, np.cumsum(block_size)][:-1]
        kind_off = block_off[:, None] + np.c_[np.zeros(G, np.intp), np.cumsum(per_block, 1)[:, :-1]]
        size = int(block_size.sum())
        # buffer position of d(e_a)/d(column c) of observation o at pos[a, c, o]
        col0 = np.r_[0, np.cumsum([kind.dim for kind in kinds])][:-1]
        pos = np.empty((2, model.columns, n), np.intp)
        rows_of = (2 * sizes)[self._block_of]  # rows of each observation's block
        r = 2 * k_in_block + np.arange(2)[:, None, None]  # (2, 1, n)
        trash = 0
        for j, q in enumerate(order):
            d = kinds[q].dim
            loc = local[q]
            where = kind_off[self._block_of, j] + np.maximum(loc, 0) * rows_of * d
            at = where + rows_of * np.arange(d)[:, None] + r
            none = loc < 0
            if none.any():  # observations without a variable of this kind: a trash area
                trash_at = size + trash + d * np.arange(2)[:, None, None] + np.arange(d)[:, None]
                at[:, :, none] = trash_at
                trash += 2 * d
            pos[:, col0[q] : col0[q] + d] = at
        self._size = size
        self.buf = np.zeros(size + trash)
        self.pos = pos
        self._e_cost = np.zeros(2 * n)
        self._e_lin = np.zeros(2 * n)
        self._e_px = np.zeros((n, 2))
        self._blocks: list[_Block] = []
        for g, (s, e, c, o, z) in enumerate(
            zip(
                starts[:-1].tolist(),
                starts[1:].tolist(),
                counts[:, order].tolist(),
                block_off.tolist(),
                block_size.tolist(),
            )
        ):
            shape = (2 * (e - s), *[d for d, k in zip(dims.tolist(), c) for _ in range(k)])
            self._blocks.append(
                _Block(
                    s, e, g, shape, o, z, self._e_cost[2 * s : 2 * e], self._e_lin[2 * s : 2 * e]
                )
            )
        self._natives: dict[tuple, tuple] = {}
        # the cache: variables it was computed at, validity per block and mode
        self._X = [np.full((len(self.keys[q]), kinds[q].width), np.nan) for q in range(nk)]
        self._valid_cost = np.zeros(G, bool)
        self._valid_lin = np.zeros(G, bool)
        # the variables of the stored results (a Values), and per block its keys' part
        self._snapshot: gtsam.Values | None = None
        self._snap_block: list[gtsam.Values | None] = [None] * G
        self._spent_s = 0.0  # on single blocks since the last full pass
        self._full_pass_s = 2e-6 * n  # estimate until measured
        rng = np.random.default_rng(0)
        # (kind, key, row, observations using it) of a few variables of each kind
        self._sample = []
        for q in range(nk):
            uses = np.bincount(self.obs[q][self.obs[q] >= 0], minlength=len(self.keys[q]))
            pick = rng.choice(len(self.keys[q]), size=min(8, len(self.keys[q])), replace=False)
            self._sample += [(q, self.keys[q][i], i, int(uses[i])) for i in sorted(pick.tolist())]
        self._lock = threading.RLock()
        # per mode (cost, linearisation): token of the trusted pass whose Values the
        # cache holds for every block of that mode (None: check the variables)
        self._ready: list[object | None] = [None, None]
        self.stats = {"hits": 0, "single": 0, "full_passes": 0}

    @classmethod
    def from_blocks(cls, model, blocks, whitener: Whitener) -> FactorEngine:
        """An engine from a list of blocks.

        Parameters
        ----------
        model : ProjectionModel
        blocks : list of (list of list of int, list of ndarray of int)
            Per block, per kind of ``model.kinds``: the block's keys (any order) and
            each observation's slot in them (m,), -1 for none.
        whitener : Whitener
        """
        nk = len(model.kinds)
        sizes = [len(local[0]) for _, local in blocks]
        counts = [[len(keys[q]) for q in range(nk)] for keys, _ in blocks]
        keys = [np.array([int(k) for ks, _ in blocks for k in ks[q]], np.int64) for q in range(nk)]
        local = [
            np.concatenate([np.asarray(loc[q], np.intp).reshape(-1) for _, loc in blocks])
            for q in range(nk)
        ]
        return cls(model, sizes, counts, keys, local, whitener)

    # ---------------------------------------------------------------- public

    def block_keys(self, g: int) -> list[list[int]]:
        """Block ``g``'s keys per kind of ``model.kinds``, in the order given."""
        a, b = self._key_start[g], self._key_start[g + 1]
        return [self._cat[q][a[q] : b[q]].tolist() for q in range(len(self.kinds))]

    def factor_keys(self, g: int) -> list[int]:
        """Block ``g``'s factor keys: per kind in ``model.key_order``, its keys."""
        b = self._blocks[g]
        if b.keys is None:
            keys = self.block_keys(g)
            b.keys = [k for q in self._order for k in keys[q]]
        return b.keys

    @property
    def n_blocks(self) -> int:
        """Number of blocks (factors)."""
        return len(self._blocks)

    def factor(self, g: int) -> gtsam.CustomFactor:
        """Block ``g``'s ``gtsam.CustomFactor``.

        Keys: per kind in ``model.key_order`` the block's keys; unit noise model
        of dimension ``2 m`` (whitening is done inside); error rows ``2k, 2k+1``
        for observation ``k`` of the block.
        """
        b = self._blocks[g]
        model = gtsam.noiseModel.Unit.Create(b.shape[0])
        return gtsam.CustomFactor(model, self.factor_keys(g), self.callback(g))

    def residuals_px(self, values: gtsam.Values, g: int | None = None) -> np.ndarray:
        """Unweighted residuals (px) of block ``g`` (m, 2), or of all (n, 2), engine order."""
        if g is not None:
            out = self._result(g, values, False)[0]
            return np.array(out, copy=True)
        tables = [kind.read(values, keys) for kind, keys in zip(self.kinds, self.keys)]
        e, _ = self.model.residual(tables, self.obs, slice(None), False)
        return e

    def jacobians_px(self, values: gtsam.Values) -> tuple[np.ndarray, np.ndarray]:
        """Unweighted residuals and their Jacobian at ``values``, every block, engine order.

        The same evaluation as a linearisation's, without the whitening and robust
        weights (not cached).

        Returns
        -------
        e_px : ndarray, shape (n, 2)
            ``measured - predicted`` (px).
        J : ndarray, shape (2, columns, n)
            ``d e / d x`` (px per unit of ``x``): rows ``u``, ``v``; columns as the
            model's :meth:`jacobian` lays them out; observation last.
        """
        tables = [kind.read(values, keys) for kind, keys in zip(self.kinds, self.keys)]
        e, ctx = self.model.residual(tables, self.obs, slice(None), True)
        return e, self.model.jacobian(ctx, np.ones(len(e)))

    # ---------------------------------------------------------------- callbacks

    def callback(self, g: int):
        """Block ``g``'s ``gtsam.CustomFactor`` callback ``evaluate(this, values, H)``.

        Returns the whitened, robustly weighted error (2m,): with ``H`` None its
        squared norm is ``2 sum(rho)``; with ``H`` (a ``gtsam.JacobianVector`` or a
        list) it is the IRLS system ``sqrt(w) sqrt_info e`` and ``H`` receives the
        matching Jacobian blocks, Fortran-ordered, one per key.
        """
        b = self._blocks[g]
        lock, ready = self._lock, self._ready
        valid_cost, valid_lin = self._valid_cost, self._valid_lin
        stats, native_type = self.stats, gtsam.JacobianVector

        def evaluate(this, values, H):
            trusted = _TRUSTED
            # in a trusted pass whose Values a full pass has validated: no variable is read
            if trusted is not None and values is trusted[0]:
                with lock:
                    if H is None:
                        if ready[0] is trusted[1] and valid_cost[g]:
                            stats["hits"] += 1
                            return b.e_cost
                    elif ready[1] is trusted[1] and valid_lin[g] and type(H) is native_type:
                        stats["hits"] += 1
                        for target, view in b.copies or self._copies(b):
                            target[...] = view
                        H[:] = b.native  # one C++ copy of all blocks
                        return b.e_lin
            _, e_cost, e_lin, views = self._result(g, values, H is not None)
            if H is None:
                return e_cost
            self._hand_over(b, views, H)
            return e_lin

        return evaluate

    def _views(self, b: _Block) -> list:
        """Block ``b``'s Jacobian blocks: (2m, dim) Fortran views of the buffer, per key."""
        rows, at, views = b.shape[0], b.offset, []
        for c in b.shape[1:]:
            views.append(self.buf[at : at + c * rows].reshape(c, rows).T)
            at += c * rows
        b.views = views
        return views

    def _copies(self, b: _Block) -> list:
        """Block ``b``'s (view of its native, view of the buffer) pairs, made on first use."""
        native, targets = self._native(b)
        b.native = native
        b.copies = list(zip(targets, b.views or self._views(b)))
        return b.copies

    def _native(self, b: _Block):
        """The ``gtsam.JacobianVector`` of ``b``'s shape and writable numpy views of it."""
        native = self._natives.get(b.shape)
        if native is None:
            shapes = [(b.shape[0], c) for c in b.shape[1:]]
            vec = gtsam.JacobianVector([np.zeros(shape, order="F") for shape in shapes])
            native = self._natives[b.shape] = (vec, [vec[q] for q in range(len(vec))])
        return native

    def _hand_over(self, b: _Block, views, H) -> None:
        """Give GTSAM's ``H`` the Jacobian blocks ``views`` (Fortran-ordered, one per key)."""
        if isinstance(H, gtsam.JacobianVector):
            native, targets = self._native(b)
            for target, view in zip(targets, views):
                np.copyto(target, view)
            H[:] = native  # one C++ copy of all blocks
        else:  # a Python list keeps what it is given: new arrays
            for q, view in enumerate(views):
                H[q] = np.array(view, order="F")

    def _result(self, g: int, values, linear: bool):
        """Block ``g`` at ``values``: (e_px (m, 2), e_cost (2m,), e_lin (2m,), views)."""
        b = self._blocks[g]
        trusted = _TRUSTED
        rows = slice(b.start, b.end)
        if trusted is not None and values is trusted[0]:
            # a trusted pass: one full pass validates every block without reading it
            with self._lock:
                valid = self._valid_lin if linear else self._valid_cost
                if self._ready[linear] is not trusted[1]:
                    self._full_pass(values, linear or trusted[2], trusted[1])
                if valid[g]:
                    self.stats["hits"] += 1
                    return self._e_px[rows], b.e_cost, b.e_lin, b.views or self._views(b)
        with self._lock:
            if not _VALUES_EXTRACT:  # no cheap exact check of a block's variables
                return self._single(b, values, linear)
            hit = self._hit(g, b, values, linear)
            if not hit and self._want_full_pass(values, linear):
                self._full_pass(values, linear)
                hit = self._hit(g, b, values, linear)
            if hit:
                self.stats["hits"] += 1
                return self._e_px[rows], b.e_cost, b.e_lin, b.views or self._views(b)
            return self._single(b, values, linear)

    def _hit(self, g: int, b: _Block, values, linear: bool) -> bool:
        """The cache holds block ``g`` computed at exactly its variables in ``values``.

        ``Values.equals`` with tolerance 0 on the block's keys: same keys, same types,
        IEEE-equal numbers (blocks with a non-finite variable, which ``equals`` matches
        loosely, are never stored).
        """
        if not (self._valid_lin[g] if linear else self._valid_cost[g]):
            return False
        own = self._snap_block[g]
        keys = b.keys or self.factor_keys(g)
        if own is None:
            own = self._snap_block[g] = self._snapshot.extract(keys)
        return values.extract(keys).equals(own, 0.0)

    def _want_full_pass(self, values, linear: bool) -> bool:
        """On a miss: will most blocks miss in this pass (a batch optimiser's step)?

        Yes if most blocks are not cached for this mode, or if variables used by most
        of a small sample's observations changed since the last full pass (each
        sampled variable weighs as many observations as use it: a changed intrinsics
        vector, in every observation, means a full pass); otherwise (an incremental
        solver relinearising a few blocks) evaluate single blocks until their time
        exceeds that of a full pass (ski rental).
        """
        valid = self._valid_lin if linear else self._valid_cost
        if np.count_nonzero(valid) < 0.5 * len(valid):
            return True
        changed = seen = 0
        for q, k, i, uses in self._sample:
            if not values.exists(k):
                continue
            seen += uses
            if self.kinds[q].key_bytes(values, k) != self._X[q][i].tobytes():
                changed += uses
        if seen and changed > 0.5 * seen:
            return True
        return self._spent_s >= self._full_pass_s

    def _single(self, b: _Block, values, linear: bool):
        """Evaluate one block at ``values`` (not stored)."""
        t0 = time.perf_counter()
        tables = [
            np.array(
                [np.frombuffer(kind.key_bytes(values, k), float) for k in keys], float
            ).reshape(len(keys), kind.width)
            for kind, keys in zip(self.kinds, self.block_keys(b.index))
        ]
        rows = slice(b.start, b.end)
        local = [loc[b.start : b.end] for loc in self._local]
        e_px, ctx = self.model.residual(tables, local, rows, linear)
        e_cost, e_lin, left = self.whitener.weigh(e_px, linear)
        views = None
        if linear:
            J = self.model.jacobian(ctx, left)
            scratch = np.zeros(b.size + len(self.buf) - self._size)
            p = self.pos[:, :, rows]
            scratch[np.where(p >= self._size, p - self._size + b.size, p - b.offset)] = J
            views, at, m2 = [], 0, b.shape[0]
            for c in b.shape[1:]:
                views.append(scratch[at : at + c * m2].reshape(c, m2).T)
                at += c * m2
            e_lin = e_lin.ravel()
        self.stats["single"] += 1
        self._spent_s += time.perf_counter() - t0
        return e_px, e_cost.ravel(), e_lin, views

    def _full_pass(self, values, linear: bool, token: object | None = None) -> None:
        """Read every variable, re-evaluate every block whose variables changed.

        ``token``: that of the trusted pass whose ``values`` these are (None
        outside one); the cache then serves that pass without reading variables.
        """
        t0 = time.perf_counter()
        have = [None] * len(self.kinds)
        if values.size() < self._n_keys:  # some keys are absent: find them once
            have = [_present(values, np.asarray(keys, np.uint64)) for keys in self.keys]
        X = [kind.read(values, keys, h) for kind, keys, h in zip(self.kinds, self.keys, have)]
        n = self.n
        changed_obs = np.zeros(n, bool)
        missing_obs = np.zeros(n, bool)
        for q in range(len(self.kinds)):
            if not len(X[q]):
                continue
            changed = np.r_[~(X[q] == self._X[q]).all(1), False]  # index -1: none
            missing = np.r_[~np.isfinite(X[q]).all(1), False]  # absent or not finite
            changed_obs |= changed[self.obs[q]]
            missing_obs |= missing[self.obs[q]]
        starts = self._start[:-1]
        changed = np.logical_or.reduceat(changed_obs, starts) if n else changed_obs
        missing = np.logical_or.reduceat(missing_obs, starts) if n else missing_obs
        self._valid_cost &= ~changed
        self._valid_lin &= ~changed
        present = np.concatenate(
            [np.asarray(self.keys[q], np.uint64)[np.isfinite(X[q]).all(1)] for q in range(len(X))]
        ).tolist()
        self._snapshot = values.extract(present) if _VALUES_EXTRACT else gtsam.Values(values)
        self._snap_block = [None] * len(self._blocks)
        todo = ~missing & ~(self._valid_lin if linear else self._valid_cost)
        if todo.all():
            rows = slice(None)
            index = self.obs
        else:
            rows = np.flatnonzero(todo[self._block_of])
            index = [o[rows] for o in self.obs]
        if not isinstance(rows, np.ndarray) or len(rows):
            e_px, ctx = self.model.residual(X, index, rows, linear)
            e_cost, e_lin, left = self.whitener.weigh(e_px, linear)
            self._e_px[rows] = e_px
            E = self._e_cost.reshape(-1, 2)
            E[rows] = e_cost
            self._valid_cost |= todo
            if linear:
                self._e_lin.reshape(-1, 2)[rows] = e_lin
                J = self.model.jacobian(ctx, left)
                self.buf[self.pos if isinstance(rows, slice) else self.pos[:, :, rows]] = J
                self._valid_lin |= todo
        self._X = X
        # the cache now holds `values` for every block (both modes after a linearisation:
        # a block with Jacobians has its cost); the Jacobians still do if they were
        # those of the same trusted Values, otherwise they must be checked
        if linear or (token is not None and self._ready[1] is token):
            self._ready[1] = token
        else:
            self._ready[1] = None
        self._ready[0] = token
        self._spent_s = 0.0
        self._full_pass_s = time.perf_counter() - t0
        self.stats["full_passes"] += 1
