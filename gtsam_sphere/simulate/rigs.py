"""Seeded simulated camera rigs moving through the paper's room (``dataset@2``).

A rig is several cameras fixed to one body. At each frame the body stands at a
station drawn by the room's pose sampler (:mod:`gtsam_sphere.simulate.room`:
inside the room, varied heading and tilt, portrait every other frame); every
camera images the room's targets through its own true lens at
``cam_from_world = cam_from_rig * rig_from_world``. The rig frame is the first
camera's frame (``cam_from_rig`` of ``cameras[0]`` is the identity), as the data
contract says.

Rigs (:data:`RIG_KINDS`):

``stereo``
    Two forward Kannala-Brandt fisheyes (190 degrees, circular image), 0.12 m
    apart along the rig ``x`` axis, converging by half a degree.
``dual360``
    Two 220 degree fisheyes back to back (the second turned 180 degrees about the
    rig's ``y`` axis), their centres 3 cm apart: together they see the whole sphere.
``ring4``
    Four outward cameras at 90 degree steps of heading, 120 degree diagonal fisheyes
    on portrait sensors (2:3). Every ray a camera images lies within 45 degrees of
    heading of its axis, so no two cameras share any field of view: they are tied
    only through the room's surveyed targets.
``mixed``
    One 185 degree fisheye and one 60 degree pinhole with Brown distortion, 0.08 m
    apart, looking the same way.

The lens zoo's rigs (:data:`ZOO_RIG_KINDS`, ``benchmarks/bench_rig.py --zoo``): lens
families and image circles the four above do not have, 0.3 px of noise like them:

``dual360-small-circle``
    Two 250 degree equisolid fisheyes back to back on 1600x1600 sensors, each image
    circle 0.32 of the short side (the issue-12 case that failed a single camera),
    the second's principal point 12 and 10 px off centre.
``catadioptric-stereo``
    Two 220 degree unified (catadioptric) cameras, circles 0.4 of a 1280x960 sensor,
    0.12 m apart.
``double-sphere-stereo``
    Two 240 degree double-sphere fisheyes, circles 0.45 of 1024x1024, 0.10 m apart,
    diverging by 5 degrees.
``fov-ring3``
    Three 170 degree field-of-view-model lenses (``omega = 1.5``) on 1280x800, at 120
    degree steps of heading on a ring of radius 5 cm.
``stereographic-pinhole``
    A 300 degree stereographic fisheye on a 0.3 circle of 1920x1080 and a 90 degree
    pinhole with Brown terms (principal point 40 and 25 px off centre), 0.08 m apart.
``cropped-stereo``
    Two 200 degree Kannala-Brandt fisheyes whose circle (1.2 times the half diagonal
    of 1280x800) the sensor crops, 0.11 m apart.

Any other rig: ``RigOptions(rig="my-rig", cameras=(RigCamera(...), ...))`` with lenses
from :func:`~gtsam_sphere.simulate.lenses.make_lens` (every family, field of view and
image circle of the single-camera simulator).

A frame's pose is redrawn until every camera sees at least
``preferred_targets_per_image`` targets (after 50 tries, at least
``min_targets_per_image``; after 300, the best pose found). A camera that still sees
fewer than ``min_targets_per_image`` targets loses its image of that frame; the
frame stays (the count is in the truth's statistics). Pixels get Gaussian noise
(``noise_px`` per axis); there are no blunders.

The same seed gives byte-identical files (:func:`write_rig_simulation`):
``dataset.json`` (``dataset@2``), ``checkpoints.json`` (``checkpoints@1``) and
``truth.json`` (``truth@2``: a ``calibration@2``-like layout holding each camera's
true lens and ``cam_from_rig``, each frame's ``rig_from_world``, each image's
``cam_from_world`` and the true targets).
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..core.errors import OptionsError
from .lenses import ErrorField, make_lens
from .room import (
    SimulationOptions,
    _jsonable,
    _observe,
    _room_scene,
    _write_json_atomic,
    checkpoint_file,
)

__all__ = [
    "RIG_KINDS",
    "ZOO_RIG_KINDS",
    "RIG_DATASET_FORMAT",
    "RIG_TRUTH_FORMAT",
    "RigCamera",
    "RigOptions",
    "RigSimulation",
    "check_rig_cameras",
    "rig_cameras",
    "simulate_rig",
    "write_rig_simulation",
]

RIG_KINDS = ("stereo", "dual360", "ring4", "mixed")
ZOO_RIG_KINDS = (
    "dual360-small-circle",
    "catadioptric-stereo",
    "double-sphere-stereo",
    "fov-ring3",
    "stereographic-pinhole",
    "cropped-stereo",
)
RIG_DATASET_FORMAT = "gtsam-sphere/dataset@2"
RIG_TRUTH_FORMAT = "gtsam-sphere/truth@2"

Pose = tuple[np.ndarray, np.ndarray]


@dataclass
class RigOptions:
    """Everything that defines a simulated rig calibration in the room.

    Attributes
    ----------
    rig : str
        One of :data:`RIG_KINDS` or :data:`ZOO_RIG_KINDS`; with ``cameras``, any name.
    n_frames : int
        Number of rig poses (frames).
    noise_px : float
        Pixel noise standard deviation per axis.
    seed : int
        Seed of the whole simulation.
    n_targets : int
        Targets over the room's faces.
    target_sigma_m : float
        Noise (per axis, metres) of the approximate target coordinates written to
        the dataset, with that ``sigma``.
    n_checkpoints : int
        Targets whose true coordinates go to the check-point file.
    checkpoint_noise_m : float
        Noise (per axis, metres) of the check points.
    min_targets_per_image : int
        A camera seeing fewer targets in a frame loses that image.
    preferred_targets_per_image : int
        A pose is accepted at once when every camera sees this many targets.
    error_field_px : float
        Amplitude (px) of a smooth error field in every camera's lens (each its own,
        seeded with ``seed + 7919 + k`` for camera ``k``, as
        :func:`~gtsam_sphere.simulate.room.build_lens` does): what no radial
        or Brown term holds and a kNN correction learns; 0 = none.
    room : SimulationOptions
        The room (size, wall clearance, station heights, tilt, margins, facing and
        range limits); its lens, image size and counts are not used.
    cameras : tuple of RigCamera or None
        A rig of one's own: these cameras (the first is the rig frame: its
        ``cam_from_rig`` is the identity; ids unique) instead of :func:`rig_cameras`,
        and ``rig`` is only the rig's name (any non-empty string). None: the rig
        ``rig`` of :data:`RIG_KINDS` or :data:`ZOO_RIG_KINDS`.
    """

    rig: str = "stereo"
    n_frames: int = 12
    noise_px: float = 0.3
    seed: int = 0
    n_targets: int = 370
    target_sigma_m: float = 0.01
    n_checkpoints: int = 191
    checkpoint_noise_m: float = 0.0
    min_targets_per_image: int = 8
    preferred_targets_per_image: int = 20
    error_field_px: float = 0.0
    room: SimulationOptions = field(default_factory=SimulationOptions)
    cameras: tuple[RigCamera, ...] | None = None

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first inconsistent option."""
        if self.cameras is None:
            if self.rig not in RIG_KINDS + ZOO_RIG_KINDS:
                raise ValueError(
                    f"rig must be one of {RIG_KINDS + ZOO_RIG_KINDS}, got {self.rig!r}"
                )
        else:
            check_rig_cameras(self.cameras)
            if not isinstance(self.rig, str) or not self.rig:
                raise ValueError(f"rig must name the rig (a non-empty string), got {self.rig!r}")
        if self.n_frames < 1 or self.n_targets < 1:
            raise ValueError("n_frames and n_targets must be positive")
        if self.noise_px < 0 or self.target_sigma_m < 0 or self.checkpoint_noise_m < 0:
            raise ValueError("noise_px, target_sigma_m and checkpoint_noise_m must be >= 0")
        if not math.isfinite(self.error_field_px) or self.error_field_px < 0:
            raise ValueError(f"error_field_px must be >= 0, got {self.error_field_px}")
        if self.n_checkpoints < 0:
            raise ValueError("n_checkpoints must be >= 0")
        if self.min_targets_per_image < 1:
            raise ValueError("min_targets_per_image must be positive")
        self.room.validate()


