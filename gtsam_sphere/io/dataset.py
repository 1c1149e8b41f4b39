"""The data contract: ``dataset@1``, ``dataset@2`` (rigs) and ``checkpoints@1`` in, atomic JSON out.

See ``../shared/spec/dataset.md`` (mirrored in ``docs/conventions.md``).
Every problem found in an input file is reported with the item it concerns
(target id, image id, observation index). Problems that make the file
unusable raise :class:`DatasetError`; problems that only remove an
observation or an image are recorded in :attr:`Dataset.dropped` /
:attr:`Dataset.skipped_images` and counted in the output statistics.
"""

from __future__ import annotations

import errno
import json
import math
import numbers
import os
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..core.errors import DatasetError, InputError

DATASET_FORMAT = "gtsam-sphere/dataset@1"
RIG_DATASET_FORMAT = "gtsam-sphere/dataset@2"
CHECKPOINTS_FORMAT = "gtsam-sphere/checkpoints@1"
CALIBRATION_FORMAT = "gtsam-sphere/calibration@1"
RIG_CALIBRATION_FORMAT = "gtsam-sphere/calibration@2"

#: Largest accepted image side (px). Beyond this, pixel arithmetic leaves the range
#: where float64 resolves a tenth of a pixel, and no real sensor comes close.
MAX_IMAGE_SIDE_PX = 1_000_000
#: Largest accepted absolute coordinate or target sigma (object units). Larger numbers
#: overflow when squared inside the adjustment long before they can be meaningful.
MAX_ABS_COORDINATE = 1e12
#: Smallest accepted positive target sigma (object units); use 0 for exact control.
MIN_POSITIVE_SIGMA = 1e-12


@dataclass
class Dataset:
    """A validated ``dataset@1``, flattened into arrays.

    Attributes
    ----------
    width, height : int
        Image size in pixels.
    units : str
        Object-space units (``"m"`` unless the file says otherwise).
    target_ids : list of str, length T
    target_xyz : ndarray, shape (T, 3)
        Approximate world coordinates, in ``units``.
    target_sigma : ndarray, shape (T,)
        Isotropic standard deviation of ``target_xyz`` in ``units``; ``0`` exact
        control, ``NaN`` when absent (free network).
    image_ids : list of str, length M
        Images kept (those with enough observations).
    obs_image : ndarray of int, shape (N,)
        Index into ``image_ids`` per observation.
    obs_target : ndarray of int, shape (N,)
        Index into ``target_ids`` per observation.
    uv_px : ndarray, shape (N, 2)
        Observed pixel positions, ``(0, 0)`` = centre of the top-left pixel.
    skipped_images : list of (str, str)
        ``(image id, reason)`` for images left out.
    dropped : list of (str, str, str)
        ``(image id, target id, reason)`` for observations left out.
    """

    width: int
    height: int
    units: str
    target_ids: list[str]
    target_xyz: np.ndarray
    target_sigma: np.ndarray
    image_ids: list[str]
    obs_image: np.ndarray
    obs_target: np.ndarray
    uv_px: np.ndarray
    skipped_images: list[tuple[str, str]] = field(default_factory=list)
    dropped: list[tuple[str, str, str]] = field(default_factory=list)
    source: str | None = None
    n_input_observations: int = 0

    @property
    def n_observations(self) -> int:
        """Number of observations kept."""
        return len(self.obs_image)

    def target_index(self) -> dict[str, int]:
        """Map target id -> row of ``target_xyz``."""
        return {t: i for i, t in enumerate(self.target_ids)}

    def subset_images(self, keep: np.ndarray, reasons: dict[int, str] | None = None) -> Dataset:
        """Return a copy keeping images where ``keep`` (M,) is True.

        Images removed are appended to ``skipped_images`` with ``reasons[i]``.
        """
        keep = np.asarray(keep, bool)
        reasons = reasons or {}
        new_index = -np.ones(len(self.image_ids), int)
        new_index[keep] = np.arange(keep.sum())
        obs_keep = keep[self.obs_image]
        skipped = list(self.skipped_images) + [
            (self.image_ids[i], reasons.get(i, "removed")) for i in np.flatnonzero(~keep)
        ]
        return Dataset(
            width=self.width,
            height=self.height,
            units=self.units,
            target_ids=self.target_ids,
            target_xyz=self.target_xyz,
            target_sigma=self.target_sigma,
            image_ids=[m for m, k in zip(self.image_ids, keep) if k],
            obs_image=new_index[self.obs_image[obs_keep]],
            obs_target=self.obs_target[obs_keep],
            uv_px=self.uv_px[obs_keep],
            skipped_images=skipped,
            dropped=list(self.dropped),
            source=self.source,
            n_input_observations=self.n_input_observations,
        )

    def subset_observations(self, keep: np.ndarray, reason: str) -> Dataset:
        """Return a copy keeping the observations where ``keep`` (N,) is True.

        Every image stays (:meth:`subset_images` removes images); the observations
        removed are appended to ``dropped`` as ``(image id, target id, reason)``, so the
        output statistics count them (``n_rejected``, ``dropped_observations``).
        """
        keep = np.asarray(keep, bool)
        if keep.shape != (self.n_observations,):
            raise ValueError(f"keep must have shape ({self.n_observations},), got {keep.shape}")
        gone = np.flatnonzero(~keep)
        dropped = list(self.dropped) + [
            (self.image_ids[self.obs_image[o]], self.target_ids[self.obs_target[o]], reason)
            for o in gone
        ]
        return replace(
            self,
            obs_image=self.obs_image[keep],
            obs_target=self.obs_target[keep],
            uv_px=self.uv_px[keep],
            dropped=dropped,
            skipped_images=list(self.skipped_images),
        )


