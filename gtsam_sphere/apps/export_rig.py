"""Export a calibrated rig (``calibration@2``): a Kalibr camchain, an OpenCV stereo pair.

Each camera's standard model is fitted to its calibrated ray field by
:func:`gtsam_sphere.apps.export.export_calibration` (the single-camera export:
its fit residual, in pixels, is printed and written with the file); the
extrinsics come from the calibration's ``cam_from_rig`` as they are.

``kalibr``
    A Kalibr ``camchain.yaml``: ``cam0 .. camN`` in the calibration's camera
    order, each with ``camera_model``, ``intrinsics``, ``distortion_model``,
    ``distortion_coeffs``, ``resolution``, ``cam_overlaps`` (the cameras that
    saw a target in common with it in one frame) and, from ``cam1`` on,
    ``T_cn_cnm1``: the 4x4 transform taking points of camera ``n-1`` to
    camera ``n`` (``cam_from_rig[n] * inverse(cam_from_rig[n-1])``), in
    metres. Models (:data:`KALIBR_MODELS`): ``pinhole-equi`` (Kannala-Brandt,
    OpenCV fisheye; rays below 90 deg only), ``omni-radtan`` (unified / Mei,
    ``cv2.omnidir``), ``ds-none`` (double sphere), ``eucm-none`` (extended unified
    model, on request); ``auto`` fits the first three and
    keeps, per camera, the one that covers most of the observed region, then the
    smallest residual.
``opencv-stereo``
    Two cameras (the first two unless named): ``R``, ``T`` with OpenCV's
    ``stereoCalibrate`` meaning (``p2 = R p1 + T``, camera 2 from camera 1, in
    the calibration's units), each camera's ``K``, ``D`` (and ``xi`` for
    ``omnidir``) and image size, in a file ``cv2.FileStorage`` reads (YAML or
    JSON by the output's extension). Both cameras get one model, as OpenCV's
    stereo functions need: ``fisheye`` (``cv2.fisheye``) or ``omnidir``
    (``cv2.omnidir``); ``auto`` takes ``fisheye`` when it covers both
    cameras' observed regions and ``omnidir`` otherwise.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.errors import OptionsError
from ..io.dataset import DatasetError, write_bytes_atomic
from .export import ExportResult, export_calibration

logger = logging.getLogger(__name__)

#: Kalibr model name -> single-camera export target
KALIBR_MODELS: dict[str, str] = {
    "pinhole-equi": "kalibr-equi",
    "omni-radtan": "kalibr-omni",
    "ds-none": "kalibr-ds",
    "eucm-none": "kalibr-eucm",
}
#: the models ``auto`` chooses from (``eucm-none`` on request: the double sphere, as many
#: parameters, fits wide lenses at least as well)
KALIBR_AUTO: tuple[str, ...] = ("pinhole-equi", "omni-radtan", "ds-none")
#: OpenCV stereo model -> single-camera export target
STEREO_MODELS: dict[str, str] = {"fisheye": "opencv-fisheye", "omnidir": "opencv-omnidir"}
#: metres per unit of the calibration's ``units`` (Kalibr works in metres)
_METRES = {"m": 1.0, "cm": 0.01, "mm": 0.001}
#: a fit covering at least this fraction of the observed region counts as complete
_FULL_COVERAGE = 0.999


@dataclass
class RigExport:
    """What a rig export wrote: the text and each camera's fitted model.

    Attributes
    ----------
    text : str
        The file's content.
    fits : dict of str -> ExportResult
        Camera id -> fitted standard model (with its fit residual).
    """

    text: str
    fits: dict[str, ExportResult]

    def summary(self) -> str:
        """One line per camera: model and fit residual."""
        lines = []
        for cid, fit in self.fits.items():
            obs = fit.observations
            at_obs = (
                f", RMS {obs['rms_px']:.4f} px at {obs['n_covered']}/{obs['n']} observations"
                if obs
                else ""
            )
            lines.append(
                f"  camera {cid}: {fit.target}, fit RMS {fit.rms_px:.4f} px, "
                f"max {fit.max_px:.4f} px, covers {100 * fit.coverage:.1f}% of the observed "
                f"region{at_obs}{_outside_text(fit)}"
            )
        return "\n".join(lines)


def _outside_text(fit: ExportResult) -> str:
    """``", outside the observed region (a-b deg) max x px[, do not use past y deg]"``."""
    o = fit.outside
    if not o:
        return ""
    text = f", outside the observed region ({o['from_deg']:.1f}-{o['to_deg']:.1f} deg) "
    if not o.get("n"):
        return text + "no image pixel in the model's domain"
    text += f"max {o['max_px']:.4f} px"
    if o.get("exceeds"):
        text += f", do not use past {o['valid_to_deg']:.1f} deg"
    return text


def _check_rig(calib, source: str) -> None:
    if not hasattr(calib, "camera_ids"):
        raise OptionsError(
            f"{source} is a single-camera calibration (calibration@1): --to kalibr / "
            "opencv-stereo export a rig (calibration@2); use --to kalibr-equi, kalibr-omni, "
            "kalibr-ds or an opencv-* target"
        )


def relative_pose(calib, from_id: str, to_id: str) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` taking points of camera ``from_id`` to camera ``to_id``: ``p_to = R p_from + t``.

    ``cam_from_rig[to] * inverse(cam_from_rig[from])``, in the calibration's units.
    """
    Ra, ta = calib.cam_from_rig[from_id]
    Rb, tb = calib.cam_from_rig[to_id]
    R = Rb @ Ra.T
    return R, tb - R @ ta


