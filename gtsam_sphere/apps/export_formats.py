"""Export to the files other tools read: ROS ``CameraInfo`` YAML, mrcal ``.cameramodel``,
basalt ``calibration.json``; and read a ``.cameramodel`` back.

Every camera's model is fitted by :func:`gtsam_sphere.apps.export.export_calibration` (the
single-camera export: its fit error inside and outside the observed region is printed,
and written in the file where the format has comments).

``ros``
    The YAML ``camera_calibration`` and ``camera_info_manager`` write for a
    ``sensor_msgs/CameraInfo`` (``camera_calibration_parsers``' layout):
    ``image_width``, ``image_height``, ``camera_name``, ``camera_matrix`` (3x3),
    ``distortion_model``, ``distortion_coefficients`` (1xN), ``rectification_matrix``
    (3x3, identity: a monocular camera) and ``projection_matrix`` (3x4, ``[K | 0]``: the
    pinhole a ROS pipeline such as ``image_proc`` rectifies to has the fitted focal
    lengths and principal point), each as ``{rows, cols, data}`` (row-major).
    Distortion models (:data:`ROS_MODELS`): ``equidistant`` (``cv2.fisheye``,
    Kannala-Brandt ``k1..k4``; rays below 90 deg), ``plumb_bob`` (``k1, k2, p1, p2,
    k3``), ``rational_polynomial`` (``k1, k2, p1, p2, k3, k4, k5, k6``; both pinhole,
    rays below 80 deg by default). ``auto`` fits ``equidistant`` and
    ``rational_polynomial`` and keeps the one covering most of the observed region, then
    the smaller residual. A ROS pipeline rectifies to the perspective part of the field:
    the coverage and the error outside the observed region say how much is lost.
``mrcal``
    A ``.cameramodel``: a Python dict literal (mrcal's documented format,
    https://mrcal.secretsauce.net/cameramodels.html) with ``lensmodel``,
    ``intrinsics``, ``imagersize``, ``extrinsics`` (``rt_cam_ref``: Rodrigues
    rotation then translation, ``p_cam = R(r) p_ref + t``) and, with observations,
    ``valid_intrinsics_region`` (the convex hull of the observed pixels, closed).
    Models (:data:`MRCAL_MODELS`): ``LENSMODEL_OPENCV8`` (the ``opencv-rational`` fit)
    where the observed region's widest ray is below ``MRCAL_OPENCV8_MAX_DEG`` (a lens
    below ~150 deg) and its largest fit error is at most ``MRCAL_OPENCV8_MAX_PX``, otherwise
    ``LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=.._Ny=.._fov_x_deg=..`` fitted to the
    calibration (:mod:`gtsam_sphere.apps.splined`). A rig's cameras get one file each,
    ``extrinsics`` relative to camera 0 (the rig frame) in metres.
``basalt``
    basalt's ``calibration.json`` (cereal JSON, ``value0``): ``T_imu_cam`` (per camera,
    ``px, py, pz`` metres and the quaternion ``qx, qy, qz, qw``), ``intrinsics`` (per
    camera ``camera_type`` ``kb4`` / ``ds`` / ``eucm`` and its named parameters),
    ``resolution`` and the IMU entries (placeholders: zero biases, default noise; fill
    them from an IMU calibration). The "IMU" frame is the rig frame (camera 0): a single
    camera's ``T_imu_cam`` is the identity, a rig camera's ``inverse(cam_from_rig)``.
    ``auto`` keeps, per camera, the model covering most of the observed region, then the
    smaller residual (:data:`BASALT_MODELS`).

Reading (:func:`read_cameramodel`): ``LENSMODEL_PINHOLE``, ``OPENCV4/5/8``,
``STEREOGRAPHIC`` and ``SPLINED_STEREOGRAPHIC_order=3`` project in
:class:`MrcalCamera`; ``gtsam-sphere compare CALIB --with FILE.cameramodel`` prints the
projection differences over the field (:mod:`gtsam_sphere.apps.kalibr_compare`).
"""

from __future__ import annotations

