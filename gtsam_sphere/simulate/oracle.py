"""The oracle of a simulated calibration: the same data adjusted with the true lens known.

The accuracy goals compare a model's 3D check-point error with this oracle:
only poses and targets are estimated, the lens is the simulator's own.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from ..core.camera import Model
from ..estimation.calibrate import CalibrationOptions, calibrate
from ..io.calibration import Calibration
from ..io.dataset import Dataset, parse_dataset


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
    unprojected without knowing which). A non-central pupil stays unmodelled,
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


def oracle_calibration(
    sim, seed: int = 0, progress: Callable[[str], None] | None = None
) -> Calibration:
    """Adjust a simulation with its true lens held fixed (poses and targets only).

    Parameters
    ----------
    sim : Simulation
        From :func:`gtsam_sphere.simulate.simulate_room`.
    seed : int
    progress : callable(str), optional

    Returns
    -------
    Calibration
        Its ``camera`` is the ideal model, not the true lens; use it for the
        adjusted network (:func:`gtsam_sphere.analysis.evaluate.evaluate_calibration`).
    """
    dataset = parse_dataset(sim.dataset)
    ideal, model, fixed = oracle_dataset(dataset, sim.lens, sim.truth["lens"])
    options = CalibrationOptions(
        model=model,
        brown_terms=(),
        radial_terms=0,
        fixed_intrinsics=fixed,
        seed=seed,
        covariance=False,
    )
    return calibrate(ideal, options, progress)
