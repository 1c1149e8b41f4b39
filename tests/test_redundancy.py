"""The mean redundancy number and the rule that does not trust a geometry below
``calibrate.MIN_MEAN_REDUNDANCY`` (zoo stress 2912 s13: 120 observations of 50 free
targets in 5 images, mean 0.20, trusted at 2.9x the oracle's 3D error). A free network
of 10 images at 0.32 stays trusted (``test_undetermined_targets.py``)."""

import copy

import numpy as np
import pytest
from helpers import small_free_room, summary_statistics

from gtsam_sphere.estimation.calibrate import (
    MIN_MEAN_REDUNDANCY,
    Distrust,
    low_redundancy,
    mean_redundancy,
)


def test_the_mean_counts_the_equations_of_observations_and_of_target_priors():
    # 100 observations: 200 equations; 10 targets with a prior: 30 more
    assert mean_redundancy(46, 100, 0) == pytest.approx(0.23)
    assert mean_redundancy(115, 100, 10) == pytest.approx(0.5)
    assert np.isnan(mean_redundancy(0, 0, 0))


def test_the_limit_is_judged_on_the_mean_either_side():
    n = 120
    below = {"redundancy": 48, "n_observations": n, "mean_redundancy": 48 / 240}
    why = low_redundancy(below)
    assert "redundancy 48 for 120 observations" in why
    assert "mean redundancy number 0.20" in why and "limit 0.25" in why
    assert "three or more" in why
    just_below = dict(below, mean_redundancy=0.99 * MIN_MEAN_REDUNDANCY)
    assert low_redundancy(just_below)
    assert low_redundancy(dict(below, mean_redundancy=MIN_MEAN_REDUNDANCY)) == ""
    assert low_redundancy(dict(below, mean_redundancy=0.8)) == ""
    # nothing to judge: a statistics dict from before the rule, or no equation at all
    assert low_redundancy({"redundancy": 48, "n_observations": n}) == ""
    assert low_redundancy(dict(below, mean_redundancy=float("nan"))) == ""


def _first_images(doc: dict, n: int) -> dict:
    out = copy.deepcopy(doc)
    out["images"] = out["images"][:n]
    return out


@pytest.mark.slow
def test_a_free_room_of_three_images_is_not_trusted_and_says_why():
    """Three images of the small free room: most targets meet two rays, 94 observations,
    a mean redundancy number of 0.21; all ten images: 0.41, trusted."""
    from gtsam_sphere.estimation.calibrate import CalibrationOptions, calibrate
    from gtsam_sphere.io.dataset import parse_dataset

    sim = small_free_room(21)
    weak = calibrate(
        parse_dataset(_first_images(sim.dataset, 3), "room.json"), CalibrationOptions()
    )
    st = weak.statistics
    assert st["datum"] == "free"
    # a free network has no target prior: the equations are the observations'
    assert st["mean_redundancy"] == pytest.approx(st["redundancy"] / (2 * st["n_observations"]))
    assert st["mean_redundancy"] < MIN_MEAN_REDUNDANCY
    assert not st["trusted"]
    assert str(Distrust.LOW_REDUNDANCY) in st["distrust_codes"]
    assert any("barely over-determine" in d for d in st["distrust"])

    full = calibrate(parse_dataset(sim.dataset, "room.json"), CalibrationOptions())
    assert full.statistics["mean_redundancy"] >= MIN_MEAN_REDUNDANCY
    assert full.statistics["trusted"], full.statistics["distrust"]


def test_the_summary_prints_the_mean_beside_the_redundancy(capsys):
    from gtsam_sphere.cli.common import print_statistics

    stats = summary_statistics()
    print_statistics(dict(stats, mean_redundancy=0.2))
    line = next(x for x in capsys.readouterr().out.splitlines() if "redundancy" in x)
    assert line.split()[-2:] == ["48", "(0.20)"]
    print_statistics(stats)  # a file written before the statistic existed
    line = next(x for x in capsys.readouterr().out.splitlines() if "redundancy" in x)
    assert line.split()[-1] == "48"