def _is_number(v: Any) -> bool:
    """True for a real number that is not a bool (JSON ``true`` is not a number here)."""
    return isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_))


def _finite_float(v: Any, where: str, what: str) -> float:
    """``float(v)`` for a finite real number ``v``, else :class:`DatasetError` naming ``where``."""
    if not _is_number(v):
        raise DatasetError(f"{where}: expected a number for {what}, got {v!r}")
    try:
        out = float(v)
    except (OverflowError, ValueError):
        raise DatasetError(f"{where}: {what} {_short(v)} is too large") from None
    if not math.isfinite(out):
        raise DatasetError(f"{where}: {what} is NaN or inf ({v!r})")
    return out


def _short(value: Any, limit: int = 60) -> str:
    """``repr(value)`` cut to ``limit`` characters, for messages about huge input."""
    text = repr(value) if not isinstance(value, int) or value.bit_length() < 200 else "<huge int>"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _finite_vector(value: Any, n: int, where: str, max_abs: float | None = None) -> np.ndarray:
    """Validate a JSON list of ``n`` finite numbers into an (n,) float array.

    Raises :class:`DatasetError` naming ``where`` for a wrong length or type, NaN,
    inf, or (with ``max_abs``) a number larger than ``max_abs`` in magnitude.
    """
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise DatasetError(f"{where}: expected a list of {n} numbers, got {_short(value)}")
    out = []
    for k, v in enumerate(value):
        f = _finite_float(v, where, f"element {k} of {_short(value)}")
        if max_abs is not None and abs(f) > max_abs:
            raise DatasetError(f"{where}: {f:g} exceeds the largest accepted magnitude {max_abs:g}")
        out.append(f)
    return np.array(out)


def _check_format(doc: Any, expected: str, path: str) -> None:
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: top level must be a JSON object, got {type(doc).__name__}")
    fmt = doc.get("format")
    if fmt != expected:
        family = expected.rsplit("@", 1)[0]
        if isinstance(fmt, str) and fmt.startswith(family + "@"):
            raise DatasetError(
                f"{path}: unsupported version {_short(fmt)}; this reader knows {expected!r}"
            )
        raise DatasetError(f"{path}: 'format' is {_short(fmt)}, expected {expected!r}")


