"""``detect --bag`` (issue 15, item 2): ROS1 and ROS2 bags written with ``rosbags``.

Skipped when the optional ``rosbags`` package is absent (``pip install 'gtsam-sphere[ros]'``).
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

rosbags = pytest.importorskip("rosbags", reason="the optional 'rosbags' package is absent")

from rosbags.typesys import Stores, get_typestore  # noqa: E402
from test_kalibr_target import APRILGRID_YAML, _render  # noqa: E402

from gtsam_sphere.apps.rosbag_images import camera_ids_of_topics  # noqa: E402
from gtsam_sphere.cli import main  # noqa: E402

STAMP0 = 1_700_000_000 * 10**9


@pytest.fixture(scope="module")
def views():
    return [_render(v)[0] for v in ("front", "side")]


def _messages(typestore, views, n=4, offset_ns=5_000_000):
    """(topic, msgtype, stamp_ns, message) of a 2-camera stream: cam0 raw mono8, cam1 PNG
    compressed 5 ms later; n frames 0.1 s apart."""
    Image = typestore.types["sensor_msgs/msg/Image"]
    Compressed = typestore.types["sensor_msgs/msg/CompressedImage"]
    Header = typestore.types["std_msgs/msg/Header"]
    Time = typestore.types["builtin_interfaces/msg/Time"]
    out = []
    for k in range(n):
        img = views[k % len(views)]
        t0 = STAMP0 + k * 100_000_000
        for topic, t in (("/cam0/image_raw", t0), ("/cam1/image_raw", t0 + offset_ns)):
            stamp = Time(sec=t // 10**9, nanosec=t % 10**9)
            ros1 = "seq" in Header.__dataclass_fields__  # ROS1 headers carry a sequence number
            extra = {"seq": k} if ros1 else {}
            header = Header(stamp=stamp, frame_id=topic[1:5], **extra)
            if topic.startswith("/cam0"):
                msg = Image(
                    header=header,
                    height=img.shape[0],
                    width=img.shape[1],
                    encoding="mono8",
                    is_bigendian=0,
                    step=img.shape[1],
                    data=np.ascontiguousarray(img).ravel(),
                )
                out.append((topic, "sensor_msgs/msg/Image", t, msg))
            else:
                data = np.frombuffer(cv2.imencode(".png", img)[1].tobytes(), np.uint8)
                msg = Compressed(header=header, format="png", data=data)
                out.append((topic, "sensor_msgs/msg/CompressedImage", t, msg))
    return out


def _write_ros1(path, views):
    from rosbags.rosbag1 import Writer

    ts = get_typestore(Stores.ROS1_NOETIC)
    with Writer(path) as w:
        conns = {}
        for topic, msgtype, t, msg in _messages(ts, views):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=ts)
            w.write(conns[topic], t, ts.serialize_ros1(msg, msgtype))


def _write_ros2(path, views):
    from rosbags.rosbag2 import Writer

    ts = get_typestore(Stores.ROS2_HUMBLE)
    with Writer(path, version=8) as w:
        conns = {}
        for topic, msgtype, t, msg in _messages(ts, views):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=ts)
            w.write(conns[topic], t, ts.serialize_cdr(msg, msgtype))


def test_camera_ids_of_topics():
    assert camera_ids_of_topics(["/cam0/image_raw", "/cam1/image_raw"]) == ["cam0", "cam1"]
    assert camera_ids_of_topics(["/stereo/left", "/stereo/right"]) == [
        "stereo_left",
        "stereo_right",
    ]


@pytest.mark.slow  # renders a rig into a bag and detects it: 5-8 s each (CI runs it)
@pytest.mark.parametrize("kind", ["ros1", "ros2"])
def test_detect_bag_two_topics_is_a_rig(tmp_path, views, kind, capsys):
    bag = tmp_path / ("cams.bag" if kind == "ros1" else "cams")
    (_write_ros1 if kind == "ros1" else _write_ros2)(bag, views)
    target = tmp_path / "target.yaml"
    target.write_text(APRILGRID_YAML)
    out = tmp_path / "rig.json"
    topics = ["/cam0/image_raw", "/cam1/image_raw"]
    argv = ["detect", "--bag", str(bag), "--topics", *topics, "--target", str(target)]
    assert main([*argv, "-o", str(out), "--no-progress"]) == 0
    doc = json.loads(out.read_text())
    assert doc["format"] == "gtsam-sphere/dataset@2"
    assert [c["id"] for c in doc["cameras"]] == ["cam0", "cam1"]
    frames = {}
    for im in doc["images"]:
        frames.setdefault(im.get("frame"), []).append(im["id"])
    assert len(frames) == 4 and all(len(v) == 2 for v in frames.values())  # 5 ms < 0.02 s
    front = [im for im in doc["images"] if im["id"].startswith("cam0/")][0]
    assert len(front["observations"]) == 144  # the raw mono8 front view
    # --bag-freq 5: one image per topic every 0.2 s (frames 0.1 s apart): 2 frames
    assert main([*argv, "-o", str(out), "--no-progress", "--bag-freq", "5"]) == 0
    assert len(json.loads(out.read_text())["images"]) == 4
    # a tolerance below the 5 ms offset pairs nothing
    assert main([*argv, "-o", str(out), "--no-progress", "--approx-sync", "0.001"]) == 0
    assert not any("frame" in im for im in json.loads(out.read_text())["images"])
    capsys.readouterr()


def test_detect_bag_one_topic_and_errors(tmp_path, views, capsys):
    bag = tmp_path / "cams.bag"
    _write_ros1(bag, views)
    target = tmp_path / "target.yaml"
    target.write_text(APRILGRID_YAML)
    out = tmp_path / "ds.json"
    base = ["detect", "--bag", str(bag), "--target", str(target), "-o", str(out), "--no-progress"]
    assert main([*base, "--topics", "/cam1/image_raw"]) == 0  # compressed images
    doc = json.loads(out.read_text())
    assert doc["format"] == "gtsam-sphere/dataset@1" and len(doc["images"]) == 4
    capsys.readouterr()
    assert main([*base, "--topics", "/cam9/image_raw"]) == 2
    assert "/cam9/image_raw" in capsys.readouterr().err
    assert main([*base]) == 2  # no --topics
    assert "--topics" in capsys.readouterr().err


@pytest.mark.slow  # end-to-end: 7 renders into a bag, detect --bag, calibrate, export
@pytest.mark.parametrize("kind", ["ros1", "ros2"])
def test_bag_to_calibration_to_kalibr_recovers_the_lens(tmp_path, kind, capsys):
    """Issue 15: an AprilGrid (Kalibr's 6x6, 88 mm, spacing 0.3) through a 200 degree
    fisheye, in a bag -> detect --bag -> calibrate -> export --to kalibr-equi."""
    yaml = pytest.importorskip("yaml")
    from test_kalibr_target import CALIBRATION_VIEWS, GRID, LENS, H, W

    from gtsam_sphere.estimation.calibrate import CalibrationOptions, calibrate
    from gtsam_sphere.io.dataset import load_dataset
    from gtsam_sphere.simulate.render import render_board_image

    views = []
    for k, (R, t) in enumerate(CALIBRATION_VIEWS.values()):
        img, _ = render_board_image(
            GRID,
            LENS.project,
            LENS.unproject,
            R,
            t,
            W,
            H,
            px_per_square=100,
            supersample=3,
            blur_sigma_px=0.8,
            noise_sigma=2.0,
            seed=k,
        )
        views.append(img)
    bag = tmp_path / ("cams.bag" if kind == "ros1" else "cams")
    ts = get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)
    messages = [m for m in _messages(ts, views, n=len(views)) if m[0] == "/cam0/image_raw"]
    if kind == "ros1":
        from rosbags.rosbag1 import Writer

        with Writer(bag) as w:
            conn = w.add_connection("/cam0/image_raw", messages[0][1], typestore=ts)
            for _, msgtype, t, msg in messages:
                w.write(conn, t, ts.serialize_ros1(msg, msgtype))
    else:
        from rosbags.rosbag2 import Writer

        with Writer(bag, version=8) as w:
            conn = w.add_connection("/cam0/image_raw", messages[0][1], typestore=ts)
            for _, msgtype, t, msg in messages:
                w.write(conn, t, ts.serialize_cdr(msg, msgtype))
    target = tmp_path / "target.yaml"
    target.write_text(APRILGRID_YAML)
    ds = tmp_path / "ds.json"
    argv = ["detect", "--bag", str(bag), "--topics", "/cam0/image_raw", "--target", str(target)]
    assert main([*argv, "-o", str(ds), "--no-progress"]) == 0
    options = CalibrationOptions(model="radial", radial_terms=0, brown_terms=(), covariance=True)
    calib = calibrate(load_dataset(ds), options)
    cam, sig = calib.camera, calib.statistics["intrinsics_sigma"]
    capsys.readouterr()
    with capsys.disabled():
        print(
            f"{kind}: {calib.statistics['n_observations']} corners, RMS "
            f"{calib.statistics['rms_px']:.4f} px; xp {cam.xp - LENS.cx:+.4f} "
            f"({sig['xp_px']:.4f}), yp {cam.yp - LENS.cy:+.4f} ({sig['yp_px']:.4f}), "
            f"c {cam.c - LENS.f:+.4f} ({sig['c_px']:.4f}) px"
        )
    for est, true, s in (
        (cam.xp, LENS.cx, sig["xp_px"]),
        (cam.yp, LENS.cy, sig["yp_px"]),
        (cam.c, LENS.f, sig["c_px"]),
    ):
        assert abs(est - true) < 3 * s, (est, true, s)
    calib_path = calib.save(tmp_path / "calib.json")
    chain = tmp_path / "camchain.yaml"
    assert main(["export", str(calib_path), "--to", "kalibr-equi", "-o", str(chain)]) in (0, 1)
    doc = yaml.safe_load(chain.read_text())["cam0"]
    assert doc["camera_model"] == "pinhole" and doc["distortion_model"] == "equidistant"
    assert len(doc["intrinsics"]) == 4 and len(doc["distortion_coeffs"]) == 4
    assert doc["resolution"] == [W, H] and doc["rostopic"].startswith("/")
    capsys.readouterr()
