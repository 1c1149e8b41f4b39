"""Detection for rigs: one folder (or glob) per camera, images paired into frames, ``dataset@2``.

``gtsam-sphere detect --camera cam0=DIR_OR_GLOB --camera cam1=... --board SPEC -o RIG.json``

Pairing (``--sync``):

``stem``
    Images of different cameras with the same file-name stem (``left/0007.png``
    and ``right/0007.png``) were taken together: frame ``"0007"``.
``timestamp``
    The last number in each stem is a time stamp (``1403636579763555584.png``,
    ``cam1_1650000000.125.jpg``); images of different cameras whose stamps lie
    within ``--sync-tolerance`` seconds of the frame's first image form one
    frame (greedy, in time order, at most one image per camera). The unit is
    ``--timestamp-unit`` or, by default, guessed from the integer part's number
    of digits (>= 17 ns, >= 14 us, >= 11 ms, else s).

An image without a partner in any other camera keeps no ``frame`` (the
contract's "image with a pose of its own": it still constrains its camera)
and is reported; so is a frame missing one of the cameras. Image ids are
``CAMERA/STEM``. A file that cannot be read or holds no target is skipped and
reported, as for one camera; a camera with no usable image is an error naming
it. ``--recover`` recovers the corners the detector missed per camera
(:func:`gtsam_sphere.apps.detect.recover_dataset`; ``--recover-with`` a
``calibration@2`` gives the first predictions of the cameras it holds).
"""

from __future__ import annotations

import argparse
import glob
import os
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

from ..core.errors import InputError, OptionsError, TargetMismatchError

#: file name extensions of a camera folder's images
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm", ".ppm", ".webp")
SYNC_MODES = ("stem", "timestamp")
#: seconds per unit of ``--timestamp-unit``
TIMESTAMP_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
_ID = re.compile(r"^[A-Za-z0-9_.:-]+$")
_NUMBER = re.compile(r"\d+(?:\.\d+)?")


def parse_camera_options(values: list[str]) -> list[tuple[str, str]]:
    """``["cam0=DIR", "cam1=GLOB"]`` -> ``[("cam0", "DIR"), ...]`` in the order given.

    Raises
    ------
    OptionsError
        Naming the bad ``--camera`` value (no ``=``, a bad or repeated id).
    """
    out: list[tuple[str, str]] = []
    for value in values:
        cid, sep, spec = value.partition("=")
        cid, spec = cid.strip(), spec.strip()
        if not sep or not cid or not spec:
            raise OptionsError(f"--camera {value!r}: expected ID=DIR_OR_GLOB")
        if not _ID.match(cid) or "/" in cid:
            raise OptionsError(
                f"--camera {value!r}: camera id {cid!r} must be letters, digits or _.:-"
            )
        if cid in dict(out):
            raise OptionsError(f"--camera {value!r}: camera {cid!r} given twice")
        out.append((cid, spec))
    return out


def camera_images(camera_id: str, spec: str) -> list[str]:
    """The image files of one camera: every image in folder ``spec``, or the files matching
    the glob ``spec``, sorted.

    Raises
    ------
    InputError
        No image (naming the camera and ``spec``), or two files with one stem.
    """
    if os.path.isdir(spec):
        paths = [
            str(p)
            for p in sorted(Path(spec).iterdir())
            if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
        ]
    else:
        paths = sorted(p for p in glob.glob(spec) if os.path.isfile(p))
    if not paths:
        raise InputError(f"camera {camera_id!r}: no image file in {spec!r}")
    stems: dict[str, str] = {}
    for p in paths:
        stem = Path(p).stem
        if stem in stems:
            raise InputError(
                f"camera {camera_id!r}: {stems[stem]!r} and {p!r} share the stem {stem!r}; "
                "a camera's images need distinct names"
            )
        stems[stem] = p
    return paths