import ast
import json
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.errors import DatasetError, OptionsError
from ..io.dataset import write_bytes_atomic
from .export import (
    FORMAT_TARGETS,
    ExportResult,
    ds_project,
    ds_valid,
    eucm_project,
    eucm_valid,
    export_calibration,
    kb_project,
    rational_project,
)
from .export_rig import _METRES, _best, fits_exit_status, relative_pose
from .splined import SplineConfig, splined_project, stereographic_u

logger = logging.getLogger(__name__)

__all__ = [
    "BASALT_MODELS",
    "FORMAT_TARGETS",
    "MRCAL_MODELS",
    "ROS_MODELS",
    "FormatExport",
    "MrcalCamera",
    "basalt_calibration",
    "mrcal_cameramodels",
    "read_cameramodel",
    "ros_camera_infos",
    "run_cli",
]

#: ROS ``distortion_model`` -> single-camera export target
ROS_MODELS: dict[str, str] = {
    "equidistant": "opencv-fisheye",
    "plumb_bob": "opencv-plumb-bob",
    "rational_polynomial": "opencv-rational",
}
#: mrcal model choice -> single-camera export target
MRCAL_MODELS: dict[str, str] = {"opencv8": "opencv-rational", "splined": "mrcal-splined"}
#: basalt ``camera_type`` -> single-camera export target
BASALT_MODELS: dict[str, str] = {"kb4": "opencv-fisheye", "ds": "kalibr-ds", "eucm": "kalibr-eucm"}
#: ``--mrcal-model auto`` takes OPENCV8 only when the observed field is narrower than this (deg)
MRCAL_OPENCV8_MAX_DEG = 75.0
#: ... and its largest fit error over the observed region is at most this (px)
MRCAL_OPENCV8_MAX_PX = 0.1


@dataclass
class FormatExport:
    """What an export to another tool's format holds.

    Attributes
    ----------
    files : dict of str -> str
        File key -> text; the key is ``""`` for the one file of a single camera (or of
        basalt), the camera id for per-camera files of a rig.
    fits : dict of str -> ExportResult
        Camera id -> fitted model (with its fit error inside and outside the observed
        region).
    models : dict of str -> str
        Camera id -> the model written (``equidistant``, ``LENSMODEL_OPENCV8``, ``kb4``, ...).
    """

    files: dict[str, str]
    fits: dict[str, ExportResult]
    models: dict[str, str] = field(default_factory=dict)

    def summary(self) -> str:
        """Per camera: the model written and its fit's summary."""
        lines = []
        for cid, fit in self.fits.items():
            lines.append(f"camera {cid}: {self.models.get(cid, fit.target)}")
            lines.extend("  " + line for line in fit.summary().splitlines())
        return "\n".join(lines)


# --------------------------------------------------------------------------- helpers


def _cameras(calib, camera: str | None, source: str) -> list[tuple[str, object]]:
    """``[(camera id, calibration@1)]`` of a single camera or a rig (all or ``camera``)."""
    if hasattr(calib, "camera_ids"):
        ids = list(calib.camera_ids)
        if camera is not None:
            if camera not in calib.cameras:
                raise OptionsError(
                    f"--camera {camera!r}: no such camera in {source} (cameras {ids})"
                )
            ids = [camera]
        return [(cid, calib.camera_calibration(cid)) for cid in ids]
    if camera is not None:
        raise OptionsError(f"--camera {camera!r}: {source} is a single-camera calibration")
    return [("cam0", calib)]


def _fit_choice(one, names: list[str], table: dict[str, str], what: str, src: str, **kwargs):
    """Fit each of ``names`` (keys of ``table``); the one covering most, then the smallest
    residual (``export_rig._best``), with its name."""
    fits, errors = {}, []
    for name in names:
        try:
            fits[name] = export_calibration(one, table[name], source=src, **kwargs)
        except DatasetError as exc:
            errors.append(f"{name}: {exc}")
    if not fits:
        raise DatasetError(f"{src}: no {what} model fits ({'; '.join(errors)})")
    best = _best(list(fits.values()))
    return next(n for n, f in fits.items() if f is best), best


