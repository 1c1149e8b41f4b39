"""Using a calibrated camera in your own GTSAM graph (frozen calibration).

Two ways to put observations of a calibrated :class:`~gtsam_sphere.core.camera.SphereCamera`
into a graph whose variables are GTSAM camera poses ``world_from_cam``
(``gtsam.Pose3``) and landmarks (``gtsam.Point3``), frames as in
``docs/conventions.md`` (camera ``x`` right, ``y`` down, ``z`` forward):

**Frozen pixel factor** (:func:`make_projection_factor`, :func:`make_projection_block`,
:class:`ProjectionBlocks`). The residual is in pixels of the ideal image,

    e = camera.ideal_from_pixels(uv_measured) - camera.ideal_from_points(R_wc^T (p_w - t_wc))

i.e. the calibration's own measurement model (paper Eq. 1-5): the Brown terms
and the learned kNN correction act on the measurement and are applied once,
at construction; the spherical or radial mapping is evaluated at the current
estimate. Jacobians are analytic (right perturbation ``world_from_cam *
Exp([omega, v])``, rotation first, like GTSAM's own camera factors). Any
``gtsam.noiseModel`` works: the single-observation factor hands it to GTSAM
unchanged; the vectorised block applies its whitening (any Gaussian model) and
its M-estimator per observation, exactly as a ``gtsam.noiseModel.Robust``
single-observation factor would. Use it when pixel-space weighting must be
exact (anisotropic lenses, residuals and robust thresholds in pixels, the
sphere mapping near and past 90 degrees where a pixel does not pin the ray
down) or the learned correction matters. Cost: Python callbacks. One callback
per observation is ~200 times slower than a C++ factor; the blocks put the
observations of one landmark (``max_obs`` of them at a time) into one
``gtsam.CustomFactor`` and evaluate all blocks in one shared numpy pass; see
``benchmarks/bench_map.py`` for measured ratios.

**Bearing path** (:func:`bearings`, :func:`bearing_sigma_rad`,
:func:`bearing_sqrt_information`, :func:`make_bearing_factors`,
:meth:`Calibration.bearing <gtsam_sphere.io.calibration.Calibration.bearing>`).
The calibration turns each pixel into a unit ray once (measurement
corrections included, ``camera.unproject``) and GTSAM's C++ factors carry the
load: ``gtsam.BearingFactor3D`` on ``Pose3`` + ``Point3`` (what
:func:`make_bearing_factors` builds), or ``gtsam.GeneralSFMFactorSphericalCamera``
(``gtsam.SphericalCamera`` variables) and the smart factors
``gtsam.SmartProjectionFactorSphericalCamera`` /
``gtsam.SmartProjectionRigFactorSphericalCamera`` (landmark eliminated,
``Pose3`` body poses with a ``gtsam.CameraSetSpherical`` rig) with the same
``gtsam.Unit3`` measurements. The noise is angular: ``sigma_rad = sigma_px /
s`` where ``s`` (px per rad) is the local scale of the model at the ray
(:func:`bearing_sigma_rad`, the geometric mean of the radial scale
``c g'(alpha)`` and the tangential scale ``c g(alpha) / sin(alpha)``); an
isotropic angular sigma is an approximation wherever the two differ (every
fisheye off-axis). :func:`bearing_sqrt_information` gives the exact local
pixel metric as a 2x2 square-root information in the ``gtsam.Unit3`` basis of
the measured ray, for ``GeneralSFMFactorSphericalCamera`` (which measures the
error in that basis; ``BearingFactor3D`` measures it in the basis of the
predicted ray, so only isotropic noise is right there). Use the bearing path
for large maps and real-time work: it runs at C++ speed. Mind the "sphere"
mapping: it is two-to-one past 90 degrees (the front and back halves of the
image sphere share the image disc), so :func:`bearings` needs the hemisphere
of every observation (``+1`` front, ``-1`` back, e.g. from the sign of ``z``
of a predicted camera-frame point); the angular sigma grows without bound at
90 degrees there. The "radial" mapping is one-to-one up to
``camera.max_alpha_rad()`` and needs no hemisphere.

**Exact bearings on Pose3**: :mod:`~gtsam_sphere.estimation.exact_bearing`
carries the full 2x2 pixel metric into C++ factors on ``Pose3`` + ``Point3``
(one virtual pinhole camera per measured ray), with a rig and a smart-factor
variant; prefer it to the isotropic ``BearingFactor3D``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import gtsam
import numpy as np

from ..core.camera import SphereCamera, check_uv
from ..core.lie import skew
from ..core.rays import bearings as bearings  # re-exported: its home is the core
from ..core.rays import camera_of
from ..core.robust import Loss, robust_weight, whitening_scale

__all__ = [
    "ProjectionBlocks",
    "bearing_sigma_rad",
    "bearing_sqrt_information",
    "bearings",
    "levenberg_marquardt",
    "make_bearing_factors",
    "make_projection_block",
    "make_projection_factor",
    "model_scale_px_per_rad",
]


def _keys(keys, n: int, name: str) -> np.ndarray:
    """Keys as a (n,) uint64 array (a scalar is repeated)."""
    arr = np.asarray(keys, dtype=np.uint64).reshape(-1)
    if arr.size == 1 and n != 1:
        arr = np.full(n, arr[0], dtype=np.uint64)
    if arr.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},) like uv_px, got {arr.shape}")
    return arr


# --------------------------------------------------------------------------- noise


class _Whitener:
    """Per-observation whitening and robust weighting of a 2-D GTSAM noise model.

    ``sqrt_info`` (2, 2) is the base model's square-root information; the
    M-estimator (if the model is ``Robust``) acts on the whitened norm
    ``r = |sqrt_info @ e|``. Huber, Cauchy, Tukey and Geman-McClure are
    vectorised (their parameter is read back from the estimator and checked
    against its own ``weight``/``loss``); any other estimator is called per
    observation.
    """

    _KINDS = (
        ("Huber", Loss.HUBER),
        ("Cauchy", Loss.CAUCHY),
        ("Tukey", Loss.TUKEY),
        ("GemanMcClure", Loss.GEMAN_MCCLURE),
    )

    def __init__(self, noise_model) -> None:
        if not isinstance(noise_model, gtsam.noiseModel.Base):
            raise TypeError(f"expected a gtsam.noiseModel, got {type(noise_model).__name__}")
        if noise_model.dim() != 2:
            raise ValueError(f"the noise model must be 2-dimensional, got {noise_model.dim()}")
        base, self.mest = noise_model, None
        if isinstance(noise_model, gtsam.noiseModel.Robust):
            base, self.mest = noise_model.noise(), noise_model.robust()
        if not isinstance(base, gtsam.noiseModel.Gaussian) or base.isConstrained():
            raise ValueError(
                f"unsupported noise model {type(base).__name__}: use a Gaussian model "
                "(Unit, Isotropic, Diagonal, Gaussian), optionally inside Robust"
            )
        self.sqrt_info = np.asarray(base.Whiten(np.eye(2)), float)
        self.loss, self.k = None, 0.0
        if self.mest is None or isinstance(self.mest, gtsam.noiseModel.mEstimator.Null):
            self.loss = Loss.L2
        else:
            for name, loss in self._KINDS:
                if isinstance(self.mest, getattr(gtsam.noiseModel.mEstimator, name)):
                    k = self._parameter(loss)
                    if k is not None:
                        self.loss, self.k = loss, k
                    break

    def _parameter(self, loss: Loss) -> float | None:
        """Read the estimator's threshold back from its functions; None if they disagree
        with :func:`gtsam_sphere.core.robust.robust_weight` (then it is called per
        observation)."""
        m, big = self.mest, 1e6
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

    def weights(self, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """IRLS weights ``w(r)`` and costs ``rho(r)`` of whitened norms ``r`` (n,)."""
        if self.loss is not None:
            return robust_weight(r, self.loss, self.k)
        w = np.array([self.mest.weight(float(x)) for x in r])
        rho = np.array([self.mest.loss(float(x)) for x in r])
        return w, rho


# --------------------------------------------------------------------------- pixel factors


def _frozen_residual(camera: SphereCamera, ideal_px, R_wc, t_wc, p_w, jacobians: bool):
    """``e = ideal_px - ideal(P)`` with ``P = R_wc^T (p_w - t_wc)``; all (n, ...).

    Returns ``e`` (n, 2) px, and with ``jacobians`` also ``de/dP`` (n, 2, 3)
    px/m and ``P`` (n, 3) m.
    """
    pc = np.einsum("nji,nj->ni", R_wc, p_w - t_wc)
    if not jacobians:
        return ideal_px - camera.ideal_from_points(pc)
    pred, J = camera.ideal_from_points(pc, jacobians=True)
    return ideal_px - pred, -J, pc


def make_projection_factor(
    calibration_or_camera,
    uv_px: np.ndarray,
    pose_key: int,
    point_key: int,
    noise_model: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """One observation with a frozen calibration, as a ``gtsam.CustomFactor``.

    Residual (px, ideal image, relative to the principal point):
    ``camera.ideal_from_pixels(uv_px) - camera.ideal_from_points(R_wc^T (p_w - t_wc))``;
    the measurement side (Brown terms, learned correction) is evaluated once, here.

    Parameters
    ----------
    calibration_or_camera : Calibration or SphereCamera
    uv_px : array_like, shape (2,) or (1, 2)
        Raw measured pixel (OpenCV convention, ``docs/conventions.md``).
    pose_key : int
        Key of a ``gtsam.Pose3`` ``world_from_cam`` (metres).
    point_key : int
        Key of a ``gtsam.Point3`` landmark, world frame (metres).
    noise_model : gtsam.noiseModel.Base
        2-D model in pixels (``Isotropic.Sigma(2, sigma_px)``,
        ``Robust.Create(mEstimator.Huber.Create(k), ...)``, ...), used by
        GTSAM exactly as for its own factors.

    Returns
    -------
    gtsam.CustomFactor
        Keys ``[pose_key, point_key]``; Jacobians 2x6 (tangent ``[omega, v]``
        of ``world_from_cam * Exp(xi)``) and 2x3. Keep no other reference:
        the factor holds its callback.
    """
    camera = camera_of(calibration_or_camera)
    uv = check_uv(uv_px)
    if len(uv) != 1:
        raise ValueError(f"make_projection_factor takes one pixel, got {len(uv)}")
    ideal = camera.ideal_from_pixels(uv)
    if not np.all(np.isfinite(ideal)):
        raise ValueError(f"pixel {uv[0].tolist()} has no finite corrected coordinates")
    pk, lk = int(pose_key), int(point_key)

    def evaluate(this, values, H):
        T = values.atPose3(pk).matrix()
        R, t = T[None, :3, :3], T[None, :3, 3]
        p = np.asarray(values.atPoint3(lk), float)[None]
        if H is None:
            return _frozen_residual(camera, ideal, R, t, p, False)[0]
        e, J, pc = _frozen_residual(camera, ideal, R, t, p, True)
        J = J[0]
        H[0] = np.hstack([J @ skew(pc[0]), -J])
        H[1] = J @ R[0].T
        return e[0]

    return gtsam.CustomFactor(noise_model, [pk, lk], evaluate)


class ProjectionBlocks:
    """Many observations with a frozen calibration, as a few vectorised ``gtsam.CustomFactor`` s.

    Each observation contributes the residual of :func:`make_projection_factor`
    (px). ``noise_model`` is applied per observation: its whitening, then its
    M-estimator on that observation's whitened norm ``r`` (cost ``rho(r)``,
    IRLS weight ``sqrt(w(r))`` on the linear system), exactly as
    ``gtsam.noiseModel.Robust`` does for a single-observation factor.

    The observations are cut into blocks (:attr:`groups`), one
    ``gtsam.CustomFactor`` each (unit noise model of dimension ``2 n_block``).
    A block's linearisation is one dense Jacobian over all its keys, so a
    block should touch few keys: by default one landmark and at most
    ``max_obs`` of the images seeing it (the linearised cost of a block grows
    like ``max_obs^3``, its Python overhead per observation falls like
    ``1 / max_obs``; measured at 1e5 observations: 8 is the optimum for
    batch LM, ISAM2 ran 13% faster with 16).

    All blocks share one vectorised evaluation. Inside
    :func:`levenberg_marquardt` the first callback of each linearisation or
    evaluation evaluates every block whose variables changed in one numpy
    call and the others only copy their rows out. Elsewhere (``gtsam.ISAM2``,
    GTSAM's optimisers) a callback reads its own variables and uses the cache
    only if they equal, bit for bit, those the cache was computed at; on a
    miss it evaluates its block alone, unless a sample of the variables shows
    that most of them changed (a batch step) or the time spent on single
    blocks since the last full evaluation exceeds the cost of one, in which
    case it reads all variables and re-evaluates every changed block at once.
    A result is therefore always the one its own variables give. A linearised
    block hands its Jacobian blocks to GTSAM in one C++ copy from a zero-padded
    ``gtsam.JacobianVector`` that all blocks of its sparsity pattern share (the
    same number of landmarks and images, each observation in the same slots: with
    the default grouping, one per block size), each callback writing only its
    non-zeros.

    GTSAM's C++ optimisers hand every ``CustomFactor`` callback a copy of
    their whole ``gtsam.Values`` (see :func:`levenberg_marquardt`): use that
    function for batch refinement, and hold ``isam.getLinearizationPoint()``
    while using ``gtsam.ISAM2``.

    Parameters
    ----------
    calibration_or_camera : Calibration or SphereCamera
    uv_px : array_like, shape (N, 2)
        Raw measured pixels; the measurement corrections are applied here, once.
    pose_keys : array_like of int, shape (N,) or scalar
        ``gtsam.Pose3`` ``world_from_cam`` key of each observation (metres).
    point_keys : array_like of int, shape (N,) or scalar
        ``gtsam.Point3`` landmark key (world frame, metres) of each observation.
    noise_model : gtsam.noiseModel.Base
        2-D pixel noise model: Gaussian (Unit, Isotropic, Diagonal, full) or
        ``Robust`` around one; any M-estimator (Huber, Cauchy, Tukey and
        Geman-McClure are vectorised, others are called per observation),
        with GTSAM's default ``Block`` reweighting (one weight per 2-vector).
    max_obs : int
        Largest number of observations per block when ``groups`` is None.
    groups : list of array_like of int, or None
        Observation indices of each block (a partition of ``range(N)``);
        None: one landmark per block, its observations in input order cut
        into chunks of ``max_obs``.

    Attributes
    ----------
    groups : list of ndarray of int
        Observation indices (into the input) of each block.
    ideal_px : ndarray, shape (N, 2)
        Corrected measurements ``camera.ideal_from_pixels(uv_px)`` (px), input order.
    """

    def __init__(
        self,
        calibration_or_camera,
        uv_px,
        pose_keys,
        point_keys,
        noise_model,
        max_obs: int = 8,
        groups=None,
    ):
        import threading

        self.camera = camera_of(calibration_or_camera)
        uv = check_uv(uv_px)
        n = len(uv)
        if n == 0:
            raise ValueError("no observations")
        pk = _keys(pose_keys, n, "pose_keys")
        lk = _keys(point_keys, n, "point_keys")
        self.ideal_px = self.camera.ideal_from_pixels(uv)
        bad = np.flatnonzero(~np.isfinite(self.ideal_px).all(1))
        if len(bad):
            raise ValueError(f"observations {bad[:5].tolist()} have no finite corrected pixel")
        self.whitener = _Whitener(noise_model)
        self.noise_model = noise_model
        self.groups = _landmark_groups(lk, max_obs) if groups is None else _check_groups(groups, n)
        self.n = n
        # everything below is in block order: block g owns rows start[g]:start[g+1]
        order = np.concatenate(self.groups)
        self._order = order
        sizes = np.array([len(g) for g in self.groups])
        self._start = np.r_[0, np.cumsum(sizes)]
        self._block_of = np.repeat(np.arange(len(self.groups)), sizes)
        poses, obs_pose = np.unique(pk[order], return_inverse=True)
        points, obs_point = np.unique(lk[order], return_inverse=True)
        self._pose_keys = [int(k) for k in poses]
        self._point_keys = [int(k) for k in points]
        self._obs_pose, self._obs_point = obs_pose, obs_point
        self._ideal = self.ideal_px[order]
        # cache (block order): variables it was computed at, results, validity per block
        self._T = np.full((len(poses), 4, 4), np.nan)
        self._P = np.full((len(points), 3), np.nan)
        self._e_cost = np.zeros((n, 2))
        self._e_lin = np.zeros((n, 2))
        self._J_pose = np.zeros((n, 2, 6))
        self._J_point = np.zeros((n, 2, 3))
        # blocks of one sparsity pattern share one zero-padded C++ copy of their Jacobian
        # blocks (a _Staging, made at the first linearisation of the pattern)
        self._staging: dict[tuple, _Staging] = {}
        self._blocks = []
        for g in range(len(self.groups)):
            s, e = int(self._start[g]), int(self._start[g + 1])
            bp, lp = np.unique(obs_pose[s:e], return_inverse=True)
            bl, ll = np.unique(obs_point[s:e], return_inverse=True)
            pattern = (len(bl), len(bp), ll.astype(np.intp).tobytes(), lp.astype(np.intp).tobytes())
            self._blocks.append(
                _Block(
                    s,
                    e,
                    bp,
                    bl,
                    [self._pose_keys[i] for i in bp],
                    [self._point_keys[i] for i in bl],
                    pattern,
                    self._e_cost[s:e].reshape(-1),
                    self._e_lin[s:e].reshape(-1),
                    self._J_pose[s:e],
                    self._J_point[s:e],
                )
            )
        self._valid_cost = np.zeros(len(self.groups), bool)
        self._valid_lin = np.zeros(len(self.groups), bool)
        self._sig = np.full(len(self.groups), None, dtype=object)  # bytes of known hits
        self._pose_key_arr = np.array(self._pose_keys, dtype=np.uint64)
        self._pose_rows: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._spent_s = 0.0  # on single blocks since the last full pass
        self._full_pass_s = 2e-6 * n  # estimate until measured
        rng = np.random.default_rng(0)
        pick_pose = rng.choice(len(poses), size=min(8, len(poses)), replace=False)
        pick_point = rng.choice(len(points), size=min(8, len(points)), replace=False)
        # (key, index): poses index >= 0, landmarks -1 - index
        self._sample = [(self._pose_keys[i], int(i)) for i in pick_pose] + [
            (self._point_keys[i], -1 - int(i)) for i in pick_point
        ]
        self._lock = threading.RLock()
        # per mode (cost, linearisation): token of the trusted pass whose Values the cache
        # holds for every block of that mode (None: check the variables)
        self._ready: list[object | None] = [None, None]
        self.stats = {"hits": 0, "single": 0, "full_passes": 0}

    # ---------------------------------------------------------------- public

    def factors(self) -> list[gtsam.CustomFactor]:
        """The factors to add to a graph, one per block.

        Returns
        -------
        list of gtsam.CustomFactor, length ``len(groups)``
            Keys ``[landmarks..., poses...]`` (each sorted); error dimension
            ``2 n_block`` (observation ``k`` of the block in rows ``2k, 2k+1``,
            ``u`` then ``v``, whitened and robustly weighted); Jacobian blocks
            ``2 n_block x 3`` per landmark and ``2 n_block x 6`` per pose
            (tangent ``[omega, v]`` of ``world_from_cam * Exp(xi)``).
        """
        out = []
        for g, b in enumerate(self._blocks):
            model = gtsam.noiseModel.Unit.Create(2 * (b.end - b.start))
            out.append(gtsam.CustomFactor(model, b.point_keys + b.pose_keys, self._callback(g)))
        return out

    def residuals_px(self, values: gtsam.Values) -> np.ndarray:
        """Unweighted residuals of all observations.

        Parameters
        ----------
        values : gtsam.Values
            Holds every pose (``Pose3`` world_from_cam) and landmark (``Point3``, world).

        Returns
        -------
        e_px : ndarray, shape (N, 2)
            ``ideal_from_pixels(uv) - ideal_from_points(P_cam)`` in pixels of
            the ideal image, input order.
        """
        R, t, p = self._read_obs(values)
        out = np.empty((self.n, 2))
        out[self._order] = _frozen_residual(self.camera, self._ideal, R, t, p, False)
        return out

    def whitened_norms(self, values: gtsam.Values) -> np.ndarray:
        """Whitened residual norms (dimensionless, units of sigma) before the M-estimator.

        Parameters
        ----------
        values : gtsam.Values

        Returns
        -------
        r : ndarray, shape (N,)
            ``|sqrt_info @ e_px|`` per observation, input order.
        """
        e = self.residuals_px(values) @ self.whitener.sqrt_info.T
        return np.sqrt((e * e).sum(1))

    def robust_weights(self, values: gtsam.Values) -> np.ndarray:
        """IRLS weights of the observations (1 for inliers of Huber, < 1 down-weighted).

        Parameters
        ----------
        values : gtsam.Values

        Returns
        -------
        w : ndarray, shape (N,)
            ``w(r)`` of the noise model's M-estimator (1 without one), input order.
        """
        return self.whitener.weights(self.whitened_norms(values))[0]

    # ---------------------------------------------------------------- internals

    def _read_obs(self, values):
        T = np.array([values.atPose3(k).matrix() for k in self._pose_keys])
        P = np.array([values.atPoint3(k) for k in self._point_keys], float).reshape(-1, 3)
        return T[self._obs_pose, :3, :3], T[self._obs_pose, :3, 3], P[self._obs_point]

    def _callback(self, g: int):
        b = self._blocks[g]
        lock, ready, valid_cost, valid_lin = (
            self._lock,
            self._ready,
            self._valid_cost,
            self._valid_lin,
        )
        stats, native_type = self.stats, gtsam.JacobianVector

        def evaluate(this, values, H):
            trusted = _TRUSTED_PASS
            # inside levenberg_marquardt, once a full pass has validated the cache for this
            # pass's Values (which does not change during the pass): no variable is read
            if trusted is not None and values is trusted[0]:
                with lock:
                    if H is None:
                        if ready[0] is trusted[1] and valid_cost[g]:
                            stats["hits"] += 1
                            return b.e_cost
                    elif ready[1] is trusted[1] and valid_lin[g] and type(H) is native_type:
                        stats["hits"] += 1
                        staging = b.staging or self._staged(b)
                        staging.write(b.J_pose, b.J_point)
                        H[:] = staging.native  # one C++ copy of all blocks
                        return b.e_lin
            return self._evaluate(g, values, H)

        return evaluate

    def _compute(self, rows, R, t, p, linear: bool):
        """Whitened weighted errors (and Jacobians) of the rows ``rows`` (block order)."""
        S = self.whitener.sqrt_info
        if not linear:
            e = _frozen_residual(self.camera, self._ideal[rows], R, t, p, False) @ S.T
            r = np.sqrt((e * e).sum(1))
            _, rho = self.whitener.weights(r)
            scale = whitening_scale(r, rho)
            return e * scale[:, None], None, None, None
        e, J, pc = _frozen_residual(self.camera, self._ideal[rows], R, t, p, True)
        e = e @ S.T
        r = np.sqrt((e * e).sum(1))
        w, rho = self.whitener.weights(r)
        scale = whitening_scale(r, rho)
        sw = np.sqrt(w)
        if S[0, 1] == 0.0 and S[1, 0] == 0.0 and S[0, 0] == S[1, 1]:  # isotropic: S = s I
            J = J * S[0, 0]  # the einsum's numbers (but the sign of a zero), 30x faster
        else:
            J = np.einsum("ab,nbc->nac", S, J)
        J *= sw[:, None, None]  # d(whitened e)/dP
        J_pose = np.concatenate([J @ skew(pc), -J], axis=2)
        J_point = J @ R.transpose(0, 2, 1)  # J @ R_wc^T
        return e * scale[:, None], e * sw[:, None], J_pose, J_point

    def _evaluate(self, g: int, values, H):
        b = self._blocks[g]
        linear = H is not None
        trusted = _TRUSTED_PASS
        if trusted is not None and values is trusted[0]:
            # inside levenberg_marquardt: this Values object does not change during the pass,
            # so one full pass per pass validates every block without reading its variables
            with self._lock:
                valid = self._valid_lin if linear else self._valid_cost
                if self._ready[linear] is not trusted[1]:
                    self._full_pass(values, linear or trusted[2], trusted[1])
                if valid[g]:
                    self.stats["hits"] += 1
                    if not linear:
                        return b.e_cost
                    self._fill_jacobians(b, H, b.J_pose, b.J_point)
                    return b.e_lin
        # the block's variables, bit for bit (C order): poses (4x4 each), then landmarks
        sig = b"".join(
            [values.atPose3(k).matrix().tobytes() for k in b.pose_keys]
            + [np.asarray(values.atPoint3(k), float).tobytes() for k in b.point_keys]
        )
        with self._lock:
            hit = self._hit(g, b, sig, linear)
            if not hit and self._want_full_pass(values, linear):
                self._full_pass(values, linear)
                hit = self._hit(g, b, sig, linear)
            if not hit:
                return self._single(b, sig, H)
            self.stats["hits"] += 1
            if not linear:
                return b.e_cost
            self._fill_jacobians(b, H, b.J_pose, b.J_point)
            return b.e_lin

    def _want_full_pass(self, values, linear: bool) -> bool:
        """On a miss: will most blocks miss in this pass (a batch optimiser's step)?

        Yes if most blocks are not cached for this mode, or if most of a small
        sample of variables changed since the last full pass; otherwise (an
        incremental solver relinearising a few blocks) evaluate single blocks
        until their time exceeds that of a full pass (ski rental).
        """
        valid = self._valid_lin if linear else self._valid_cost
        if np.count_nonzero(valid) < 0.5 * len(valid):
            return True
        changed = seen = 0
        for k, i in self._sample:
            if not values.exists(k):
                continue
            seen += 1
            if i >= 0:
                changed += values.atPose3(k).matrix().tobytes() != self._T[i].tobytes()
            else:
                changed += (
                    np.asarray(values.atPoint3(k), float).tobytes() != self._P[-1 - i].tobytes()
                )
        if seen and changed > 0.5 * seen:
            return True
        return self._spent_s >= self._full_pass_s

    def _hit(self, g: int, b, sig: bytes, linear: bool) -> bool:
        """The cache holds block ``g`` computed at exactly the variables ``sig``."""
        if not (self._valid_lin[g] if linear else self._valid_cost[g]):
            return False
        known = self._sig[g]
        if known is not None:
            return sig == known
        if sig == self._T[b.poses].tobytes() + self._P[b.points].tobytes():
            self._sig[g] = sig
            return True
        return False

    def _single(self, b, sig: bytes, H):
        """Evaluate one block directly (not cached)."""
        t0 = time.perf_counter()
        T, P = _unpack(sig, len(b.poses))
        s, e = b.start, b.end
        pl = np.searchsorted(b.poses, self._obs_pose[s:e])
        ll = np.searchsorted(b.points, self._obs_point[s:e])
        rows = slice(s, e)
        R, t, p = T[pl, :3, :3], T[pl, :3, 3], P[ll]
        if H is None:
            out = self._compute(rows, R, t, p, False)[0].ravel()
        else:
            _, e_lin, J_pose, J_point = self._compute(rows, R, t, p, True)
            self._fill_jacobians(b, H, J_pose, J_point)
            out = e_lin.ravel()
        self.stats["single"] += 1
        self._spent_s += time.perf_counter() - t0
        return out

    def _fill_jacobians(self, b, H, J_pose, J_point) -> None:
        """Hand block ``b``'s Jacobian blocks (non-zeros ``J_pose`` (m, 2, 6), ``J_point``
        (m, 2, 3), observation order) to GTSAM's ``H``, zero-padded, one per key."""
        staging = b.staging or self._staged(b)
        staging.write(J_pose, J_point)
        if isinstance(H, gtsam.JacobianVector):
            H[:] = staging.native  # one C++ copy of all blocks
        else:  # a Python list keeps what it is given: new arrays
            for q in range(len(staging.native)):
                H[q] = np.array(staging.native[q], order="F")

    def _staged(self, b) -> _Staging:
        """The staging area of block ``b``'s sparsity pattern (made on first use)."""
        staging = self._staging.get(b.pattern)
        if staging is None:
            staging = self._staging[b.pattern] = _Staging(*b.pattern)
        b.staging = staging
        return staging

    def _read_variables(self, values) -> tuple[np.ndarray, np.ndarray]:
        """Every pose (n_poses, 4, 4) and landmark (n_points, 3) of the set; NaN if absent.

        Poses in one C++ call (``gtsam.utilities.extractPose3``: every ``Pose3`` of
        ``values`` in key order, rows ``[R row-major, t]``, the same numbers as
        ``Pose3.matrix()``); landmarks one call each.
        """
        T = np.full_like(self._T, np.nan)
        rows = gtsam.utilities.extractPose3(values)
        keys = gtsam.utilities.allPose3s(values).keys()
        cached = self._pose_rows
        if cached is None or len(cached[0]) != len(keys) or cached[0].tolist() != keys:
            arr = np.array(keys, dtype=np.uint64)
            at = np.minimum(np.searchsorted(arr, self._pose_key_arr), max(len(arr) - 1, 0))
            found = np.flatnonzero(arr[at] == self._pose_key_arr) if len(arr) else at[:0]
            cached = self._pose_rows = (arr, found, at[found])
        _, found, at = cached
        if len(found):
            T[found, :3, :3] = rows[at, :9].reshape(-1, 3, 3)
            T[found, :3, 3] = rows[at, 9:12]
            T[found, 3] = (0.0, 0.0, 0.0, 1.0)
        try:
            P = np.array([values.atPoint3(k) for k in self._point_keys], float).reshape(-1, 3)
        except RuntimeError:  # absent (NaN) or not a Point3 (raised below, as before)
            P = np.full_like(self._P, np.nan)
            for i, k in enumerate(self._point_keys):
                if values.exists(k):
                    P[i] = values.atPoint3(k)
        return T, P

    def _full_pass(self, values, linear: bool, token: object | None = None) -> None:
        """Read every variable, re-evaluate every block whose variables changed.

        ``token``: that of the trusted pass whose ``values`` these are (None
        outside one); the cache then serves that pass without reading variables.
        """
        t0 = time.perf_counter()
        T, P = self._read_variables(values)
        missing_pose = np.isnan(T[:, 0, 0])
        missing_point = np.isnan(P[:, 0])
        changed_pose = ~(T == self._T).all((1, 2))
        changed_point = ~(P == self._P).all(1)
        starts = self._start[:-1]
        changed = np.logical_or.reduceat(
            changed_pose[self._obs_pose] | changed_point[self._obs_point], starts
        )
        missing = np.logical_or.reduceat(
            missing_pose[self._obs_pose] | missing_point[self._obs_point], starts
        )
        self._valid_cost &= ~changed
        self._valid_lin &= ~changed
        self._sig[changed] = None
        todo = ~missing & ~(self._valid_lin if linear else self._valid_cost)
        rows = np.flatnonzero(todo[self._block_of])
        if len(rows):
            ip, il = self._obs_pose[rows], self._obs_point[rows]
            R, t, p = T[ip, :3, :3], T[ip, :3, 3], P[il]
            e_cost, e_lin, J_pose, J_point = self._compute(rows, R, t, p, linear)
            self._e_cost[rows] = e_cost
            self._valid_cost |= todo
            if linear:
                self._e_lin[rows] = e_lin
                self._J_pose[rows] = J_pose
                self._J_point[rows] = J_point
                self._valid_lin |= todo
        self._T, self._P = T, P
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


def _unpack(sig: bytes, n_poses: int) -> tuple[np.ndarray, np.ndarray]:
    """Pose matrices (n_poses, 4, 4) and landmarks (k, 3) from a block signature."""
    flat = np.frombuffer(sig, dtype=float)
    return flat[: 16 * n_poses].reshape(-1, 4, 4), flat[16 * n_poses :].reshape(-1, 3)


@dataclass
class _Block:
    """Rows ``start:end`` (block order) of one CustomFactor and views of its cached results."""

    start: int
    end: int
    poses: np.ndarray  # indices into the set's pose keys (sorted)
    points: np.ndarray  # indices into the set's landmark keys (sorted)
    pose_keys: list
    point_keys: list
    pattern: tuple  # (n_points, n_poses, point slot per obs, pose slot per obs): _Staging
    e_cost: np.ndarray  # (2m,) view of the cached cost residuals
    e_lin: np.ndarray  # (2m,) view of the cached linearised residuals
    J_pose: np.ndarray  # (m, 2, 6) view of the cached pose Jacobians
    J_point: np.ndarray  # (m, 2, 3) view of the cached landmark Jacobians
    staging: _Staging | None = None  # that of `pattern`, once linearised


class _Staging:
    """Zero-padded Jacobian blocks of one sparsity pattern, held in C++.

    A block's Jacobian over its keys ``[landmarks..., poses...]`` is zero except
    rows ``2k, 2k+1`` of observation ``k`` in the columns of its landmark and its
    pose. Every block of a pattern (the same number of keys and the same key slot
    per observation) writes the same positions, so one ``gtsam.JacobianVector``
    serves them all: a callback writes its non-zeros through numpy views of the C++
    matrices (the zeros stay from construction) and hands the vector to GTSAM in
    one C++ copy (``H[:] = native``), instead of converting one array per key.
    """

    def __init__(self, n_points: int, n_poses: int, point_slot: bytes, pose_slot: bytes):
        ll = np.frombuffer(point_slot, dtype=np.intp)
        lp = np.frombuffer(pose_slot, dtype=np.intp)
        m = len(lp)
        self.native = gtsam.JacobianVector(
            [np.zeros((2 * m, 3), order="F")] * n_points
            + [np.zeros((2 * m, 6), order="F")] * n_poses
        )
        views = [self.native[q] for q in range(n_points + n_poses)]
        for q, view in enumerate(views):  # the views must write into the C++ matrices
            view[0, 0] = 1.0
            shared = view.shape[0] == 2 * m and self.native[q][0, 0] == 1.0
            view[0, 0] = 0.0
            if not shared:
                raise RuntimeError("gtsam.JacobianVector gives no writable views of its matrices")
        self.m = m
        # one landmark: its block is dense (one copy); else observation k's rows of its
        # landmark's block; and of its pose's block
        self.point_all = views[0] if n_points == 1 else None
        self.point_rows = [views[int(a)][2 * k : 2 * k + 2] for k, a in enumerate(ll)]
        self.pose_rows = [views[n_points + int(a)][2 * k : 2 * k + 2] for k, a in enumerate(lp)]

    def write(self, J_pose: np.ndarray, J_point: np.ndarray) -> None:
        """Write the non-zeros of one block: ``J_pose`` (m, 2, 6), ``J_point`` (m, 2, 3)."""
        if self.point_all is not None:
            self.point_all[...] = J_point.reshape(2 * self.m, 3)
        else:
            for rows, J in zip(self.point_rows, J_point):
                rows[...] = J
        for rows, J in zip(self.pose_rows, J_pose):
            rows[...] = J


def _landmark_groups(point_keys: np.ndarray, max_obs: int) -> list[np.ndarray]:
    """Observation indices grouped by landmark, input order kept, chunks of ``max_obs``."""
    if max_obs < 1:
        raise ValueError(f"max_obs must be >= 1, got {max_obs}")
    n = len(point_keys)
    order = np.argsort(point_keys, kind="stable")
    sk = point_keys[order]
    starts = np.flatnonzero(np.r_[True, sk[1:] != sk[:-1]])
    ends = np.r_[starts[1:], n]
    return [
        order[a : min(a + max_obs, e)] for s, e in zip(starts, ends) for a in range(s, e, max_obs)
    ]


def _check_groups(groups, n: int) -> list[np.ndarray]:
    """Validate that ``groups`` partitions ``range(n)``."""
    out = [np.asarray(g, dtype=np.intp).reshape(-1) for g in groups]
    if any(len(g) == 0 for g in out):
        raise ValueError("groups must not be empty")
    allidx = np.concatenate(out)
    if len(allidx) != n or not np.array_equal(np.sort(allidx), np.arange(n)):
        raise ValueError(f"groups must partition range({n}) (every observation exactly once)")
    return out


def make_projection_block(
    calibration_or_camera,
    uv_px: np.ndarray,
    pose_keys,
    point_keys,
    noise_model: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """All given observations in one vectorised ``gtsam.CustomFactor`` (e.g. one target).

    Per-observation whitening and robust weights as in :class:`ProjectionBlocks`.

    Parameters
    ----------
    calibration_or_camera : Calibration or SphereCamera
    uv_px : array_like, shape (n, 2)
        Raw measured pixels.
    pose_keys, point_keys : array_like of int, shape (n,) or scalar
        ``Pose3`` (world_from_cam) and ``Point3`` keys per observation.
    noise_model : gtsam.noiseModel.Base
        2-D pixel noise model.

    Returns
    -------
    gtsam.CustomFactor
        Keys: landmarks (sorted), then poses (sorted); error dimension ``2 n``
        (observation ``k`` in rows ``2k, 2k+1``, ``u`` then ``v``).
    """
    uv = check_uv(uv_px)
    blocks = ProjectionBlocks(
        calibration_or_camera, uv, pose_keys, point_keys, noise_model, groups=[np.arange(len(uv))]
    )
    return blocks.factors()[0]


# --------------------------------------------------------------------------- bearing path


def _tangent_basis(rays: np.ndarray) -> np.ndarray:
    """Orthonormal tangent bases (N, 3, 2) of unit rays (N, 3), any orientation."""
    a = np.abs(rays)
    axis = np.eye(3)[np.argmin(a, axis=1)]
    b1 = np.cross(rays, axis)
    b1 /= np.linalg.norm(b1, axis=1, keepdims=True)
    b2 = np.cross(rays, b1)
    return np.stack([b1, b2], axis=2)


def model_scale_px_per_rad(calibration_or_camera, rays: np.ndarray) -> np.ndarray:
    """Local scale of the camera model at unit rays: singular values of d ideal / d ray.

    Parameters
    ----------
    calibration_or_camera : Calibration or SphereCamera
    rays : array_like, shape (N, 3)
        Unit rays, camera frame.

    Returns
    -------
    scales : ndarray, shape (N, 2)
        Largest and smallest image displacement (px) per radian of ray
        rotation. For a radial model these are the tangential scale
        ``c g(alpha) / sin(alpha)`` and the radial scale ``c g'(alpha)`` (in
        whichever order); for the sphere mapping ``c`` and ``c |cos(alpha)|``.
    """
    camera = camera_of(calibration_or_camera)
    r = np.asarray(rays, float).reshape(-1, 3)
    _, J = camera.ideal_from_points(r, jacobians=True)
    JB = J @ _tangent_basis(r)  # |P| = 1: d ideal / d ray on the tangent plane
    return np.linalg.svd(JB, compute_uv=False)


def bearing_sigma_rad(
    calibration_or_camera, uv_px: np.ndarray, sigma_px: float, hemisphere=1.0
) -> np.ndarray:
    """Isotropic angular standard deviation of the bearings of pixels.

    ``sigma_rad = sigma_px / sqrt(s_max * s_min)`` with the local scales of
    :func:`model_scale_px_per_rad` at the measured ray: the angular sigma of
    an isotropic pixel noise, averaged (geometrically) over the two tangent
    directions. Exact where the model is locally conformal (the optical axis;
    the tangential and radial scales differ elsewhere, see
    :func:`bearing_sqrt_information` for the exact 2x2 metric).

    Parameters
    ----------
    calibration_or_camera : Calibration or SphereCamera
    uv_px : array_like, shape (N, 2)
        Raw measured pixels.
    sigma_px : float
        Pixel noise standard deviation per axis (px).
    hemisphere : float or array_like, shape (N,)
        See :func:`bearings`.

    Returns
    -------
    sigma_rad : ndarray, shape (N,)
        Radians; NaN where the pixel has no ray, ``inf`` where the model's
        local scale vanishes (the sphere mapping at 90 deg).
    """
    rays = bearings(calibration_or_camera, uv_px, hemisphere)
    out = np.full(len(rays), np.nan)
    ok = np.isfinite(rays).all(1)
    if ok.any():
        s = model_scale_px_per_rad(calibration_or_camera, rays[ok])
        with np.errstate(divide="ignore"):
            out[ok] = float(sigma_px) / np.sqrt(s[:, 0] * s[:, 1])
    return out


def bearing_sqrt_information(
    calibration_or_camera, uv_px: np.ndarray, sigma_px=1.0, hemisphere=1.0
) -> np.ndarray:
    """Square-root information of bearing errors that reproduces pixel-space weighting.

    For ``gtsam.GeneralSFMFactorSphericalCamera`` (error
    ``measured.errorVector(predicted)`` in the measured ray's ``gtsam.Unit3``
    basis ``B``): ``R = S_px @ J(ray) @ B`` with ``J`` the model's ``d ideal /
    d P`` at the measured ray and ``S_px`` the pixel noise's square-root
    information, so ``|R @ error| = |S_px @ e_px|`` to first order in the
    error. Use ``gtsam.noiseModel.Gaussian.SqrtInformation(R[k])``.

    Parameters
    ----------
    calibration_or_camera : Calibration or SphereCamera
    uv_px : array_like, shape (N, 2)
        Raw measured pixels.
    sigma_px : float or ndarray, shape (2, 2)
        Pixel noise: a standard deviation per axis (px), or the 2x2
        square-root information of the pixel noise (1/px).
    hemisphere : float or array_like, shape (N,)
        See :func:`bearings`.

    Returns
    -------
    R : ndarray, shape (N, 2, 2)
        Per observation, 1/rad; NaN where the pixel has no ray.
    """
    rays = bearings(calibration_or_camera, uv_px, hemisphere)
    S = np.asarray(sigma_px, float)
    S = np.eye(2) / float(S) if S.ndim == 0 else S
    out = np.full((len(rays), 2, 2), np.nan)
    ok = np.flatnonzero(np.isfinite(rays).all(1))
    if len(ok):
        camera = camera_of(calibration_or_camera)
        _, J = camera.ideal_from_points(rays[ok], jacobians=True)
        B = np.array([gtsam.Unit3(rays[k]).basis() for k in ok])
        out[ok] = np.einsum("ab,nbc,ncd->nad", S, J, B)
    return out


def make_bearing_factors(
    calibration_or_camera,
    uv_px: np.ndarray,
    pose_keys,
    point_keys,
    sigma_px: float,
    robust=None,
    hemisphere=1.0,
    sigma_resolution: float = 1e-3,
) -> list:
    """C++ bearing factors (``gtsam.BearingFactor3D``) for pixels: the fast path.

    Each pixel becomes the unit ray of :func:`bearings` (``gtsam.Unit3``,
    measurement corrections included) measured from a ``Pose3``
    ``world_from_cam`` to a ``Point3``, with isotropic angular noise
    :func:`bearing_sigma_rad`. Sigmas are rounded to a relative
    ``sigma_resolution`` so observations share noise-model objects.

    Parameters
    ----------
    calibration_or_camera : Calibration or SphereCamera
    uv_px : array_like, shape (N, 2)
        Raw measured pixels; every one must have a ray (filter with
        ``np.isfinite(bearings(...)).all(1)``).
    pose_keys, point_keys : array_like of int, shape (N,) or scalar
    sigma_px : float
        Pixel noise standard deviation per axis (px).
    robust : gtsam.noiseModel.mEstimator.Base or None
        M-estimator on the whitened angular error (threshold in sigmas, the
        same number as in pixel space), e.g. ``mEstimator.Huber.Create(2.45)``.
    hemisphere : float or array_like, shape (N,)
        See :func:`bearings`.
    sigma_resolution : float
        Relative rounding of the angular sigmas (0: one model per observation).

    Returns
    -------
    list of gtsam.BearingFactor3D
    """
    uv = check_uv(uv_px)
    n = len(uv)
    pk = _keys(pose_keys, n, "pose_keys")
    lk = _keys(point_keys, n, "point_keys")
    rays = bearings(calibration_or_camera, uv, hemisphere)
    sig = bearing_sigma_rad(calibration_or_camera, uv, sigma_px, hemisphere)
    bad = np.flatnonzero(~(np.isfinite(rays).all(1) & np.isfinite(sig) & (sig > 0)))
    if len(bad):
        raise ValueError(
            f"{len(bad)} pixels have no usable ray (first {bad[:5].tolist()}); filter them out"
        )
    if sigma_resolution > 0:
        step = math.log1p(sigma_resolution)
        sig = np.exp(np.round(np.log(sig) / step) * step)
    models: dict[float, gtsam.noiseModel.Base] = {}
    factors = []
    for k in range(n):
        s = float(sig[k])
        model = models.get(s)
        if model is None:
            model = gtsam.noiseModel.Isotropic.Sigma(2, s)
            if robust is not None:
                model = gtsam.noiseModel.Robust.Create(robust, model)
            models[s] = model
        factors.append(gtsam.BearingFactor3D(int(pk[k]), int(lk[k]), gtsam.Unit3(rays[k]), model))
    return factors


# --------------------------------------------------------------------------- optimising

#: (values, token, jacobians) while levenberg_marquardt evaluates a Values it owns
_TRUSTED_PASS: tuple | None = None


class _Trusted:
    """Context for the passes (linearisations, evaluations) of a graph at ``values``.

    The promise: ``values`` is not modified from the construction of this object
    on, so a cache validated in one of its passes serves every later one. With
    ``jacobians``, an evaluation may also compute the Jacobians (a linearisation
    at the same values is expected next).
    """

    def __init__(self, values: gtsam.Values, jacobians: bool = False) -> None:
        self.values = values
        self.token = object()
        self.jacobians = jacobians

    def __enter__(self):
        global _TRUSTED_PASS
        _TRUSTED_PASS = (self.values, self.token, self.jacobians)
        return self.values

    def __exit__(self, *exc) -> None:
        global _TRUSTED_PASS
        _TRUSTED_PASS = None


def levenberg_marquardt(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    params: gtsam.LevenbergMarquardtParams | None = None,
) -> tuple[gtsam.Values, dict]:
    """Levenberg-Marquardt driven from Python, for graphs holding many ``CustomFactor`` s.

    Why: GTSAM's C++ optimisers hand their internal ``gtsam.Values`` to every
    ``CustomFactor`` callback, and the Python wrapper (pybind11) copies a
    ``Values`` that Python does not own before each call. Inside
    ``gtsam.LevenbergMarquardtOptimizer`` a callback therefore costs time
    proportional to the number of variables, and a graph of Python factors
    costs ``O(factors x variables)`` per iteration (measured: 22 us per
    callback with 100 variables, 2.3 ms with 10,000). This loop linearises
    and evaluates the graph on Python-owned ``Values`` (no copy) and leaves the
    damping, elimination and retraction to GTSAM's C++. For ``gtsam.ISAM2``,
    hold ``isam.getLinearizationPoint()`` (a reference to its internal
    ``Values``) in a variable for as long as the ``ISAM2`` lives: the callbacks
    then receive that registered object instead of a copy.

    The algorithm is GTSAM's default LM: damping ``lambda * I`` on every
    variable, ``lambda`` divided by ``lambdaFactor`` after an accepted step
    and multiplied after a rejected one, COLAMD ordering computed once,
    multifrontal elimination (Cholesky preferred), convergence on the
    relative or absolute decrease of the error as in
    ``gtsam.checkConvergence``; an indeterminate linear system counts as a
    rejected step (``lambda`` grows), as in GTSAM.

    :class:`ProjectionBlocks` factors are evaluated once per pass, all blocks
    in one numpy call. The cost evaluation of an iteration's first trial step
    also computes their Jacobians (LM usually accepts it, and the next
    linearisation is at that point), so the linearisation at an accepted step
    only hands the Jacobians over; a rejected step costs that extra work once.

    Parameters
    ----------
    graph : gtsam.NonlinearFactorGraph
    initial : gtsam.Values
        Not modified.
    params : gtsam.LevenbergMarquardtParams or None
        ``maxIterations``, ``relativeErrorTol``, ``absoluteErrorTol``,
        ``errorTol``, ``lambdaInitial``, ``lambdaFactor``,
        ``lambdaLowerBound``, ``lambdaUpperBound`` are used; GTSAM's defaults if None.

    Returns
    -------
    values : gtsam.Values
    info : dict
        ``iterations``, ``initial_error``, ``error``, ``lambda``,
        ``iteration_s`` (list of wall-clock seconds per iteration, float),
        ``converged`` (bool).
    """
    p = params or gtsam.LevenbergMarquardtParams()
    values = gtsam.Values(initial)
    # the passes at one Values share a _Trusted (no Values is modified here), and the
    # evaluation of a point LM may step to next computes its Jacobians on the way
    passes = _Trusted(values, jacobians=True)
    with passes:
        error = graph.error(values)
    info = {"initial_error": error, "iteration_s": [], "converged": False}
    lam = p.getlambdaInitial()
    zero = values.zeroVectors()
    # lambda * I on every variable: one factor per variable, built once; each trial only
    # sets its sigma 1 / sqrt(lambda) (setModel gives the Isotropic model of equal sigmas)
    damping = gtsam.GaussianFactorGraph()
    dims = []
    for k in values.keys():
        d = len(zero.at(k))
        damping.add(
            gtsam.JacobianFactor(k, np.eye(d), np.zeros(d), gtsam.noiseModel.Unit.Create(d))
        )
        dims.append(d)
    # the graph's own factors (add() stores a copy): setModel acts on what the solver sees
    damping_dims = [(damping.at(q), d) for q, d in enumerate(dims)]
    ordering = None
    for _ in range(p.getMaxIterations()):
        t0 = time.perf_counter()
        with passes:
            lin = graph.linearize(values)
        if ordering is None:
            ordering = gtsam.Ordering.Colamd(gtsam.VariableIndex(lin))
        lin_zero_error = lin.error(zero)
        accepted = False
        first_trial = True  # after a rejected step, evaluate the next trials' cost only
        while lam <= p.getlambdaUpperBound():
            sigma = 1.0 / math.sqrt(lam)
            sigmas: dict[int, np.ndarray] = {}
            for factor, d in damping_dims:
                sig = sigmas.get(d)
                if sig is None:
                    sig = sigmas[d] = np.full(d, sigma)
                factor.setModel(False, sig)
            damped = gtsam.GaussianFactorGraph()
            damped.push_back(lin)
            damped.push_back(damping)
            try:
                delta = damped.optimize(ordering)
            except RuntimeError as exc:  # as GTSAM's LM: an indeterminate system is a failed step
                if "ndeterminate" not in str(exc):
                    raise
                lam *= p.getlambdaFactor()
                continue
            predicted = lin_zero_error - lin.error(delta)
            trial = values.retract(delta)
            trial_passes = _Trusted(trial, jacobians=first_trial)
            first_trial = False
            with trial_passes:
                trial_error = graph.error(trial)
            if trial_error < error and predicted > 0:
                lam = max(lam / p.getlambdaFactor(), p.getlambdaLowerBound())
                accepted = True
                break
            lam *= p.getlambdaFactor()
        info["iteration_s"].append(time.perf_counter() - t0)
        if not accepted:
            info["converged"] = True  # no decrease possible: at a minimum within tolerance
            break
        decrease = error - trial_error
        values, error, passes = trial, trial_error, trial_passes
        if (
            decrease < p.getAbsoluteErrorTol()
            or decrease < p.getRelativeErrorTol() * (error + decrease)
            or error < p.getErrorTol()
        ):
            info["converged"] = True
            break
    info.update(iterations=len(info["iteration_s"]), error=error, **{"lambda": lam})
    return values, info
