"""The report of a rig calibration (``calibration@2``): a rig page and one page per camera.

:func:`write_rig_report` writes into ``out_dir``:

``rig.png``
    Top view of the rig (its cameras' centres and optical axes in the rig
    frame, the reference camera at the origin) and of the frames' trajectory
    in the world (the rig's positions, the reference camera's viewing
    direction, the targets in grey). "Top" is the world axis closest to the
    cameras' mean "up" (their ``-y`` axis) when the rig was held upright, else
    the axis the scene spreads least along: the plot shows the other two.
``index.html``, ``report.md``
    Per-camera residual statistics, the extrinsics (``cam_from_rig``) with the
    sigmas the calibration file gives, the figure, links to the cameras' pages.
``<camera id>/``
    Each camera's single-camera report
    (:func:`gtsam_sphere.apps.report.write_report` of
    :meth:`~gtsam_sphere.io.calibration.RigCalibration.camera_calibration`).
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np

from ..core.errors import OptionsError
from ..io.calibration import RigCalibration
from .report import (
    PLOTS,
    _html,
    _Image,
    _markdown,
    _save,
    _subplots,
    _Table,
    _value,
    observations_of,
    write_report,
)

_SAFE = re.compile(r"[^A-Za-z0-9_.-]+")


def camera_dir_name(camera_id: str) -> str:
    """The folder name of a camera's page (its id, made safe for a path)."""
    name = _SAFE.sub("_", camera_id).strip(".") or "camera"
    return name


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle (deg) of a rotation matrix."""
    c = (np.trace(R) - 1.0) / 2.0
    s = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    return math.degrees(math.atan2(s, c))


def rotation_vector_deg(R: np.ndarray) -> np.ndarray:
    """Axis times angle (deg), (3,)."""
    angle = rotation_angle_deg(R)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    n = np.linalg.norm(v)
    if n < 1e-12:
        if angle < 90:
            return np.zeros(3)
        w, vecs = np.linalg.eigh((R + R.T) / 2)  # 180 deg: the axis is R's +1 eigenvector
        return vecs[:, -1] * angle
    return v / n * angle


def _find(d, key: str):
    """First value of ``key`` in nested dicts ``d`` (depth first), None if absent."""
    if isinstance(d, dict):
        if key in d:
            return d[key]
        for v in d.values():
            found = _find(v, key)
            if found is not None:
                return found
    return None


def extrinsic_sigmas(statistics: dict, camera_id: str) -> tuple[float | None, np.ndarray | None]:
    """``(rotation sigma deg, translation sigma (3,))`` of a camera's ``cam_from_rig`` as
    the calibration's ``statistics.cameras[id]`` gives them (``None`` where absent)."""
    cs = statistics.get("cameras", {}).get(camera_id, {})
    rot = _find(cs, "rotation_sigma_deg")
    trans = _find(cs, "translation_sigma")
    try:
        rot = None if rot is None else float(rot)
    except (TypeError, ValueError):
        rot = None
    try:
        trans = None if trans is None else np.asarray(trans, float).reshape(3)
    except (TypeError, ValueError):
        trans = None
    return rot, trans


