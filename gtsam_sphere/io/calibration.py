"""The calibration result: ``calibration@1`` / ``calibration@2`` (rigs) writing and
:func:`load_calibration`."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.camera import SphereCamera
from ..core.correction_model import correction_from_dict
from ..core.errors import OptionsError
from ..core.rays import bearings
from .dataset import (
    CALIBRATION_FORMAT,
    RIG_CALIBRATION_FORMAT,
    DatasetError,
    _check_format,
    read_json,
    write_json_atomic,
)


@dataclass
class Calibration:
    """A calibrated camera with its adjusted network.

    Attributes
    ----------
    model : str
        ``"sphere"``, ``"brown"``, ``"sphere+knn"``, ...
    camera : SphereCamera
        ``project(points_cam (N,3)) -> (N,2)`` px and ``unproject(uv (N,2)) -> (N,3)``.
    image_ids : list of str, length M
    cam_from_world_R : ndarray, shape (M, 3, 3)
    cam_from_world_t : ndarray, shape (M, 3)
        ``p_cam = R @ p_world + t`` in the dataset's world frame and units.
    target_ids : list of str, length T
    target_xyz : ndarray, shape (T, 3)
        Adjusted target coordinates, world frame.
    statistics : dict
        ``rms_px``, ``n_observations``, ``n_rejected`` and more (see
        ``docs/conventions.md``).
    extra : dict
        Other top-level entries of the file (history, down-weighted
        observations, options, skipped images).
    """

    model: str
    camera: SphereCamera
    image_ids: list[str]
    cam_from_world_R: np.ndarray
    cam_from_world_t: np.ndarray
    target_ids: list[str]
    target_xyz: np.ndarray
    statistics: dict
    units: str = "m"
    extra: dict = field(default_factory=dict)

    def target(self, target_id: str) -> np.ndarray:
        """Adjusted coordinates (3,) of one target."""
        return self.target_xyz[self.target_ids.index(target_id)]

    def bearing(self, uv_px: np.ndarray, hemisphere=1.0) -> list:
        """Unit rays of raw pixels as ``gtsam.Unit3``, for GTSAM's spherical-camera factors.

        Measurement corrections (Brown terms, learned correction) are applied
        (``camera.unproject``). See :mod:`gtsam_sphere.estimation.external` for the
        factors, the angular noise and when to prefer the pixel factor.

        Parameters
        ----------
        uv_px : array_like, shape (N, 2)
            Raw measured pixels (OpenCV convention).
        hemisphere : float or array_like, shape (N,)
            "sphere" mapping only: ``+1`` front half of the image sphere
            (incidence below 90 deg), ``-1`` back half (the mapping is
            two-to-one past 90 deg); ignored by the "radial" mapping.

        Returns
        -------
        list of gtsam.Unit3, length N
            Camera frame (x right, y down, z forward).

        Raises
        ------
        ValueError
            If a pixel has no ray (outside the model's image).
        """
        import gtsam

        rays = bearings(self.camera, uv_px, hemisphere)
        bad = np.flatnonzero(~np.isfinite(rays).all(1))
        if len(bad):
            raise ValueError(
                f"{len(bad)} pixels have no ray (outside the model's image), "
                f"first indices {bad[:5].tolist()}"
            )
        return [gtsam.Unit3(r) for r in rays]

    def to_dict(self) -> dict:
        """The ``gtsam-sphere/calibration@1`` document."""
        camera = camera_to_dict(self.camera)
        doc = {
            "format": CALIBRATION_FORMAT,
            "model": self.model,
            "units": self.units,
            "camera": camera,
            "images": [
                {"id": i, "cam_from_world": {"R": R, "t": t}}
                for i, R, t in zip(self.image_ids, self.cam_from_world_R, self.cam_from_world_t)
            ],
            "targets": [{"id": t, "xyz": p} for t, p in zip(self.target_ids, self.target_xyz)],
            "statistics": self.statistics,
        }
        doc.update(self.extra)
        return doc

    def save(self, path: str | os.PathLike) -> Path:
        """Write the ``calibration@1`` file atomically."""
        return write_json_atomic(path, self.to_dict())


class RigCameraError(DatasetError, AttributeError):
    """``.camera`` of a rig calibration: a rig has no single camera.

    A :class:`DatasetError` (the command line exits 2 with the message) and an
    ``AttributeError`` (``hasattr(calib, "camera")`` is False for a rig).
    """


def _pose_dict(R: np.ndarray, t: np.ndarray) -> dict:
    return {"R": np.asarray(R, float), "t": np.asarray(t, float)}


@dataclass
class RigCalibration:
    """A calibrated rig (``calibration@2``): several cameras fixed to one body.

    The rig frame is the frame of ``camera_ids[0]`` (its ``cam_from_rig`` is the
    identity). Poses map points ``p_cam = R @ p + t``, world frame and units of the
    dataset.

    Attributes
    ----------
    camera_ids : list of str, length C
    cameras : dict of str -> SphereCamera
        Camera id -> model with ``project(points_cam (N,3)) -> (N,2)`` px and
        ``unproject(uv (N,2)) -> (N,3)`` rays, as ``calibration@1``'s camera.
    models : dict of str -> str
        Camera id -> model name (``"radial+knn"``, ...).
    cam_from_rig : dict of str -> (ndarray (3, 3), ndarray (3,))
        Camera id -> ``(R, t)``: ``p_cam = R @ p_rig + t`` (dataset units).
    frame_ids : list of str, length F
    rig_from_world_R : ndarray, shape (F, 3, 3)
    rig_from_world_t : ndarray, shape (F, 3)
        ``p_rig = R @ p_world + t`` per frame.
    image_ids : list of str, length M
    image_camera : list of str, length M
        Camera id of each image.
    image_frame : list of (str or None), length M
        Frame id of each image, ``None`` for an image with a pose of its own.
    cam_from_world_R : ndarray, shape (M, 3, 3)
    cam_from_world_t : ndarray, shape (M, 3)
        Every image's pose; for a framed image ``cam_from_rig * rig_from_world``.
    target_ids : list of str, length T
    target_xyz : ndarray, shape (T, 3)
        Adjusted target coordinates, world frame.
    statistics : dict
        Whole-rig figures (``rms_px``, ``n_observations``, ``n_rejected``, ``trusted``,
        ``distrust``, ``rig_adjustment``) and ``statistics["cameras"][id]`` per camera
        (``rms_px`` and the rest of ``calibration@1``'s statistics, plus the
        precision of ``cam_from_rig``).
    extra : dict
        Other top-level entries of the file.
    """

    camera_ids: list[str]
    cameras: dict[str, SphereCamera]
    models: dict[str, str]
    cam_from_rig: dict[str, tuple[np.ndarray, np.ndarray]]
    frame_ids: list[str]
    rig_from_world_R: np.ndarray
    rig_from_world_t: np.ndarray
    image_ids: list[str]
    image_camera: list[str]
    image_frame: list[str | None]
    cam_from_world_R: np.ndarray
    cam_from_world_t: np.ndarray
    target_ids: list[str]
    target_xyz: np.ndarray
    statistics: dict
    units: str = "m"
    extra: dict = field(default_factory=dict)

    @property
    def model(self) -> str:
        """The model of every camera, or ``"cam0=radial+knn,cam1=radial"`` when they differ."""
        names = [self.models[c] for c in self.camera_ids]
        if len(set(names)) == 1:
            return names[0]
        return ",".join(f"{c}={self.models[c]}" for c in self.camera_ids)

    @property
    def camera(self) -> SphereCamera:
        """Not defined for a rig: raises :class:`RigCameraError` (use ``cameras[id]``).

        A rig has no single camera, and silently handing code written for
        ``calibration@1`` the first camera would pair it with the other cameras'
        images; ``cameras[camera_ids[0]]`` is the rig's reference camera.
        """
        raise RigCameraError(
            f"this is a rig calibration (calibration@2) with cameras {self.camera_ids}: "
            f"use .cameras[id] (e.g. .cameras[{self.camera_ids[0]!r}], the rig's reference "
            "camera) or .camera_calibration(id) for one camera"
        )

    def camera_calibration(self, camera_id: str) -> Calibration:
        """One camera of the rig as a ``calibration@1`` :class:`Calibration`.

        Its images (with their ``cam_from_world``), the rig's targets, and that
        camera's statistics (``statistics["cameras"][camera_id]``).
        """
        if camera_id not in self.cameras:
            raise KeyError(f"no camera {camera_id!r} in this rig (cameras {self.camera_ids})")
        mine = np.array([c == camera_id for c in self.image_camera], bool)
        per_camera = self.extra.get("camera_results", {}).get(camera_id, {})
        return Calibration(
            model=self.models[camera_id],
            camera=self.cameras[camera_id],
            image_ids=[i for i, m in zip(self.image_ids, mine) if m],
            cam_from_world_R=self.cam_from_world_R[mine],
            cam_from_world_t=self.cam_from_world_t[mine],
            target_ids=list(self.target_ids),
            target_xyz=self.target_xyz,
            statistics=dict(self.statistics.get("cameras", {}).get(camera_id, {})),
            units=self.units,
            extra=dict(per_camera) if isinstance(per_camera, dict) else {},
        )

    def to_dict(self) -> dict:
        """The ``gtsam-sphere/calibration@2`` document."""
        cameras = []
        for cid in self.camera_ids:
            R, t = self.cam_from_rig[cid]
            entry = {"id": cid, "model": self.models[cid]}
            entry.update(camera_to_dict(self.cameras[cid]))
            entry["cam_from_rig"] = _pose_dict(R, t)
            cameras.append(entry)
        images = []
        for k, iid in enumerate(self.image_ids):
            entry = {"id": iid, "camera": self.image_camera[k]}
            if self.image_frame[k] is not None:
                entry["frame"] = self.image_frame[k]
            entry["cam_from_world"] = _pose_dict(self.cam_from_world_R[k], self.cam_from_world_t[k])
            images.append(entry)
        doc = {
            "format": RIG_CALIBRATION_FORMAT,
            "model": self.model,
            "units": self.units,
            "cameras": cameras,
            "frames": [
                {"id": f, "rig_from_world": _pose_dict(R, t)}
                for f, R, t in zip(self.frame_ids, self.rig_from_world_R, self.rig_from_world_t)
            ],
            "images": images,
            "targets": [{"id": t, "xyz": p} for t, p in zip(self.target_ids, self.target_xyz)],
            "statistics": self.statistics,
        }
        doc.update(self.extra)
        return doc

    def save(self, path: str | os.PathLike) -> Path:
        """Write the ``calibration@2`` file atomically."""
        return write_json_atomic(path, self.to_dict())


def camera_to_dict(camera: SphereCamera) -> dict:
    """The model-specific camera entries of a calibration file (``calibration@1``'s
    ``camera``, each of ``calibration@2``'s ``cameras[]``), learned correction included."""
    out = camera.to_dict()
    if camera.correction is not None:
        out["correction"] = camera.correction.to_dict()
    return out


def camera_from_dict(cam: dict, source: str = "<calibration>") -> SphereCamera:
    """Build the camera model from a ``calibration@1`` ``camera`` object.

    Raises
    ------
    DatasetError
        Naming ``source`` and the entry when the object is incomplete or malformed.
    """
    if not isinstance(cam, dict):
        raise DatasetError(f"{source}: 'camera' must be an object, got {type(cam).__name__}")
    mapping = cam.get("mapping", "sphere")
    if mapping not in ("sphere", "radial"):
        raise DatasetError(f"{source}: unknown camera mapping {mapping!r}")
    for key in ("brown", "radial"):
        if key in cam and not isinstance(cam[key], dict):
            raise DatasetError(f"{source}: camera.{key} must be an object of named terms")
    try:
        camera = SphereCamera(
            width=int(cam["width"]),
            height=int(cam["height"]),
            xp=float(cam["xp_px"]),
            yp=float(cam["yp_px"]),
            c=float(cam["c_px"]),
            brown={k: float(v) for k, v in cam.get("brown", {}).items()},
            brown_scale_px=float(cam.get("brown_scale_px", 0.0)),
            radial=None
            if mapping == "sphere"
            else {k: float(v) for k, v in cam.get("radial", {}).items()},
            observed_alpha_rad=None
            if cam.get("observed_alpha_rad") is None
            else float(cam["observed_alpha_rad"]),
            valid_region_alpha_rad=cam.get("valid_region_alpha_rad"),
        )
    except KeyError as exc:
        raise DatasetError(f"{source}: camera entry misses {exc}") from None
    except (TypeError, ValueError, OverflowError) as exc:
        raise DatasetError(f"{source}: camera entry is malformed ({exc})") from None
    if "correction" in cam:
        try:
            camera.correction = correction_from_dict(cam["correction"])
        except KeyError as exc:
            raise DatasetError(f"{source}: camera.correction misses {exc}") from None
        except (TypeError, ValueError, AttributeError) as exc:
            raise DatasetError(f"{source}: camera.correction is malformed ({exc})") from None
    return camera


def _observed_field_from_statistics(camera: SphereCamera, statistics: dict) -> None:
    """A file written before ``camera.observed_alpha_rad`` existed: take its statistics'.

    ``statistics.max_incidence_deg`` (every calibration writes it) is the same
    figure over all observations; without either the camera has no observed field.
    """
    if camera.observed_alpha_rad is not None:
        return
    deg = statistics.get("max_incidence_deg")
    if isinstance(deg, (int, float)) and 0 < float(deg) <= 180:
        camera.observed_alpha_rad = float(np.radians(float(deg)))


def _entries(doc: dict, key: str, source: str) -> list:
    items = doc.get(key, [])
    if not isinstance(items, list):
        raise DatasetError(f"{source}: '{key}' must be a list, got {type(items).__name__}")
    for k, item in enumerate(items):
        if not isinstance(item, dict) or "id" not in item:
            raise DatasetError(f"{source}: {key}[{k}] must be an object with an 'id'")
    return items


def _finite_array(value, shape: tuple, what: str, source: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise DatasetError(f"{source}: {what} must be numbers of shape {shape}") from None
    if arr.shape != shape:
        raise DatasetError(f"{source}: {what} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise DatasetError(f"{source}: {what} holds NaN or inf")
    return arr


def _pose(obj, what: str, source: str) -> tuple[np.ndarray, np.ndarray]:
    """``(R (3, 3), t (3,))`` of a ``{"R", "t"}`` pose object; ``what`` names it in messages."""
    if not isinstance(obj, dict):
        raise DatasetError(f"{source}: {what} is not a pose object {{R, t}}")
    R = _finite_array(obj.get("R"), (3, 3), f"{what} R", source)
    t = _finite_array(obj.get("t"), (3,), f"{what} t", source)
    return R, t


def _image_poses(images: list, source: str) -> tuple[np.ndarray, np.ndarray]:
    R, t = [], []
    for im in images:
        if not isinstance(im.get("cam_from_world"), dict):
            raise DatasetError(f"{source}: image {im['id']!r} has no cam_from_world {{R, t}}")
        Ri, ti = _pose(im["cam_from_world"], f"image {im['id']!r}", source)
        R.append(Ri)
        t.append(ti)
    return np.array(R, float).reshape(-1, 3, 3), np.array(t, float).reshape(-1, 3)


def _statistics(doc: dict, source: str, version: str) -> dict:
    statistics = doc.get("statistics", {})
    if not isinstance(statistics, dict):
        raise DatasetError(f"{source}: 'statistics' must be an object")
    for key in ("rms_px", "n_observations", "n_rejected"):
        if key not in statistics:
            raise DatasetError(f"{source}: statistics misses {key!r} ({version} requires it)")
    return statistics


def load_calibration(path: str | os.PathLike) -> Calibration | RigCalibration:
    """Read a ``gtsam-sphere/calibration@1`` or ``calibration@2`` (rig) file.

    Parameters
    ----------
    path : str or PathLike

    Returns
    -------
    Calibration or RigCalibration
        ``calibration@1``: a :class:`Calibration`, whose ``.camera.project`` /
        ``.camera.unproject`` reproduce the model that was estimated, learned
        correction included. ``calibration@2``: a :class:`RigCalibration` with
        ``.cameras[id]`` (the same per camera) and ``.cam_from_rig[id] = (R, t)``;
        its ``.camera`` raises (a rig has no single camera).

    Raises
    ------
    DatasetError
        Naming the file and the entry for a missing, malformed or non-finite item.
    """
    source = str(path)
    doc = read_json(path)
    if isinstance(doc, dict) and doc.get("format") == RIG_CALIBRATION_FORMAT:
        return _rig_calibration_from_doc(doc, source)
    _check_format(doc, CALIBRATION_FORMAT, source)
    camera = camera_from_dict(doc.get("camera", {}), source)
    images = _entries(doc, "images", source)
    targets = _entries(doc, "targets", source)
    R, t = _image_poses(images, source)
    xyz = [_finite_array(tg.get("xyz"), (3,), f"target {tg['id']!r} xyz", source) for tg in targets]
    statistics = _statistics(doc, source, "calibration@1")
    _observed_field_from_statistics(camera, statistics)
    known = {"format", "model", "units", "camera", "images", "targets", "statistics"}
    return Calibration(
        model=str(doc.get("model", "sphere")),
        camera=camera,
        image_ids=[str(im["id"]) for im in images],
        cam_from_world_R=R,
        cam_from_world_t=t,
        target_ids=[str(tg["id"]) for tg in targets],
        target_xyz=np.array(xyz, float).reshape(-1, 3),
        statistics=statistics,
        units=doc.get("units", "m"),
        extra={k: v for k, v in doc.items() if k not in known},
    )


def _rig_calibration_from_doc(doc: dict, source: str) -> RigCalibration:
    """Validate a ``calibration@2`` document into a :class:`RigCalibration`."""
    cameras = _entries(doc, "cameras", source)
    if not cameras:
        raise DatasetError(f"{source}: 'cameras' must list at least one camera")
    camera_ids: list[str] = []
    models, models_by_id, cam_from_rig = {}, {}, {}
    for k, cam in enumerate(cameras):
        cid = cam["id"]
        if not isinstance(cid, str) or cid in models:
            raise DatasetError(f"{source}: cameras[{k}] id {cid!r} is not a new string id")
        camera_ids.append(cid)
        models[cid] = camera_from_dict(cam, f"{source}: camera {cid!r}")
        models_by_id[cid] = str(cam.get("model", "sphere"))
        if not isinstance(cam.get("cam_from_rig"), dict):
            raise DatasetError(f"{source}: camera {cid!r} has no cam_from_rig {{R, t}}")
        cam_from_rig[cid] = _pose(cam["cam_from_rig"], f"camera {cid!r} cam_from_rig", source)
    frames = _entries(doc, "frames", source)
    frame_ids = [str(f["id"]) for f in frames]
    frame_poses = [
        _pose(f.get("rig_from_world"), f"frame {f['id']!r} rig_from_world", source) for f in frames
    ]
    images = _entries(doc, "images", source)
    image_camera, image_frame = [], []
    for im in images:
        if im.get("camera") not in models:
            raise DatasetError(
                f"{source}: image {im['id']!r} names unknown camera {im.get('camera')!r}"
            )
        image_camera.append(im["camera"])
        frame = im.get("frame")
        if frame is not None and str(frame) not in frame_ids:
            raise DatasetError(f"{source}: image {im['id']!r} names unknown frame {frame!r}")
        image_frame.append(None if frame is None else str(frame))
    R, t = _image_poses(images, source)
    targets = _entries(doc, "targets", source)
    xyz = [_finite_array(tg.get("xyz"), (3,), f"target {tg['id']!r} xyz", source) for tg in targets]
    statistics = _statistics(doc, source, "calibration@2")
    per_camera = statistics.get("cameras")
    if not isinstance(per_camera, dict) or any(
        not isinstance(per_camera.get(c), dict) or "rms_px" not in per_camera[c] for c in camera_ids
    ):
        raise DatasetError(
            f"{source}: statistics.cameras must give each camera's rms_px "
            "(calibration@2 requires it)"
        )
    for cid in camera_ids:
        _observed_field_from_statistics(models[cid], per_camera[cid])
    known = {"format", "model", "units", "cameras", "frames", "images", "targets", "statistics"}
    return RigCalibration(
        camera_ids=camera_ids,
        cameras=models,
        models=models_by_id,
        cam_from_rig=cam_from_rig,
        frame_ids=frame_ids,
        rig_from_world_R=np.array([p[0] for p in frame_poses], float).reshape(-1, 3, 3),
        rig_from_world_t=np.array([p[1] for p in frame_poses], float).reshape(-1, 3),
        image_ids=[str(im["id"]) for im in images],
        image_camera=image_camera,
        image_frame=image_frame,
        cam_from_world_R=R,
        cam_from_world_t=t,
        target_ids=[str(tg["id"]) for tg in targets],
        target_xyz=np.array(xyz, float).reshape(-1, 3),
        statistics=statistics,
        units=doc.get("units", "m"),
        extra={k: v for k, v in doc.items() if k not in known},
    )


def single_camera(calib, camera_id: str | None, source: str, hint: str = "") -> Calibration:
    """The ``calibration@1`` a one-camera command works on, by the ``--camera`` rules.

    A rig (``calibration@2``) needs ``camera_id`` and gives that camera
    (:meth:`RigCalibration.camera_calibration`); a single-camera calibration takes none.

    Parameters
    ----------
    calib : Calibration or RigCalibration
    camera_id : str or None
        The ``--camera`` option.
    source : str
        The calibration file's name, for the messages.
    hint : str
        Appended to the message asking for ``--camera`` (e.g. the rig commands).

    Raises
    ------
    OptionsError
        A rig without ``camera_id``, an unknown camera, or ``camera_id`` with a
        single-camera calibration; the message names the item.
    """
    if hasattr(calib, "camera_ids"):
        if camera_id is None:
            raise OptionsError(
                f"{source} is a rig (cameras {calib.camera_ids}): name the camera with "
                f"--camera ID{hint}"
            )
        if camera_id not in calib.cameras:
            raise OptionsError(
                f"--camera {camera_id!r}: no such camera in {source} (cameras {calib.camera_ids})"
            )
        return calib.camera_calibration(camera_id)
    if camera_id is not None:
        raise OptionsError(f"--camera {camera_id!r}: {source} is a single-camera calibration")
    return calib