def timestamp_seconds(stem: str, unit: str = "auto") -> float:
    """The time stamp (s) in a file stem: its last number, in ``unit`` (or guessed).

    Raises
    ------
    InputError
        The stem holds no number.
    """
    found = _NUMBER.findall(stem)
    if not found:
        raise InputError(f"image {stem!r}: no time stamp (number) in the file name")
    text = found[-1]
    if unit == "auto":
        digits = len(text.split(".")[0])
        unit = "ns" if digits >= 17 else "us" if digits >= 14 else "ms" if digits >= 11 else "s"
    if unit not in TIMESTAMP_UNITS:
        raise OptionsError(
            f"--timestamp-unit {unit!r}: choose auto or {', '.join(TIMESTAMP_UNITS)}"
        )
    return float(text) * TIMESTAMP_UNITS[unit]


@dataclass
class Pairing:
    """Images of several cameras paired into frames.

    Attributes
    ----------
    frame_of : dict of (str, str) -> str or None
        ``(camera id, path)`` -> frame id, ``None`` for an image without partner.
    unpaired : list of (str, str)
        ``(camera id, path)`` of the images without partner.
    incomplete : list of (str, list of str)
        ``(frame id, cameras missing from it)``.
    """

    frame_of: dict[tuple[str, str], str | None] = field(default_factory=dict)
    unpaired: list[tuple[str, str]] = field(default_factory=list)
    incomplete: list[tuple[str, list[str]]] = field(default_factory=list)

    @property
    def n_frames(self) -> int:
        """Number of frames (with at least two images)."""
        return len({f for f in self.frame_of.values() if f is not None})

    def summary(self, limit: int = 10) -> str:
        """Multi-line summary: frames, images without partner, incomplete frames."""
        lines = [
            f"frames: {self.n_frames}, images without partner: {len(self.unpaired)}, "
            f"frames missing a camera: {len(self.incomplete)}"
        ]
        for cid, path in self.unpaired[:limit]:
            lines.append(f"  no partner (no frame): camera {cid} image {path}")
        if len(self.unpaired) > limit:
            lines.append(f"  ... and {len(self.unpaired) - limit} more without partner")
        for fid, missing in self.incomplete[:limit]:
            lines.append(f"  frame {fid}: no image of camera(s) {', '.join(missing)}")
        if len(self.incomplete) > limit:
            lines.append(f"  ... and {len(self.incomplete) - limit} more incomplete frames")
        return "\n".join(lines)


def pair_images(
    images: dict[str, list[str]],
    sync: str = "stem",
    tolerance_s: float = 0.01,
    timestamp_unit: str = "auto",
) -> Pairing:
    """Pair the cameras' images into frames (see the module's description).

    Parameters
    ----------
    images : dict of str -> list of str
        Camera id -> image paths (distinct stems per camera), in camera order.
    sync : {"stem", "timestamp"}
    tolerance_s : float
        ``timestamp``: largest difference (s) to the frame's first image.
    timestamp_unit : str
        ``auto`` or a key of :data:`TIMESTAMP_UNITS`.

    Returns
    -------
    Pairing
    """
    if sync not in SYNC_MODES:
        raise OptionsError(f"--sync {sync!r}: choose {' or '.join(SYNC_MODES)}")
    if not (tolerance_s >= 0):
        raise OptionsError(f"--sync-tolerance {tolerance_s!r}: must be >= 0 seconds")
    cams = list(images)
    groups: list[tuple[str, list[tuple[str, str]]]] = []  # (frame id, [(camera, path)])
    if sync == "stem":
        by_stem: dict[str, list[tuple[str, str]]] = {}
        for cid in cams:
            for p in images[cid]:
                by_stem.setdefault(Path(p).stem, []).append((cid, p))
        groups = sorted(by_stem.items())
    else:
        stamped = []
        for cid in cams:
            for p in images[cid]:
                try:
                    t = timestamp_seconds(Path(p).stem, timestamp_unit)
                except InputError as exc:
                    raise InputError(f"camera {cid!r}: {p}: {exc}") from None
                stamped.append((t, cams.index(cid), cid, p))
        stamped.sort()
        current: list[tuple[str, str]] = []
        t0 = None
        for t, _, cid, p in stamped:
            if t0 is not None and t - t0 <= tolerance_s and cid not in {c for c, _ in current}:
                current.append((cid, p))
                continue
            if current:
                groups.append((Path(current[0][1]).stem, current))
            current, t0 = [(cid, p)], t
        if current:
            groups.append((Path(current[0][1]).stem, current))
    out = Pairing()
    used_ids: set[str] = set()
    for fid, members in groups:
        if len(members) < 2:
            cid, p = members[0]
            out.frame_of[(cid, p)] = None
            out.unpaired.append((cid, p))
            continue
        base, k = fid, 1
        while fid in used_ids:  # time stamps of different cameras may repeat a stem
            k += 1
            fid = f"{base}#{k}"
        used_ids.add(fid)
        for cid, p in members:
            out.frame_of[(cid, p)] = fid
        present = {c for c, _ in members}
        missing = [c for c in cams if c not in present]
        if missing:
            out.incomplete.append((fid, missing))
    return out