def _centre(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Centre of a ``p_local = R p + t`` frame in the outer frame."""
    return -R.T @ t


def _top_axes(up: np.ndarray, points: np.ndarray) -> tuple[int, int, str]:
    """The two world axes of the top view and its description.

    ``up`` is the mean of the frames' "up" directions (unit vectors): when the
    rig was held upright (norm above 0.8) the world axis closest to it is
    dropped, else the axis along which ``points`` (targets, rig positions)
    spread least.
    """
    names = "XYZ"
    if np.linalg.norm(up) > 0.8:
        k = int(np.argmax(np.abs(up)))
        how = f"{names[k]} {'up' if up[k] > 0 else 'down'} (the rig's mean up)"
    else:
        k = int(np.argmin(np.ptp(points, axis=0)))
        how = f"along {names[k]} (the scene's thinnest axis)"
    a, b = [i for i in range(3) if i != k]
    return a, b, f"world {names[a]}-{names[b]} plane, seen {how}"


def plot_rig(calib: RigCalibration, path: Path) -> Path:
    """Write ``rig.png``: the rig's cameras (top view, rig frame) and the trajectory."""
    fig, (ax0, ax1) = _subplots(1, 2, figsize=(12, 5.5))
    units = calib.units
    # rig frame: camera x right, y down, z forward: top view is x (right) and z (forward)
    centres = {c: _centre(*calib.cam_from_rig[c]) for c in calib.camera_ids}
    extent = max([np.linalg.norm(p[[0, 2]]) for p in centres.values()] + [1e-9])
    arrow = 0.35 * extent if extent > 1e-6 else 1.0
    for k, cid in enumerate(calib.camera_ids):
        R, _ = calib.cam_from_rig[cid]
        p = centres[cid]
        axis = R.T @ np.array([0.0, 0.0, 1.0])
        colour = f"C{k % 10}"
        ax0.plot(p[0], p[2], "o", color=colour, ms=8)
        # the arrow's tip, invisible: keeps it inside the axes' data limits
        ax0.plot(p[0] + arrow * axis[0], p[2] + arrow * axis[2], "o", alpha=0.0)
        ax0.annotate(
            "",
            (p[0] + arrow * axis[0], p[2] + arrow * axis[2]),
            (p[0], p[2]),
            arrowprops={"arrowstyle": "->", "color": colour, "lw": 2},
        )
        ax0.text(p[0], p[2], f"  {cid}", color=colour, va="bottom")
    ax0.set_xlabel(f"rig x ({units}, right of the reference camera)")
    ax0.set_ylabel(f"rig z ({units}, forward)")
    ax0.set_title("Rig (top view, rig frame)\ncamera centres and optical axes", fontsize=10)
    ax0.set_aspect("equal", adjustable="datalim")
    ax0.margins(0.3)
    ax0.grid(alpha=0.3)
    # world: frames' trajectory
    if len(calib.frame_ids):
        Rw, tw = calib.rig_from_world_R, calib.rig_from_world_t
        pos = np.array([_centre(R, t) for R, t in zip(Rw, tw)])
        up = np.mean([R.T @ np.array([0.0, -1.0, 0.0]) for R in Rw], axis=0)
        fwd = np.array([R.T @ np.array([0.0, 0.0, 1.0]) for R in Rw])
        a, b, label = _top_axes(up, np.vstack([pos, calib.target_xyz]))
        if len(calib.target_ids):
            ax1.plot(
                calib.target_xyz[:, a],
                calib.target_xyz[:, b],
                ".",
                color="0.75",
                ms=3,
                label="targets",
            )
        ax1.plot(pos[:, a], pos[:, b], "-", color="0.4", lw=1)
        ax1.plot(pos[:, a], pos[:, b], "o", color="C0", ms=4, label="rig (frames)")
        span = np.ptp(np.vstack([pos, calib.target_xyz])[:, [a, b]], axis=0).max()
        step = 0.05 * (span if span > 0 else 1.0)
        ax1.quiver(
            pos[:, a],
            pos[:, b],
            fwd[:, a] * step,
            fwd[:, b] * step,
            angles="xy",
            scale_units="xy",
            scale=1,
            color="C3",
            width=0.004,
            label=f"{calib.camera_ids[0]} viewing direction",
        )
        ax1.set_title(f"Trajectory of {len(pos)} frames (top view)\n{label}", fontsize=10)
        ax1.set_xlabel(f"{'XYZ'[a]} ({units})")
        ax1.set_ylabel(f"{'XYZ'[b]} ({units})")
        ax1.set_aspect("equal", adjustable="datalim")
        ax1.legend(fontsize=8, loc="best", framealpha=0.9)
        ax1.grid(alpha=0.3)
    else:
        ax1.text(0.5, 0.5, "no frames in the calibration", ha="center", va="center")
        ax1.set_axis_off()
    return _save(fig, path, tight=True)


def _residual_percentiles(calib: RigCalibration, camera_id: str) -> tuple[str, str]:
    """Median and 95th percentile (px) of a camera's stored residual norms ("" without)."""
    obs = observations_of(calib.camera_calibration(camera_id))
    if obs is None or not len(obs.residual_px):
        return "", ""
    norm = np.linalg.norm(obs.residual_px, axis=1)
    norm = norm[np.isfinite(norm)]
    if not len(norm):
        return "", ""
    return _value(float(np.median(norm))), _value(float(np.percentile(norm, 95)))


def _camera_table(calib: RigCalibration, links: dict[str, str]) -> _Table:
    rows = []
    for cid in calib.camera_ids:
        median, p95 = _residual_percentiles(calib, cid)
        cs = calib.statistics.get("cameras", {}).get(cid, {})
        cam = calib.cameras[cid]
        n_img = sum(1 for c in calib.image_camera if c == cid)
        trusted = cs.get("trusted", cs.get("converged"))
        rows.append(
            [
                f"[{cid}]({links[cid]})",
                f"`{calib.models[cid]}`",
                f"{cam.width} x {cam.height}",
                str(n_img),
                _value(cs.get("rms_px")),
                _value(cs.get("rms_px_rig")) if "rms_px_rig" in cs else "",
                _value(cs.get("rms_px_without_outliers"))
                if "rms_px_without_outliers" in cs
                else "",
                median,
                p95,
                f"{cs.get('n_observations', '')} / {cs.get('n_rejected', '')}",
                str(cs.get("n_outliers", "")),
                "" if trusted is None else ("yes" if trusted else "**no**"),
            ]
        )
    return _Table(
        [
            "camera",
            "model",
            "image (px)",
            "images",
            "RMS (px)",
            "RMS with rig poses (px)",
            "RMS w/o outliers (px)",
            "median residual (px)",
            "95% residual (px)",
            "observations used / rejected",
            "outliers",
            "trusted",
        ],
        rows,
    )


def _extrinsics_table(calib: RigCalibration) -> _Table:
    u = calib.units
    rows = []
    for cid in calib.camera_ids:
        R, t = calib.cam_from_rig[cid]
        rv = rotation_vector_deg(R)
        rot_s, tr_s = extrinsic_sigmas(calib.statistics, cid)
        ref = cid == calib.camera_ids[0]
        cs = calib.statistics.get("cameras", {}).get(cid, {})
        base_s = _find(cs, "baseline_sigma")
        how = _find(cs, "sigma_source")
        if how is None and rot_s is not None and _find(cs, "rotation_spread_deg") is not None:
            how = "spread of the frames' relative poses"
        rows.append(
            [
                cid,
                f"{rotation_angle_deg(R):.4f}",
                ", ".join(f"{v:.4f}" for v in rv),
                "reference" if ref else ("n/a" if rot_s is None else f"{rot_s:.4f}"),
                ", ".join(f"{v:.5g}" for v in t),
                f"{np.linalg.norm(_centre(R, t)):.5g}",
                "reference"
                if ref
                else ("n/a" if tr_s is None else ", ".join(f"{v:.3g}" for v in tr_s)),
                "" if ref or base_s is None else _value(base_s),
                "" if ref or how is None else str(how),
            ]
        )
    return _Table(
        [
            "camera",
            "rotation (deg)",
            "rotation vector (deg)",
            "rotation sigma (deg)",
            f"t x, y, z ({u})",
            f"distance to reference ({u})",
            f"t sigma x, y, z ({u})",
            f"distance sigma ({u})",
            "sigmas from",
        ],
        rows,
    )


def write_rig_report(
    calib: RigCalibration,
    out_dir: str | os.PathLike,
    *,
    title: str | None = None,
    source: str | None = None,
    camera_pages: bool = True,
) -> dict[str, Path]:
    """Write the rig page (``index.html``, ``report.md``, ``rig.png``) and each camera's page.

    Parameters
    ----------
    calib : RigCalibration
    out_dir : path
        Created if needed; a camera's page goes to ``out_dir/<camera id>/``.
    title : str, optional
    source : str, optional
        The calibration file, named on the page.
    camera_pages : bool
        Also write each camera's single-camera report.

    Returns
    -------
    dict
        ``{"rig": rig.png, "markdown": ..., "html": ..., "camera:<id>": that camera's
        index.html}``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {"rig": plot_rig(calib, out / "rig.png")}
    links = {}
    for cid in calib.camera_ids:
        sub = camera_dir_name(cid)
        links[cid] = f"{sub}/index.html"
        if camera_pages:
            page = write_report(
                calib.camera_calibration(cid),
                out / sub,
                title=f"Camera {cid} of the rig {Path(source).name if source else ''}".strip(),
            )
            paths[f"camera:{cid}"] = page["html"]
    st = calib.statistics
    name = Path(source).name if source else calib.model
    title = title or f"Rig calibration report: {name}"
    blocks: list = [(1, title)]
    intro = (
        f"{len(calib.camera_ids)} cameras ({', '.join(calib.camera_ids)}), "
        f"{len(calib.frame_ids)} frames, {len(calib.image_ids)} images, units {calib.units}; "
        f"the rig frame is camera {calib.camera_ids[0]}'s"
    )
    if source:
        intro += f"; file `{source}`"
    blocks.append(intro + ".")
    summary = [f"RMS {_value(st.get('rms_px'))} px"]
    if "rms_px_rig" in st:
        summary.append(f"{_value(st['rms_px_rig'])} px with the rig poses")
    summary.append(f"{st.get('n_observations')} observations")
    if "rig_adjustment" in st:
        summary.append(f"adjustment `{st['rig_adjustment']}`")
    if "trusted" in st:
        summary.append("trusted" if st["trusted"] else "**not trusted**")
    blocks.append("Summary: " + ", ".join(summary) + ".")
    for reason in st.get("distrust", []) or []:
        blocks.append(f"**Do not trust:** {reason}")
    for warning in st.get("warnings", []) or []:
        blocks.append(f"Warning: {warning}")
    blocks += [
        (2, "Cameras: residuals"),
        "Per camera, over its observations (`statistics.cameras` of the file); the "
        "camera's name links to its own report.",
        _camera_table(calib, links),
        (2, "Extrinsics (cam_from_rig)"),
        "`p_cam = R p_rig + t`; the rotation vector is axis times angle. The sigmas are "
        "those the calibration file gives (`statistics.cameras[id]`), n/a where it gives "
        "none.",
        _extrinsics_table(calib),
        (2, "Rig and trajectory"),
        _Image("rig.png", "Top view of the rig's cameras and of the frames' trajectory."),
    ]
    paths["markdown"] = out / "report.md"
    paths["markdown"].write_text(_markdown(blocks), encoding="utf-8")
    paths["html"] = out / "index.html"
    paths["html"].write_text(_html(blocks, title), encoding="utf-8")
    return paths


def write_any_report(
    calibration_path_or_obj,
    out_dir,
    compare_with=None,
    title: str | None = None,
) -> dict:
    """The report of a calibration of either kind: :func:`write_rig_report` for a rig
    (calibration@2), :func:`~gtsam_sphere.apps.report.write_report` for one camera.

    Same arguments and return value as those; ``compare_with`` (single cameras only)
    on a rig raises ``OptionsError``.
    """
    from ..io.calibration import Calibration, RigCalibration, load_calibration

    source = None if isinstance(calibration_path_or_obj, Calibration) else calibration_path_or_obj
    calib = (
        calibration_path_or_obj
        if isinstance(calibration_path_or_obj, (Calibration, RigCalibration))
        else load_calibration(calibration_path_or_obj)
    )
    if not isinstance(calib, RigCalibration):
        return write_report(calib, out_dir, compare_with=compare_with, title=title)
    if compare_with:
        raise OptionsError(
            "--compare compares single-camera calibrations; a rig's report compares its "
            "cameras on the rig page"
        )
    return write_rig_report(
        calib, out_dir, title=title, source=None if source is None else str(source)
    )


def run_cli(args) -> int:
    """Run ``gtsam-sphere report``; 0 on success (bad input raises ``DatasetError``)."""
    paths = write_any_report(
        args.calibration, args.output, compare_with=list(args.compare), title=args.title
    )
    cameras = [k.split(":", 1)[1] for k in paths if k.startswith("camera:")]
    if cameras:
        print(
            f"wrote {paths['html']} and {paths['markdown']} (rig page, {paths['rig'].name}) and "
            f"a page per camera: " + ", ".join(str(paths[f"camera:{c}"]) for c in cameras)
        )
        return 0
    print(f"wrote {paths['html']} and {paths['markdown']} with {len(PLOTS)} plots")
    return 0
