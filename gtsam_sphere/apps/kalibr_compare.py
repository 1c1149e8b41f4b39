"""Compare a calibration with a Kalibr ``camchain.yaml`` or an mrcal ``.cameramodel``:
projections over the field.

An mrcal file (``--with FILE.cameramodel``, read by
:func:`gtsam_sphere.apps.export_formats.read_cameramodel`: ``LENSMODEL_PINHOLE``,
``OPENCV4/5/8``, ``STEREOGRAPHIC``, ``SPLINED_STEREOGRAPHIC``) is compared the same way
as a Kalibr camera; its ``extrinsics`` are not used.

``gtsam-sphere compare CALIB.json --with camchain.yaml [--camera cam0]`` reads the
Kalibr camera (models ``pinhole-equi``, ``omni-radtan``, ``ds-none``, ``eucm-none``;
Kalibr's camchain keys ``camera_model``, ``intrinsics``, ``distortion_model``,
``distortion_coeffs``, ``resolution``), samples the region the calibration observed on a pixel grid
(:func:`gtsam_sphere.apps.export.sample_region`), takes our ray of every sample pixel and
projects it with Kalibr's model: the distance between Kalibr's pixel and the sample
pixel is the projection difference of the two calibrations for that ray (px; both in
OpenCV's pixel convention, ``(0, 0)`` the centre of the top-left pixel, as Kalibr's).
It is printed overall and per band of incidence angle, with the rays Kalibr's model
cannot project (``pinhole-equi`` past 90 degrees, outside the omni / double-sphere
validity region) counted. With the calibration's observations, the same is given at
the observed pixels: the reprojection difference of the two calibrations there
(Kalibr's pixel for our ray of each observed corner).

The camera frames of the two calibrations are both the camera's (x right, y down, z
forward); a difference includes any rotation between them (a different principal point
shows as one).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field

import numpy as np

from ..core.errors import DatasetError, OptionsError
from .export import (
    ds_project,
    ds_valid,
    eucm_project,
    eucm_valid,
    kb_project,
    omni_project,
    omni_valid,
    sample_region,
)

__all__ = [
    "KalibrCamera",
    "compare_with_kalibr",
    "read_kalibr_camchain",
    "run_cli",
]

#: Kalibr models this module projects: (camera_model, distortion_model) -> name
MODELS = {
    ("pinhole", "equidistant"): "pinhole-equi",
    ("omni", "radtan"): "omni-radtan",
    ("ds", "none"): "ds-none",
    ("eucm", "none"): "eucm-none",
}
BANDS_DEG = (0.0, 30.0, 60.0, 90.0, 120.0, 180.0)


@dataclass
class KalibrCamera:
    """One camera of a Kalibr camchain.

    Attributes
    ----------
    camera_id : str
        Its key in the file (``cam0``, ...).
    model : str
        ``pinhole-equi``, ``omni-radtan``, ``ds-none`` or ``eucm-none``.
    intrinsics : ndarray
        Kalibr's ``intrinsics``: ``[fu, fv, pu, pv]`` (pinhole), ``[xi, fu, fv, pu, pv]``
        (omni), ``[xi, alpha, fu, fv, pu, pv]`` (ds); pixels and dimensionless.
    distortion : ndarray
        Kalibr's ``distortion_coeffs``: ``k1..k4`` (equidistant), ``k1, k2, r1, r2``
        (radtan), empty (none).
    resolution : tuple of int
        ``(width, height)`` in pixels.
    rostopic : str
        The camera's topic, ``""`` when absent.
    """

    camera_id: str
    model: str
    intrinsics: np.ndarray
    distortion: np.ndarray
    resolution: tuple[int, int]
    rostopic: str = ""
    tool: str = "Kalibr"

    def project(self, rays: np.ndarray) -> np.ndarray:
        """Pixels ``(N, 2)`` of camera-frame rays ``(N, 3)``; NaN where the model has none."""
        rays = np.asarray(rays, float).reshape(-1, 3)
        i, d = self.intrinsics, self.distortion
        if self.model == "pinhole-equi":
            uv = kb_project(np.concatenate([i, d]), rays)
            ok = rays[:, 2] > 0  # Kalibr projects onto the plane z = 1 first
        elif self.model == "omni-radtan":
            params = np.concatenate([i, d])
            uv, ok = omni_project(params, rays), omni_valid(params, rays)
        elif self.model == "eucm-none":
            uv, ok = eucm_project(i, rays), eucm_valid(i, rays)
        else:
            uv, ok = ds_project(i, rays), ds_valid(i, rays)
        uv = np.where(ok[:, None], uv, np.nan)
        return uv


def _scalar(text: str):
    text = text.strip()
    if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"":
        return text[1:-1]
    try:
        return float(text) if any(c in text for c in ".eE") else int(text)
    except ValueError:
        return text


def _flow_list(text: str, where: str) -> list:
    text = text.strip()
    if not (text.startswith("[") and text.endswith("]")):
        raise DatasetError(f"{where}: expected a list '[a, b, ...]', got {text!r}")
    inner = text[1:-1].strip()
    return [_scalar(x) for x in inner.split(",")] if inner else []


def _parse_camchain(text: str, path: str) -> dict[str, dict]:
    """Kalibr's camchain subset of YAML: ``camN:`` blocks of ``key: value`` lines whose
    values are scalars, flow lists ``[a, b]`` or block lists of flow lists (``T_cn_cnm1``)."""
    cams: dict[str, dict] = {}
    cam = key = None
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].rstrip()
        if not line.strip():
            continue
        where = f"{path}:{lineno}"
        indent = len(line) - len(line.lstrip())
        body = line.strip()
        if indent == 0:
            if not body.endswith(":"):
                raise DatasetError(f"{where}: expected a camera block 'camN:', got {body!r}")
            cam = body[:-1].strip()
            cams[cam] = {}
            key = None
        elif cam is None:
            raise DatasetError(f"{where}: indented line outside a camera block")
        elif body.startswith("- "):
            if key is None or not isinstance(cams[cam].get(key), list):
                raise DatasetError(f"{where}: list item without a key")
            cams[cam][key].append(_flow_list(body[2:], where))
        else:
            if ":" not in body:
                raise DatasetError(f"{where}: expected 'key: value', got {body!r}")
            key, value = (x.strip() for x in body.split(":", 1))
            if value == "":
                cams[cam][key] = []
            elif value.startswith("["):
                cams[cam][key] = _flow_list(value, where)
            else:
                cams[cam][key] = _scalar(value)
    return cams


def read_kalibr_camchain(path: str) -> dict[str, KalibrCamera]:
    """Read the cameras of a Kalibr ``camchain.yaml`` (or a single-camera ``camchain``).

    Parameters
    ----------
    path : str

    Returns
    -------
    dict of str to KalibrCamera
        In file order.

    Raises
    ------
    DatasetError
        A malformed file or camera block; the message names the camera and key.
    OptionsError
        A model this package does not project (e.g. ``pinhole-radtan``, ``eucm``).
    """
    with open(path, encoding="utf-8") as fh:
        blocks = _parse_camchain(fh.read(), str(path))
    if not blocks:
        raise DatasetError(f"{path}: no camera block (expected 'cam0:' ...)")
    out = {}
    sizes = {"pinhole-equi": (4, 4), "omni-radtan": (5, 4), "ds-none": (6, 0), "eucm-none": (6, 0)}
    for cid, b in blocks.items():
        for k in ("camera_model", "intrinsics", "distortion_model", "resolution"):
            if k not in b:
                raise DatasetError(f"{path}: {cid} has no {k!r}")
        name = MODELS.get((str(b["camera_model"]), str(b["distortion_model"])))
        if name is None:
            raise OptionsError(
                f"{path}: {cid}: model {b['camera_model']}-{b['distortion_model']} is not "
                f"supported; expected one of {', '.join(MODELS.values())}"
            )
        intr = np.asarray(b["intrinsics"], float)
        dist = np.asarray(b.get("distortion_coeffs", []), float)
        if (len(intr), len(dist)) != sizes[name]:
            raise DatasetError(
                f"{path}: {cid}: {name} needs {sizes[name][0]} intrinsics and "
                f"{sizes[name][1]} distortion_coeffs, got {len(intr)} and {len(dist)}"
            )
        res = b["resolution"]
        if not (isinstance(res, list) and len(res) == 2):
            raise DatasetError(f"{path}: {cid}: resolution must be [width, height]")
        out[cid] = KalibrCamera(
            cid, name, intr, dist, (int(res[0]), int(res[1])), str(b.get("rostopic", ""))
        )
    return out


@dataclass
class KalibrComparison:
    """Projection differences between our calibration and a Kalibr camera.

    Attributes
    ----------
    camera_id : str
        The Kalibr camera compared.
    model : str
        Its model.
    region : str
        What was sampled.
    field_stats : dict
        Over the sampled region: ``n``, ``n_projected`` (Kalibr's model has a pixel),
        ``rms_px``, ``p95_px``, ``max_px`` (over the projected samples).
    bands : list of dict
        The same per incidence band ``[lo_deg, hi_deg)``.
    observed : dict
        The same at the calibration's observed pixels (empty without them).
    """

    camera_id: str
    model: str
    region: str
    field_stats: dict = field(default_factory=dict)
    bands: list = field(default_factory=list)
    observed: dict = field(default_factory=dict)
    tool: str = "Kalibr"

    def summary(self) -> str:
        """Human-readable lines."""

        def row(label: str, s: dict) -> str:
            if not s.get("n_projected"):
                return f"  {label}: {s.get('n', 0)} rays, none projected by {self.tool}'s model"
            return (
                f"  {label}: {s['n_projected']} of {s['n']} rays, RMS {s['rms_px']:.4f} px, "
                f"95% {s['p95_px']:.4f} px, max {s['max_px']:.4f} px"
            )

        lines = [
            f"{self.tool} {self.camera_id} ({self.model}) vs this calibration: pixel of our ray "
            f"through {self.tool}'s model minus ours, over the {self.region}",
            row("field", self.field_stats),
        ]
        lines += [row(f"{b['lo_deg']:.0f}-{b['hi_deg']:.0f} deg", b) for b in self.bands if b["n"]]
        if self.observed:
            lines.append(row("observed corners (reprojection difference)", self.observed))
        return "\n".join(lines)


def _stats(err: np.ndarray) -> dict:
    ok = np.isfinite(err)
    out = {"n": int(len(err)), "n_projected": int(ok.sum())}
    if ok.any():
        e = err[ok]
        out.update(
            rms_px=float(np.sqrt(np.mean(e**2))),
            p95_px=float(np.percentile(e, 95)),
            max_px=float(np.max(e)),
        )
    return out


def compare_with_kalibr(
    calib, kalibr: KalibrCamera, region: str = "hull", n_samples: int = 20000
) -> KalibrComparison:
    """Projection differences of a Kalibr camera against a calibration over its field.

    Parameters
    ----------
    calib : Calibration
        Ours (its ``extra["observations"]["uv_px"]`` give the observed region).
    kalibr : KalibrCamera or MrcalCamera
        Anything with ``camera_id``, ``model``, ``resolution``, ``tool`` and
        ``project(rays (N, 3)) -> (N, 2)`` px.
    region : {"hull", "radius", "image"}
        The sampled region (:func:`gtsam_sphere.apps.export.sample_region`).
    n_samples : int
        About how many grid pixels to sample.

    Returns
    -------
    KalibrComparison

    Raises
    ------
    DatasetError
        When the image sizes differ.
    """
    from ..core.rays import pixel_rays

    cam = calib.camera
    if (int(cam.width), int(cam.height)) != tuple(kalibr.resolution):
        raise DatasetError(
            f"{kalibr.tool} {kalibr.camera_id} has resolution {kalibr.resolution[0]}x"
            f"{kalibr.resolution[1]}, the calibration {int(cam.width)}x{int(cam.height)}"
        )
    obs = calib.extra.get("observations") if isinstance(calib.extra, dict) else None
    uv_obs = None
    if isinstance(obs, dict) and obs.get("uv_px") is not None:
        uv_obs = np.asarray(obs["uv_px"], float).reshape(-1, 2)
    sample = sample_region(cam, uv_obs, region, n_samples)
    err = np.linalg.norm(kalibr.project(sample.rays) - sample.uv_px, axis=1)
    inc = sample.incidence_deg
    result = KalibrComparison(
        kalibr.camera_id, kalibr.model, sample.description, _stats(err), tool=kalibr.tool
    )
    for lo, hi in zip(BANDS_DEG[:-1], BANDS_DEG[1:]):
        sel = (inc >= lo) & (inc < hi)
        result.bands.append({"lo_deg": lo, "hi_deg": hi, **_stats(err[sel])})
    if uv_obs is not None and len(uv_obs):
        uv_obs = uv_obs[np.all(np.isfinite(uv_obs), axis=1)]
        rays = pixel_rays(cam, uv_obs)
        good = np.all(np.isfinite(rays), axis=1)
        e = np.full(len(uv_obs), np.nan)
        e[good] = np.linalg.norm(kalibr.project(rays[good]) - uv_obs[good], axis=1)
        result.observed = _stats(e)
    return result


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``gtsam-sphere compare CALIB.json --with camchain.yaml``."""
    parser.add_argument(
        "--camera",
        default=None,
        help="--with: the Kalibr camera to compare (default: every camera of the file; a rig "
        "calibration's camera of the same id)",
    )
    parser.add_argument(
        "--region",
        choices=("hull", "radius", "image"),
        default="hull",
        help="--with: the sampled region (default: hull of the observed corners)",
    )


def run_cli(args: argparse.Namespace) -> int:
    """``gtsam-sphere compare CALIB.json --with camchain.yaml``: print the differences."""
    from ..io.calibration import load_calibration, single_camera

    calib = load_calibration(args.dataset)
    if str(args.with_).endswith(".cameramodel"):
        from .export_formats import read_cameramodel

        mrcal_cam = read_cameramodel(args.with_)
        calib = single_camera(calib, args.camera or None, args.dataset, f" ({args.with_})")
        print(compare_with_kalibr(calib, mrcal_cam, region=args.region).summary())
        return 0
    cams = read_kalibr_camchain(args.with_)
    wanted = [args.camera] if args.camera else list(cams)
    for cid in wanted:
        if cid not in cams:
            raise OptionsError(f"--camera {cid}: not in {args.with_} (has {', '.join(cams)})")
    rig = hasattr(calib, "camera_ids")
    if not rig and len(wanted) > 1:
        raise OptionsError(
            f"{args.with_} holds {len(wanted)} cameras ({', '.join(wanted)}) and "
            f"{args.dataset} one: choose the Kalibr camera with --camera"
        )
    for cid in wanted:
        if rig:
            if cid not in calib.camera_ids:
                raise OptionsError(
                    f"Kalibr camera {cid!r} is not a camera of {args.dataset} "
                    f"({', '.join(calib.camera_ids)}): choose one with --camera"
                )
            one = calib.camera_calibration(cid)
        else:
            one = calib
        result = compare_with_kalibr(one, cams[cid], region=args.region)
        print(result.summary())
    return 0