def camera_overlaps(calib) -> dict[str, list[int]]:
    """Kalibr's ``cam_overlaps``: per camera, the indices of the cameras that saw a target in
    common with it in one frame (from the calibration's stored observations; empty without
    them)."""
    frame_of = dict(zip(calib.image_ids, calib.image_frame))
    seen: dict[str, set] = {}
    for cid in calib.camera_ids:
        result = calib.extra.get("camera_results", {}).get(cid, {})
        obs = result.get("observations") if isinstance(result, dict) else None
        pairs = set()
        if isinstance(obs, dict) and isinstance(obs.get("image"), list):
            for iid, tid in zip(obs["image"], obs.get("target") or []):
                frame = frame_of.get(iid)
                if frame is not None:
                    pairs.add((frame, tid))
        seen[cid] = pairs
    ids = calib.camera_ids
    return {a: [k for k, b in enumerate(ids) if b != a and seen[a] & seen[b]] for a in ids}


def fit_camera(calib, camera_id: str, target: str, **kwargs) -> ExportResult:
    """Fit the single-camera export ``target`` to one camera of a rig."""
    return export_calibration(calib.camera_calibration(camera_id), target, **kwargs)


def _best(fits: list[ExportResult]) -> ExportResult:
    """The fit covering most of the observed region, then with the smallest residual."""

    def key(f: ExportResult):
        rms = f.rms_px if math.isfinite(f.rms_px) else math.inf
        return (-round(f.coverage, 3), rms)

    return min(fits, key=key)


def _fit_kalibr(calib, cid: str, model: str, source: str, **kwargs) -> ExportResult:
    names = list(KALIBR_AUTO) if model == "auto" else [model]
    fits, errors = [], []
    for name in names:
        try:
            fits.append(fit_camera(calib, cid, KALIBR_MODELS[name], source=source, **kwargs))
        except DatasetError as exc:
            errors.append(f"{name}: {exc}")
    if not fits:
        raise DatasetError(f"camera {cid!r}: no Kalibr model fits ({'; '.join(errors)})")
    return _best(fits)