def read_json(path: str | os.PathLike) -> Any:
    """Read a JSON file; a missing, unreadable, malformed or truncated file raises
    :class:`DatasetError` naming the path.

    Parameters
    ----------
    path : path-like

    Returns
    -------
    object
        The parsed document (``NaN`` / ``Infinity`` literals parse as floats and are
        refused later, where the item can be named).
    """
    path = str(path)
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except FileNotFoundError:
        raise DatasetError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise DatasetError(f"{path}: is a directory, not a JSON file") from None
    except OSError as exc:
        raise DatasetError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc})") from None
    except (ValueError, RecursionError) as exc:
        # ValueError: an integer literal past Python's digit limit; RecursionError:
        # arrays or objects nested deeper than the parser's stack
        raise DatasetError(f"{path}: not valid JSON for this reader ({str(exc)[:120]})") from None


def _image_size(cam: Any, where: str) -> tuple[int, int]:
    """Validated ``(width, height)`` (px) of a camera object; ``where`` names it in messages."""
    try:
        width, height = cam["width"], cam["height"]
    except KeyError as exc:
        raise DatasetError(f"{where} is missing {exc.args[0]!r}") from None
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Integral) or v <= 0:
            raise DatasetError(f"{where}.{name} must be a positive integer, got {_short(v)}")
        if v > MAX_IMAGE_SIDE_PX:
            raise DatasetError(f"{where}.{name} {_short(v)} exceeds {MAX_IMAGE_SIDE_PX} px")
    return int(width), int(height)


def _parse_units(doc: dict, source: str) -> str:
    units = doc.get("units", "m")
    if not isinstance(units, str):
        raise DatasetError(f"{source}: 'units' must be a string, got {_short(units)}")
    return units


def _parse_targets(
    doc: dict, source: str
) -> tuple[list[str], np.ndarray, np.ndarray, dict[str, int]]:
    """Validate ``targets``: ids (T,), xyz (T, 3), sigma (T,) (NaN when absent), id -> row."""
    targets = doc.get("targets")
    if not isinstance(targets, list) or not targets:
        raise DatasetError(f"{source}: 'targets' must be a non-empty list")
    ids, xyz, sigma, index = [], [], [], {}
    for k, t in enumerate(targets):
        if not isinstance(t, dict):
            raise DatasetError(f"{source}: targets[{k}] must be an object, got {_short(t)}")
        tid = t.get("id")
        if not isinstance(tid, str) or not tid:
            raise DatasetError(f"{source}: targets[{k}] has no string 'id' (got {_short(tid)})")
        if tid in index:
            raise DatasetError(f"{source}: duplicate target id {tid!r} (targets[{k}])")
        where = f"{source}: target {tid!r}"
        if "xyz" not in t:
            raise DatasetError(f"{where}: missing 'xyz'")
        p = _finite_vector(t["xyz"], 3, where + " xyz", MAX_ABS_COORDINATE)
        s = t.get("sigma", None)
        if s is None:
            s = math.nan
        else:
            if not _is_number(s):
                raise DatasetError(f"{where}: sigma must be a finite number >= 0, got {_short(s)}")
            s = _finite_float(s, where, "sigma")
            if s < 0:
                raise DatasetError(f"{where}: sigma must be >= 0, got {s!r}")
            if 0 < s < MIN_POSITIVE_SIGMA or s > MAX_ABS_COORDINATE:
                raise DatasetError(
                    f"{where}: sigma {s:g} is outside [{MIN_POSITIVE_SIGMA:g}, "
                    f"{MAX_ABS_COORDINATE:g}] (use 0 for exact control, omit it for free)"
                )
        index[tid] = len(ids)
        ids.append(tid)
        xyz.append(p)
        sigma.append(float(s))
    return ids, np.array(xyz), np.array(sigma), index


def _image_list(doc: dict, source: str) -> list:
    images = doc.get("images")
    if not isinstance(images, list) or not images:
        raise DatasetError(f"{source}: 'images' must be a non-empty list")
    return images