def detect_rig(
    cameras: list[tuple[str, str]],
    board,
    *,
    sync: str = "stem",
    tolerance_s: float = 0.01,
    timestamp_unit: str = "auto",
    progress: bool = True,
    markers_csv: str | None = None,
    min_points: int = 1,
    recover: bool = False,
    recover_with=None,
    recover_options: dict | None = None,
    recover_progress=None,
    check_size: bool = True,
):
    """Detect ``board`` in each camera's images and write a ``gtsam-sphere/dataset@2``.

    Parameters
    ----------
    cameras : list of (str, str)
        ``(camera id, folder or glob)``, the rig's reference camera first.
    board : BoardSpec
    sync, tolerance_s, timestamp_unit
        See :func:`pair_images`.
    progress, markers_csv, min_points, check_size
        As :func:`gtsam_sphere.apps.detect.detect_images`, per camera.
    recover : bool
        Recover the corners the detector missed, per camera
        (:func:`gtsam_sphere.apps.detect.recover_dataset`).
    recover_with : RigCalibration, optional
        First predictions of each camera it holds from its calibration (implies
        ``recover``); the other cameras calibrate their detections.
    recover_options : dict, optional
        ``model``, ``rounds``, ``max_offset_px`` of ``recover_dataset``.
    recover_progress : callable(str), optional
        Receives the recovery's progress lines.

    Returns
    -------
    dataset : dict
        The ``dataset@2`` document (``source.pairing`` lists the images without
        partner and the incomplete frames).
    reports : dict of str -> DetectionReport
        Per camera.
    pairing : Pairing
    recoveries : dict of str -> RecoveryReport
        Per camera, when recovering (else empty).

    Raises
    ------
    InputError
        Naming the camera: no image, no usable image, clashing stems, a file name
        without time stamp (``timestamp``); OptionsError for a bad option.
    """
    from .detect import detect_images, recover_dataset

    if not cameras:
        raise OptionsError("--camera: give at least one camera ID=DIR_OR_GLOB")
    images = {cid: camera_images(cid, spec) for cid, spec in cameras}
    pairing = pair_images(images, sync, tolerance_s, timestamp_unit)
    cam_entries, doc_images, reports, recoveries = [], [], {}, {}
    recover = recover or recover_with is not None
    targets: dict[str, dict] = {}
    for cid, _ in cameras:
        paths = images[cid]
        try:
            ds, report = detect_images(
                paths,
                board,
                progress=progress,
                markers_csv=markers_csv,
                min_points=min_points,
                check_size=check_size,
            )
        except OptionsError:
            raise
        except TargetMismatchError as exc:
            raise TargetMismatchError(f"camera {cid!r}: {exc}") from None
        except InputError as exc:
            raise InputError(f"camera {cid!r}: {exc}") from None
        reports[cid] = report
        if recover:
            first = None
            if recover_with is not None and cid in recover_with.cameras:
                first = recover_with.camera_calibration(cid)
            try:
                ds, recoveries[cid] = recover_dataset(
                    ds,
                    paths,
                    board,
                    calibration=first,
                    progress=None
                    if recover_progress is None
                    else (lambda line, cid=cid: recover_progress(f"camera {cid}: {line}")),
                    **(recover_options or {}),
                )
            except OptionsError:
                raise
            except InputError as exc:
                raise InputError(f"camera {cid!r}: recovery: {exc}") from None
        path_of = {Path(p).stem: p for p in paths}
        cam_entries.append({"id": cid, **ds["camera"]})
        for t in ds["targets"]:
            targets.setdefault(t["id"], t)
        for im in ds["images"]:
            entry = {"id": f"{cid}/{im['id']}", "camera": cid}
            frame = pairing.frame_of.get((cid, path_of[im["id"]]))
            if frame is not None:
                entry["frame"] = frame
            entry["observations"] = im["observations"]
            doc_images.append(entry)
    dataset = {
        "format": "gtsam-sphere/dataset@2",
        "units": "m",
        "cameras": cam_entries,
        "targets": [targets[k] for k in sorted(targets)],
        "images": doc_images,
        "source": {
            "detector": "gtsam_sphere.apps.detect",
            "board": board.text,
            "cameras": {cid: spec for cid, spec in cameras},
            "sync": sync,
            **({"sync_tolerance_s": tolerance_s} if sync == "timestamp" else {}),
            "pairing": {
                "n_frames": pairing.n_frames,
                "unpaired": [{"camera": c, "path": p} for c, p in pairing.unpaired],
                "incomplete_frames": [
                    {"frame": f, "missing_cameras": m} for f, m in pairing.incomplete
                ],
            },
        },
    }
    if recoveries:
        dataset["source"]["recovery"] = {
            cid: {"added": rec.total, "rescued": list(rec.rescued)}
            for cid, rec in recoveries.items()
        }
    return dataset, reports, pairing, recoveries


