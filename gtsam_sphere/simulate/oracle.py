"""The oracle of a simulated calibration: the same data adjusted with the true lens known.

The accuracy goals compare a model's 3D check-point error with this oracle:
only poses and targets are estimated, the lens is the simulator's own. For a
simulated rig (:func:`oracle_rig_calibration`) the true ``cam_from_rig`` are held too;
with ``known_lenses=False`` the same ideal measurements are adjusted with each lens's
principal point and principal distance and the extrinsics free: the reference of an
adjustment that knows each lens's family but not its parameters.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from ..core.camera import Model
from ..core.errors import InitialisationError
from ..estimation.calibrate import CalibrationOptions, Initialisation, calibrate
from ..estimation.rig import assemble_rig
from ..io.calibration import Calibration, RigCalibration
from ..io.dataset import Dataset, parse_dataset, parse_rig_dataset, split_rig


def _base_kind(desc: dict) -> str:
    while desc.get("kind") in ("error-field", "non-central"):
        desc = desc["lens"]
    return str(desc.get("kind"))


def oracle_dataset(dataset: Dataset, lens, lens_desc: dict) -> tuple[Dataset, Model, tuple]:
    """Measurements mapped through the true lens onto an ideal model with known intrinsics.

    Every raw pixel is unprojected with the true (central part of the) lens
    and re-imaged by the ideal model ``pp + f * g(alpha) * direction``:
    equidistant (``g = alpha``) for every lens, or the sphere mapping for the
    sphere lens (whose two hemispheres share the image and cannot be
    unprojected without knowing which; its decentering and affinity are undone
    in the image plane). A non-central pupil stays unmodelled,
    as it is for every estimated model.

    Parameters
    ----------
    dataset : Dataset
        The raw measurements (uv_px, (N, 2)).
    lens : lens object
        ``Simulation.lens`` (``unproject``, ``cx``, ``cy``, ``f``).
    lens_desc : dict
        ``truth["lens"]``.

    Returns
    -------
    dataset : Dataset
        A copy whose ``uv_px`` are the ideal pixels.
    model : Model
    fixed_intrinsics : tuple
        ``(cx, cy, f)`` in px.
    """
    pp = np.array([lens.cx, lens.cy])
    if _base_kind(lens_desc) == "sphere":
        uv = lens.remove_field(dataset.uv_px) if hasattr(lens, "remove_field") else dataset.uv_px
        central = lens
        while hasattr(central, "lens"):  # the wrappers (error field, pupil) hold it
            central = central.lens
        if central.a1 or central.a2 or central.has_decentering:  # sensor defects
            uv = central.ideal_pixels(uv)
        return replace(dataset, uv_px=np.asarray(uv, float)), Model.SPHERE, (*pp, lens.f)
    rays = lens.unproject(dataset.uv_px)
    rho = np.hypot(rays[:, 0], rays[:, 1])
    alpha = np.arctan2(rho, rays[:, 2])
    with np.errstate(invalid="ignore", divide="ignore"):
        direction = np.where(rho[:, None] > 0, rays[:, :2] / rho[:, None], 0.0)
    ideal = pp + lens.f * alpha[:, None] * direction
    ok = np.isfinite(ideal).all(1)
    # a noisy pixel just outside a circular fisheye's image has no true ray: the oracle
    # leaves it out and lists it in ``dropped``
    dropped = list(dataset.dropped) + [
        (
            dataset.image_ids[dataset.obs_image[o]],
            dataset.target_ids[dataset.obs_target[o]],
            "oracle: outside the true lens's image",
        )
        for o in np.flatnonzero(~ok)
    ]
    out = replace(
        dataset,
        uv_px=ideal[ok],
        obs_image=dataset.obs_image[ok],
        obs_target=dataset.obs_target[ok],
        dropped=dropped,
    )
    return out, Model.RADIAL, (*pp, lens.f)


def _true_pose_initialisation(ideal: Dataset, truth: dict, model: Model, fixed: tuple):
    """The true ``cam_from_world`` of ``ideal``'s images as an :class:`Initialisation`.

    The adjustment's optimum does not depend on its start: the oracles skip the
    lens-unknown initialisation.
    """
    true_pose = {
        im["id"]: (np.array(im["cam_from_world"]["R"]), np.array(im["cam_from_world"]["t"]))
        for im in truth["images"]
    }
    return Initialisation(
        ideal,
        np.array([true_pose[i][0] for i in ideal.image_ids]),
        np.array([true_pose[i][1] for i in ideal.image_ids]),
        len(ideal.image_ids),
        str(model),
        float(fixed[2]),
        principal_point_px=np.array(fixed[:2], float),
    )


def oracle_calibration(
    sim,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    known_lens: bool = True,
    known_field: bool = True,
    learn_correction: bool = False,
) -> Calibration:
    """Adjust a simulation with its true lens held fixed (poses and targets only).

    Parameters
    ----------
    sim : Simulation
        From :func:`gtsam_sphere.simulate.simulate_room`.
    seed : int
    progress : callable(str), optional
    known_lens : bool
        False: the family oracle. The same ideal measurements (:func:`oracle_dataset`),
        with the ideal model's principal point and principal distance estimated too
        (from the true poses): an adjustment that knows the lens family and its
        distortion exactly but not its scale and centre. The gap between the two
        oracles is what not knowing those three numbers costs on this geometry.
    known_field : bool
        False: the field-blind oracle. A simulated smooth error field
        (:class:`~gtsam_sphere.simulate.lenses.ErrorField`) stays in the measurements
        as unmodelled error: the rest of the lens is known. Its gap to the oracle is
        the part of the field that no correction learned from the residuals can
        recover, because the poses (and targets) absorb it.
    learn_correction : bool
        With ``known_field=False``: the ideal model plus the kNN correction rounds
        (``radial+knn`` with no radial terms): whether the correction gets the field
        back once the radial model is exact.

    Returns
    -------
    Calibration
        Its ``camera`` is the ideal model, not the true lens; use it for the
        adjusted network (:func:`gtsam_sphere.analysis.evaluate.evaluate_calibration`).
    """
    dataset = parse_dataset(sim.dataset)
    lens = sim.lens
    if not known_field and sim.truth["lens"].get("kind") == "error-field":
        lens = lens.lens  # the field is always the outermost wrapper (room.py)
    ideal, model, fixed = oracle_dataset(dataset, lens, sim.truth["lens"])
    if learn_correction and model is not Model.RADIAL:
        raise ValueError(f"learn_correction needs the radial ideal model, not {model}")
    options = CalibrationOptions(
        model=Model.RADIAL_KNN if learn_correction else model,
        brown_terms=(),
        radial_terms=0,
        fixed_intrinsics=fixed if known_lens else None,
        seed=seed,
        covariance=False,
    )
    if known_lens:
        try:
            return calibrate(ideal, options, progress)
        except InitialisationError:
            # the initialisation knows no lens; the ideal pixels of a lens no family
            # approximates well enough (a 279 deg field-of-view room in 640x480 with 1.5
            # px noise: 36 % consistent) start from the true poses instead
            pass
    init = _true_pose_initialisation(ideal, sim.truth, model, fixed)
    return calibrate(ideal, options, progress, init=init)


def oracle_rig_calibration(
    sim,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    known_lenses: bool = True,
) -> RigCalibration:
    """Adjust a simulated rig with its true lenses (and true extrinsics) known.

    Every camera's measurements are mapped through its true lens onto the ideal model
    (:func:`oracle_dataset`); each camera is adjusted alone on them (poses and
    targets, its ideal intrinsics held), then the rig's joint adjustment
    (:func:`gtsam_sphere.estimation.rig.assemble_rig`) runs on them with the true
    ``cam_from_rig`` held: only the frames' ``rig_from_world`` and the targets move.

    Parameters
    ----------
    sim : RigSimulation
        From :func:`gtsam_sphere.simulate.simulate_rig` (its ``cameras`` hold the
        true lenses and ``cam_from_rig``, metres).
    seed : int
    progress : callable(str), optional
    known_lenses : bool
        False: the ideal intrinsics (principal point, principal distance) and the
        extrinsics are estimated too, starting from the averaged ones: an adjustment
        that knows each lens's family exactly but not its parameters (fewer
        parameters than the true family, so its covariance is, if anything, a
        slightly optimistic expected error). Its ``cam_from_rig_precision`` is the
        joint stage's marginal covariance.

    Returns
    -------
    RigCalibration
        Its cameras are the ideal models, not the true lenses; use it for the
        adjusted network (targets, ``rig_from_world``) and, without
        ``known_lenses``, for the extrinsics and their sigma.
    """
    say = progress or (lambda _line: None)
    rig = parse_rig_dataset(sim.dataset)
    parts = split_rig(rig)
    lens_desc = {cam["id"]: cam["lens"] for cam in sim.truth["cameras"]}
    calibs: dict[str, Calibration] = {}
    options: dict[str, CalibrationOptions] = {}
    for cam in sim.cameras:
        ideal, model, fixed = oracle_dataset(parts[cam.id], cam.lens, lens_desc[cam.id])
        init = _true_pose_initialisation(ideal, sim.truth, model, fixed)
        opts = CalibrationOptions(
            model=model,
            brown_terms=(),
            radial_terms=0,
            fixed_intrinsics=fixed if known_lenses else None,
            seed=seed,
            covariance=False,
        )
        options[cam.id] = opts
        calibs[cam.id] = calibrate(
            ideal, opts, lambda line, c=cam.id: say(f"[{c}] {line}"), init=init
        )
    truth = {cam.id: cam.cam_from_rig for cam in sim.cameras} if known_lenses else None
    return assemble_rig(rig, calibs, options, say, joint=True, fixed_extrinsics=truth)