def _check_model(name: str, table: dict[str, str], option: str) -> None:
    if name != "auto" and name not in table:
        raise OptionsError(f"{option} {name!r}: choose auto or one of {', '.join(table)}")


def _comment_lines(fit: ExportResult, prefix: str = "# ") -> list[str]:
    head = f"{prefix}exported by gtsam-sphere" + (f" from {fit.source}" if fit.source else "")
    return [head, *(f"{prefix}{line}" for line in fit.summary().splitlines())]


def _metres(calib) -> float:
    scale = _METRES.get(str(getattr(calib, "units", "m")))
    if scale is None:
        logger.warning(
            "units %r are not metres, cm or mm: translations are written in %s, not metres",
            calib.units,
            calib.units,
        )
        scale = 1.0
    return scale


def _seq(values) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


# --------------------------------------------------------------------------- ROS


def ros_yaml(fit: ExportResult, distortion_model: str, camera_name: str) -> str:
    """The ``sensor_msgs/CameraInfo`` YAML of one fitted camera (see the module docstring).

    Parameters
    ----------
    fit : ExportResult
        ``opencv-fisheye``, ``opencv-plumb-bob`` or ``opencv-rational`` (``K`` px, ``D``).
    distortion_model : str
        ``equidistant``, ``plumb_bob`` or ``rational_polynomial`` (matching ``fit``).
    camera_name : str

    Returns
    -------
    str
        The YAML, the fit's summary (error inside and outside the observed region) in
        leading comments.
    """
    K = fit.K
    P = np.hstack([K, np.zeros((3, 1))])
    D = fit.D

    def matrix(name: str, rows: int, cols: int, data) -> list[str]:
        return [f"{name}:", f"  rows: {rows}", f"  cols: {cols}", f"  data: {_seq(np.ravel(data))}"]

    lines = _comment_lines(fit)
    lines.append(
        "# projection_matrix: the pinhole camera image_proc rectifies to ([K | 0]); "
        "rectification_matrix: identity (monocular)"
    )
    lines += [
        f"image_width: {int(fit.width)}",
        f"image_height: {int(fit.height)}",
        f"camera_name: {camera_name}",
        *matrix("camera_matrix", 3, 3, K),
        f"distortion_model: {distortion_model}",
        *matrix("distortion_coefficients", 1, len(D), D),
        *matrix("rectification_matrix", 3, 3, np.eye(3)),
        *matrix("projection_matrix", 3, 4, P),
    ]
    return "\n".join(lines) + "\n"


def ros_camera_infos(
    calib, model: str = "auto", camera: str | None = None, source: str | None = None, **kwargs
) -> FormatExport:
    """ROS ``CameraInfo`` YAML of a calibration: one file per camera.

    Parameters
    ----------
    calib : Calibration or RigCalibration
    model : str
        ``"auto"`` or one of :data:`ROS_MODELS`.
    camera : str, optional
        A rig's camera to export (default every camera, one file each).
    source : str, optional
        Calibration file name, written in a comment.
    **kwargs
        ``region``, ``max_incidence_deg``, ``n_samples`` of
        :func:`~gtsam_sphere.apps.export.export_calibration`.

    Returns
    -------
    FormatExport

    Raises
    ------
    OptionsError
        An unknown model or camera.
    DatasetError
        A camera no model fits.
    """
    src = source or "calibration"
    _check_model(model, ROS_MODELS, "--ros-model")
    names = ["equidistant", "rational_polynomial"] if model == "auto" else [model]
    out = FormatExport({}, {})
    cams = _cameras(calib, camera, src)
    for cid, one in cams:
        name, fit = _fit_choice(one, names, ROS_MODELS, "ROS", src, **kwargs)
        key = "" if len(cams) == 1 else cid
        out.files[key] = ros_yaml(fit, name, cid)
        out.fits[cid], out.models[cid] = fit, name
    return out


# --------------------------------------------------------------------------- mrcal