def _image_id(im: Any, k: int, seen: set[str], source: str) -> str:
    """The validated, unique string id of ``images[k]`` (added to ``seen``)."""
    if not isinstance(im, dict):
        raise DatasetError(f"{source}: images[{k}] must be an object")
    iid = im.get("id")
    if not isinstance(iid, str) or not iid:
        raise DatasetError(f"{source}: images[{k}] has no string 'id' (got {_short(iid)})")
    if iid in seen:
        raise DatasetError(f"{source}: duplicate image id {iid!r} (images[{k}])")
    seen.add(iid)
    return iid


def _image_observations(
    im: dict,
    iid: str,
    index: dict[str, int],
    width: int,
    height: int,
    source: str,
    dropped: list[tuple[str, str, str]],
) -> tuple[list[tuple[int, np.ndarray]], int]:
    """Validate one image's observations against a ``width`` x ``height`` image.

    Returns the usable ``(target row, uv (2,))`` pairs and the number of input
    observations; those outside the image are appended to ``dropped``.
    """
    observations = im.get("observations", [])
    if not isinstance(observations, list):
        raise DatasetError(f"{source}: image {iid!r}: 'observations' must be a list")
    rows: list[tuple[int, np.ndarray]] = []
    seen_targets: set[str] = set()
    for q, ob in enumerate(observations):
        where = f"{source}: image {iid!r} observation {q}"
        if not isinstance(ob, dict):
            raise DatasetError(f"{where}: must be an object")
        tid = ob.get("target")
        if not isinstance(tid, str):
            raise DatasetError(f"{where}: 'target' must be a string id, got {_short(tid)}")
        if tid not in index:
            raise DatasetError(f"{where}: unknown target id {tid!r}")
        if tid in seen_targets:
            raise DatasetError(f"{where}: target {tid!r} observed twice in this image")
        seen_targets.add(tid)
        if "uv" not in ob:
            raise DatasetError(f"{where}: missing 'uv'")
        p = _finite_vector(ob["uv"], 2, where + " uv")
        if not (-0.5 <= p[0] <= width - 0.5 and -0.5 <= p[1] <= height - 0.5):
            dropped.append((iid, tid, f"uv {p.tolist()} outside the {width}x{height} image"))
            continue
        rows.append((index[tid], p))
    return rows, len(observations)


def _too_few(n: int, min_observations_per_image: int) -> str:
    return f"only {n} usable observations (< {min_observations_per_image})"


def parse_dataset(
    doc: Any, source: str = "<dataset>", min_observations_per_image: int = 4
) -> Dataset:
    """Validate a ``dataset@1`` document (already parsed JSON) into a :class:`Dataset`.

    Parameters
    ----------
    doc : dict
        The JSON document.
    source : str
        Name used in messages (usually the file path).
    min_observations_per_image : int
        Images with fewer usable observations are skipped and reported.

    Returns
    -------
    Dataset
        Observations outside the image are left out and listed in
        ``dropped``; images with fewer than ``min_observations_per_image``
        usable observations are left out and listed in ``skipped_images``.

    Raises
    ------
    DatasetError
        For anything that makes the file unusable: wrong format or version,
        missing keys, duplicate target or image ids, an observation of an
        unknown target, NaN/inf, wrong types, an image side above
        ``MAX_IMAGE_SIDE_PX``, a coordinate or sigma above ``MAX_ABS_COORDINATE``
        in magnitude, a positive sigma below ``MIN_POSITIVE_SIGMA``, no usable
        image. The message names the item.
    """
    _check_format(doc, DATASET_FORMAT, source)
    units = _parse_units(doc, source)
    cam = doc.get("camera")
    if not isinstance(cam, dict):
        raise DatasetError(f"{source}: missing 'camera' object with width and height")
    width, height = _image_size(cam, f"{source}: camera")
    ids, xyz, sigma, index = _parse_targets(doc, source)
    images = _image_list(doc, source)
    image_ids: list[str] = []
    seen_images: set[str] = set()
    obs_image, obs_target, uv = [], [], []
    skipped: list[tuple[str, str]] = []
    dropped: list[tuple[str, str, str]] = []
    n_input = 0
    for k, im in enumerate(images):
        iid = _image_id(im, k, seen_images, source)
        rows, n = _image_observations(im, iid, index, width, height, source, dropped)
        n_input += n
        if len(rows) < min_observations_per_image:
            skipped.append((iid, _too_few(len(rows), min_observations_per_image)))
            continue
        m = len(image_ids)
        image_ids.append(iid)
        for t_idx, p in rows:
            obs_image.append(m)
            obs_target.append(t_idx)
            uv.append(p)
    if not image_ids:
        reasons = "; ".join(f"{i}: {r}" for i, r in skipped[:5])
        raise DatasetError(f"{source}: no usable image ({reasons})")
    return Dataset(
        width=int(width),
        height=int(height),
        units=units,
        target_ids=ids,
        target_xyz=xyz,
        target_sigma=sigma,
        image_ids=image_ids,
        obs_image=np.array(obs_image, int),
        obs_target=np.array(obs_target, int),
        uv_px=np.array(uv, float).reshape(-1, 2),
        skipped_images=skipped,
        dropped=dropped,
        source=source,
        n_input_observations=n_input,
    )


