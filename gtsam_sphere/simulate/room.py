"""Simulated inside-out calibration of a camera in a target room (Chow et al. 2018, Sec. 4).

World frame: origin at a floor corner of a box-shaped room, ``X`` along its
length, ``Y`` along its width, ``Z`` up, metres. Coded targets are spread
roughly uniformly (stratified jitter, density proportional to area) over the
floor, ceiling and four walls; camera stations stand inside the room at
least ``wall_clearance_m`` from every wall, look in varied headings and
tilts, and alternate landscape (roll 0) and portrait (roll 90 degrees).

The same pipeline simulates a planar board or a cube corner seen from
outside (``scene="board"`` / ``"object3d"``, geometry and pose sampling in
:mod:`gtsam_sphere.simulate.scenes`): only the targets and the pose sampler
differ, observation, noise, blunders, the check points and the three
documents are shared.

A target is observed in an image when the lens can image it, its pixel lies
at least ``margin_px`` inside the image (whatever the principal point), its
incidence angle is at most ``fov_deg / 2``, it is at least ``min_range_m``
away and it faces the camera (``normal . view_direction < -facing_cos``). Poses
are redrawn until every image sees at least ``min_targets_per_image``
targets (and preferably ``preferred_targets_per_image``), so no image is
dropped. Pixels then get Gaussian noise
(``noise_px`` per axis) and a fraction ``blunder_rate`` of the observations
is made gross: half (rounded down to an even count) by swapping the labels
of two observations of the same image (kind ``"mislabel"``, which keeps
every (image, target) pair unique), the rest by a 10-50 px offset in a
random direction (kind ``"offset"``), clipped to the image.

Targets no image observes are left out of the dataset (they stay in the
truth file with ``n_observations = 0``); check points are drawn from the
dataset's targets, preferring those seen in at least two images.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..core.errors import OptionsError
from .lenses import ErrorField, NonCentral, make_lens
from .scenes import (
    AimedPoses,
    board_targets,
    board_view_dir,
    corner_view_dir,
    field_half_angle_rad,
    inside_image,
    object3d_targets,
)

__all__ = [
    "SimulationOptions",
    "Simulation",
    "simulate_room",
    "write_simulation",
    "build_lens",
    "nikon_like",
    "gopro_like",
    "SIGMA_MODES",
    "SCENES",
]

SIGMA_MODES = ("weighted", "free", "fixed")
SCENES = ("room", "board", "object3d")
DATASET_FORMAT = "gtsam-sphere/dataset@1"
CHECKPOINTS_FORMAT = "gtsam-sphere/checkpoints@1"
TRUTH_FORMAT = "gtsam-sphere/truth@1"


@dataclass
class SimulationOptions:
    """Everything that defines a simulated calibration (room, board or 3D object).

    Attributes
    ----------
    lens : str
        Lens kind for :func:`~gtsam_sphere.simulate.lenses.make_lens`.
    fov_deg : float
        Full field of view (degrees) over the diagonal or the image circle.
    width, height : int
        Image size in pixels (default 4000 x 3000 like the data contract's
        example; landscape, portrait images are the same sensor rolled).
    fill : str or None
        ``"circle"`` / ``"diagonal"`` / None (see ``make_lens``).
    circle_radius_px : float or None
        Radius (pixels) at which ``fov_deg / 2`` lands; overrides ``fill``
        (see ``make_lens``): from a small circle on a large sensor to a
        circle larger than the half diagonal, cropped by the image.
    lens_options : dict
        Extra lens parameters (``k1``, ``xi``, ``alpha``, ``omega``, ``cx``,
        ``cy`` in pixels, ...) passed to ``make_lens``.
    p1, p2 : float
        Decentering distortion (normalised coordinates).
    a1, a2 : float
        Affinity and shear (Brown/Chow Eq. 5).
    pupil_shift_m : float
        Moving entrance pupil shift at 90 degrees (metres); 0 = central lens.
    error_field_px : float
        Amplitude (pixels) of a smooth non-parametric error field; 0 = none.
    error_field_terms : int
        Number of sinusoids in the error field.
    n_images : int
        Number of images (default 52, the paper's GoPro).
    room_size_m : tuple of float
        Room length, width, height (metres).
    n_targets : int
        Number of targets over floor, ceiling and walls.
    wall_clearance_m : float
        Minimum distance of a camera station from walls.
    station_height_m : tuple of float
        Range of camera heights above the floor (metres).
    tilt_deg : float
        Maximum absolute camera tilt (pitch) from horizontal (degrees).
    noise_px : float
        Standard deviation of pixel noise per axis.
    target_sigma_m : float
        Standard deviation per axis of the approximate target coordinates.
    sigma_mode : str or None
        ``"weighted"`` (write ``sigma = target_sigma_m``), ``"free"`` (omit
        sigma) or ``"fixed"`` (exact coordinates with ``sigma = 0``); None:
        the scene's default, ``"weighted"`` for the room and ``"fixed"`` for
        the printed objects (``"board"``, ``"object3d"``).
    n_checkpoints : int
        Number of targets whose true coordinates go to the checkpoints file.
    checkpoint_noise_m : float
        Standard deviation per axis added to the check point coordinates.
    blunder_rate : float
        Fraction of observations made gross.
    min_targets_per_image : int
        Minimum visible targets for an image to be kept.
    preferred_targets_per_image : int
        A pose is accepted at once when it sees this many targets; otherwise
        the best of 50 or more random poses is kept (at least the minimum).
    margin_px : float
        Minimum distance of an observation from the image border.
    facing_cos : float
        A target is visible when ``normal . view_dir < -facing_cos``.
    min_range_m : float or None
        Minimum camera-to-target distance (metres); None: 0.3 for the room,
        0.05 for the objects.
    seed : int
        Seed used when ``simulate_room`` gets no generator.
    scene : str
        ``"room"`` (targets on the walls, seen inside-out), ``"board"`` (a
        planar grid) or ``"object3d"`` (three orthogonal grids, a cube corner);
        see :mod:`gtsam_sphere.simulate.scenes`.
    board_shape : tuple of int
        ``(cols, rows)`` corners of the board.
    board_spacing_m : float
        Corner spacing of the board (metres).
    board_tilt_deg : float
        Largest angle between a viewing direction and the board normal.
    object_grid : int
        Points per side of each of the cube corner's three grids.
    object_spacing_m : float
        Grid spacing of the cube corner (metres).
    """

    lens: str = "equidistant"
    fov_deg: float = 150.0
    width: int = 4000
    height: int = 3000
    fill: str | None = None
    circle_radius_px: float | None = None
    lens_options: dict[str, float] = field(default_factory=dict)
    p1: float = 0.0
    p2: float = 0.0
    a1: float = 0.0
    a2: float = 0.0
    pupil_shift_m: float = 0.0
    error_field_px: float = 0.0
    error_field_terms: int = 6
    n_images: int = 52
    room_size_m: tuple[float, float, float] = (7.0, 6.0, 3.0)
    n_targets: int = 370
    wall_clearance_m: float = 1.0
    station_height_m: tuple[float, float] = (1.0, 2.0)
    tilt_deg: float = 45.0
    noise_px: float = 0.3
    target_sigma_m: float = 0.01
    sigma_mode: str | None = None
    n_checkpoints: int = 191
    checkpoint_noise_m: float = 0.0
    blunder_rate: float = 0.0
    min_targets_per_image: int = 8
    preferred_targets_per_image: int = 20
    margin_px: float = 5.0
    facing_cos: float = 0.1
    min_range_m: float | None = None
    seed: int = 0
    scene: str = "room"
    board_shape: tuple[int, int] = (12, 9)
    board_spacing_m: float = 0.04
    board_tilt_deg: float = 60.0
    object_grid: int = 8
    object_spacing_m: float = 0.05

    @property
    def effective_sigma_mode(self) -> str:
        """``sigma_mode``, or the scene's default when it is None."""
        if self.sigma_mode is not None:
            return self.sigma_mode
        return "weighted" if self.scene == "room" else "fixed"

    @property
    def effective_min_range_m(self) -> float:
        """``min_range_m``, or the scene's default (metres) when it is None."""
        if self.min_range_m is not None:
            return float(self.min_range_m)
        return 0.3 if self.scene == "room" else 0.05

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first inconsistent option."""
        if self.scene not in SCENES:
            raise ValueError(f"scene must be one of {SCENES}, got {self.scene!r}")
        if self.effective_sigma_mode not in SIGMA_MODES:
            raise ValueError(f"sigma_mode must be one of {SIGMA_MODES}, got {self.sigma_mode!r}")
        if not 0.0 <= self.blunder_rate < 1.0:
            raise ValueError(f"blunder_rate must be in [0, 1), got {self.blunder_rate}")
        if self.n_images < 1 or self.n_targets < 1:
            raise ValueError("n_images and n_targets must be positive")
        if self.width < 2 or self.height < 2:
            raise ValueError(f"bad image size {self.width}x{self.height}")
        if self.noise_px < 0 or self.target_sigma_m < 0 or self.checkpoint_noise_m < 0:
            raise ValueError("noise_px, target_sigma_m and checkpoint_noise_m must be >= 0")
        if self.scene == "board":
            if min(self.board_shape) < 2 or self.board_spacing_m <= 0:
                raise ValueError(f"bad board {self.board_shape} x {self.board_spacing_m} m")
            if not 0.0 < self.board_tilt_deg < 85.0:
                raise ValueError(f"board_tilt_deg must be in (0, 85), got {self.board_tilt_deg}")
        if self.scene == "object3d" and (self.object_grid < 2 or self.object_spacing_m <= 0):
            raise ValueError(f"bad object grid {self.object_grid} x {self.object_spacing_m} m")
        if self.scene != "room":
            return
        length, width, height = self.room_size_m
        c = self.wall_clearance_m
        if min(length, width) <= 2 * c or height <= 0:
            raise ValueError(f"room {self.room_size_m} too small for wall_clearance_m={c}")
        lo, hi = self.station_height_m
        if not 0.0 < lo <= hi < height:
            raise ValueError(f"station_height_m {self.station_height_m} must lie inside the room")


@dataclass
class Simulation:
    """Result of :func:`simulate_room`.

    Attributes
    ----------
    dataset : dict
        ``gtsam-sphere/dataset@1`` document (noisy pixels, approximate targets).
    checkpoints : dict
        ``gtsam-sphere/checkpoints@1`` document (true coordinates of a subset).
    truth : dict
        ``gtsam-sphere/truth@1`` document: lens description, true targets and
        poses, blunders, per-observation incidence angles summary.
    lens : lens object
        The true lens (``project`` / ``unproject``).
    """

    dataset: dict[str, Any]
    checkpoints: dict[str, Any]
    truth: dict[str, Any]
    lens: Any


def build_lens(options: SimulationOptions) -> Any:
    """Build the true lens described by ``options`` (wrappers included).

    Parameters
    ----------
    options : SimulationOptions
        Lens kind, field of view, image size, distortion and imperfections.

    Returns
    -------
    lens : lens object
        ``make_lens(...)``, wrapped in ``NonCentral`` when ``pupil_shift_m`` is
        non-zero and in ``ErrorField`` (seeded with ``options.seed + 7919``,
        frequencies relative to the larger image side) when ``error_field_px``
        is non-zero.
    """
    params = dict(options.lens_options)
    for name in ("p1", "p2", "a1", "a2"):
        value = getattr(options, name)
        if value:
            params[name] = value
    lens = make_lens(
        options.lens,
        options.fov_deg,
        options.width,
        options.height,
        fill=options.fill,
        circle_radius_px=options.circle_radius_px,
        **params,
    )
    if options.pupil_shift_m:
        lens = NonCentral(lens, options.pupil_shift_m)
    if options.error_field_px:
        lens = ErrorField(
            lens,
            options.error_field_px,
            n_terms=options.error_field_terms,
            seed=options.seed + 7919,
            scale_px=float(max(options.width, options.height)),
        )
    return lens


# -- geometry --------------------------------------------------------------------


def _room_faces(size: tuple[float, float, float]) -> list[dict[str, Any]]:
    """Faces as origin, two in-plane axes with extents, inward normal."""
    lx, ly, lz = size
    ex, ey, ez = np.eye(3)
    return [
        {"name": "floor", "o": np.zeros(3), "a": ex * lx, "b": ey * ly, "n": ez},
        {"name": "ceiling", "o": ez * lz, "a": ex * lx, "b": ey * ly, "n": -ez},
        {"name": "wall_x0", "o": np.zeros(3), "a": ey * ly, "b": ez * lz, "n": ex},
        {"name": "wall_x1", "o": ex * lx, "a": ey * ly, "b": ez * lz, "n": -ex},
        {"name": "wall_y0", "o": np.zeros(3), "a": ex * lx, "b": ez * lz, "n": ey},
        {"name": "wall_y1", "o": ey * ly, "a": ex * lx, "b": ez * lz, "n": -ey},
    ]


def _place_targets(options: SimulationOptions, rng: np.random.Generator):
    """Stratified-jitter targets on the six faces; returns xyz, normals, face names."""
    faces = _room_faces(options.room_size_m)
    areas = np.array([np.linalg.norm(f["a"]) * np.linalg.norm(f["b"]) for f in faces])
    raw = options.n_targets * areas / areas.sum()
    counts = np.floor(raw).astype(int)
    for i in np.argsort(-(raw - counts))[: options.n_targets - counts.sum()]:
        counts[i] += 1
    xyz, normals, names = [], [], []
    edge = 0.05  # keep targets off the room's edges (fraction of each face)
    for face, n in zip(faces, counts, strict=True):
        if n == 0:
            continue
        la, lb = np.linalg.norm(face["a"]), np.linalg.norm(face["b"])
        na = max(1, int(round(math.sqrt(n * la / lb))))
        nb = int(math.ceil(n / na))
        cells = rng.permutation(na * nb)[:n]
        ia, ib = cells % na, cells // na
        sa = edge + (1 - 2 * edge) * (ia + rng.uniform(0.15, 0.85, n)) / na
        sb = edge + (1 - 2 * edge) * (ib + rng.uniform(0.15, 0.85, n)) / nb
        pts = face["o"] + sa[:, None] * face["a"] + sb[:, None] * face["b"]
        xyz.append(pts)
        normals.append(np.repeat(face["n"][None, :], n, axis=0))
        names += [face["name"]] * n
    return np.concatenate(xyz), np.concatenate(normals), names


def _rotation_world_from_cam(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Columns: camera x (right), y (down), z (forward) in the world frame (Z up)."""
    fwd = np.array(
        [math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)]
    )
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    c, s = math.cos(roll), math.sin(roll)
    x = c * right + s * down
    y = -s * right + c * down
    return np.stack([x, y, fwd], axis=1)