def _seq(values) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def kalibr_camchain(
    calib,
    model: str = "auto",
    camera_models: dict[str, str] | None = None,
    source: str | None = None,
    **kwargs,
) -> RigExport:
    """A Kalibr ``camchain.yaml`` of a rig calibration.

    Parameters
    ----------
    calib : RigCalibration
    model : str
        ``"auto"`` or one of :data:`KALIBR_MODELS`: the cameras not in ``camera_models``.
    camera_models : dict of str -> str, optional
        Camera id -> model, for some cameras.
    source : str, optional
        Calibration file name, written in a comment.
    **kwargs
        ``region``, ``max_incidence_deg``, ``n_samples`` of
        :func:`~gtsam_sphere.apps.export.export_calibration`.

    Returns
    -------
    RigExport

    Raises
    ------
    OptionsError
        A single-camera calibration, or an unknown ``model``.
    DatasetError
        A camera no model fits.
    """
    src = source or "calibration"
    _check_rig(calib, src)
    models = dict(camera_models or {})
    models.update({cid: model for cid in calib.camera_ids if cid not in models})
    for cid, name in models.items():
        if cid not in calib.cameras:
            raise OptionsError(
                f"--kalibr-model {cid}={name}: no camera {cid!r} in {src} "
                f"(cameras {calib.camera_ids})"
            )
        if name != "auto" and name not in KALIBR_MODELS:
            raise OptionsError(
                f"--kalibr-model {name!r}: choose auto or one of {', '.join(KALIBR_MODELS)}"
            )
    scale = _METRES.get(str(calib.units))
    if scale is None:
        logger.warning(
            "units %r are not metres, cm or mm: T_cn_cnm1 translations are written in %s, "
            "Kalibr expects metres",
            calib.units,
            calib.units,
        )
        scale = 1.0
    fits = {
        cid: _fit_kalibr(calib, cid, models.get(cid, "auto"), src, **kwargs)
        for cid in calib.camera_ids
    }
    overlaps = camera_overlaps(calib)
    lines = [f"# Kalibr camchain exported by gtsam-sphere from {src}"]
    lines.append(
        "# T_cn_cnm1: points of camera n-1 to camera n (metres), from the calibration's "
        "cam_from_rig"
    )
    for n, cid in enumerate(calib.camera_ids):
        fit = fits[cid]
        lines.append(f"# cam{n} = camera {cid!r} ({calib.models[cid]}), fitted {fit.target}:")
        lines.extend(f"#   {line}" for line in fit.summary().splitlines())
    for n, cid in enumerate(calib.camera_ids):
        fit = fits[cid]
        p = fit.params
        if fit.family == "kannala-brandt":
            cam_model, dist_model = "pinhole", "equidistant"
            intr, dist = [p["fx"], p["fy"], p["cx"], p["cy"]], list(fit.D)
        elif fit.family == "omni":
            cam_model, dist_model = "omni", "radtan"
            intr, dist = [p["xi"], p["fx"], p["fy"], p["cx"], p["cy"]], list(fit.D)
        elif fit.family == "eucm":
            cam_model, dist_model = "eucm", "none"
            intr, dist = [p["alpha"], p["beta"], p["fx"], p["fy"], p["cx"], p["cy"]], []
        else:
            cam_model, dist_model = "ds", "none"
            intr, dist = [p["xi"], p["alpha"], p["fx"], p["fy"], p["cx"], p["cy"]], []
        lines.append(f"cam{n}:")
        if n > 0:
            R, t = relative_pose(calib, calib.camera_ids[n - 1], cid)
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = t * scale
            lines.append("  T_cn_cnm1:")
            lines.extend(f"  - {_seq(row)}" for row in T)
        lines += [
            f"  camera_model: {cam_model}",
            f"  intrinsics: {_seq(intr)}",
            f"  distortion_model: {dist_model}",
            f"  distortion_coeffs: {_seq(dist)}",
            f"  resolution: [{int(fit.width)}, {int(fit.height)}]",
            f"  cam_overlaps: [{', '.join(str(k) for k in overlaps[cid])}]",
            f"  rostopic: /cam{n}/image_raw",
            f"  # fit RMS {fit.rms_px:.4f} px, max {fit.max_px:.4f} px, "
            f"coverage {100 * fit.coverage:.1f}%{_outside_text(fit)}",
        ]
    return RigExport("\n".join(lines) + "\n", fits)