def load_dataset(path: str | os.PathLike, min_observations_per_image: int = 4) -> Dataset:
    """Read and validate a ``gtsam-sphere/dataset@1`` file.

    Parameters
    ----------
    path : path-like
    min_observations_per_image : int
        Images with fewer usable observations are skipped and reported.

    Returns
    -------
    Dataset
    """
    return parse_dataset(read_json(path), str(path), min_observations_per_image)


# -- rigs: dataset@2 ---------------------------------------------------------------


@dataclass
class RigDataset:
    """A validated ``dataset@2``: several cameras fixed to one body, flattened.

    Attributes
    ----------
    camera_ids : list of str, length C
        In file order; ``camera_ids[0]`` is the rig frame (its ``cam_from_rig``
        is the identity).
    camera_sizes : list of (int, int), length C
        ``(width, height)`` of each camera, px.
    units : str
        Object-space units (``"m"`` unless the file says otherwise).
    target_ids : list of str, length T
    target_xyz : ndarray, shape (T, 3)
        Approximate world coordinates, in ``units``; shared by all cameras.
    target_sigma : ndarray, shape (T,)
        As :class:`Dataset` (``0`` exact control, ``NaN`` absent).
    image_ids : list of str, length M
        Images kept (all cameras, file order).
    image_camera : ndarray of int, shape (M,)
        Index into ``camera_ids`` per kept image.
    image_frame : list of (str or None), length M
        Frame id of each kept image (the rig pose it was taken at), ``None``
        for an image with a pose of its own.
    obs_image, obs_target : ndarray of int, shape (N,)
    uv_px : ndarray, shape (N, 2)
        As :class:`Dataset`.
    skipped_images : list of (str, str)
        ``(image id, reason)`` for images left out (all cameras).
    dropped : list of (str, str, str)
        ``(image id, target id, reason)`` for observations left out.
    """

    camera_ids: list[str]
    camera_sizes: list[tuple[int, int]]
    units: str
    target_ids: list[str]
    target_xyz: np.ndarray
    target_sigma: np.ndarray
    image_ids: list[str]
    image_camera: np.ndarray
    image_frame: list[str | None]
    obs_image: np.ndarray
    obs_target: np.ndarray
    uv_px: np.ndarray
    skipped_images: list[tuple[str, str]] = field(default_factory=list)
    dropped: list[tuple[str, str, str]] = field(default_factory=list)
    source: str | None = None
    #: camera id of every input image (kept or skipped), for per-camera counts
    input_image_camera: dict[str, str] = field(default_factory=dict)
    #: input observations per camera id
    n_input_observations: dict[str, int] = field(default_factory=dict)

    @property
    def frame_ids(self) -> list[str]:
        """Frame ids of the kept images, in order of first appearance."""
        return list(dict.fromkeys(f for f in self.image_frame if f is not None))