def _observations(one) -> np.ndarray | None:
    obs = one.extra.get("observations") if isinstance(one.extra, dict) else None
    if not isinstance(obs, dict) or obs.get("uv_px") is None:
        return None
    uv = np.asarray(obs["uv_px"], float).reshape(-1, 2)
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    return uv if len(uv) >= 3 else None


def cameramodel_text(
    fit: ExportResult,
    lensmodel: str,
    rt_cam_ref: np.ndarray,
    valid_region: np.ndarray | None = None,
) -> str:
    """A ``.cameramodel`` (a Python dict literal with comments) of one fitted camera.

    Parameters
    ----------
    fit : ExportResult
        ``opencv-rational`` (written as ``LENSMODEL_OPENCV8``) or ``mrcal-splined``.
    lensmodel : str
        mrcal's model string.
    rt_cam_ref : ndarray, shape (6,)
        Rodrigues rotation (rad) then translation (metres): ``p_cam = R p_ref + t``.
    valid_region : ndarray, shape (V, 2), optional
        Closed polygon (px) where the intrinsics are trusted.
    """
    if fit.family not in ("rational", "splined-stereographic"):
        raise ValueError(f"{fit.target}: not an mrcal model (opencv-rational, mrcal-splined)")
    intr = fit.vector
    lines = _comment_lines(fit)
    lines += [
        "{",
        f"    'lensmodel': {lensmodel!r},",
        "    # intrinsics are fx,fy,cx,cy,distortion0,distortion1,....",
        f"    'intrinsics': {_seq(intr)},",
    ]
    if valid_region is not None:
        pts = ", ".join(
            f"[{round(float(u), 3)!r}, {round(float(v), 3)!r}]" for u, v in valid_region
        )
        lines.append(f"    'valid_intrinsics_region': [{pts}],")
    lines += [
        "    # extrinsics are rt_fromref",
        f"    'extrinsics': {_seq(rt_cam_ref)},",
        f"    'imagersize': [{int(fit.width)}, {int(fit.height)}],",
        "}",
    ]
    return "\n".join(lines) + "\n"


def _hull(uv: np.ndarray | None) -> np.ndarray | None:
    if uv is None:
        return None
    import cv2

    hull = cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2).astype(float)
    return np.vstack([hull, hull[:1]]) if len(hull) >= 3 else None


def mrcal_cameramodels(
    calib, model: str = "auto", camera: str | None = None, source: str | None = None, **kwargs
) -> FormatExport:
    """mrcal ``.cameramodel`` files of a calibration: one per camera.

    Parameters
    ----------
    calib : Calibration or RigCalibration
    model : str
        ``"auto"`` or one of :data:`MRCAL_MODELS` (``opencv8``, ``splined``).
    camera : str, optional
        A rig's camera (default every camera, one file each); ``extrinsics`` are
        relative to the rig's camera 0 either way.
    source : str, optional
    **kwargs
        As :func:`ros_camera_infos`.

    Returns
    -------
    FormatExport
    """
    import cv2

    src = source or "calibration"
    _check_model(model, MRCAL_MODELS, "--mrcal-model")
    out = FormatExport({}, {})
    cams = _cameras(calib, camera, src)
    rig = hasattr(calib, "camera_ids")
    scale = _metres(calib) if rig else 1.0
    for cid, one in cams:
        name = model
        fit = None
        if model in ("auto", "opencv8"):
            fit = export_calibration(one, MRCAL_MODELS["opencv8"], source=src, **kwargs)
            if model == "auto" and not (
                fit.max_incidence_deg_region < MRCAL_OPENCV8_MAX_DEG
                and fit.coverage >= 0.999
                and fit.max_px <= MRCAL_OPENCV8_MAX_PX
            ):
                fit = None
            name = "opencv8"
        if fit is None:
            fit = export_calibration(one, MRCAL_MODELS["splined"], source=src, **kwargs)
            name = "splined"
        lensmodel = "LENSMODEL_OPENCV8" if name == "opencv8" else fit.spline.lensmodel
        rt = np.zeros(6)
        if rig:
            R, t = relative_pose(calib, calib.camera_ids[0], cid)
            rt[:3] = cv2.Rodrigues(np.asarray(R, float))[0].ravel()
            rt[3:] = np.asarray(t, float) * scale
        key = "" if len(cams) == 1 else cid
        out.files[key] = cameramodel_text(fit, lensmodel, rt, _hull(_observations(one)))
        out.fits[cid], out.models[cid] = fit, lensmodel
    return out