def opencv_stereo(
    calib,
    cameras: tuple[str, str] | None = None,
    model: str = "auto",
    fmt: str = "yaml",
    source: str | None = None,
    **kwargs,
) -> RigExport:
    """An OpenCV stereo pair (``R``, ``T``, ``K1, D1, K2, D2``) of two cameras of a rig.

    Parameters
    ----------
    calib : RigCalibration
    cameras : (str, str), optional
        Camera ids; default the first two.
    model : {"auto", "fisheye", "omnidir"}
    fmt : {"yaml", "json"}
        ``cv2.FileStorage`` format of the text.
    source : str, optional
    **kwargs
        As :func:`kalibr_camchain`.

    Returns
    -------
    RigExport

    Raises
    ------
    OptionsError
        A single-camera calibration, fewer than two cameras, an unknown camera
        or model.
    """
    import cv2

    src = source or "calibration"
    _check_rig(calib, src)
    if cameras is None:
        if len(calib.camera_ids) < 2:
            raise OptionsError(f"--to opencv-stereo: {src} has only camera(s) {calib.camera_ids}")
        cameras = (calib.camera_ids[0], calib.camera_ids[1])
    if len(cameras) != 2 or cameras[0] == cameras[1]:
        raise OptionsError(f"--stereo-cameras needs two different camera ids, got {cameras}")
    for cid in cameras:
        if cid not in calib.cameras:
            raise OptionsError(
                f"--stereo-cameras: no camera {cid!r} in {src} (cameras {calib.camera_ids})"
            )
    if model != "auto" and model not in STEREO_MODELS:
        raise OptionsError(
            f"--stereo-model {model!r}: choose auto or one of {', '.join(STEREO_MODELS)}"
        )
    if fmt not in ("yaml", "json"):
        raise OptionsError(f"opencv-stereo writes YAML or JSON, not {fmt!r}")
    fits: dict[str, ExportResult] = {}
    if model in ("auto", "fisheye"):
        fits = {c: fit_camera(calib, c, "opencv-fisheye", source=src, **kwargs) for c in cameras}
        if model == "auto" and any(f.coverage < _FULL_COVERAGE for f in fits.values()):
            fits = {}
    if not fits:
        fits = {c: fit_camera(calib, c, "opencv-omnidir", source=src, **kwargs) for c in cameras}
    chosen = "fisheye" if fits[cameras[0]].family == "kannala-brandt" else "omnidir"
    R, T = relative_pose(calib, cameras[0], cameras[1])
    flags = cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY
    flags |= cv2.FILE_STORAGE_FORMAT_JSON if fmt == "json" else cv2.FILE_STORAGE_FORMAT_YAML
    fs = cv2.FileStorage("", flags)
    if fmt == "yaml":
        fs.writeComment(f"OpenCV stereo pair exported by gtsam-sphere from {src}")
        fs.writeComment("R, T: p2 = R p1 + T (camera 2 from camera 1, as cv2.stereoCalibrate)")
        for k, cid in enumerate(cameras, 1):
            fs.writeComment(
                f"camera {k} = {cid!r}: {fits[cid].target} fit RMS {fits[cid].rms_px:.4f} px, "
                f"max {fits[cid].max_px:.4f} px, coverage {100 * fits[cid].coverage:.1f}%"
            )
    fs.write("format", "gtsam-sphere/export-opencv-stereo@1")
    fs.write("model", chosen)
    fs.write("units", str(calib.units))
    for k, cid in enumerate(cameras, 1):
        fit = fits[cid]
        fs.write(f"camera_{k}", cid)
        fs.write(f"image_size_{k}", np.array([[fit.width, fit.height]], np.int32))
        fs.write(f"K{k}", fit.K)
        fs.write(f"D{k}", fit.D.reshape(1, -1))
        if chosen == "omnidir":
            fs.write(f"xi{k}", np.array([[fit.params["xi"]]]))
        fs.write(f"fit_rms_px_{k}", float(fit.rms_px))
        fs.write(f"fit_max_px_{k}", float(fit.max_px))
        fs.write(f"fit_coverage_{k}", float(fit.coverage))
        if fit.outside:
            o = fit.outside
            fs.write(f"fit_inside_to_deg_{k}", float(o["from_deg"]))
            fs.write(f"fit_outside_to_deg_{k}", float(o["to_deg"]))
            fs.write(f"fit_outside_rms_px_{k}", float(o["rms_px"]))
            fs.write(f"fit_outside_max_px_{k}", float(o["max_px"]))
            fs.write(f"fit_valid_to_deg_{k}", float(o["valid_to_deg"]))
    fs.write("R", R)
    fs.write("T", T.reshape(3, 1))
    text = fs.releaseAndGetString()
    return RigExport(text, fits)