def parse_rig_dataset(
    doc: Any, source: str = "<dataset>", min_observations_per_image: int = 4
) -> RigDataset:
    """Validate a ``dataset@2`` document (a rig of cameras) into a :class:`RigDataset`.

    Targets, observations and images follow exactly the rules of
    :func:`parse_dataset` (``dataset@1``), each image checked against the size of
    its own camera.

    Parameters
    ----------
    doc : dict
        The JSON document.
    source : str
        Name used in messages (usually the file path).
    min_observations_per_image : int
        Images with fewer usable observations are skipped and reported.

    Returns
    -------
    RigDataset

    Raises
    ------
    DatasetError
        Everything :func:`parse_dataset` refuses, and: a missing or empty
        ``cameras`` list, a camera without a string id, duplicate camera ids, an
        image naming an unknown camera (or none), a ``frame`` that is not a
        non-empty string, two images of one camera in one frame, a camera with no
        usable image. The message names the item.
    """
    _check_format(doc, RIG_DATASET_FORMAT, source)
    units = _parse_units(doc, source)
    if "camera" in doc:
        raise DatasetError(
            f"{source}: dataset@2 describes its cameras in 'cameras' (a list), not 'camera'"
        )
    cameras = doc.get("cameras")
    if not isinstance(cameras, list) or not cameras:
        raise DatasetError(f"{source}: 'cameras' must be a non-empty list of {{id, width, height}}")
    camera_ids: list[str] = []
    sizes: list[tuple[int, int]] = []
    for k, cam in enumerate(cameras):
        if not isinstance(cam, dict):
            raise DatasetError(f"{source}: cameras[{k}] must be an object, got {_short(cam)}")
        cid = cam.get("id")
        if not isinstance(cid, str) or not cid:
            raise DatasetError(f"{source}: cameras[{k}] has no string 'id' (got {_short(cid)})")
        if cid in camera_ids:
            raise DatasetError(f"{source}: duplicate camera id {cid!r} (cameras[{k}])")
        sizes.append(_image_size(cam, f"{source}: camera {cid!r}"))
        camera_ids.append(cid)
    camera_index = {c: i for i, c in enumerate(camera_ids)}
    ids, xyz, sigma, index = _parse_targets(doc, source)
    images = _image_list(doc, source)

    image_ids: list[str] = []
    image_camera: list[int] = []
    image_frame: list[str | None] = []
    seen_images: set[str] = set()
    frame_owner: dict[tuple[str, str], str] = {}
    obs_image, obs_target, uv = [], [], []
    skipped: list[tuple[str, str]] = []
    dropped: list[tuple[str, str, str]] = []
    input_camera: dict[str, str] = {}
    n_input = dict.fromkeys(camera_ids, 0)
    for k, im in enumerate(images):
        iid = _image_id(im, k, seen_images, source)
        cid = im.get("camera")
        if not isinstance(cid, str):
            raise DatasetError(
                f"{source}: image {iid!r}: 'camera' must name one of {camera_ids}, "
                f"got {_short(cid)}"
            )
        if cid not in camera_index:
            raise DatasetError(
                f"{source}: image {iid!r}: unknown camera {cid!r} (cameras are {camera_ids})"
            )
        frame = im.get("frame")
        if frame is not None:
            if not isinstance(frame, str) or not frame:
                raise DatasetError(
                    f"{source}: image {iid!r}: 'frame' must be a non-empty string id, "
                    f"got {_short(frame)}"
                )
            other = frame_owner.get((frame, cid))
            if other is not None:
                raise DatasetError(
                    f"{source}: frame {frame!r} holds two images of camera {cid!r} "
                    f"({other!r} and {iid!r}); a frame holds at most one image per camera"
                )
            frame_owner[(frame, cid)] = iid
        input_camera[iid] = cid
        width, height = sizes[camera_index[cid]]
        rows, n = _image_observations(im, iid, index, width, height, source, dropped)
        n_input[cid] += n
        if len(rows) < min_observations_per_image:
            skipped.append((iid, _too_few(len(rows), min_observations_per_image)))
            continue
        m = len(image_ids)
        image_ids.append(iid)
        image_camera.append(camera_index[cid])
        image_frame.append(frame)
        for t_idx, p in rows:
            obs_image.append(m)
            obs_target.append(t_idx)
            uv.append(p)
    for c, cid in enumerate(camera_ids):
        if c not in image_camera:
            why = [f"{i}: {r}" for i, r in skipped if input_camera.get(i) == cid][:5]
            detail = f" ({'; '.join(why)})" if why else " (no image names it)"
            raise DatasetError(f"{source}: camera {cid!r} has no usable image{detail}")
    return RigDataset(
        camera_ids=camera_ids,
        camera_sizes=sizes,
        units=units,
        target_ids=ids,
        target_xyz=xyz,
        target_sigma=sigma,
        image_ids=image_ids,
        image_camera=np.array(image_camera, int),
        image_frame=image_frame,
        obs_image=np.array(obs_image, int),
        obs_target=np.array(obs_target, int),
        uv_px=np.array(uv, float).reshape(-1, 2),
        skipped_images=skipped,
        dropped=dropped,
        source=source,
        input_image_camera=input_camera,
        n_input_observations=n_input,
    )