@dataclass
class MrcalCamera:
    """A camera read from an mrcal ``.cameramodel``.

    Attributes
    ----------
    camera_id : str
        The file's name (for messages).
    model : str
        mrcal's ``lensmodel`` string.
    intrinsics : ndarray
        mrcal's intrinsics vector (``fx, fy, cx, cy``, then the model's own).
    resolution : tuple of int
        ``imagersize``: ``(width, height)`` px.
    rt_cam_ref : ndarray, shape (6,)
        ``extrinsics``: Rodrigues rotation then translation, ``p_cam = R p_ref + t``.
    """

    camera_id: str
    model: str
    intrinsics: np.ndarray
    resolution: tuple[int, int]
    rt_cam_ref: np.ndarray
    tool: str = "mrcal"

    def project(self, rays: np.ndarray) -> np.ndarray:
        """Pixels ``(N, 2)`` of camera-frame rays ``(N, 3)``; NaN where the model has none."""
        rays = np.asarray(rays, float).reshape(-1, 3)
        i = self.intrinsics
        if self.model.startswith("LENSMODEL_SPLINED_STEREOGRAPHIC"):
            return splined_project(i, rays, SplineConfig.parse(self.model))
        if self.model == "LENSMODEL_STEREOGRAPHIC":
            u = stereographic_u(rays)
            return np.column_stack([i[0] * u[:, 0] + i[2], i[1] * u[:, 1] + i[3]])
        full = np.zeros(12)
        full[: len(i)] = i
        uv = rational_project(full, rays)
        return np.where((rays[:, 2] > 0)[:, None], uv, np.nan)


#: mrcal models :class:`MrcalCamera` projects -> number of intrinsics (None: by its config)
_MRCAL_READ = {
    "LENSMODEL_PINHOLE": 4,
    "LENSMODEL_STEREOGRAPHIC": 4,
    "LENSMODEL_OPENCV4": 8,
    "LENSMODEL_OPENCV5": 9,
    "LENSMODEL_OPENCV8": 12,
}


def read_cameramodel(path: str | os.PathLike) -> MrcalCamera:
    """Read an mrcal ``.cameramodel`` (a Python dict literal, ``ast.literal_eval``).

    Parameters
    ----------
    path : path-like

    Returns
    -------
    MrcalCamera

    Raises
    ------
    DatasetError
        Not a dict literal, a missing or malformed key (named), a wrong number of
        intrinsics.
    OptionsError
        A lens model this package does not project (e.g. ``LENSMODEL_CAHVORE``).
    """
    path = str(path)
    try:
        with open(path, encoding="utf-8") as fh:
            doc = ast.literal_eval(fh.read())
    except (SyntaxError, ValueError) as exc:
        raise DatasetError(
            f"{path}: not an mrcal .cameramodel (a Python dict literal): {exc}"
        ) from None
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: not an mrcal .cameramodel: expected a dict")
    for key in ("lensmodel", "intrinsics", "imagersize"):
        if key not in doc:
            raise DatasetError(f"{path}: no {key!r}")
    model = str(doc["lensmodel"])
    if model.startswith("LENSMODEL_SPLINED_STEREOGRAPHIC"):
        try:
            n = SplineConfig.parse(model).n_params
        except ValueError as exc:
            raise OptionsError(f"{path}: lensmodel {model!r}: {exc}") from None
    elif model in _MRCAL_READ:
        n = _MRCAL_READ[model]
    else:
        raise OptionsError(
            f"{path}: lensmodel {model!r} is not supported; expected one of "
            f"{', '.join(_MRCAL_READ)} or LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_..."
        )
    try:
        intr = np.asarray(doc["intrinsics"], float).ravel()
    except (TypeError, ValueError):
        raise DatasetError(f"{path}: 'intrinsics' is not a list of numbers") from None
    if len(intr) != n or not np.all(np.isfinite(intr)):
        raise DatasetError(f"{path}: {model} needs {n} finite intrinsics, got {len(intr)}")
    size = doc["imagersize"]
    if not (isinstance(size, (list, tuple)) and len(size) == 2):
        raise DatasetError(f"{path}: 'imagersize' must be [width, height]")
    rt = np.asarray(doc.get("extrinsics", np.zeros(6)), float).ravel()
    if len(rt) != 6:
        raise DatasetError(f"{path}: 'extrinsics' must hold 6 numbers (rt_cam_ref)")
    return MrcalCamera(Path(path).name, model, intr, (int(size[0]), int(size[1])), rt)


