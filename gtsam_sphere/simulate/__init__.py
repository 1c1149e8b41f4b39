"""Seeded simulator of calibrations: the paper's room (Chow et al. 2018), a board, a 3D object.

Public API::

    from gtsam_sphere.simulate import SimulationOptions, simulate_room, write_simulation
    sim = simulate_room(SimulationOptions(lens="sphere", fov_deg=200, seed=1))
    write_simulation(sim, "out/")   # dataset.json, checkpoints.json, truth.json

    from gtsam_sphere.simulate import RigOptions, simulate_rig, write_rig_simulation
    rig = simulate_rig(RigOptions(rig="ring4", n_frames=12, seed=1))
    write_rig_simulation(rig, "out_rig/")   # dataset@2, checkpoints@1, truth@2

Lens families live in :mod:`gtsam_sphere.simulate.lenses`, the room and the
shared pipeline in :mod:`gtsam_sphere.simulate.room`, the board and the cube
corner (``SimulationOptions(scene="board" | "object3d")``) in
:mod:`gtsam_sphere.simulate.scenes`, camera rigs moving through the room
(``dataset@2``: stereo, dual360, ring4, mixed) in :mod:`gtsam_sphere.simulate.rigs`.
:func:`add_cli_arguments` and
:func:`run_cli` implement ``gtsam-sphere simulate``.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from typing import Any

from .lenses import (
    LENS_KINDS,
    DoubleSphere,
    Equidistant,
    Equisolid,
    ErrorField,
    FieldOfView,
    KannalaBrandt,
    NonCentral,
    PinholeBrown,
    SphereLens,
    Stereographic,
    Unified,
    incidence_angle,
    lens_from_dict,
    make_lens,
)
from .rigs import (
    RIG_KINDS,
    ZOO_RIG_KINDS,
    RigCamera,
    RigOptions,
    RigSimulation,
    check_rig_cameras,
    rig_cameras,
    simulate_rig,
    write_rig_simulation,
)
from .room import (
    SCENES,
    SIGMA_MODES,
    Simulation,
    SimulationOptions,
    build_lens,
    gopro_like,
    nikon_like,
    simulate_room,
    write_simulation,
)

__all__ = [
    "LENS_KINDS",
    "RIG_KINDS",
    "ZOO_RIG_KINDS",
    "SCENES",
    "SIGMA_MODES",
    "DoubleSphere",
    "Equidistant",
    "Equisolid",
    "ErrorField",
    "FieldOfView",
    "KannalaBrandt",
    "NonCentral",
    "PinholeBrown",
    "RigCamera",
    "RigOptions",
    "RigSimulation",
    "Simulation",
    "SimulationOptions",
    "SphereLens",
    "Stereographic",
    "Unified",
    "add_cli_arguments",
    "build_lens",
    "gopro_like",
    "incidence_angle",
    "lens_from_dict",
    "make_lens",
    "nikon_like",
    "options_from_args",
    "check_rig_cameras",
    "rig_cameras",
    "rig_options_from_args",
    "run_cli",
    "simulate_rig",
    "simulate_room",
    "write_rig_simulation",
    "write_simulation",
]

_PRESETS = {"nikon": nikon_like, "gopro": gopro_like}

# command-line flag -> SimulationOptions field (flags default to None = keep preset)
_FLAGS: dict[str, tuple[str, type, str]] = {
    "--lens": ("lens", str, f"lens kind: {', '.join(LENS_KINDS)}"),
    "--fov-deg": ("fov_deg", float, "full field of view in degrees (diagonal or circle)"),
    "--width": ("width", int, "image width in pixels"),
    "--height": ("height", int, "image height in pixels"),
    "--fill": ("fill", str, "where fov/2 lands: circle or diagonal"),
    "--circle-radius-px": (
        "circle_radius_px",
        float,
        "radius (px) where fov/2 lands (overrides --fill; may exceed the half diagonal)",
    ),
    "--scene": ("scene", str, "room (inside-out), board (planar grid) or object3d (cube corner)"),
    "--n-images": ("n_images", int, "number of images"),
    "--n-targets": ("n_targets", int, "number of targets in the room"),
    "--n-checkpoints": ("n_checkpoints", int, "number of check points"),
    "--checkpoint-noise-m": ("checkpoint_noise_m", float, "check point noise (m)"),
    "--noise-px": ("noise_px", float, "pixel noise standard deviation (px)"),
    "--target-sigma-m": ("target_sigma_m", float, "approximate target noise (m)"),
    "--sigma-mode": ("sigma_mode", str, "weighted | free | fixed"),
    "--blunder-rate": ("blunder_rate", float, "fraction of gross observations"),
    "--pupil-shift-m": ("pupil_shift_m", float, "entrance pupil shift at 90 deg (m)"),
    "--error-field-px": ("error_field_px", float, "smooth error field amplitude (px)"),
    "--p1": ("p1", float, "decentering p1"),
    "--p2": ("p2", float, "decentering p2"),
    "--a1": ("a1", float, "affinity a1"),
    "--a2": ("a2", float, "shear a2"),
    "--seed": ("seed", int, "random seed"),
}


def add_cli_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``gtsam-sphere simulate`` options to an argparse parser.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        Parser (or sub-parser) to extend.

    Returns
    -------
    parser : argparse.ArgumentParser
        The same parser, for chaining.
    """
    parser.add_argument(
        "--preset", choices=sorted(_PRESETS), default=None, help="start from a paper camera"
    )
    for flag, (dest, typ, help_text) in _FLAGS.items():
        kwargs: dict[str, Any] = {"dest": dest, "type": typ, "default": None, "help": help_text}
        if dest == "lens":
            kwargs["choices"] = list(LENS_KINDS)
        elif dest == "sigma_mode":
            kwargs["choices"] = list(SIGMA_MODES)
        elif dest == "fill":
            kwargs["choices"] = ["circle", "diagonal"]
        elif dest == "scene":
            kwargs["choices"] = list(SCENES)
        parser.add_argument(flag, **kwargs)
    for flag, name in (("--cx", "u"), ("--cy", "v")):
        parser.add_argument(
            flag,
            type=float,
            default=None,
            help=f"principal point {name} in px (default: the image centre)",
        )
    parser.add_argument(
        "--lens-option",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="any other lens parameter, e.g. xi=-0.2, alpha=0.6 (double-sphere), "
        "omega=1.0 (fov), k1=0.03 (repeatable)",
    )
    parser.add_argument(
        "--rig",
        choices=list(RIG_KINDS + ZOO_RIG_KINDS),
        default=None,
        help="simulate a camera rig moving through the room (dataset@2): stereo, dual360 "
        "(back-to-back 220 deg), ring4 (four outward cameras, no common field of view), "
        "mixed (fisheye + 60 deg pinhole), or a lens zoo rig: dual360-small-circle, "
        "catadioptric-stereo, double-sphere-stereo, fov-ring3, stereographic-pinhole, "
        "cropped-stereo (gtsam_sphere.simulate.rigs says what each is); with --seed, "
        "--noise-px, --frames, --n-targets, --n-checkpoints, --checkpoint-noise-m, "
        "--target-sigma-m, --error-field-px",
    )
    parser.add_argument(
        "--frames", type=int, default=None, help="rigs: number of rig poses (default 12)"
    )
    parser.add_argument(
        "-o", "--out", "--output", dest="out", required=True, help="output directory"
    )
    return parser