def load_rig_dataset(path: str | os.PathLike, min_observations_per_image: int = 4) -> RigDataset:
    """Read and validate a ``gtsam-sphere/dataset@2`` file (:func:`parse_rig_dataset`)."""
    return parse_rig_dataset(read_json(path), str(path), min_observations_per_image)


def dataset_version(doc: Any, source: str = "<dataset>") -> int:
    """``1`` for a ``dataset@1`` document, ``2`` for a ``dataset@2`` (rig) document.

    Raises
    ------
    DatasetError
        Anything else (naming the format found and the ones known).
    """
    if isinstance(doc, dict) and doc.get("format") == RIG_DATASET_FORMAT:
        return 2
    if isinstance(doc, dict) and doc.get("format") == DATASET_FORMAT:
        return 1
    if isinstance(doc, dict) and isinstance(doc.get("format"), str):
        fmt = doc["format"]
        if fmt.startswith("gtsam-sphere/dataset@"):
            raise DatasetError(
                f"{source}: unsupported version {_short(fmt)}; this reader knows "
                f"{DATASET_FORMAT!r} and {RIG_DATASET_FORMAT!r}"
            )
    _check_format(doc, DATASET_FORMAT, source)  # raises, naming what was found
    return 1


def split_rig(rig: RigDataset) -> dict[str, Dataset]:
    """One ``dataset@1``-equivalent :class:`Dataset` per camera of a rig.

    Every camera's dataset shares the rig's targets (same ids, arrays and
    sigmas), holds that camera's kept images in file order with their
    observations, and the skipped images and dropped observations of that
    camera. Frames are not part of a :class:`Dataset`; ``rig.image_frame``
    keeps them.

    Parameters
    ----------
    rig : RigDataset

    Returns
    -------
    dict of str -> Dataset
        Camera id -> its dataset, in the order of ``rig.camera_ids``.
    """
    out: dict[str, Dataset] = {}
    for c, cid in enumerate(rig.camera_ids):
        keep = np.flatnonzero(rig.image_camera == c)
        new_index = -np.ones(len(rig.image_ids), int)
        new_index[keep] = np.arange(len(keep))
        obs = np.flatnonzero(new_index[rig.obs_image] >= 0)
        mine = {i for i, cam in rig.input_image_camera.items() if cam == cid}
        width, height = rig.camera_sizes[c]
        out[cid] = Dataset(
            width=width,
            height=height,
            units=rig.units,
            target_ids=rig.target_ids,
            target_xyz=rig.target_xyz,
            target_sigma=rig.target_sigma,
            image_ids=[rig.image_ids[i] for i in keep],
            obs_image=new_index[rig.obs_image[obs]],
            obs_target=rig.obs_target[obs],
            uv_px=rig.uv_px[obs],
            skipped_images=[(i, r) for i, r in rig.skipped_images if i in mine],
            dropped=[d for d in rig.dropped if d[0] in mine],
            source=f"{rig.source} (camera {cid})" if rig.source else f"camera {cid}",
            n_input_observations=rig.n_input_observations.get(cid, 0),
        )
    return out


