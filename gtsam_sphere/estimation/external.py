"""Using a calibrated camera in your own GTSAM graph (frozen calibration).

Two ways to put observations of a calibrated :class:`~gtsam_sphere.core.camera.SphereCamera`
into a graph whose variables are GTSAM camera poses ``world_from_cam``
(``gtsam.Pose3``) and landmarks (``gtsam.Point3``), frames as in
``docs/conventions.md`` (camera ``x`` right, ``y`` down, ``z`` forward):

**Frozen pixel factor** (:func:`make_projection_factor`, :func:`make_projection_block`,
:class:`ProjectionBlocks`). The residual is in pixels of the ideal image,

    e = M (camera.ideal_from_pixels(uv_measured) - camera.ideal_from_points(R_wc^T (p_w - t_wc)))

i.e. the calibration's own measurement model (paper Eq. 1-5): the Brown terms
and the learned kNN correction act on the measurement and are applied once,
at construction; the spherical or radial mapping is evaluated at the current
estimate. ``M`` (2x2, constant per observation, the identity without
decentering and affinity terms) is the adjustment's own residual metric
(:meth:`~gtsam_sphere.core.camera.SphereCamera.measurement_metric`), so the
calibration's ``sigma_px`` applies as it is. Jacobians are analytic (right
perturbation ``world_from_cam * Exp([omega, v])``, rotation first, like GTSAM's own
camera factors). Any ``gtsam.noiseModel`` works: the single-observation factor hands it to GTSAM
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

import gtsam
import numpy as np

from ..core.camera import SphereCamera, check_uv
from ..core.rays import bearings as bearings  # re-exported: its home is the core
from ..core.rays import camera_of
from .engine import FactorEngine, FrozenMeasurement, ProjectionModel, Whitener, check_keys
from .optimize import levenberg_marquardt as levenberg_marquardt  # re-exported

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


# --------------------------------------------------------------------------- pixel factors


def _frozen_model(
    camera: SphereCamera, ideal_px: np.ndarray, metric: np.ndarray | None
) -> ProjectionModel:
    """The engine's projection model with the calibration frozen (no intrinsics key)."""
    return ProjectionModel(FrozenMeasurement(camera, ideal_px, metric))