#: ``SimulationOptions`` fields that a rig simulation also takes (same flag, same meaning)
_RIG_FIELDS = (
    "seed",
    "noise_px",
    "n_targets",
    "n_checkpoints",
    "checkpoint_noise_m",
    "target_sigma_m",
    "error_field_px",
)


def rig_options_from_args(args: argparse.Namespace) -> RigOptions:
    """Build :class:`RigOptions` from arguments parsed with ``--rig``.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed by a parser prepared with :func:`add_cli_arguments`.

    Returns
    -------
    options : RigOptions

    Raises
    ------
    ValueError
        A single-camera option given with ``--rig`` (named), or a bad value.
    """
    unused = [
        flag
        for flag, (dest, _, _) in _FLAGS.items()
        if dest not in _RIG_FIELDS and getattr(args, dest, None) is not None
    ]
    unused += [
        flag
        for flag, dest in (("--preset", "preset"), ("--cx", "cx"), ("--cy", "cy"))
        if getattr(args, dest, None) is not None
    ]
    if getattr(args, "lens_option", None):
        unused.append("--lens-option")
    if unused:
        raise ValueError(
            f"single-camera option(s) {', '.join(unused)} not used with --rig "
            "(the rig fixes its cameras)"
        )
    overrides: dict[str, Any] = {
        name: getattr(args, name) for name in _RIG_FIELDS if getattr(args, name, None) is not None
    }
    if getattr(args, "frames", None) is not None:
        overrides["n_frames"] = args.frames
    options = RigOptions(rig=args.rig, **overrides)
    options.validate()
    return options


