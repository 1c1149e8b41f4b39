"""Targets without a sigma seen in one image only (estimation.calibrate.
without_undetermined_targets): left out of a camera's adjustment and counted, taken back
by a rig's joint adjustment where another camera determines them."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import dataset_doc

from gtsam_sphere.estimation.calibrate import (
    MIN_DETERMINED_OBSERVATIONS,
    UNDETERMINED_REASON,
    without_undetermined_targets,
)
from gtsam_sphere.io.dataset import parse_dataset


def _doc(sigma=None):
    """Three images: T0-T5 seen by A and B, T6 by A only, T7-T9 by C only (C also sees
    T0 and T1), so C keeps 2 determined observations (< 4) and goes; then T0, T1 are
    still seen twice."""
    targets = []
    for k in range(10):
        t = {"id": f"T{k}", "xyz": [float(k), 0.3 * k, 2.0]}
        if sigma is not None:
            t["sigma"] = sigma
        targets.append(t)

    def obs(ks):
        return [{"target": f"T{k}", "uv": [100.0 + 10 * k, 200.0 + k]} for k in ks]

    return dataset_doc(
        targets,
        [
            {"id": "A", "observations": obs(range(7))},
            {"id": "B", "observations": obs(range(6))},
            {"id": "C", "observations": obs([0, 1, 7, 8, 9])},
        ],
    )


def test_free_targets_seen_once_are_left_out_and_counted():
    ds = parse_dataset(_doc())
    assert MIN_DETERMINED_OBSERVATIONS == 4
    out, keep_obs, keep_img = without_undetermined_targets(ds)
    assert keep_img.tolist() == [True, True, False]
    assert out.image_ids == ["A", "B"]
    assert out.skipped_images[0][0] == "C" and "fewer than 4" in out.skipped_images[0][1]
    # A's T6 is left out one by one; C's observations go with C
    assert out.dropped == [("A", "T6", UNDETERMINED_REASON)]
    assert out.n_observations == 12 == int(keep_obs.sum())
    assert sorted({out.target_ids[j] for j in out.obs_target}) == [f"T{k}" for k in range(6)]
    # every target kept is seen by two images
    pairs = np.unique(np.stack([out.obs_image, out.obs_target], 1), axis=0)
    assert np.bincount(pairs[:, 1]).max() == 2 and set(np.bincount(pairs[:, 1])) <= {0, 2}


@pytest.mark.parametrize("sigma", [0.0, 0.01])
def test_targets_with_a_sigma_are_determined_by_their_prior(sigma):
    ds = parse_dataset(_doc(sigma))
    out, keep_obs, keep_img = without_undetermined_targets(ds)
    assert out is ds and keep_obs.all() and keep_img.all()


def test_rig_joint_adjustment_takes_back_what_a_camera_left_out():
    """A camera's calibration left out the free targets it sees in one image only; in the
    rig another camera sees them, so the joint adjustment uses them: its solution is the
    one with every observation in the camera's list."""
    from test_rig_joint import _in_model_rig

    from gtsam_sphere.estimation.rig_joint import adjust_rig_jointly

    rig, _, calibs, ext0, frames0, xyz0 = _in_model_rig(0, n_surveyed=0)
    full = adjust_rig_jointly(rig, calibs, ext0, frames0, xyz0)
    n_full = {cid: len(full.residuals_px[cid]) for cid in calibs}
    moved = 0
    for cal in calibs.values():
        obs = cal.extra["observations"]
        tg = np.array(obs["target"])
        seen = {}
        for i, t in zip(obs["image"], obs["target"]):
            seen.setdefault(t, set()).add(i)
        once = np.array([len(seen[t]) < 2 for t in tg])
        moved += int(once.sum())
        uv = np.asarray(obs["uv_px"])
        cal.extra["undetermined_observations"] = {
            "image": [i for i, o in zip(obs["image"], once) if o],
            "target": tg[once].tolist(),
            "uv_px": uv[once],
        }
        cal.extra["observations"] = {
            "image": [i for i, o in zip(obs["image"], once) if not o],
            "target": tg[~once].tolist(),
            "uv_px": uv[~once],
        }
    assert moved > 0
    jr = adjust_rig_jointly(rig, calibs, ext0, frames0, xyz0)
    for cid in calibs:
        assert len(jr.residuals_px[cid]) == n_full[cid]
        assert np.isfinite(jr.residuals_px[cid]).all(axis=1).sum() == (
            np.isfinite(full.residuals_px[cid]).all(axis=1).sum()
        )
    R, t = jr.cam_from_rig["cam1"]
    R0, t0 = full.cam_from_rig["cam1"]
    assert np.allclose(R, R0, atol=1e-7) and np.allclose(t, t0, atol=1e-7)


@pytest.mark.slow  # end-to-end, 3-5 s
def test_free_network_of_few_images_is_trusted():
    """A room of 10 images whose targets have no sigma: half the targets are seen once.
    Adjusted with them, the normal equations were singular and the result untrusted
    ("some intrinsics are not determined") though its 3D error matched the oracle's."""
    from gtsam_sphere.estimation.calibrate import calibrate
    from gtsam_sphere.simulate import SimulationOptions, simulate_room

    sim = simulate_room(
        SimulationOptions(
            lens="equisolid", fov_deg=100.0, width=752, height=480, n_images=10,
            sigma_mode="free", noise_px=0.1, n_checkpoints=50, seed=5,
        )
    )  # fmt: skip
    ds = parse_dataset(sim.dataset)
    _, keep_obs, _ = without_undetermined_targets(ds)
    assert (~keep_obs).sum() > 50
    calib = calibrate(ds)
    st = calib.statistics
    assert st["datum"] == "free"
    assert st["trusted"], st["distrust"]
    assert st["n_undetermined_observations"] > 50
    assert st["n_rejected"] >= st["n_undetermined_observations"]
    left = calib.extra["undetermined_observations"]
    assert len(left["image"]) == len(left["target"]) == len(left["uv_px"])
    assert set(left["target"]).isdisjoint(calib.target_ids)


def test_undetermined_targets_counts_images_not_observations():
    """One image observing a target twice does not determine it; NaN and inf sigma are
    both 'no sigma'; a target with a sigma is never undetermined."""
    from gtsam_sphere.estimation.diagnose import undetermined_targets

    obs_image = np.array([0, 0, 0, 1, 1, 2])
    obs_target = np.array([0, 0, 1, 1, 2, 3])
    sigma = np.array([np.nan, np.nan, np.inf, 0.01, np.nan])
    # T0 twice in image 0, T1 in images 0 and 1, T2 once, T3 once with a sigma, T4 unseen
    assert undetermined_targets(obs_image, obs_target, sigma).tolist() == [
        True, False, True, False, True,
    ]  # fmt: skip
    assert undetermined_targets([], [], sigma).tolist() == [True, True, True, False, True]