def make_projection_factor(
    calibration_or_camera,
    uv_px: np.ndarray,
    pose_key: int,
    point_key: int,
    noise_model: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """One observation with a frozen calibration, as a ``gtsam.CustomFactor``.

    Residual (px, ideal image, relative to the principal point):
    ``M (camera.ideal_from_pixels(uv_px) - camera.ideal_from_points(R_wc^T (p_w - t_wc)))``
    with ``M = camera.measurement_metric(uv_px)`` (the adjustment's metric; the
    identity without decentering and affinity terms); the measurement side (Brown
    terms, learned correction, ``M``) is evaluated once, here.
    The residual and Jacobians are those of the factor engine's projection model
    (:class:`~gtsam_sphere.estimation.engine.ProjectionModel`); the noise model is
    GTSAM's.

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
    metric = camera.measurement_metric(uv)
    if not (np.all(np.isfinite(ideal)) and (metric is None or np.all(np.isfinite(metric)))):
        raise ValueError(f"pixel {uv[0].tolist()} has no finite corrected coordinates")
    pk, lk = int(pose_key), int(point_key)
    model = _frozen_model(camera, ideal, metric)
    index = [np.zeros(1, np.intp), np.zeros(1, np.intp)]
    one = np.ones(1)

    def evaluate(this, values, H):
        tables = [
            values.atPose3(pk).matrix().reshape(1, 16),
            np.asarray(values.atPoint3(lk), float).reshape(1, 3),
        ]
        e, ctx = model.residual(tables, index, slice(None), H is not None)
        if H is not None:
            J = model.jacobian(ctx, one)[:, :, 0]  # (2, 9): [omega, v] of the pose, point
            H[0] = np.asfortranarray(J[:, :6])
            H[1] = np.asfortranarray(J[:, 6:9])
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

    The blocks run on the package's one factor engine
    (:class:`~gtsam_sphere.estimation.engine.FactorEngine`) with the projection
    model of a frozen camera: one shared evaluation of every block whose
    variables changed, a stored result used only at bit-identical variables,
    single blocks evaluated alone under an incremental solver, and inside
    :func:`levenberg_marquardt` one evaluation per pass without reading the
    variables again (see the engine's documentation).

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
    engine : FactorEngine
    stats : dict
        The engine's counters: ``hits``, ``single``, ``full_passes``.
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
        self.camera = camera_of(calibration_or_camera)
        uv = check_uv(uv_px)
        n = len(uv)
        if n == 0:
            raise ValueError("no observations")
        pk = check_keys(pose_keys, n, "pose_keys")
        lk = check_keys(point_keys, n, "point_keys")
        self.ideal_px = self.camera.ideal_from_pixels(uv)
        metric = self.camera.measurement_metric(uv)
        finite = np.isfinite(self.ideal_px).all(1)
        if metric is not None:
            finite &= np.isfinite(metric).all((1, 2))
        bad = np.flatnonzero(~finite)
        if len(bad):
            raise ValueError(f"observations {bad[:5].tolist()} have no finite corrected pixel")
        self.whitener = Whitener.from_noise_model(noise_model)
        self.noise_model = noise_model
        self.groups = _landmark_groups(lk, max_obs) if groups is None else _check_groups(groups, n)
        self.n = n
        # the engine's order is the blocks': block g owns rows start[g]:start[g+1]
        order = np.concatenate(self.groups)
        self._order = order
        sizes = np.array([len(g) for g in self.groups])
        block = np.repeat(np.arange(len(sizes)), sizes)
        # per block, its poses and its landmarks (each sorted) and each observation's slot
        counts, keys, local = [], [], []
        for k in (pk[order], lk[order]):
            by = np.lexsort((k, block))
            kb, bb = k[by], block[by]
            new = np.r_[True, (kb[1:] != kb[:-1]) | (bb[1:] != bb[:-1])]
            uid = np.cumsum(new) - 1  # index of (block, key) among all
            first = uid[np.searchsorted(bb, np.arange(len(sizes)))]  # block's first
            slot = np.empty(len(k), np.intp)
            slot[by] = uid - first[bb]
            counts.append(np.bincount(bb[new], minlength=len(sizes)))
            keys.append(kb[new].astype(np.int64))
            local.append(slot)
        model = _frozen_model(
            self.camera, self.ideal_px[order], None if metric is None else metric[order]
        )
        self.engine = FactorEngine(
            model, sizes, np.column_stack(counts), keys, local, self.whitener
        )
        self.stats = self.engine.stats

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
        return [self.engine.factor(g) for g in range(self.engine.n_blocks)]

    def residuals_px(self, values: gtsam.Values) -> np.ndarray:
        """Unweighted residuals of all observations.

        Parameters
        ----------
        values : gtsam.Values
            Holds every pose (``Pose3`` world_from_cam) and landmark (``Point3``, world).

        Returns
        -------
        e_px : ndarray, shape (N, 2)
            ``M (ideal_from_pixels(uv) - ideal_from_points(P_cam))`` in pixels of
            the ideal image (``M = camera.measurement_metric(uv)``), input order.
        """
        out = np.empty((self.n, 2))
        out[self._order] = self.engine.residuals_px(values)
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
        return self.whitener.norms(self.residuals_px(values))

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


def model_scale_px_per_rad(
    calibration_or_camera, rays: np.ndarray, metric: np.ndarray | None = None
) -> np.ndarray:
    """Local scale of the camera model at unit rays: singular values of d ideal / d ray.

    Parameters
    ----------
    calibration_or_camera : Calibration or SphereCamera
    rays : array_like, shape (N, 3)
        Unit rays, camera frame.
    metric : ndarray, shape (N, 2, 2), or None
        The residual metric ``M`` of each ray's pixel
        (:meth:`~gtsam_sphere.core.camera.SphereCamera.measurement_metric`): the scales of
        ``M d ideal / d ray``; None: the identity.

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
    if metric is not None:
        J = np.asarray(metric, float) @ J
    JB = J @ _tangent_basis(r)  # |P| = 1: d ideal / d ray on the tangent plane
    return np.linalg.svd(JB, compute_uv=False)


def bearing_sigma_rad(
    calibration_or_camera, uv_px: np.ndarray, sigma_px: float, hemisphere=1.0
) -> np.ndarray:
    """Isotropic angular standard deviation of the bearings of pixels.

    ``sigma_rad = sigma_px / sqrt(s_max * s_min)`` with the local scales of
    :func:`model_scale_px_per_rad` at the measured ray (times the calibration's
    residual metric ``M``, :meth:`~gtsam_sphere.core.camera.SphereCamera.measurement_metric`,
    where it has decentering or affinity terms): the angular sigma of
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
    camera = camera_of(calibration_or_camera)
    metric = camera.measurement_metric(check_uv(uv_px))
    ok = np.isfinite(rays).all(1)
    if metric is not None:
        ok &= np.isfinite(metric).all((1, 2))
    if ok.any():
        s = model_scale_px_per_rad(camera, rays[ok], None if metric is None else metric[ok])
        with np.errstate(divide="ignore"):
            out[ok] = float(sigma_px) / np.sqrt(s[:, 0] * s[:, 1])
    return out


def bearing_sqrt_information(
    calibration_or_camera, uv_px: np.ndarray, sigma_px=1.0, hemisphere=1.0
) -> np.ndarray:
    """Square-root information of bearing errors that reproduces pixel-space weighting.

    For ``gtsam.GeneralSFMFactorSphericalCamera`` (error
    ``measured.errorVector(predicted)`` in the measured ray's ``gtsam.Unit3``
    basis ``B``): ``R = S_px @ M @ J(ray) @ B`` with ``J`` the model's ``d ideal /
    d P`` at the measured ray, ``M`` the calibration's residual metric at the pixel
    (:meth:`~gtsam_sphere.core.camera.SphereCamera.measurement_metric`, the
    identity without decentering and affinity terms) and ``S_px`` the pixel
    noise's square-root information, so ``|R @ error| = |S_px @ e_px|`` (the
    frozen pixel factor's residual) to first order in the error. Use
    ``gtsam.noiseModel.Gaussian.SqrtInformation(R[k])``.

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
    camera = camera_of(calibration_or_camera)
    metric = camera.measurement_metric(check_uv(uv_px))
    S = np.asarray(sigma_px, float)
    S = np.eye(2) / float(S) if S.ndim == 0 else S
    out = np.full((len(rays), 2, 2), np.nan)
    ok = np.flatnonzero(np.isfinite(rays).all(1))
    if len(ok):
        _, J = camera.ideal_from_points(rays[ok], jacobians=True)
        if metric is not None:
            J = metric[ok] @ J
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
    pk = check_keys(pose_keys, n, "pose_keys")
    lk = check_keys(point_keys, n, "point_keys")
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