@dataclass(frozen=True)
class RigCamera:
    """One camera of a rig: its true lens and where it sits on the body.

    Attributes
    ----------
    id : str
    lens : lens object
        True lens (``project`` / ``unproject`` / ``to_dict``).
    width, height : int
        Image size, px.
    fov_deg : float
        Full field of view (degrees): no target beyond ``fov_deg / 2`` of incidence
        is observed.
    cam_from_rig : (ndarray (3, 3), ndarray (3,))
        ``p_cam = R @ p_rig + t``, metres.
    """

    id: str
    lens: Any
    width: int
    height: int
    fov_deg: float
    cam_from_rig: Pose


def check_rig_cameras(cameras: Any) -> None:
    """Raise ``ValueError`` naming the first camera of ``cameras`` that no rig can hold.

    Parameters
    ----------
    cameras : sequence of RigCamera
        At least one; ids unique non-empty strings; sizes and ``fov_deg`` positive; the
        first camera's ``cam_from_rig`` the identity (the rig frame is its frame, as the
        data contract says); every ``cam_from_rig`` a rotation (3, 3) and a
        translation (3,), metres.
    """
    if not isinstance(cameras, list | tuple) or not cameras:
        raise ValueError(f"cameras must be a non-empty sequence of RigCamera, got {cameras!r}")
    seen: set[str] = set()
    for k, cam in enumerate(cameras):
        if not isinstance(cam, RigCamera):
            raise ValueError(f"cameras[{k}] must be a RigCamera, got {type(cam).__name__}")
        name = f"camera {cam.id!r} (cameras[{k}])"
        if not isinstance(cam.id, str) or not cam.id:
            raise ValueError(f"cameras[{k}] needs a non-empty string id, got {cam.id!r}")
        if cam.id in seen:
            raise ValueError(f"{name}: the id is used twice")
        seen.add(cam.id)
        if int(cam.width) < 1 or int(cam.height) < 1:
            raise ValueError(f"{name}: image size must be positive, got {cam.width}x{cam.height}")
        if not math.isfinite(cam.fov_deg) or cam.fov_deg <= 0:
            raise ValueError(f"{name}: fov_deg must be positive, got {cam.fov_deg}")
        R = np.asarray(cam.cam_from_rig[0], float)
        t = np.asarray(cam.cam_from_rig[1], float)
        if R.shape != (3, 3) or t.shape != (3,):
            raise ValueError(
                f"{name}: cam_from_rig must be (R (3, 3), t (3,)), got {R.shape} and {t.shape}"
            )
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-9) or np.linalg.det(R) < 0:
            raise ValueError(f"{name}: cam_from_rig's R is not a rotation")
        if k == 0 and (not np.allclose(R, np.eye(3), atol=1e-12) or np.any(t != 0.0)):
            raise ValueError(f"{name} is the rig frame: its cam_from_rig must be the identity")