def run_cli(args: argparse.Namespace) -> int:
    """Run ``gtsam-sphere detect --camera ID=DIR ...``: a rig, written as dataset@2."""
    from ..io.calibration import load_calibration
    from .detect import board_from_args, write_json_atomic

    if args.images:
        raise OptionsError(
            "give the images either positionally (one camera) or per camera with --camera, "
            f"not both (positional: {args.images[0]!r}...)"
        )
    from ..core.camera import Model

    board = board_from_args(args)
    recover_with = None
    if getattr(args, "recover_with", None):
        from ..io.calibration import load_calibration

        recover_with = load_calibration(args.recover_with)
        if not hasattr(recover_with, "camera_ids"):
            raise OptionsError(
                f"--recover-with {args.recover_with}: a rig (--camera) needs a rig calibration "
                "(calibration@2)"
            )
    if args.recover_model not in {m.value for m in Model}:
        raise OptionsError(
            f"--recover-model {args.recover_model!r}: choose from "
            + ", ".join(m.value for m in Model)
        )

    def say(line: str) -> None:
        if not getattr(args, "no_progress", False):
            print(f"recovery: {line}", file=sys.stderr, flush=True)

    dataset, reports, pairing, recoveries = detect_rig(
        parse_camera_options(args.camera),
        board,
        sync=args.sync,
        tolerance_s=args.sync_tolerance,
        timestamp_unit=args.timestamp_unit,
        progress=not getattr(args, "no_progress", False),
        markers_csv=args.markers_csv,
        min_points=getattr(args, "min_points", 1),
        recover=bool(getattr(args, "recover", False)),
        recover_with=recover_with,
        recover_options={
            "model": args.recover_model,
            "rounds": args.recover_rounds,
            "max_offset_px": args.recover_max_offset_px,
        },
        recover_progress=say,
        check_size=not getattr(args, "no_size_check", False),
    )
    write_json_atomic(dataset, args.output)
    for cid, report in reports.items():
        print(f"camera {cid}: " + report.summary())
        if cid in recoveries:
            print(f"camera {cid}: " + recoveries[cid].summary())
    print(pairing.summary())
    print(
        f"wrote {args.output}: dataset@2, {len(reports)} cameras, {pairing.n_frames} frames, "
        f"{len(dataset['images'])} images, {len(dataset['targets'])} targets"
    )
    return 0