def _observe(lens, options, R, t, centre, xyz, normals):
    """Visible target indices, their true pixels and incidence angles (deg).

    Visible: inside the image by ``margin_px``, incidence at most
    ``fov_deg / 2``, facing the camera and at least the minimum range away.
    """
    p_cam = xyz @ R.T + t
    view = xyz - centre
    dist = np.linalg.norm(view, axis=1)
    facing = np.sum(normals * view, axis=1) / np.maximum(dist, 1e-12) < -options.facing_cos
    uv = lens.project(p_cam)
    alpha = np.degrees(np.arctan2(np.hypot(p_cam[:, 0], p_cam[:, 1]), p_cam[:, 2]))
    inside = inside_image(uv, options.width, options.height, options.margin_px) & (
        alpha <= options.fov_deg / 2.0 + 1e-9
    )
    keep = np.flatnonzero(facing & inside & (dist >= options.effective_min_range_m))
    return keep, uv[keep], alpha[keep]


@dataclass
class _Scene:
    """Targets (world frame, metres) and a pose sampler ``(j, rng) -> (R, t, centre, label)``."""

    xyz: np.ndarray
    normals: np.ndarray
    labels: list[str]
    sample_pose: Callable[[int, np.random.Generator], tuple]


def _room_scene(options: SimulationOptions, lens: Any, rng: np.random.Generator) -> _Scene:
    """The paper's room: targets on every face, stations inside, portrait every other image."""
    xyz, normals, faces = _place_targets(options, rng)
    lx, ly, _ = options.room_size_m
    clear = options.wall_clearance_m
    h_lo, h_hi = options.station_height_m
    tilt = math.radians(options.tilt_deg)

    def sample_pose(j: int, gen: np.random.Generator):
        portrait = j % 2 == 1
        centre = np.array([gen.uniform(clear, lx - clear), gen.uniform(clear, ly - clear), 0.0])
        centre[2] = gen.uniform(h_lo, h_hi)
        yaw = gen.uniform(-math.pi, math.pi)
        pitch = gen.uniform(-tilt, tilt)
        roll = (math.pi / 2 if portrait else 0.0) + math.radians(gen.normal(0.0, 2.0))
        R = _rotation_world_from_cam(yaw, pitch, roll).T  # cam_from_world
        return R, -R @ centre, centre, "portrait" if portrait else "landscape"

    return _Scene(xyz, normals, faces, sample_pose)