def parse_kalibr_models(values: list[str] | None) -> tuple[str, dict[str, str]]:
    """``--kalibr-model`` values (``MODEL`` for the cameras not named, ``ID=MODEL`` per
    camera) -> ``(model, camera_models)`` of :func:`kalibr_camchain`."""
    default, per_camera = None, {}
    for value in values or []:
        cid, sep, name = value.partition("=")
        if not sep:
            if default is not None:
                raise OptionsError(f"--kalibr-model {value!r}: a second model for every camera")
            default = value.strip()
            continue
        cid, name = cid.strip(), name.strip()
        if not cid or cid in per_camera:
            raise OptionsError(f"--kalibr-model {value!r}: expected ID=MODEL, each camera once")
        per_camera[cid] = name
    return default or "auto", per_camera


def write_rig_export(export: RigExport, path: str | os.PathLike) -> Path:
    """Write ``export.text`` atomically."""
    return write_bytes_atomic(path, export.text.encode("utf-8"))


def stereo_format(path: str | os.PathLike) -> str:
    """``"yaml"`` or ``"json"`` from the output's extension (``--output``)."""
    ext = Path(path).suffix.lower()
    if ext in (".yaml", ".yml"):
        return "yaml"
    if ext == ".json":
        return "json"
    raise OptionsError(
        f"--output {str(path)!r}: opencv-stereo writes .yaml/.yml or .json (cv2.FileStorage)"
    )


def run_cli(args) -> int:
    """Run ``gtsam-sphere export --to kalibr|opencv-stereo`` on a rig; 0 on success, 1 if
    a camera's fit is poor (bad input raises)."""
    from ..core.errors import OptionsError
    from ..io.calibration import load_calibration
    from .export import check_target_options

    check_target_options(args)
    if args.camera is not None:
        raise OptionsError(f"--camera applies to single-camera targets, not --to {args.target}")
    calib = load_calibration(args.calibration)

    kwargs = dict(
        region=args.region,
        max_incidence_deg=args.max_incidence_deg,
        n_samples=args.samples,
        source=str(args.calibration),
    )
    if args.target == "kalibr":
        model, per_camera = parse_kalibr_models(args.kalibr_model)
        result = kalibr_camchain(calib, model, per_camera, **kwargs)
    else:
        cameras = None
        if args.stereo_cameras:
            cameras = tuple(c.strip() for c in args.stereo_cameras.split(","))
        fmt = stereo_format(args.output)
        result = opencv_stereo(calib, cameras=cameras, model=args.stereo_model, fmt=fmt, **kwargs)
    path = write_rig_export(result, args.output)
    print(f"wrote {path}")
    print(result.summary())
    return fits_exit_status(result.fits, args.max_rms_px)


def fits_exit_status(fits: dict, max_rms_px: float) -> int:
    """Exit status of an export: 1 (and a warning naming them) when a camera's fit RMS
    exceeds ``max_rms_px`` (px) or its fit did not converge, else 0.

    Parameters
    ----------
    fits : dict of str -> fit
        Per camera id, objects with ``rms_px`` (px) and ``converged``.
    max_rms_px : float
    """
    bad = [cid for cid, fit in fits.items() if not (fit.rms_px <= max_rms_px) or not fit.converged]
    if bad:
        logger.warning(
            "camera(s) %s: fit RMS exceeds %g px or the fit did not converge: the exported "
            "model does not reproduce the calibration",
            ", ".join(bad),
            max_rms_px,
        )
        return 1
    return 0