def load_checkpoints(path: str | os.PathLike) -> tuple[list[str], np.ndarray, str]:
    """Read a ``gtsam-sphere/checkpoints@1`` file.

    Parameters
    ----------
    path : path-like

    Returns
    -------
    ids : list of str, length K
    xyz : ndarray, shape (K, 3)
        Independently surveyed coordinates, in ``units``.
    units : str

    Raises
    ------
    DatasetError
        Wrong format or version, missing or duplicate ids, NaN/inf, wrong types;
        the message names the check point.
    """
    source = str(path)
    doc = read_json(path)
    _check_format(doc, CHECKPOINTS_FORMAT, source)
    units = doc.get("units", "m")
    if not isinstance(units, str):
        raise DatasetError(f"{source}: 'units' must be a string, got {_short(units)}")
    targets = doc.get("targets")
    if not isinstance(targets, list) or not targets:
        raise DatasetError(f"{source}: 'targets' must be a non-empty list")
    ids: list[str] = []
    seen: set[str] = set()
    xyz = []
    for k, t in enumerate(targets):
        if not isinstance(t, dict) or not isinstance(t.get("id"), str) or not t["id"]:
            raise DatasetError(f"{source}: targets[{k}] needs a non-empty string 'id'")
        if t["id"] in seen:
            raise DatasetError(f"{source}: duplicate check point id {t['id']!r} (targets[{k}])")
        seen.add(t["id"])
        ids.append(t["id"])
        where = f"{source}: check point {t['id']!r} xyz"
        xyz.append(_finite_vector(t.get("xyz"), 3, where, MAX_ABS_COORDINATE))
    return ids, np.array(xyz), units


def _jsonable(obj: Any, where: str = "") -> Any:
    """Plain JSON types for ``obj``; NaN or inf raise ``ValueError`` naming the key path."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v, f"{where}.{k}" if where else str(k)) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v, f"{where}[{i}]") for i, v in enumerate(obj)]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist(), where)
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        if not math.isfinite(v):
            raise InputError(
                f"refusing to write NaN or inf to a JSON output file (at {where or 'top level'})"
            )
        return v
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temporary file in the same folder + rename).

    A reader never sees a half-written file, and an interrupted write leaves
    any existing file untouched and no temporary behind.

    Parameters
    ----------
    path : path-like
        Destination; missing parent directories are created.
    data : bytes

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    OSError
        ``path`` cannot be written (a directory, no permission, ...); the
        exception's ``filename`` is ``path``, never the temporary file.
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(errno.EISDIR, "is a directory, not a file", str(path))
    directory = path.parent if str(path.parent) else Path(".")
    try:
        directory.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    except OSError as exc:
        raise type(exc)(exc.errno, exc.strerror, str(path)) from exc
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError) and exc.errno is not None:
            raise type(exc)(exc.errno, exc.strerror, str(path)) from exc
        raise
    return path


def write_json_atomic(path: str | os.PathLike, doc: Any, indent: int | None = 1) -> Path:
    """Write ``doc`` as JSON to ``path`` atomically (:func:`write_bytes_atomic`).

    NaN or inf anywhere raises ``ValueError`` naming the key path and leaves
    any existing file untouched.

    Parameters
    ----------
    path : path-like
        Destination; missing parent directories are created.
    doc : object
        JSON-able document (dicts, lists, numbers, strings, numpy arrays and scalars).
    indent : int or None
        ``json.dumps`` indentation.

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    ValueError
        NaN or inf in ``doc``.
    OSError
        ``path`` cannot be written; the exception's ``filename`` is ``path``.
    """
    text = json.dumps(_jsonable(doc), indent=indent, allow_nan=False)
    return write_bytes_atomic(path, (text + "\n").encode("utf-8"))