def _object_scene(options: SimulationOptions, lens: Any, rng: np.random.Generator) -> _Scene:
    """A board or a cube corner, aimed at random places of the image (``scenes.AimedPoses``)."""
    if options.scene == "board":
        xyz, normals, labels = board_targets(options.board_shape, options.board_spacing_m)
        view_dir = board_view_dir(math.radians(options.board_tilt_deg))
    else:
        xyz, normals, labels = object3d_targets(options.object_grid, options.object_spacing_m)
        view_dir = corner_view_dir()
    centre = xyz.mean(axis=0)
    poses = AimedPoses(
        lens=lens,
        centre_world=centre,
        radius_m=float(np.linalg.norm(xyz - centre, axis=1).max()),
        view_dir=view_dir,
        half_fov_rad=math.radians(options.fov_deg / 2.0),
        field_half_rad=field_half_angle_rad(
            lens, options.fov_deg, options.width, options.height, options.margin_px
        ),
        width=options.width,
        height=options.height,
        margin_px=options.margin_px,
    )
    return _Scene(xyz, normals, labels, poses)


def _shoot(options: SimulationOptions, lens: Any, scene: _Scene, rng: np.random.Generator):
    """Draw ``n_images`` poses that see enough targets; noisy observations of each."""
    images = []
    for j in range(options.n_images):
        best = None
        for attempt in range(1000):
            R, t, centre, label = scene.sample_pose(j, rng)
            keep, uv, alpha = _observe(lens, options, R, t, centre, scene.xyz, scene.normals)
            if best is None or keep.size > best[0].size:
                best = (keep, uv, alpha, R, t, centre, label)
            if keep.size >= options.preferred_targets_per_image:
                break
            if attempt >= 50 and best[0].size >= options.min_targets_per_image:
                break
        keep, uv, alpha, R, t, centre, label = best
        if keep.size < options.min_targets_per_image:
            raise OptionsError(
                f"image {j + 1}: no pose in 1000 tries sees {options.min_targets_per_image} "
                "targets; increase n_targets or fov_deg"
            )
        uv_obs = uv + rng.normal(0.0, options.noise_px, uv.shape)
        uv_obs[:, 0] = np.clip(uv_obs[:, 0], -0.5, options.width - 0.5)
        uv_obs[:, 1] = np.clip(uv_obs[:, 1], -0.5, options.height - 0.5)
        images.append(
            {
                "id": f"IMG_{j + 1:04d}",
                "R": R,
                "t": t,
                "centre": centre,
                "orientation": label,
                "targets": keep.copy(),
                "uv": uv_obs,
                "alpha": alpha,
            }
        )
    return images


