"""The calibration result: ``calibration@1`` writing and :func:`load_calibration`."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .camera import SphereCamera
from .dataset import CALIBRATION_FORMAT, DatasetError, _check_format, read_json, write_json_atomic


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
        (``camera.unproject``). See :mod:`gtsam_sphere.external` for the
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

        from .external import bearings

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
        camera = self.camera.to_dict()
        if self.camera.correction is not None:
            camera["correction"] = self.camera.correction.to_dict()
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


def camera_from_dict(cam: dict, source: str = "<calibration>") -> SphereCamera:
    """Build the camera model from a ``calibration@1`` ``camera`` object.

    Raises
    ------
    DatasetError
        Naming ``source`` and the entry when the object is incomplete or malformed.
    """
    from .correct import correction_from_dict

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


def load_calibration(path: str | os.PathLike) -> Calibration:
    """Read a ``gtsam-sphere/calibration@1`` file.

    Parameters
    ----------
    path : str or PathLike

    Returns
    -------
    Calibration
        ``.camera.project`` / ``.camera.unproject`` reproduce the model that
        was estimated, learned correction included.

    Raises
    ------
    DatasetError
        Naming the file and the entry for a missing, malformed or non-finite item.
    """
    source = str(path)
    doc = read_json(path)
    _check_format(doc, CALIBRATION_FORMAT, source)
    camera = camera_from_dict(doc.get("camera", {}), source)
    images = _entries(doc, "images", source)
    targets = _entries(doc, "targets", source)
    R, t = [], []
    for im in images:
        pose = im.get("cam_from_world")
        if not isinstance(pose, dict):
            raise DatasetError(f"{source}: image {im['id']!r} has no cam_from_world {{R, t}}")
        R.append(_finite_array(pose.get("R"), (3, 3), f"image {im['id']!r} R", source))
        t.append(_finite_array(pose.get("t"), (3,), f"image {im['id']!r} t", source))
    xyz = [_finite_array(tg.get("xyz"), (3,), f"target {tg['id']!r} xyz", source) for tg in targets]
    statistics = doc.get("statistics", {})
    if not isinstance(statistics, dict):
        raise DatasetError(f"{source}: 'statistics' must be an object")
    for key in ("rms_px", "n_observations", "n_rejected"):
        if key not in statistics:
            raise DatasetError(f"{source}: statistics misses {key!r} (calibration@1 requires it)")
    known = {"format", "model", "units", "camera", "images", "targets", "statistics"}
    return Calibration(
        model=str(doc.get("model", "sphere")),
        camera=camera,
        image_ids=[str(im["id"]) for im in images],
        cam_from_world_R=np.array(R, float).reshape(-1, 3, 3),
        cam_from_world_t=np.array(t, float).reshape(-1, 3),
        target_ids=[str(tg["id"]) for tg in targets],
        target_xyz=np.array(xyz, float).reshape(-1, 3),
        statistics=statistics,
        units=doc.get("units", "m"),
        extra={k: v for k, v in doc.items() if k not in known},
    )