def _rotation(axis: Any, deg: float) -> np.ndarray:
    """Rotation matrix by ``deg`` degrees about ``axis`` (Rodrigues)."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    th = math.radians(deg)
    return np.eye(3) + math.sin(th) * K + (1.0 - math.cos(th)) * (K @ K)


def _mount(rig_from_cam_R: np.ndarray, centre_rig: Any) -> Pose:
    """``cam_from_rig`` of a camera whose axes are ``rig_from_cam_R``'s columns,
    its perspective centre at ``centre_rig`` (rig frame, metres)."""
    R = np.asarray(rig_from_cam_R, float).T
    return R, -R @ np.asarray(centre_rig, float)


_IDENTITY: Pose = (np.eye(3), np.zeros(3))


def rig_cameras(kind: str) -> list[RigCamera]:
    """The cameras of the rig ``kind`` (see the module docstring), first = rig frame.

    Parameters
    ----------
    kind : str
        One of :data:`RIG_KINDS` or :data:`ZOO_RIG_KINDS`.

    Returns
    -------
    list of RigCamera
    """
    if kind == "stereo":
        size = (1280, 1024)
        return [
            RigCamera(
                "left",
                make_lens("kannala-brandt", 190.0, *size, fill="circle", k1=0.02, k2=-0.004),
                *size,
                190.0,
                _IDENTITY,
            ),
            RigCamera(
                "right",
                make_lens(
                    "kannala-brandt",
                    190.0,
                    *size,
                    fill="circle",
                    k1=0.015,
                    k2=-0.003,
                    cx=641.7,
                    cy=509.2,
                ),
                *size,
                190.0,
                _mount(_rotation([0.2, 1.0, 0.1], -0.5), [0.12, 0.0, 0.0]),
            ),
        ]
    if kind == "dual360":
        size = (1200, 1200)
        return [
            RigCamera(
                "front",
                make_lens("kannala-brandt", 220.0, *size, fill="circle", k1=0.01),
                *size,
                220.0,
                _IDENTITY,
            ),
            RigCamera(
                "back",
                make_lens(
                    "kannala-brandt", 220.0, *size, fill="circle", k1=0.008, cx=600.8, cy=598.6
                ),
                *size,
                220.0,
                _mount(_rotation([0.0, 1.0, 0.0], 180.0), [0.0, 0.0, -0.03]),
            ),
        ]
    if kind == "ring4":
        size = (800, 1200)  # portrait 2:3: every imaged ray within 45 deg of heading
        families = ("equidistant", "kannala-brandt", "equidistant", "kannala-brandt")
        names = ("front", "right", "back", "left")
        cams = []
        for k, (name, family) in enumerate(zip(names, families, strict=True)):
            extra = {"k1": 0.01} if family == "kannala-brandt" else {}
            heading = 90.0 * k  # about the rig's y axis (down): front, right, back, left
            R = _rotation([0.0, 1.0, 0.0], heading)
            centre = 0.06 * R[:, 2] - 0.06 * np.array([0.0, 0.0, 1.0])  # ring of radius 6 cm
            pose = _IDENTITY if k == 0 else _mount(R, centre)
            cams.append(
                RigCamera(
                    name,
                    make_lens(family, 120.0, *size, fill="diagonal", **extra),
                    *size,
                    120.0,
                    pose,
                )
            )
        return cams
    if kind == "mixed":
        fish = (1024, 1024)
        pin = (1280, 960)
        return [
            RigCamera(
                "fisheye",
                make_lens("equidistant", 185.0, *fish, fill="circle"),
                *fish,
                185.0,
                _IDENTITY,
            ),
            RigCamera(
                "pinhole",
                make_lens("pinhole", 60.0, *pin, fill="diagonal", k1=-0.05, k2=0.01),
                *pin,
                60.0,
                _mount(_rotation([1.0, 0.3, 0.0], 1.0), [0.08, 0.0, 0.0]),
            ),
        ]
    if kind in ZOO_RIG_KINDS:
        return _zoo_rig_cameras(kind)
    raise ValueError(f"rig must be one of {RIG_KINDS + ZOO_RIG_KINDS}, got {kind!r}")


def _unified_xi(fov_deg: float) -> float:
    """The unified model's ``xi`` whose largest incidence ``acos(-1 / xi)`` leaves about
    10 degrees of headroom past ``fov_deg / 2`` (as the lens zoo draws it)."""
    return round(-1.0 / math.cos(math.radians(min(fov_deg / 2.0 + 10.0, 178.0))), 4)


def _twin(
    names: tuple[str, str],
    family: str,
    fov_deg: float,
    size: tuple[int, int],
    radius_px: float,
    second_from_rig: Pose,
    second: dict[str, float] | None = None,
    **shape: float,
) -> list[RigCamera]:
    """Two cameras of one lens ``family`` (``fov_deg``, image ``size``, circle of
    ``radius_px``, ``shape`` options), the first at the rig frame, the second at
    ``second_from_rig`` with the lens options ``second`` added (e.g. its own ``cx``)."""
    w, h = size

    def lens(extra):
        return make_lens(family, fov_deg, w, h, circle_radius_px=radius_px, **shape, **extra)

    return [
        RigCamera(names[0], lens({}), w, h, fov_deg, _IDENTITY),
        RigCamera(names[1], lens(second or {}), w, h, fov_deg, second_from_rig),
    ]


def _zoo_rig_cameras(kind: str) -> list[RigCamera]:
    """The cameras of the zoo rig ``kind`` (:data:`ZOO_RIG_KINDS`, module docstring)."""
    stereo = ("left", "right")
    if kind == "dual360-small-circle":
        back = _mount(_rotation([0.0, 1.0, 0.0], 180.0), [0.0, 0.0, -0.03])
        off_centre = {"cx": 811.5, "cy": 809.5}
        return _twin(("front", "back"), "equisolid", 250.0, (1600, 1600), 0.32 * 1600, back,
                     off_centre)  # fmt: skip
    if kind == "catadioptric-stereo":
        right = _mount(_rotation([0.2, 1.0, 0.1], -0.5), [0.12, 0.0, 0.0])
        return _twin(stereo, "unified", 220.0, (1280, 960), 0.4 * 960, right,
                     {"cx": 650.0, "cy": 470.0}, xi=_unified_xi(220.0))  # fmt: skip
    if kind == "double-sphere-stereo":
        right = _mount(_rotation([0.0, 1.0, 0.0], 5.0), [0.10, 0.0, 0.0])
        return _twin(stereo, "double-sphere", 240.0, (1024, 1024), 0.45 * 1024, right,
                     xi=-0.1, alpha=0.52)  # fmt: skip
    if kind == "cropped-stereo":
        right = _mount(_rotation([0.0, 1.0, 0.0], -3.0), [0.11, 0.0, 0.0])
        radius = 1.2 * math.hypot(640.0, 400.0)  # 1.2x the half diagonal of 1280x800
        return _twin(stereo, "kannala-brandt", 200.0, (1280, 800), radius, right,
                     k1=0.03, k2=-0.008)  # fmt: skip
    if kind == "fov-ring3":
        w, h = 1280, 800
        cams = []
        for k, name in enumerate(("a", "b", "c")):
            R = _rotation([0.0, 1.0, 0.0], 120.0 * k)
            centre = 0.05 * R[:, 2] - 0.05 * np.array([0.0, 0.0, 1.0])  # ring of radius 5 cm
            lens = make_lens("fov", 170.0, w, h, fill="diagonal", omega=1.5)
            pose = _IDENTITY if k == 0 else _mount(R, centre)
            cams.append(RigCamera(name, lens, w, h, 170.0, pose))
        return cams
    if kind == "stereographic-pinhole":
        fisheye = make_lens("stereographic", 300.0, 1920, 1080, circle_radius_px=0.3 * 1080)
        pinhole = make_lens("pinhole", 90.0, 1280, 960, fill="diagonal", k1=-0.1, k2=0.02,
                            cx=679.5, cy=504.5)  # fmt: skip
        pinhole_from_rig = _mount(_rotation([1.0, 0.3, 0.0], 1.0), [0.08, 0.0, 0.0])
        return [
            RigCamera("fisheye", fisheye, 1920, 1080, 300.0, _IDENTITY),
            RigCamera("pinhole", pinhole, 1280, 960, 90.0, pinhole_from_rig),
        ]
    raise ValueError(f"zoo rig must be one of {ZOO_RIG_KINDS}, got {kind!r}")


@dataclass
class RigSimulation:
    """Result of :func:`simulate_rig`.

    Attributes
    ----------
    dataset : dict
        ``gtsam-sphere/dataset@2`` document.
    checkpoints : dict
        ``gtsam-sphere/checkpoints@1`` document.
    truth : dict
        ``gtsam-sphere/truth@2`` document.
    cameras : list of RigCamera
        The true cameras.
    """

    dataset: dict[str, Any]
    checkpoints: dict[str, Any]
    truth: dict[str, Any]
    cameras: list[RigCamera]


def _compose(a: Pose, b: Pose) -> Pose:
    return a[0] @ b[0], a[0] @ b[1] + a[1]


def _pose_doc(pose: Pose) -> dict[str, Any]:
    R, t = pose
    return {"R": [[float(v) for v in row] for row in R], "t": [float(v) for v in t]}


def _camera_options(room: SimulationOptions, cam: RigCamera) -> SimulationOptions:
    return replace(room, width=cam.width, height=cam.height, fov_deg=cam.fov_deg)


def _look(cams, cam_opts, scene, rig_pose: Pose):
    """Per camera: (visible target indices, true pixels, incidence angles, cam_from_world)."""
    out = []
    for cam, opts in zip(cams, cam_opts, strict=True):
        R, t = _compose(cam.cam_from_rig, rig_pose)
        centre = -R.T @ t
        keep, uv, alpha = _observe(cam.lens, opts, R, t, centre, scene.xyz, scene.normals)
        out.append((keep, uv, alpha, (R, t)))
    return out


def _draw_frame(j, options: RigOptions, cams, cam_opts, scene, rng):
    """The rig pose of frame ``j`` and what each camera sees from it."""
    lo, hi = options.min_targets_per_image, options.preferred_targets_per_image
    best = None
    for attempt in range(300):
        R, t, centre, label = scene.sample_pose(j, rng)
        views = _look(cams, cam_opts, scene, (R, t))
        counts = [v[0].size for v in views]
        score = (sum(c >= lo for c in counts), min(min(counts), hi), sum(counts))
        if best is None or score > best[0]:
            best = (score, (R, t), centre, label, views)
        if min(counts) >= hi or (attempt >= 50 and min(best[0][1], hi) >= lo):
            break
    return best[1:]


def simulate_rig(options: RigOptions | None = None) -> RigSimulation:
    """Simulate a rig moving through the paper's room.

    Parameters
    ----------
    options : RigOptions or None
        Default ``RigOptions()`` (the stereo rig, 12 frames, seed 0).

    Returns
    -------
    RigSimulation
        Dataset (``dataset@2``), check points, truth (``truth@2``) and the cameras.

    Raises
    ------
    ValueError
        Inconsistent options.
    OptionsError
        A camera that sees ``min_targets_per_image`` targets in no frame.
    """
    options = options if options is not None else RigOptions()
    options.validate()
    rng = np.random.default_rng(options.seed)
    cams = list(options.cameras) if options.cameras is not None else rig_cameras(options.rig)
    if options.error_field_px:
        cams = [
            replace(
                cam,
                lens=ErrorField(
                    cam.lens,
                    options.error_field_px,
                    seed=options.seed + 7919 + k,
                    scale_px=float(max(cam.width, cam.height)),
                ),
            )
            for k, cam in enumerate(cams)
        ]
    room = replace(options.room, n_targets=options.n_targets)
    cam_opts = [_camera_options(room, cam) for cam in cams]
    scene = _room_scene(room, None, rng)
    xyz = scene.xyz
    n_t = xyz.shape[0]
    target_ids = [f"T{i + 1:04d}" for i in range(n_t)]

    frames, images = [], []
    n_dropped = 0
    for j in range(options.n_frames):
        rig_pose, centre, label, views = _draw_frame(j, options, cams, cam_opts, scene, rng)
        frame_id = f"{j + 1:04d}"
        frames.append(
            {
                "id": frame_id,
                "rig_from_world": rig_pose,
                "centre": centre,
                "orientation": label,
            }
        )
        for cam, (keep, uv, alpha, pose) in zip(cams, views, strict=True):
            if keep.size < options.min_targets_per_image:
                n_dropped += 1
                continue
            uv_obs = uv + rng.normal(0.0, options.noise_px, uv.shape)
            uv_obs[:, 0] = np.clip(uv_obs[:, 0], -0.5, cam.width - 0.5)
            uv_obs[:, 1] = np.clip(uv_obs[:, 1], -0.5, cam.height - 0.5)
            images.append(
                {
                    "id": f"{cam.id}_{frame_id}",
                    "camera": cam.id,
                    "frame": frame_id,
                    "pose": pose,
                    "targets": keep,
                    "uv": uv_obs,
                    "alpha": alpha,
                }
            )
    for cam in cams:
        if not any(img["camera"] == cam.id for img in images):
            raise OptionsError(
                f"camera {cam.id!r} sees {options.min_targets_per_image} targets in no frame; "
                "increase n_targets or n_frames"
            )

    n_obs_per_target = np.zeros(n_t, dtype=int)
    for img in images:
        np.add.at(n_obs_per_target, img["targets"], 1)
    used = np.flatnonzero(n_obs_per_target > 0)
    approx = xyz + rng.normal(0.0, options.target_sigma_m, xyz.shape)
    dataset = {
        "format": RIG_DATASET_FORMAT,
        "units": "m",
        "cameras": [{"id": c.id, "width": int(c.width), "height": int(c.height)} for c in cams],
        "targets": [
            {
                "id": target_ids[i],
                "xyz": [float(v) for v in approx[i]],
                "sigma": float(options.target_sigma_m),
            }
            for i in used
        ],
        "images": [
            {
                "id": img["id"],
                "camera": img["camera"],
                "frame": img["frame"],
                "observations": [
                    {"target": target_ids[i], "uv": [float(v) for v in p]}
                    for i, p in zip(img["targets"], img["uv"], strict=True)
                ],
            }
            for img in images
        ],
    }

    checkpoints = checkpoint_file(
        used, n_obs_per_target, xyz, target_ids, options.n_checkpoints,
        options.checkpoint_noise_m, rng,
    )  # fmt: skip

    alpha = np.concatenate([img["alpha"] for img in images])
    per_camera = {
        cam.id: {
            "n_images": sum(img["camera"] == cam.id for img in images),
            "n_observations": int(
                sum(img["targets"].size for img in images if img["camera"] == cam.id)
            ),
        }
        for cam in cams
    }
    truth = {
        "format": RIG_TRUTH_FORMAT,
        "units": "m",
        "rig": options.rig,
        "scene": "room",
        # a custom rig's cameras are the truth's "cameras" below (lens objects are no JSON)
        "options": _jsonable(asdict(replace(options, cameras=None))),
        "cameras": [
            {
                "id": cam.id,
                "width": int(cam.width),
                "height": int(cam.height),
                "fov_deg": float(cam.fov_deg),
                "lens": cam.lens.to_dict(),
                "cam_from_rig": _pose_doc(cam.cam_from_rig),
            }
            for cam in cams
        ],
        "frames": [
            {
                "id": f["id"],
                "rig_from_world": _pose_doc(f["rig_from_world"]),
                "centre_world": [float(v) for v in f["centre"]],
                "orientation": f["orientation"],
            }
            for f in frames
        ],
        "images": [
            {
                "id": img["id"],
                "camera": img["camera"],
                "frame": img["frame"],
                "cam_from_world": _pose_doc(img["pose"]),
            }
            for img in images
        ],
        "targets": [
            {
                "id": target_ids[i],
                "xyz": [float(v) for v in xyz[i]],
                "normal": [float(v) for v in scene.normals[i]],
                "face": scene.labels[i],
                "n_observations": int(n_obs_per_target[i]),
            }
            for i in range(n_t)
        ],
        "statistics": {
            "n_frames": len(frames),
            "n_images": len(images),
            "n_images_dropped": n_dropped,
            "n_targets": int(used.size),
            "n_observations": int(alpha.size),
            "max_incidence_deg": float(alpha.max()),
            "cameras": per_camera,
        },
    }
    return RigSimulation(dataset=dataset, checkpoints=checkpoints, truth=truth, cameras=cams)


def write_rig_simulation(sim: RigSimulation, out_dir: str | os.PathLike[str]) -> dict[str, Path]:
    """Write ``dataset.json``, ``checkpoints.json`` and ``truth.json`` atomically.

    Parameters
    ----------
    sim : RigSimulation
    out_dir : path-like
        Directory (created if missing).

    Returns
    -------
    paths : dict of str to pathlib.Path
        Keys ``"dataset"``, ``"checkpoints"``, ``"truth"``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {key: out / f"{key}.json" for key in ("dataset", "checkpoints", "truth")}
    for key, path in paths.items():
        _write_json_atomic(path, getattr(sim, key))
    return paths