# -- main ------------------------------------------------------------------------


def simulate_room(
    options: SimulationOptions | None = None, rng: np.random.Generator | None = None
) -> Simulation:
    """Simulate a calibration: the paper's room (inside-out), a board or a 3D object.

    Parameters
    ----------
    options : SimulationOptions or None
        What to simulate; default ``SimulationOptions()``. ``options.scene``
        picks the target field (``"room"``, ``"board"``, ``"object3d"``).
    rng : numpy.random.Generator or None
        Random source; ``np.random.default_rng(options.seed)`` when None. The
        same seed gives identical output.

    Returns
    -------
    sim : Simulation
        Dataset (world frame, metres; pixels with ``(0, 0)`` at the centre of
        the top-left pixel), check points, truth and the lens.

    Raises
    ------
    ValueError
        For inconsistent options, or when no pose can be found that sees
        ``min_targets_per_image`` targets.
    """
    options = options if options is not None else SimulationOptions()
    options.validate()
    if rng is None:
        rng = np.random.default_rng(options.seed)
    lens = build_lens(options)
    build = _room_scene if options.scene == "room" else _object_scene
    scene = build(options, lens, rng)
    images = _shoot(options, lens, scene, rng)
    return _assemble(options, lens, scene, images, rng)


def _assemble(options, lens, scene: _Scene, images, rng) -> Simulation:
    """Blunders, then the dataset, check point and truth documents."""
    xyz, normals, faces = scene.xyz, scene.normals, scene.labels
    n_t = xyz.shape[0]
    target_ids = [f"T{i + 1:04d}" for i in range(n_t)]
    blunders = _add_blunders(images, options, rng, target_ids)
    sigma_mode = options.effective_sigma_mode

    # targets written to the dataset: those observed at least once
    n_obs_per_target = np.zeros(n_t, dtype=int)
    for img in images:
        np.add.at(n_obs_per_target, img["targets"], 1)
    used = np.flatnonzero(n_obs_per_target > 0)

    if sigma_mode == "fixed":
        approx = xyz.copy()
    else:
        approx = xyz + rng.normal(0.0, options.target_sigma_m, xyz.shape)
    ds_targets = []
    for i in used:
        entry: dict[str, Any] = {"id": target_ids[i], "xyz": [float(v) for v in approx[i]]}
        if sigma_mode == "weighted":
            entry["sigma"] = float(options.target_sigma_m)
        elif sigma_mode == "fixed":
            entry["sigma"] = 0.0
        ds_targets.append(entry)

    ds_images = []
    for img in images:
        order = np.argsort(img["targets"], kind="stable")
        obs = [
            {"target": target_ids[img["targets"][k]], "uv": [float(v) for v in img["uv"][k]]}
            for k in order
        ]
        ds_images.append({"id": img["id"], "observations": obs})
    dataset = {
        "format": DATASET_FORMAT,
        "units": "m",
        "camera": {"width": int(options.width), "height": int(options.height)},
        "targets": ds_targets,
        "images": ds_images,
    }

    checkpoints = checkpoint_file(
        used, n_obs_per_target, xyz, target_ids, options.n_checkpoints,
        options.checkpoint_noise_m, rng,
    )  # fmt: skip

    all_alpha = np.concatenate([img["alpha"] for img in images])
    n_obs = int(sum(img["targets"].size for img in images))
    truth = {
        "format": TRUTH_FORMAT,
        "units": "m",
        "camera": {"width": int(options.width), "height": int(options.height)},
        "scene": options.scene,
        "sigma_mode": sigma_mode,
        "lens": lens.to_dict(),
        "options": _jsonable(asdict(options)),
        "targets": [
            {
                "id": target_ids[i],
                "xyz": [float(v) for v in xyz[i]],
                "normal": [float(v) for v in normals[i]],
                "face": faces[i],
                "n_observations": int(n_obs_per_target[i]),
            }
            for i in range(n_t)
        ],
        "images": [
            {
                "id": img["id"],
                "cam_from_world": {
                    "R": [[float(v) for v in row] for row in img["R"]],
                    "t": [float(v) for v in img["t"]],
                },
                "centre_world": [float(v) for v in img["centre"]],
                "orientation": img["orientation"],
            }
            for img in images
        ],
        "blunders": blunders,
        "statistics": {
            "n_images": len(images),
            "n_targets": int(used.size),
            "n_observations": n_obs,
            "n_blunders": len(blunders),
            "max_incidence_deg": float(all_alpha.max()) if all_alpha.size else 0.0,
            "n_observations_beyond_90deg": int(np.sum(all_alpha > 90.0)),
        },
    }
    return Simulation(dataset=dataset, checkpoints=checkpoints, truth=truth, lens=lens)


