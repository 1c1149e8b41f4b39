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
    """Build the camera model from a ``calibration@1`` ``camera`` object."""
    from .correct import correction_from_dict

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
            if cam.get("mapping", "sphere") == "sphere"
            else {k: float(v) for k, v in cam.get("radial", {}).items()},
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"{source}: camera entry is incomplete or malformed ({exc})") from None
    if cam.get("mapping", "sphere") not in ("sphere", "radial"):
        raise DatasetError(f"{source}: unknown camera mapping {cam.get('mapping')!r}")
    if "correction" in cam:
        camera.correction = correction_from_dict(cam["correction"])
    return camera


def load_calibration(path: str | os.PathLike) -> Calibration:
    """Read a ``gtsam-sphere/calibration@1`` file.

    Returns
    -------
    Calibration
        ``.camera.project`` / ``.camera.unproject`` reproduce the model that
        was estimated, learned correction included.
    """
    source = str(path)
    doc = read_json(path)
    _check_format(doc, CALIBRATION_FORMAT, source)
    camera = camera_from_dict(doc.get("camera", {}), source)
    images = doc.get("images", [])
    targets = doc.get("targets", [])
    known = {"format", "model", "units", "camera", "images", "targets", "statistics"}
    return Calibration(
        model=str(doc.get("model", "sphere")),
        camera=camera,
        image_ids=[im["id"] for im in images],
        cam_from_world_R=np.array([im["cam_from_world"]["R"] for im in images], float).reshape(
            -1, 3, 3
        ),
        cam_from_world_t=np.array([im["cam_from_world"]["t"] for im in images], float).reshape(
            -1, 3
        ),
        target_ids=[t["id"] for t in targets],
        target_xyz=np.array([t["xyz"] for t in targets], float).reshape(-1, 3),
        statistics=doc.get("statistics", {}),
        units=doc.get("units", "m"),
        extra={k: v for k, v in doc.items() if k not in known},
    )
