"""``gtsam-sphere refine``: refine a map's poses and points with a frozen calibration."""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np

from ..core.errors import OptionsError
from ..estimation.optimize import stderr_progress

logger = logging.getLogger("gtsam_sphere.cli")

NAME = "refine"
HELP = "refine a map (dataset@1/@2 observations) with a frozen calibration, locally or on Ray"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Arguments of ``gtsam-sphere refine``."""
    from ..estimation.partitioned import Engine

    p.add_argument(
        "map", help="dataset@1 or dataset@2 (rig): observations; images may give cam_from_world"
    )
    p.add_argument(
        "--calibration", required=True, help="calibration@1 (a rig: @2) of the camera(s), frozen"
    )
    p.add_argument(
        "-o", "--output", required=True, help="calibration@1 (@2) holding the refined map"
    )
    p.add_argument(
        "--engine",
        choices=[e.value for e in Engine],
        default=Engine.LOCAL.value,
        help="local: this process (default); ray: the submaps on a Ray cluster "
        "(pip install 'gtsam-sphere[distributed]')",
    )
    p.add_argument(
        "--address",
        default=None,
        help="Ray cluster address (ray.init(address=...)); default: a local Ray cluster",
    )
    p.add_argument(
        "--partitions",
        type=int,
        default=None,
        help="submaps (default 1 for local, one per Ray worker for ray); local with more "
        "than 1 runs the partitioned solver in this process",
    )
    p.add_argument("--workers", type=int, default=None, help="ray: worker processes (actors)")
    p.add_argument(
        "--checkpoint",
        default=None,
        help="partitioned runs: checkpoint file (default OUTPUT.checkpoint.npz); an "
        "interrupted run started again resumes from it",
    )
    p.add_argument(
        "--sigma-px",
        type=float,
        default=None,
        help="pixel noise (px); default: the calibration's statistics.sigma_px, else 0.5",
    )
    p.add_argument(
        "--datum-sigma",
        type=float,
        default=1.0,
        help="prior sigma of targets without one (dataset units; default 1)",
    )
    p.add_argument("--max-iterations", type=int, default=100)
    p.add_argument("--quiet", action="store_true", help="no progress lines")


def run(args) -> int:
    """Run ``gtsam-sphere refine``: 0 converged, 1 not converged (bad input raises)."""
    from ..estimation.map_problem import map_problem_from_dataset, refine_global
    from ..estimation.partitioned import Engine, PartitionedOptions, refine_map
    from ..io.calibration import Calibration, RigCalibration, load_calibration, single_camera
    from ..io.map_file import load_map

    engine = Engine(args.engine)
    if args.partitions is not None and args.partitions < 1:
        raise OptionsError(f"--partitions must be >= 1, got {args.partitions}")
    if args.workers is not None and args.workers < 1:
        raise OptionsError(f"--workers must be >= 1, got {args.workers}")
    if args.address is not None and engine is not Engine.RAY:
        raise OptionsError("--address applies to --engine ray")
    if args.max_iterations < 1:
        raise OptionsError(f"--max-iterations must be >= 1, got {args.max_iterations}")
    if not args.datum_sigma > 0:
        raise OptionsError(f"--datum-sigma must be > 0, got {args.datum_sigma}")
    calib = load_calibration(args.calibration)
    dataset, initial = load_map(args.map)
    rig = hasattr(dataset, "camera_ids")
    if rig:
        if not isinstance(calib, RigCalibration):
            raise OptionsError(
                f"{args.map} is a rig map (dataset@2): --calibration must be a rig "
                "calibration (calibration@2)"
            )
        camera, cam_from_rig = calib.cameras, calib.cam_from_rig
    else:
        calib = single_camera(calib, None, args.calibration)
        camera, cam_from_rig = calib.camera, None
    sigma_px = args.sigma_px or float(calib.statistics.get("sigma_px", 0.5) or 0.5)
    if not sigma_px > 0:
        raise OptionsError(f"--sigma-px must be > 0, got {sigma_px}")
    for iid, why in dataset.skipped_images:
        logger.warning("image %r skipped: %s", iid, why)
    problem, image_ids, target_ids = map_problem_from_dataset(
        dataset,
        camera,
        initial,
        sigma_px=sigma_px,
        datum_sigma=args.datum_sigma,
        cam_from_rig=cam_from_rig,
    )
    progress = None if args.quiet else stderr_progress
    t0 = time.perf_counter()
    if engine is Engine.LOCAL and (args.partitions or 1) == 1:
        result = refine_global(problem, max_iterations=args.max_iterations)
    else:
        factory = None
        if engine is Engine.RAY:
            from ..estimation.ray_executor import RayExecutor

            factory = RayExecutor.factory(n_workers=args.workers, address=args.address)
        if args.partitions is not None:
            parts = args.partitions
        elif engine is Engine.RAY:
            parts = args.workers or 2
        else:
            parts = 1
        parts = min(parts, problem.n_images)
        checkpoint = args.checkpoint or f"{args.output}.checkpoint.npz"
        args.checkpoint = checkpoint  # named by the interruption message
        options = PartitionedOptions(max_iterations=args.max_iterations, checkpoint=checkpoint)
        result = refine_map(problem, parts, factory, options, progress)
    seconds = time.perf_counter() - t0
    R_cw = np.transpose(result.world_from_cam_R, (0, 2, 1))
    t_cw = -np.einsum("mij,mj->mi", R_cw, result.world_from_cam_t)
    pc = np.einsum("nij,nj->ni", R_cw[problem.obs_image], result.points_world[problem.obs_point])
    pc += t_cw[problem.obs_image]
    e = np.full_like(problem.uv_px, np.nan)
    for c, cam in enumerate(problem.cameras):
        sel = problem.obs_camera == c
        e[sel] = problem.uv_px[sel] - cam.project(pc[sel], valid_only=False)
    rms = float(np.sqrt(np.nanmean(np.sum(e**2, axis=1))))
    stats = {
        "rms_px": rms,
        "n_observations": problem.n_observations,
        "n_rejected": 0,
        "sigma_px": sigma_px,
        "converged": result.converged,
        "status": str(result.status),
        "iterations": result.iterations,
        "initial_cost": result.initial_error,
        "cost": result.error,
        "engine": engine.value,
        "partitions": int(result.stats.get("partitions", 1)),
        "separator_dim": int(result.stats.get("separator_dim", 0)),
        "seconds": seconds,
    }
    source = {"map": str(Path(args.map)), "calibration": str(args.calibration)}
    # what calibration@1 and @2 share: the refined network, its statistics and origin
    network = dict(
        cam_from_world_R=R_cw,
        cam_from_world_t=t_cw,
        target_ids=target_ids,
        target_xyz=result.points_world,
        statistics=stats,
        units=dataset.units,
        extra={"source": source},
    )
    if rig:
        stats["cameras"] = {
            cid: {
                "rms_px": float(np.sqrt(np.nanmean(np.sum(e[problem.obs_camera == c] ** 2, 1)))),
                "n_observations": int(np.sum(problem.obs_camera == c)),
            }
            for c, cid in enumerate(dataset.camera_ids)
        }
        out = _rig_output(calib, dataset, network)
    else:
        out = Calibration(model=calib.model, camera=calib.camera, image_ids=image_ids, **network)
    out.save(args.output)
    print(
        f"{args.output}: {problem.n_images} images, {problem.n_points} targets, "
        f"{problem.n_observations} observations; RMS {rms:.4f} px; cost "
        f"{result.initial_error:.6e} -> {result.error:.6e} ({result.status} after "
        f"{result.iterations} iterations, {stats['partitions']} submaps, {engine.value}, "
        f"{seconds:.1f} s)"
    )
    if not result.converged:
        logger.warning("the refinement did not converge: %s", result.status)
    return 0 if result.converged else 1


def _rig_output(calib, dataset, network: dict):
    """The refined rig map as a ``calibration@2`` (each frame's pose from its first image);
    ``network``: the keyword arguments calibration@1 and @2 share."""
    R_cw, t_cw = network["cam_from_world_R"], network["cam_from_world_t"]
    from ..io.calibration import RigCalibration

    ids = dataset.camera_ids
    cameras = [ids[c] for c in dataset.image_camera]
    frame_ids = dataset.frame_ids
    first = {}
    for i, f in enumerate(dataset.image_frame):
        if f is not None and f not in first:
            first[f] = i
    rig_R, rig_t = np.empty((len(frame_ids), 3, 3)), np.empty((len(frame_ids), 3))
    for q, f in enumerate(frame_ids):
        i = first[f]
        Rc, tc = calib.cam_from_rig[cameras[i]]
        # rig_from_world = (cam_from_rig)^-1 cam_from_world
        rig_R[q] = Rc.T @ R_cw[i]
        rig_t[q] = Rc.T @ (t_cw[i] - tc)
    return RigCalibration(
        camera_ids=list(ids),
        cameras={c: calib.cameras[c] for c in ids},
        models={c: calib.models[c] for c in ids},
        cam_from_rig={c: calib.cam_from_rig[c] for c in ids},
        frame_ids=frame_ids,
        rig_from_world_R=rig_R,
        rig_from_world_t=rig_t,
        image_ids=list(dataset.image_ids),
        image_camera=cameras,
        image_frame=list(dataset.image_frame),
        **network,
    )
