"""The data contract: validation errors name the item, outputs are atomic."""

import copy
import json
import os

import numpy as np
import pytest
from helpers import dataset_doc

from gtsam_sphere.io.dataset import (
    DatasetError,
    load_checkpoints,
    load_dataset,
    parse_dataset,
    write_json_atomic,
)


def _doc():
    targets = [{"id": f"T{k}", "xyz": [float(k), 0.5 * k, 2.0], "sigma": 0.01} for k in range(6)]
    obs = [{"target": f"T{k}", "uv": [100.0 + 10 * k, 200.0]} for k in range(6)]
    return dataset_doc(
        targets,
        [
            {"id": "A", "observations": obs},
            {"id": "B", "observations": [dict(o) for o in obs[:5]]},
        ],
    )


def test_valid_dataset_round_trip(tmp_path):
    path = write_json_atomic(tmp_path / "d.json", _doc())
    ds = load_dataset(path)
    assert ds.image_ids == ["A", "B"]
    assert ds.n_observations == 11
    assert ds.n_input_observations == 11
    np.testing.assert_array_equal(ds.target_sigma, 0.01)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d.update(format="gtsam-sphere/dataset@2"), "unsupported version"),
        (lambda d: d.update(format="something"), "'format' is 'something'"),
        (lambda d: d["targets"].append(dict(d["targets"][0])), "duplicate target id 'T0'"),
        (lambda d: d["images"].append(dict(d["images"][0])), "duplicate image id 'A'"),
        (
            lambda d: d["images"][0]["observations"].append({"target": "nope", "uv": [1, 2]}),
            "unknown target id 'nope'",
        ),
        (lambda d: d["targets"][2].update(xyz=[0.0, float("nan"), 1.0]), "target 'T2'"),
        (
            lambda d: d["images"][1]["observations"][0].update(uv=[1.0, float("inf")]),
            "image 'B' observation 0",
        ),
        (lambda d: d["targets"][1].update(sigma=-1), "sigma must be >= 0"),
        (lambda d: d["camera"].update(width=0), "camera.width"),
        (
            lambda d: d["images"][0]["observations"].append(
                dict(d["images"][0]["observations"][0])
            ),
            "observed twice",
        ),
        (lambda d: d["targets"][0].update(xyz=[1, 2]), "expected a list of 3 numbers"),
    ],
)
def test_bad_input_names_the_item(mutate, message):
    doc = copy.deepcopy(_doc())
    mutate(doc)
    with pytest.raises(DatasetError, match=message):
        parse_dataset(doc, "d.json")


def test_image_with_too_few_observations_is_skipped_and_reported():
    doc = _doc()
    doc["images"].append({"id": "C", "observations": doc["images"][0]["observations"][:2]})
    ds = parse_dataset(doc, min_observations_per_image=4)
    assert ds.image_ids == ["A", "B"]
    assert ds.skipped_images == [("C", "only 2 usable observations (< 4)")]
    assert ds.n_input_observations == 13


def test_observation_outside_image_is_dropped_and_counted():
    doc = _doc()
    doc["images"][0]["observations"][0]["uv"] = [700.0, 10.0]
    ds = parse_dataset(doc)
    assert ds.n_observations == 10
    assert ds.dropped[0][:2] == ("A", "T0")


def test_truncated_file(tmp_path):
    path = tmp_path / "t.json"
    path.write_text(json.dumps(_doc())[:100])
    with pytest.raises(DatasetError, match="not valid JSON"):
        load_dataset(path)


def test_checkpoints(tmp_path):
    path = write_json_atomic(
        tmp_path / "c.json",
        {
            "format": "gtsam-sphere/checkpoints@1",
            "units": "m",
            "targets": [{"id": "T1", "xyz": [1, 2, 3]}],
        },
    )
    ids, xyz, units = load_checkpoints(path)
    assert ids == ["T1"] and xyz.shape == (1, 3) and units == "m"


def test_atomic_write_refuses_nan_and_keeps_old_file(tmp_path):
    path = write_json_atomic(tmp_path / "o.json", {"a": 1})
    with pytest.raises(ValueError, match="NaN"):
        write_json_atomic(path, {"a": float("nan")})
    assert json.loads(path.read_text()) == {"a": 1}
    assert os.listdir(tmp_path) == ["o.json"]


def test_subset_observations_records_what_it_leaves_out():
    ds = parse_dataset(_doc())
    keep = np.ones(ds.n_observations, bool)
    keep[[0, 7]] = False  # A's T0, B's T1
    out = ds.subset_observations(keep, "why")
    assert out.n_observations == ds.n_observations - 2
    assert out.image_ids == ds.image_ids  # images stay
    assert out.dropped == [("A", "T0", "why"), ("B", "T1", "why")]
    assert np.array_equal(out.uv_px, ds.uv_px[keep])
    assert ds.dropped == []  # the input is unchanged
    with pytest.raises(ValueError, match=r"shape \(11,\), got \(3,\)"):
        ds.subset_observations(np.ones(3, bool), "why")