def checkpoint_file(
    used: np.ndarray,
    n_obs_per_target: np.ndarray,
    xyz: np.ndarray,
    target_ids: list[str],
    n_checkpoints: int,
    noise_m: float,
    rng: np.random.Generator,
) -> dict[str, Any]:
    """A ``checkpoints@1`` document: up to ``n_checkpoints`` of the ``used`` targets
    (indices into ``xyz`` (T, 3), m), those seen in two or more images first (they can be
    triangulated), their coordinates surveyed with ``noise_m`` (m) of noise."""
    well = used[n_obs_per_target[used] >= 2]
    rest = used[n_obs_per_target[used] < 2]
    pool = np.concatenate([rng.permutation(well), rng.permutation(rest)])
    cp_idx = np.sort(pool[: min(n_checkpoints, used.size)]).astype(int)
    cp_xyz = xyz[cp_idx] + rng.normal(0.0, noise_m, (cp_idx.size, 3))
    return {
        "format": CHECKPOINTS_FORMAT,
        "units": "m",
        "targets": [
            {"id": target_ids[i], "xyz": [float(v) for v in p]}
            for i, p in zip(cp_idx, cp_xyz, strict=True)
        ],
    }


def _add_blunders(images, options, rng, target_ids) -> list[dict[str, Any]]:
    """Corrupt ``round(blunder_rate * n_obs)`` observations in place; return their records."""
    index = [(j, k) for j, img in enumerate(images) for k in range(img["targets"].size)]
    n_total = int(round(options.blunder_rate * len(index)))
    if n_total == 0:
        return []
    n_mislabel = 2 * (n_total // 4)
    bad = {j: np.zeros(img["targets"].size, dtype=bool) for j, img in enumerate(images)}
    records: list[dict[str, Any]] = []

    swaps_done, tries = 0, 0
    while swaps_done < n_mislabel // 2 and tries < 100 * n_total:
        tries += 1
        j, k = index[rng.integers(len(index))]
        free = np.flatnonzero(~bad[j])
        if bad[j][k] or free.size < 2:
            continue
        others = free[free != k]
        m = int(others[rng.integers(others.size)])
        tg = images[j]["targets"]
        tk, tm = int(tg[k]), int(tg[m])
        tg[k], tg[m] = tm, tk
        bad[j][k] = bad[j][m] = True
        for obs, true_t, label in ((k, tk, tm), (m, tm, tk)):
            records.append(
                {
                    "image": images[j]["id"],
                    "target": target_ids[label],
                    "kind": "mislabel",
                    "true_target": target_ids[true_t],
                    "uv": [float(v) for v in images[j]["uv"][obs]],
                }
            )
        swaps_done += 1

    remaining = [(j, k) for j, k in index if not bad[j][k]]
    n_offset = min(n_total - len(records), len(remaining))
    for pos in rng.choice(len(remaining), size=n_offset, replace=False):
        j, k = remaining[int(pos)]
        img = images[j]
        mag = rng.uniform(10.0, 50.0)
        ang = rng.uniform(0.0, 2.0 * math.pi)
        uv = img["uv"][k] + mag * np.array([math.cos(ang), math.sin(ang)])
        if not (0 <= uv[0] <= options.width - 1 and 0 <= uv[1] <= options.height - 1):
            uv = img["uv"][k] - mag * np.array([math.cos(ang), math.sin(ang)])
        uv[0] = min(max(uv[0], -0.5), options.width - 0.5)
        uv[1] = min(max(uv[1], -0.5), options.height - 0.5)
        offset = uv - img["uv"][k]
        img["uv"][k] = uv
        bad[j][k] = True
        records.append(
            {
                "image": img["id"],
                "target": target_ids[int(img["targets"][k])],
                "kind": "offset",
                "offset_px": [float(v) for v in offset],
                "uv": [float(v) for v in uv],
            }
        )
    records.sort(key=lambda r: (r["image"], r["target"]))
    return records


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _write_json_atomic(path: Path, document: dict[str, Any]) -> None:
    from ..io.dataset import write_json_atomic

    write_json_atomic(path, document)


def write_simulation(sim: Simulation, out_dir: str | os.PathLike[str]) -> dict[str, Path]:
    """Write ``dataset.json``, ``checkpoints.json`` and ``truth.json`` atomically.

    Parameters
    ----------
    sim : Simulation
        Output of :func:`simulate_room`.
    out_dir : path-like
        Directory (created if missing).

    Returns
    -------
    paths : dict of str to pathlib.Path
        Keys ``"dataset"``, ``"checkpoints"``, ``"truth"``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "dataset": out / "dataset.json",
        "checkpoints": out / "checkpoints.json",
        "truth": out / "truth.json",
    }
    for key, path in paths.items():
        _write_json_atomic(path, getattr(sim, key))
    return paths


# -- presets ---------------------------------------------------------------------


def nikon_like(**overrides: Any) -> SimulationOptions:
    """The paper's Nikon D600 + 28 mm: ~75 degree diagonal, 44 images.

    Pinhole lens with Brown radial ``k1, k2`` (about 100 px of barrel
    distortion in the corners) on a 6000 x 4000 px sensor.

    Parameters
    ----------
    **overrides
        Any :class:`SimulationOptions` field.

    Returns
    -------
    options : SimulationOptions
    """
    base = SimulationOptions(
        lens="pinhole",
        fov_deg=75.0,
        width=6000,
        height=4000,
        fill="diagonal",
        lens_options={"k1": -0.08, "k2": 0.04},
        n_images=44,
    )
    return replace(base, **overrides)


def gopro_like(**overrides: Any) -> SimulationOptions:
    """The paper's GoPro Hero3: ~150 degree diagonal, 52 images.

    Kannala-Brandt lens (4000 x 3000 px) plus small decentering, a slightly
    moving entrance pupil and a 2 px smooth error field: errors no Brown
    polynomial holds.

    Parameters
    ----------
    **overrides
        Any :class:`SimulationOptions` field.

    Returns
    -------
    options : SimulationOptions
    """
    base = SimulationOptions(
        lens="kannala-brandt",
        fov_deg=150.0,
        width=4000,
        height=3000,
        fill="diagonal",
        lens_options={"k1": 0.03, "k2": -0.008, "k3": 0.001},
        p1=2e-4,
        p2=-1e-4,
        pupil_shift_m=0.002,
        error_field_px=2.0,
        n_images=52,
    )
    return replace(base, **overrides)