def _run_rig_cli(args: argparse.Namespace) -> int:
    """``gtsam-sphere simulate --rig KIND``: simulate a rig, write the three files."""
    import sys

    from ..core.errors import InputError

    try:
        options = rig_options_from_args(args)
        sim = simulate_rig(options)
    except (ValueError, InputError) as exc:
        print(f"gtsam-sphere simulate: error: {exc}", file=sys.stderr)
        return 2
    paths = write_rig_simulation(sim, args.out)
    stats = sim.truth["statistics"]
    print(
        f"simulated rig {options.rig} ({len(sim.cameras)} cameras) in the room, "
        f"{stats['n_frames']} frames, seed {options.seed}"
    )
    for cam in sim.cameras:
        cs = stats["cameras"][cam.id]
        print(
            f"  camera {cam.id}: {cam.lens.kind} {cam.fov_deg:g} deg, {cam.width}x{cam.height} px, "
            f"{cs['n_images']} images, {cs['n_observations']} observations"
        )
    print(
        f"images {stats['n_images']} ({stats['n_images_dropped']} dropped: too few targets), "
        f"targets {stats['n_targets']}, observations {stats['n_observations']}, "
        f"max incidence {stats['max_incidence_deg']:.1f} deg"
    )
    for key, path in paths.items():
        print(f"  {key}: {path}")
    return 0


def options_from_args(args: argparse.Namespace) -> SimulationOptions:
    """Build :class:`SimulationOptions` from parsed arguments.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed by a parser prepared with :func:`add_cli_arguments`.

    Returns
    -------
    options : SimulationOptions
        Preset (or defaults) overridden by every flag that was given.
    """
    preset = getattr(args, "preset", None)
    base = _PRESETS[preset]() if preset else SimulationOptions()
    overrides: dict[str, Any] = {
        dest: getattr(args, dest)
        for dest, _, _ in _FLAGS.values()
        if getattr(args, dest, None) is not None
    }
    lens_options = dict(base.lens_options)
    for item in getattr(args, "lens_option", None) or []:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise ValueError(f"--lens-option expects NAME=VALUE, got {item!r}")
        lens_options[name.strip()] = float(value)
    for name in ("cx", "cy"):
        if getattr(args, name, None) is not None:
            lens_options[name] = float(getattr(args, name))
    if lens_options != base.lens_options:
        overrides["lens_options"] = lens_options
    return replace(base, **overrides)


def run_cli(args: argparse.Namespace) -> int:
    """Run ``gtsam-sphere simulate``: simulate, write the three files, print a summary.

    With ``--rig KIND`` a camera rig (:func:`simulate_rig`, ``dataset@2``) instead.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed by a parser prepared with :func:`add_cli_arguments`.

    Returns
    -------
    status : int
        0 on success, 2 for invalid options (message on stderr).
    """
    import sys

    from ..core.errors import InputError

    if getattr(args, "rig", None) is not None:
        return _run_rig_cli(args)
    if getattr(args, "frames", None) is not None:
        print(
            "gtsam-sphere simulate: error: --frames is for --rig (else --n-images)", file=sys.stderr
        )
        return 2
    try:
        options = options_from_args(args)
        # the option checks alone (a ValueError from anywhere else is a bug: no catch-all)
        options.validate()
        build_lens(options)
    except ValueError as exc:
        print(f"gtsam-sphere simulate: error: {exc}", file=sys.stderr)
        return 2
    try:
        sim = simulate_room(options)
    except InputError as exc:  # e.g. no pose sees enough targets with these options
        print(f"gtsam-sphere simulate: error: {exc}", file=sys.stderr)
        return 2
    paths = write_simulation(sim, args.out)
    stats = sim.truth["statistics"]
    print(
        f"simulated {options.lens} lens, {options.fov_deg:g} deg, "
        f"{options.width}x{options.height} px, scene {options.scene}, seed {options.seed}"
    )
    print(
        f"images {stats['n_images']}, targets {stats['n_targets']}, "
        f"observations {stats['n_observations']} ({stats['n_blunders']} blunders), "
        f"max incidence {stats['max_incidence_deg']:.1f} deg"
    )
    for key, path in paths.items():
        print(f"  {key}: {path}")
    return 0
