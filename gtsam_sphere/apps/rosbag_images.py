"""Images from ROS bags for ``gtsam-sphere detect --bag FILE --topics T1 [T2 ...]``.

ROS1 ``.bag`` files and ROS2 bags (a folder with ``metadata.yaml`` and sqlite3 or mcap
storage, or the storage file itself) are read with the ``rosbags`` package (pure
Python, no ROS install; the optional extra ``gtsam-sphere[ros]``). Messages of type
``sensor_msgs/Image`` (``mono8``, ``mono16``, ``bgr8``, ``rgb8``, ``bgra8``, ``rgba8``,
``8UC1``, ``8UC3``) and ``sensor_msgs/CompressedImage`` (anything ``cv2.imdecode``
reads) are written as PNG files named by their header stamp in nanoseconds (the bag's
receive time when the header stamp is zero), one folder per topic, then detected like
image folders: one topic gives ``dataset@1``; several topics are a rig, paired by time
stamp within ``--approx-sync`` seconds (Kalibr's default 0.02 s) into ``dataset@2``
frames, the camera ids taken from the topics (``/cam0/image_raw`` -> ``cam0``).
``--bag-freq HZ`` keeps at most one message per topic every ``1 / HZ`` seconds, like
Kalibr's ``--bag-freq``.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from ..core.errors import DatasetError, OptionsError

__all__ = ["camera_ids_of_topics", "extract_bag_images", "message_image"]

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")


def _require_rosbags():
    try:
        from rosbags.highlevel import AnyReader
    except ImportError:  # an optional dependency
        raise OptionsError(
            "reading ROS bags needs the 'rosbags' package: pip install 'gtsam-sphere[ros]' "
            "(or pip install rosbags)"
        ) from None
    return AnyReader


def camera_ids_of_topics(topics: list[str]) -> list[str]:
    """Camera ids of image topics: the first name of each (``/cam0/image_raw`` -> ``cam0``),
    the whole topic with ``/`` as ``_`` when those clash.

    Raises
    ------
    OptionsError
        When a topic is given twice.
    """
    if len(set(topics)) != len(topics):
        raise OptionsError(f"--topics: a topic is given twice ({' '.join(topics)})")
    first = [t.strip("/").split("/")[0] or "cam" for t in topics]
    if len(set(first)) == len(first):
        return first
    return [re.sub(r"[^A-Za-z0-9_.-]+", "_", t.strip("/")) for t in topics]


def message_image(msg, msgtype: str, where: str) -> np.ndarray:
    """The image of a ``sensor_msgs`` Image or CompressedImage message.

    Returns
    -------
    ndarray, shape (H, W) or (H, W, 3), uint8 or uint16
        Colour in OpenCV's BGR order.

    Raises
    ------
    DatasetError
        An encoding this reader does not know, or data that does not decode; ``where``
        names the message.
    """
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    if msgtype.endswith("CompressedImage"):
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DatasetError(f"{where}: compressed image ({msg.format!r}) does not decode")
        return img
    enc = str(msg.encoding).lower()
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    channels = {"mono8": 1, "8uc1": 1, "bgr8": 3, "rgb8": 3, "8uc3": 3, "bgra8": 4, "rgba8": 4}
    if enc in ("mono16", "16uc1"):
        dtype = ">u2" if int(msg.is_bigendian) else "<u2"
        rows = data[: h * step].reshape(h, step)[:, : 2 * w]
        return np.ascontiguousarray(rows).view(dtype).reshape(h, w).astype(np.uint16)
    if enc not in channels:
        raise DatasetError(
            f"{where}: image encoding {msg.encoding!r} is not supported (mono8, mono16, bgr8, "
            "rgb8, bgra8, rgba8, 8UC1, 8UC3, or a CompressedImage)"
        )
    c = channels[enc]
    if len(data) < h * step or step < w * c:
        raise DatasetError(f"{where}: {len(data)} bytes for a {w}x{h} {enc} image (step {step})")
    img = data[: h * step].reshape(h, step)[:, : w * c].reshape(h, w, c)
    if c == 1:
        return img[:, :, 0].copy()
    if enc.startswith("rgb"):
        img = img[:, :, [2, 1, 0]]
    return np.ascontiguousarray(img[:, :, :3])


def extract_bag_images(
    bag: str,
    topics: list[str],
    out_dir: str | Path,
    *,
    freq_hz: float | None = None,
    progress: Callable[[int, int, str], None] | None = None,
) -> dict[str, list[Path]]:
    """Write the images of ``topics`` in ``bag`` as PNG files, a folder per topic.

    Parameters
    ----------
    bag : str
        ROS1 ``.bag`` file, or ROS2 bag folder (or its ``.db3`` / ``.mcap`` file).
    topics : list of str
        Image topics (``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage``).
    out_dir : str or Path
        Where the folders go: ``out_dir / camera_id / {stamp_ns}.png``.
    freq_hz : float, optional
        Keep at most one message per topic every ``1 / freq_hz`` seconds (header time).
    progress : callable(i, n, name), optional
        Called per message read.

    Returns
    -------
    dict of str to list of Path
        Camera id (:func:`camera_ids_of_topics`) -> the files written, in time order.

    Raises
    ------
    OptionsError
        ``rosbags`` absent, a topic not in the bag or not an image topic, a bad
        ``freq_hz``.
    DatasetError
        A bag that cannot be read, or a message that does not decode.
    """
    any_reader = _require_rosbags()
    if freq_hz is not None and not freq_hz > 0:
        raise OptionsError(f"--bag-freq {freq_hz}: must be a positive rate in Hz")
    path = Path(bag)
    if path.suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").exists():
        path = path.parent  # a ROS2 bag is its folder
    if not path.exists():
        raise OptionsError(f"--bag {bag}: no such file or folder")
    ids = camera_ids_of_topics(list(topics))
    cam_of = dict(zip(topics, ids))
    out: dict[str, list[Path]] = {cid: [] for cid in ids}
    for cid in ids:
        (Path(out_dir) / cid).mkdir(parents=True, exist_ok=True)
    try:
        reader_cm = any_reader([path])
        reader = reader_cm.__enter__()
    except Exception as exc:  # rosbags raises its own error classes per format
        raise DatasetError(f"--bag {bag}: cannot be read as a ROS bag ({exc})") from None
    try:
        have = {c.topic: c for c in reader.connections}
        for t in topics:
            if t not in have:
                image_topics = sorted(
                    c.topic for c in reader.connections if c.msgtype in IMAGE_TYPES
                )
                raise OptionsError(
                    f"--topics {t}: not in {bag} (its image topics: "
                    f"{', '.join(image_topics) or 'none'})"
                )
            if have[t].msgtype not in IMAGE_TYPES:
                raise OptionsError(f"--topics {t}: {have[t].msgtype} is not an image type")
        conns = [c for c in reader.connections if c.topic in cam_of]
        n = sum(int(c.msgcount) for c in conns)
        last: dict[str, int] = {}
        step_ns = None if freq_hz is None else int(round(1e9 / freq_hz))
        for i, (conn, t_bag, raw) in enumerate(reader.messages(connections=conns)):
            if progress is not None:
                progress(i, n, conn.topic)
            msg = reader.deserialize(raw, conn.msgtype)
            stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
            if stamp == 0:
                stamp = int(t_bag)
            cid = cam_of[conn.topic]
            if step_ns is not None and cid in last and stamp - last[cid] < step_ns:
                continue
            img = message_image(msg, conn.msgtype, f"{bag}: {conn.topic} at {stamp} ns")
            file = Path(out_dir) / cid / f"{stamp:019d}.png"
            if not cv2.imwrite(str(file), img):
                raise OSError(f"cannot write {file}")
            out[cid].append(file)
            last[cid] = stamp
        if progress is not None:
            progress(n, n, "done")
    finally:
        reader_cm.__exit__(None, None, None)
    for cid, files in out.items():
        files.sort()
        if not files:
            raise DatasetError(f"--bag {bag}: no image kept for camera {cid}")
    return out


def _progress(i: int, n: int, name: str) -> None:
    width = 30
    done = int(width * i / max(n, 1))
    sys.stderr.write(f"\r[{'#' * done}{'.' * (width - done)}] {i}/{n} messages {name[:30]:<30}")
    if i >= n:
        sys.stderr.write("\n")
    sys.stderr.flush()


def run_cli(args) -> int:
    """``detect --bag FILE --topics T1 [T2 ...]``: extract, then detect as image folders."""
    import tempfile

    from . import detect, detect_rig

    if args.images or getattr(args, "camera", None):
        raise OptionsError("--bag reads the images from the bag: give no IMAGES nor --camera")
    if not args.topics:
        raise OptionsError("--bag needs --topics TOPIC [TOPIC ...] (the image topics)")
    with tempfile.TemporaryDirectory(prefix="gtsam_sphere_bag_") as tmp:
        files = extract_bag_images(
            args.bag,
            list(args.topics),
            tmp,
            freq_hz=args.bag_freq,
            progress=None if args.no_progress else _progress,
        )
        for cid, paths in files.items():
            print(f"{cid}: {len(paths)} images from the bag", file=sys.stderr)
        if len(files) == 1:
            args.images = [str(p) for p in next(iter(files.values()))]
            return detect.run_cli(args)
        args.camera = [f"{cid}={Path(tmp) / cid}" for cid in files]
        args.sync = "timestamp"
        args.sync_tolerance = args.approx_sync
        args.timestamp_unit = "ns"
        return detect_rig.run_cli(args)