# --------------------------------------------------------------------------- basalt


def _quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion ``(qx, qy, qz, qw)`` (Hamilton, ``qw >= 0``) of a rotation (3, 3)."""
    R = np.asarray(R, float)
    tr = float(np.trace(R))
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 1e-300))
        q = [0.0, 0.0, 0.0, (R[k, j] - R[j, k]) / s]
        q[i] = s / 4
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
    q = np.array(q)
    q /= np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return tuple(float(v) for v in q)


def basalt_intrinsics(fit: ExportResult, camera_type: str) -> dict:
    """basalt's ``{"camera_type", "intrinsics"}`` entry of one fitted camera.

    Parameters
    ----------
    fit : ExportResult
        ``opencv-fisheye`` (``kb4``), ``kalibr-ds`` (``ds``) or ``kalibr-eucm`` (``eucm``).
    camera_type : {"kb4", "ds", "eucm"}

    Returns
    -------
    dict
        ``fx, fy, cx, cy`` (px) and ``k1..k4`` / ``xi, alpha`` / ``alpha, beta``.
    """
    p = fit.params
    core = {k: float(p[k]) for k in ("fx", "fy", "cx", "cy")}
    if camera_type == "kb4":
        core.update({k: float(p[k]) for k in ("k1", "k2", "k3", "k4")})
    elif camera_type == "ds":
        core.update(xi=float(p["xi"]), alpha=float(p["alpha"]))
    else:
        core.update(alpha=float(p["alpha"]), beta=float(p["beta"]))
    return {"camera_type": camera_type, "intrinsics": core}


def basalt_project(entry: dict, rays: np.ndarray) -> np.ndarray:
    """Project rays with one basalt ``intrinsics`` entry, by that model's formulas.

    Parameters
    ----------
    entry : dict
        ``{"camera_type": "kb4" | "ds" | "eucm", "intrinsics": {...}}``.
    rays : ndarray, shape (N, 3)
        Camera frame (x right, y down, z forward).

    Returns
    -------
    uv_px : ndarray, shape (N, 2)
        NaN where the model has no pixel (kb4: ``z <= 0``, as the export fitted it).
    """
    i = entry["intrinsics"]
    kind = entry["camera_type"]
    rays = np.asarray(rays, float).reshape(-1, 3)
    if kind == "kb4":
        p = [i[k] for k in ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")]
        uv, ok = kb_project(np.array(p), rays), rays[:, 2] > 0
    elif kind == "ds":
        p = np.array([i["xi"], i["alpha"], i["fx"], i["fy"], i["cx"], i["cy"]])
        uv, ok = ds_project(p, rays), ds_valid(p, rays)
    elif kind == "eucm":
        p = np.array([i["alpha"], i["beta"], i["fx"], i["fy"], i["cx"], i["cy"]])
        uv, ok = eucm_project(p, rays), eucm_valid(p, rays)
    else:
        raise OptionsError(f"basalt camera_type {kind!r} is not supported (kb4, ds, eucm)")
    return np.where(ok[:, None], uv, np.nan)


def basalt_calibration(
    calib, model: str = "auto", camera: str | None = None, source: str | None = None, **kwargs
) -> FormatExport:
    """basalt ``calibration.json`` of a calibration: every camera in one file.

    Parameters
    ----------
    calib : Calibration or RigCalibration
    model : str
        ``"auto"`` or one of :data:`BASALT_MODELS` (``kb4``, ``ds``, ``eucm``).
    camera : str, optional
        One camera of a rig only (default every camera).
    source : str, optional
    **kwargs
        As :func:`ros_camera_infos`.

    Returns
    -------
    FormatExport
        ``files[""]``: the JSON text.
    """
    src = source or "calibration"
    _check_model(model, BASALT_MODELS, "--basalt-model")
    names = list(BASALT_MODELS) if model == "auto" else [model]
    out = FormatExport({}, {})
    rig = hasattr(calib, "camera_ids")
    scale = _metres(calib) if rig else 1.0
    poses, intrinsics, resolution = [], [], []
    for cid, one in _cameras(calib, camera, src):
        name, fit = _fit_choice(one, names, BASALT_MODELS, "basalt", src, **kwargs)
        out.fits[cid], out.models[cid] = fit, name
        R, t = np.eye(3), np.zeros(3)
        if rig:
            Rc, tc = calib.cam_from_rig[cid]
            R = np.asarray(Rc, float).T  # rig_from_cam = inverse(cam_from_rig)
            t = -R @ np.asarray(tc, float) * scale
        qx, qy, qz, qw = _quaternion(R)
        poses.append(
            {"px": float(t[0]), "py": float(t[1]), "pz": float(t[2]),
             "qx": qx, "qy": qy, "qz": qz, "qw": qw}
        )  # fmt: skip
        intrinsics.append(basalt_intrinsics(fit, name))
        resolution.append([int(fit.width), int(fit.height)])
    doc = {
        "value0": {
            "T_imu_cam": poses,
            "intrinsics": intrinsics,
            "resolution": resolution,
            "calib_accel_bias": [0.0] * 9,
            "calib_gyro_bias": [0.0] * 12,
            "imu_update_rate": 200.0,
            "accel_noise_std": [0.016, 0.016, 0.016],
            "gyro_noise_std": [0.000282, 0.000282, 0.000282],
            "accel_bias_std": [0.001, 0.001, 0.001],
            "gyro_bias_std": [0.0001, 0.0001, 0.0001],
            "cam_time_offset_ns": 0,
            "vignette": [],
        }
    }
    out.files[""] = json.dumps(doc, indent=4) + "\n"
    return out


# --------------------------------------------------------------------------- CLI


def output_paths(export: FormatExport, output: str | os.PathLike) -> dict[str, Path]:
    """File key -> path: ``output`` itself for ``""``, ``STEM-ID.SUFFIX`` beside it per camera."""
    out = Path(output)
    return {
        key: out if key == "" else out.with_name(f"{out.stem}-{key}{out.suffix}")
        for key in export.files
    }


def run_cli(args) -> int:
    """Run ``gtsam-sphere export --to ros|mrcal|basalt``: 0 on success, 1 if a camera's fit
    is poor (bad input raises)."""
    from ..io.calibration import load_calibration
    from .export import check_target_options

    check_target_options(args)
    calib = load_calibration(args.calibration)
    kwargs = dict(
        region=args.region,
        max_incidence_deg=args.max_incidence_deg,
        n_samples=args.samples,
        source=str(args.calibration),
        camera=args.camera,
    )
    if args.target == "ros":
        result = ros_camera_infos(calib, getattr(args, "ros_model", None) or "auto", **kwargs)
    elif args.target == "mrcal":
        result = mrcal_cameramodels(calib, getattr(args, "mrcal_model", None) or "auto", **kwargs)
    else:
        result = basalt_calibration(calib, getattr(args, "basalt_model", None) or "auto", **kwargs)
    paths = output_paths(result, args.output)
    for key, text in result.files.items():
        print(f"wrote {write_bytes_atomic(paths[key], text.encode('utf-8'))}")
    print(result.summary())
    return fits_exit_status(result.fits, args.max_rms_px)
