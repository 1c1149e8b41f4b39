"""Property-based fuzzing (issue 6): the data contract, the camera model, the command line.

Every broken input must end in a clear error naming the item (``DatasetError`` /
``ValueError``; on the command line exit 2 with one ``error: ...`` line), or in a
documented outcome (an observation outside the image is dropped and counted, an
image with too few points is skipped and reported, ``project`` of the perspective
centre is NaN); never a traceback from inside numpy or GTSAM, never NaN or inf in an
output file. Hypothesis runs derandomized, so CI sees the same cases every time; the
number of cases run is printed at the end of the session (``fuzz: N cases ...``).
``GTSAM_SPHERE_FUZZ_SCALE=10`` multiplies every ``max_examples`` for a longer hunt.

Bugs the fuzzing found outside ``dataset.py`` (camera overflow and the 90 degree rim,
``load_calibration`` on malformed entries, partial statistics, a single free image) are
regression tests at the end of this file, each a minimal reproduction.
"""

from __future__ import annotations

import contextlib
import copy
import io
import json
import math
import os
import time
import warnings
from collections import Counter

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from gtsam_sphere.cli import main
from gtsam_sphere.core.camera import SphereCamera
from gtsam_sphere.io.calibration import Calibration
from gtsam_sphere.io.dataset import (
    MAX_ABS_COORDINATE,
    DatasetError,
    load_checkpoints,
    load_dataset,
    parse_dataset,
    write_json_atomic,
)

SCALE = float(os.environ.get("GTSAM_SPHERE_FUZZ_SCALE", "1"))
CASES: Counter[str] = Counter()


def fuzz(n: int) -> settings:
    """Deterministic, fast Hypothesis settings with ``n`` examples (times SCALE)."""
    return settings(
        max_examples=max(1, int(n * SCALE)),
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=[
            HealthCheck.too_slow,
            HealthCheck.data_too_large,
            HealthCheck.filter_too_much,
        ],
    )


class _FuzzSummary:
    """pytest plugin printing the number of fuzz cases at the end of the session."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()
        self.seconds = 0.0

    def pytest_terminal_summary(self, terminalreporter) -> None:
        total = sum(CASES.values())
        parts = ", ".join(f"{k} {v}" for k, v in sorted(CASES.items()))
        terminalreporter.write_sep(
            "-", f"fuzz: {total} cases ({parts}) in {self.seconds:.1f} s (tests/test_fuzz.py)"
        )


@pytest.fixture(scope="module", autouse=True)
def _count_cases(request):
    summary = _FuzzSummary()
    manager = request.config.pluginmanager
    if not manager.has_plugin("gtsam-sphere-fuzz-summary"):
        manager.register(summary, "gtsam-sphere-fuzz-summary")
    yield
    summary.seconds = time.perf_counter() - summary.t0


# -- strategies ------------------------------------------------------------------------------

WEIRD_NUMBERS = [
    math.nan,
    math.inf,
    -math.inf,
    1e308,
    -1e308,
    5e-324,
    1e13,
    -2e12,
    10**400,
    -(10**30),
    2**63,
    0,
    -1,
    0.0,
    -0.0,
    True,
    False,
]
json_scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**6), 10**6),
    st.floats(allow_nan=False, allow_infinity=False),
    st.sampled_from(WEIRD_NUMBERS),
    st.text(max_size=12),
)
json_values = st.recursive(
    json_scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=6), inner, max_size=4)
    ),
    max_leaves=8,
)
numbers_or_junk = st.one_of(st.sampled_from(WEIRD_NUMBERS), st.floats(), st.integers(), json_values)


def _base_doc() -> dict:
    """A valid dataset@1: 7 targets (some weighted, some free), 3 images in 640 x 480."""
    targets = []
    for k in range(7):
        t = {"id": f"T{k}", "xyz": [0.3 * k, 0.1 * k * k, 2.0 + 0.05 * k]}
        if k % 2 == 0:
            t["sigma"] = 0.01
        targets.append(t)
    images = []
    for i, name in enumerate(["A", "B", "C"]):
        obs = [
            {"target": f"T{k}", "uv": [50.0 + 70 * k + 3 * i, 40.0 + 50 * k - 2 * i]}
            for k in range(7)
            if k != i
        ]
        images.append({"id": name, "observations": obs})
    return {
        "format": "gtsam-sphere/dataset@1",
        "units": "m",
        "camera": {"width": 640, "height": 480},
        "targets": targets,
        "images": images,
    }


def _mutate_dataset(doc: dict, data) -> tuple[str, set[str]]:
    """Apply one random mutation to ``doc`` in place.

    Returns the mutation's name and the substrings one of which an error message must
    contain to name the item concerned.
    """
    kind = data.draw(
        st.sampled_from(
            [
                "top-value",
                "top-delete",
                "camera",
                "target-field",
                "target-replace",
                "target-duplicate",
                "image-field",
                "image-replace",
                "image-duplicate",
                "obs-field",
                "obs-replace",
                "obs-unknown",
                "obs-outside",
                "empty-images",
                "extra-keys",
            ]
        ),
        label="mutation",
    )
    targets, images = doc["targets"], doc["images"]
    if kind == "top-value":
        key = data.draw(st.sampled_from(["format", "units", "camera", "targets", "images"]))
        doc[key] = data.draw(json_values)
        return kind, {key, key.rstrip("s")}
    if kind == "top-delete":
        key = data.draw(st.sampled_from(["format", "units", "camera", "targets", "images"]))
        del doc[key]
        return kind, {key}
    if kind == "camera":
        key = data.draw(st.sampled_from(["width", "height"]))
        if data.draw(st.booleans()):
            del doc["camera"][key]
        else:
            doc["camera"][key] = data.draw(numbers_or_junk)
        return kind, {f"camera.{key}", f"missing {key!r}"}
    if kind.startswith("target"):
        k = data.draw(st.integers(0, len(targets) - 1))
        old = targets[k]["id"]
        tokens = {f"targets[{k}]", repr(old)}
        if kind == "target-duplicate":
            targets.append(copy.deepcopy(targets[k]))
            return kind, tokens
        if kind == "target-replace":
            targets[k] = data.draw(json_values)
            return kind, tokens
        field = data.draw(st.sampled_from(["id", "xyz", "sigma", "xyz-element", "extra"]))
        value = data.draw(
            st.one_of(json_values, st.sampled_from([f"T{j}" for j in range(7)]))
            if field == "id"
            else numbers_or_junk
        )
        if field == "xyz-element":
            targets[k]["xyz"][data.draw(st.integers(0, 2))] = value
        elif field == "extra":
            targets[k]["comment"] = value
        elif data.draw(st.booleans()) and field in targets[k]:
            del targets[k][field]
        else:
            targets[k][field] = value
        if isinstance(value, str):
            tokens.add(repr(value))
        return kind, tokens
    if kind.startswith("image"):
        k = data.draw(st.integers(0, len(images) - 1))
        old = images[k]["id"]
        tokens = {f"images[{k}]", repr(old)}
        if kind == "image-duplicate":
            images.append(copy.deepcopy(images[k]))
        elif kind == "image-replace":
            images[k] = data.draw(json_values)
        else:
            field = data.draw(st.sampled_from(["id", "observations", "extra"]))
            value = data.draw(st.one_of(json_values, st.sampled_from(["A", "B", "C", ""])))
            if field == "extra":
                images[k]["camera"] = value
            elif data.draw(st.booleans()):
                del images[k][field]
            else:
                images[k][field] = value
            if isinstance(value, str):
                tokens.add(repr(value))
        return kind, tokens
    if kind.startswith("obs"):
        k = data.draw(st.integers(0, len(images) - 1))
        obs = images[k]["observations"]
        q = data.draw(st.integers(0, len(obs) - 1))
        tokens = {f"image {images[k]['id']!r}"}
        if kind == "obs-replace":
            obs[q] = data.draw(json_values)
        elif kind == "obs-unknown":
            obs.append({"target": data.draw(st.text(max_size=5)), "uv": [1.0, 2.0]})
        elif kind == "obs-outside":
            obs[q]["uv"] = data.draw(
                st.sampled_from([[-0.51, 10.0], [639.51, 5.0], [3.0, 479.6], [1e9, -1e9]])
            )
        else:
            field = data.draw(st.sampled_from(["target", "uv", "uv-element", "extra"]))
            value = data.draw(
                st.one_of(numbers_or_junk, st.sampled_from([f"T{j}" for j in range(8)]))
            )
            if field == "uv-element":
                obs[q]["uv"][data.draw(st.integers(0, 1))] = value
            elif field == "extra":
                obs[q]["weight"] = value
            elif data.draw(st.booleans()):
                del obs[q][field]
            else:
                obs[q][field] = value
        return kind, tokens
    if kind == "empty-images":
        for im in images:
            im["observations"] = im["observations"][: data.draw(st.integers(0, 3))]
        return kind, {"no usable image"}
    # extra keys anywhere are allowed (the contract may grow)
    doc[data.draw(st.text(min_size=1, max_size=8).filter(lambda s: s not in doc))] = data.draw(
        json_values
    )
    return kind, set()


def _check_dataset(ds, width_height=None) -> None:
    """Invariants of every Dataset the loader returns."""
    T, M, N = len(ds.target_ids), len(ds.image_ids), ds.n_observations
    assert ds.target_xyz.shape == (T, 3) and np.isfinite(ds.target_xyz).all()
    assert np.abs(ds.target_xyz).max() <= MAX_ABS_COORDINATE
    sig = ds.target_sigma
    assert sig.shape == (T,) and np.all(np.isnan(sig) | ((sig >= 0) & np.isfinite(sig)))
    assert len(set(ds.target_ids)) == T and len(set(ds.image_ids)) == M >= 1
    assert ds.uv_px.shape == (N, 2) and np.isfinite(ds.uv_px).all()
    assert np.all(ds.uv_px >= -0.5)
    assert np.all(ds.uv_px <= np.array([ds.width, ds.height]) - 0.5)
    assert ds.obs_image.shape == ds.obs_target.shape == (N,)
    assert np.all((0 <= ds.obs_image) & (ds.obs_image < M))
    assert np.all((0 <= ds.obs_target) & (ds.obs_target < T))
    assert np.all(np.bincount(ds.obs_image, minlength=M) >= 4)
    pairs = set(zip(ds.obs_image.tolist(), ds.obs_target.tolist()))
    assert len(pairs) == N  # a target once per image
    assert ds.n_input_observations >= N + len(ds.dropped)
    if not ds.skipped_images:
        assert ds.n_input_observations == N + len(ds.dropped)
    known = set(ds.image_ids) | {i for i, _ in ds.skipped_images}
    assert {i for i, _, _ in ds.dropped} <= known
    assert not set(ds.image_ids) & {i for i, _ in ds.skipped_images}


def _assert_clear(exc: Exception, source: str, tokens: set[str]) -> None:
    msg = str(exc)
    assert msg.startswith(source), msg
    assert len(msg) < 1000, msg
    if tokens:
        assert any(t in msg for t in tokens | {"no usable image"}), (msg, tokens)


# -- (a) the dataset loader ------------------------------------------------------------------


def test_base_document_is_valid():
    ds = parse_dataset(_base_doc(), "base.json")
    _check_dataset(ds)
    assert ds.n_observations == 18 and not ds.dropped and not ds.skipped_images


@fuzz(400)
@given(data=st.data())
def test_parse_dataset_names_the_broken_item(data):
    doc = _base_doc()
    kind, tokens = _mutate_dataset(doc, data)
    CASES["loader"] += 1
    try:
        ds = parse_dataset(doc, "fuzz.json")
    except DatasetError as exc:
        _assert_clear(exc, "fuzz.json", tokens)
    else:
        _check_dataset(ds)
        if kind == "obs-outside":
            assert len(ds.dropped) == 1 and "outside" in ds.dropped[0][2]


@fuzz(200)
@given(data=st.data())
def test_parse_dataset_survives_several_mutations(data):
    doc = _base_doc()
    for _ in range(data.draw(st.integers(2, 5))):
        try:
            _mutate_dataset(doc, data)
        except (KeyError, TypeError, IndexError, ValueError, AttributeError):
            break  # an earlier mutation removed what this one edits: fine, test what we have
    CASES["loader"] += 1
    try:
        ds = parse_dataset(doc, "fuzz.json")
    except DatasetError as exc:
        _assert_clear(exc, "fuzz.json", set())
    else:
        _check_dataset(ds)


@fuzz(120)
@given(doc=json_values)
def test_parse_dataset_on_any_json(doc):
    CASES["loader"] += 1
    with pytest.raises(DatasetError) as info:
        parse_dataset(doc, "any.json")
    _assert_clear(info.value, "any.json", {"format", "top level"})


_VALID_TEXT = json.dumps(_base_doc(), indent=1)
_SPECIAL_TEXTS = [
    b"",
    b"   \n",
    b"null",
    b"[]",
    b"{}",
    b"NaN",
    b"[" * 50_000 + b"]" * 50_000,  # deeper than the parser's stack
    b'{"format": ' + b"9" * 5000 + b"}",  # past Python's integer digit limit
    b"\xef\xbb\xbf" + _VALID_TEXT.encode(),  # UTF-8 byte-order mark
    _VALID_TEXT.encode("utf-16"),
    b"\xff\xfe\x00garbage",
    _VALID_TEXT.replace("0.01", "NaN").encode(),
    _VALID_TEXT.replace("0.01", "Infinity").encode(),
    _VALID_TEXT.replace('"width": 640', '"width": 1' + "0" * 400).encode(),
    _VALID_TEXT.replace('"width": 640', '"width": 640.0').encode(),
    _VALID_TEXT.replace("dataset@1", "dataset@2").encode(),
    _VALID_TEXT.replace("dataset@1", "checkpoints@1").encode(),
    _VALID_TEXT.replace('"T3"', '"T1"').encode(),
]


@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


@fuzz(200)
@given(
    raw=st.one_of(
        st.sampled_from(_SPECIAL_TEXTS),
        st.builds(
            lambda cut, junk: _VALID_TEXT.encode()[:cut] + junk,
            st.integers(0, len(_VALID_TEXT)),
            st.one_of(st.just(b""), st.binary(max_size=8)),
        ),
        st.binary(max_size=64),
    )
)
def test_load_dataset_truncated_or_garbled_files(raw, fuzz_dir):
    path = fuzz_dir / "garbled.json"
    path.write_bytes(raw)
    CASES["loader"] += 1
    try:
        ds = load_dataset(path)
    except DatasetError as exc:
        _assert_clear(exc, str(path), set())
    else:
        _check_dataset(ds)
        assert raw.strip().startswith((b"{", b"\xef\xbb\xbf{"))  # only whole documents load


def test_load_dataset_missing_file_and_directory(tmp_path):
    with pytest.raises(DatasetError, match="no such file"):
        load_dataset(tmp_path / "absent.json")
    with pytest.raises(DatasetError, match="is a directory"):
        load_dataset(tmp_path)
    with pytest.raises(DatasetError, match="checkpoints: no such file"):
        load_checkpoints(tmp_path / "checkpoints")
    (tmp_path / "checkpoints").mkdir()
    with pytest.raises(DatasetError, match="is a directory"):
        load_checkpoints(tmp_path / "checkpoints")


def _base_checkpoints() -> dict:
    return {
        "format": "gtsam-sphere/checkpoints@1",
        "units": "m",
        "targets": [{"id": f"T{k}", "xyz": [0.3 * k, 0.1 * k * k, 2.0]} for k in range(5)],
    }


def _mutate_checkpoints(doc: dict, data) -> set[str]:
    kind = data.draw(st.sampled_from(["top", "delete", "field", "replace", "duplicate"]))
    targets = doc["targets"]
    if kind in ("top", "delete"):
        key = data.draw(st.sampled_from(["format", "units", "targets"]))
        if kind == "delete":
            del doc[key]
        else:
            doc[key] = data.draw(json_values)
        return {key}
    k = data.draw(st.integers(0, len(targets) - 1))
    tokens = {f"targets[{k}]", repr(targets[k]["id"])}
    if kind == "replace":
        targets[k] = data.draw(json_values)
    elif kind == "duplicate":
        targets.append(copy.deepcopy(targets[k]))
    else:
        field = data.draw(st.sampled_from(["id", "xyz", "xyz-element"]))
        value = data.draw(numbers_or_junk)
        if field == "xyz-element":
            targets[k]["xyz"][data.draw(st.integers(0, 2))] = value
        else:
            targets[k][field] = value
        if isinstance(value, str):
            tokens.add(repr(value))
    return tokens


@fuzz(200)
@given(data=st.data())
def test_load_checkpoints_names_the_broken_item(data, fuzz_dir):
    doc = _base_checkpoints()
    tokens = _mutate_checkpoints(doc, data)
    path = fuzz_dir / "checkpoints.json"
    path.write_text(json.dumps(doc))
    CASES["loader"] += 1
    try:
        ids, xyz, units = load_checkpoints(path)
    except DatasetError as exc:
        _assert_clear(exc, str(path), tokens)
    else:
        assert isinstance(units, str) and len(set(ids)) == len(ids) > 0
        assert all(isinstance(i, str) and i for i in ids)
        assert xyz.shape == (len(ids), 3) and np.isfinite(xyz).all()


# -- (b) the camera model --------------------------------------------------------------------

SPECIAL_ALPHA_DEG = [0.0, 1e-9, 1e-3, 30.0, 89.9999, 90.0, 90.0001, 135.0, 179.9999, 180.0]


@st.composite
def directions(draw, n_max: int = 12) -> np.ndarray:
    """Unit vectors (N, 3): the axis, 90 degrees, behind the camera, and anything between."""
    n = draw(st.integers(1, n_max))
    alpha = draw(
        st.lists(
            st.one_of(st.sampled_from(SPECIAL_ALPHA_DEG), st.floats(0.0, 180.0)),
            min_size=n,
            max_size=n,
        )
    )
    azim = draw(
        st.lists(
            st.one_of(st.sampled_from([0.0, 90.0, 180.0, 270.0, 45.0]), st.floats(0.0, 360.0)),
            min_size=n,
            max_size=n,
        )
    )
    a, p = np.radians(alpha), np.radians(azim)
    return np.column_stack([np.sin(a) * np.cos(p), np.sin(a) * np.sin(p), np.cos(a)])


@st.composite
def cameras(draw, brown: bool = False) -> SphereCamera:
    """Random intrinsics: any image size, principal point in the image, c from 10 to 1e4 px."""
    width = draw(st.integers(2, 20_000))
    height = draw(st.integers(2, 20_000))
    xp = draw(st.floats(-0.5, width - 0.5))
    yp = draw(st.floats(-0.5, height - 0.5))
    if not brown:
        c = 10 ** draw(st.floats(1.0, 4.0))
        return SphereCamera(width, height, xp, yp, c)
    scale = 0.5 * max(width, height)
    c = scale * draw(st.floats(0.2, 1.0))
    terms = {
        "k1": draw(st.floats(-0.05, 0.05)),
        "k2": draw(st.floats(-0.01, 0.01)),
        "k3": draw(st.floats(-0.005, 0.005)),
        "p1": draw(st.floats(-0.005, 0.005)),
        "p2": draw(st.floats(-0.005, 0.005)),
        "a1": draw(st.floats(-0.005, 0.005)),
        "a2": draw(st.floats(-0.005, 0.005)),
    }
    subset = draw(st.lists(st.sampled_from(sorted(terms)), min_size=1, unique=True))
    return SphereCamera(width, height, xp, yp, c, brown={k: terms[k] for k in subset})


def _no_warnings():
    """A context in which any warning (numpy's overflow, invalid value, ...) is an error."""
    ctx = warnings.catch_warnings()
    ctx.__enter__()
    warnings.simplefilter("error")
    return ctx


@fuzz(250)
@given(cam=cameras(), dirs=directions(), log_range=st.floats(-100.0, 100.0))
def test_sphere_project_and_unproject_in_every_direction(cam, dirs, log_range):
    """Round trip over the whole sphere, at any distance from 1e-100 to 1e100 units."""
    CASES["camera"] += 1
    points = dirs * 10.0**log_range
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        uv = cam.project(points)
        assert uv.shape == (len(points), 2) and np.isfinite(uv).all()
        ideal = uv - cam.principal_point_px
        np.testing.assert_allclose(ideal, cam.c * dirs[:, :2], rtol=0, atol=1e-9 * cam.c)
        assert np.all(np.hypot(ideal[:, 0], ideal[:, 1]) <= cam.c * (1 + 1e-12))
        hemisphere = np.where(dirs[:, 2] < 0, -1.0, 1.0)
        rays = cam.unproject(uv, hemisphere=hemisphere)
    assert rays.shape == (len(points), 3)
    # away from the rim (|cos(alpha)| > 1e-6); at the rim see the regression test below
    off_rim = np.abs(dirs[:, 2]) > 1e-6
    assert np.isfinite(rays[off_rim]).all()
    np.testing.assert_allclose(np.linalg.norm(rays[off_rim], axis=1), 1.0, atol=1e-9)
    # pixels carry ~1e-16 * (|pp| + c) of rounding; z = sqrt(1 - rho^2) amplifies it by 1/|z|
    lever = (1.0 + max(abs(cam.xp), abs(cam.yp)) / cam.c) / np.maximum(np.abs(dirs[:, 2]), 1e-6)
    err = np.linalg.norm(rays - dirs, axis=1)
    assert np.all(err[off_rim] <= 1e-9 * lever[off_rim]), err[off_rim].max()


@fuzz(150)
@given(cam=cameras(), dirs=directions(), bad=st.lists(st.sampled_from(["zero", "nan", "inf"])))
def test_project_of_the_centre_or_nan_is_nan_and_spares_the_other_rows(cam, dirs, bad):
    CASES["camera"] += 1
    rows = {"zero": [0.0, 0.0, 0.0], "nan": [math.nan, 1.0, 2.0], "inf": [1.0, math.inf, 1.0]}
    points = np.vstack([dirs] + [np.array([rows[b]]) for b in bad])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        uv = cam.project(points)
        rays = cam.unproject(np.vstack([uv, [[math.nan, 0.0]]]))
    n = len(dirs)
    assert np.isfinite(uv[:n]).all()
    # documented: NaN for the perspective centre; NaN (or inf) in gives no finite pixel or
    # ray out, and no exception. (Whole rows of NaN: see the regression test below.)
    assert np.isnan(uv[n:]).any(axis=1).all()
    assert np.isnan(rays[n:]).any(axis=1).all()


@fuzz(120)
@given(cam=cameras(brown=True), dirs=directions(), scale=st.floats(0.5, 50.0))
def test_brown_project_inverts_the_correction(cam, dirs, scale):
    """``project`` solves uv - pp - brown(uv - pp) = ideal: check it at the returned pixel."""
    front = dirs[dirs[:, 2] > math.cos(math.radians(80.0))]
    assume(len(front))
    CASES["camera"] += 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        uv = cam.project(front * scale)
        ideal = cam.ideal_from_pixels(uv)
    np.testing.assert_allclose(ideal, cam.c * front[:, :2], rtol=0, atol=1e-6)
    rays = cam.unproject(uv)
    np.testing.assert_allclose(rays, front, rtol=0, atol=1e-6)


@fuzz(150)
@given(
    cam=cameras(),
    uv=st.lists(
        st.tuples(
            st.one_of(st.floats(-1e6, 1e6), st.sampled_from([math.nan, math.inf, -1e300])),
            st.one_of(st.floats(-1e6, 1e6), st.sampled_from([math.nan, -math.inf, 1e300])),
        ),
        min_size=1,
        max_size=10,
    ),
    hemisphere=st.sampled_from([1.0, -1.0]),
)
def test_unproject_any_pixel_is_a_unit_ray_or_nan(cam, uv, hemisphere):
    CASES["camera"] += 1
    uv = np.array(uv, float)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rays = cam.unproject(uv, hemisphere=hemisphere)
    if np.all(np.abs(uv[np.isfinite(uv)]) < 1e150):
        assert not caught, [str(w.message) for w in caught]  # past 1e150: numpy's overflow
    with np.errstate(all="ignore"):
        rho2 = np.sum(((uv - cam.principal_point_px) / cam.c) ** 2, axis=1)
    rim = (rho2 > 1.0 - 1e-9) & (rho2 <= 1.0 + 1e-12)  # the rim: regression test below
    has_nan = np.isnan(rays).any(axis=1)
    finite = np.isfinite(rays).all(axis=1)
    unit = finite & (
        np.abs(np.linalg.norm(np.where(finite[:, None], rays, 0.0), axis=1) - 1) < 1e-9
    )
    assert np.all((has_nan | unit)[~rim])
    outside = ~np.isfinite(rho2) | (rho2 > 1 + 1e-12)
    assert np.all(has_nan[outside])  # no ray for a pixel off the disc or not a number
    assert np.all(np.isnan(rays[np.isfinite(rho2) & (rho2 > 1 + 1e-12)]))  # whole rows
    assert np.all(unit[~rim & (rho2 <= 1.0)])
    assert np.all(np.sign(rays[unit & ~rim & (rho2 < 1 - 1e-9), 2]) == hemisphere)


@fuzz(60)
@given(
    shape=st.sampled_from([(3,), (2,), (4,), (0,), (2, 2), (2, 4), (1, 2, 3), ()]),
    fill=st.floats(-10, 10),
)
def test_wrong_shapes_raise_value_error_naming_the_shape(shape, fill):
    CASES["camera"] += 1
    cam = SphereCamera(100, 100, 49.5, 49.5, 50.0)
    arr = np.full(shape, fill)
    for call, good in ((cam.project, (3,)), (cam.unproject, (2,))):
        if shape == good or (len(shape) == 2 and shape[1] == good[0]):
            continue
        with pytest.raises(ValueError, match=r"shape \(N, \d\)"):
            call(arr)


@fuzz(150)
@given(
    dirs=directions(),
    g=st.lists(st.floats(-0.08, 0.08), min_size=0, max_size=4),
    c=st.floats(50.0, 3000.0),
)
def test_radial_mapping_round_trip(dirs, g, c):
    names = ("g3", "g5", "g7", "g9")
    cam = SphereCamera(4000, 3000, 1999.5, 1499.5, c, radial=dict(zip(names, g)))
    a_max = cam.max_alpha_rad()
    alpha = np.arccos(np.clip(dirs[:, 2], -1, 1))
    inside = alpha < 0.98 * a_max
    assume(inside.any())
    CASES["camera"] += 1
    front = dirs[inside]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        uv = cam.project(front)
        rays = cam.unproject(uv)
    assert np.isfinite(uv).all()
    np.testing.assert_allclose(rays, front, rtol=0, atol=1e-7)


# -- (c) the command line --------------------------------------------------------------------


FAST = ["--model", "sphere", "--max-iterations", "10"]  # the cheapest calibration


def _run_cli(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(argv)
    return rc, out.getvalue(), err.getvalue()


def _assert_one_line_error(rc: int, stderr: str, *names: str) -> str:
    assert rc == 2, stderr
    assert "Traceback" not in stderr
    lines = stderr.strip().splitlines()
    errors = [line for line in lines if line.startswith("error: ")]
    assert len(errors) == 1 and lines[-1] == errors[0], stderr
    others = [line for line in lines[:-1] if not line.startswith("warning: ")]
    assert not others, stderr
    if names:
        assert any(n in errors[0] for n in names), (errors[0], names)
    return errors[0]


def _assert_no_nan_file(path) -> None:
    """An output file, if any, holds only finite numbers."""
    if path.exists():

        def refuse(name):
            raise AssertionError(f"{path} holds {name}")

        json.loads(path.read_text(), parse_constant=refuse)


@fuzz(120)
@given(data=st.data())
def test_cli_calibrate_refuses_broken_datasets(data, fuzz_dir):
    path = fuzz_dir / "broken dataset.json"
    out = fuzz_dir / "calib.json"
    if out.exists():
        out.unlink()
    if data.draw(st.booleans(), label="raw bytes"):
        raw = data.draw(
            st.one_of(
                st.sampled_from(_SPECIAL_TEXTS),
                st.integers(0, len(_VALID_TEXT) - 2).map(lambda k: _VALID_TEXT.encode()[:k]),
            )
        )
        path.write_bytes(raw)
    else:
        doc = _base_doc()
        _mutate_dataset(doc, data)
        path.write_text(json.dumps(doc))
    try:
        load_dataset(path)
        assume(False)  # still a valid dataset: calibrating it is not this test's business
    except DatasetError:
        pass
    CASES["cli"] += 1
    rc, _, err = _run_cli(["calibrate", str(path), "-o", str(out), "--quiet", *FAST])
    _assert_one_line_error(rc, err, str(path))
    assert not out.exists()


def _calibration_doc() -> dict:
    """A small valid calibration@1 document (5 targets, 2 images), built without adjusting."""
    cam = SphereCamera(640, 480, 319.5, 239.5, 300.0)
    calib = Calibration(
        model="sphere",
        camera=cam,
        image_ids=["A", "B"],
        cam_from_world_R=np.stack([np.eye(3)] * 2),
        cam_from_world_t=np.zeros((2, 3)),
        target_ids=[f"T{k}" for k in range(5)],
        target_xyz=np.array([[0.3 * k, 0.1 * k * k, 2.0] for k in range(5)]),
        statistics={
            "rms_px": 0.3,
            "rms_px_without_outliers": 0.3,
            "n_observations": 10,
            "n_rejected": 0,
            "n_images": 2,
            "n_images_skipped": 0,
            "n_downweighted": 0,
            "n_outliers": 0,
            "sigma_px": 0.3,
            "weighted_sum_squares": 10.0,
            "redundancy": 5,
            "variance_factor": 1.0,
            "max_incidence_deg": 40.0,
            "status": "converged",
            "iterations": 3,
            "converged": True,
        },
    )
    return json.loads(json.dumps(calib.to_dict(), default=np.ndarray.tolist))


@pytest.fixture(scope="module")
def calibration_file(fuzz_dir):
    path = write_json_atomic(fuzz_dir / "good calib.json", _calibration_doc())
    checkpoints = write_json_atomic(fuzz_dir / "good checkpoints.json", _base_checkpoints())
    rc, out, err = _run_cli(["evaluate", str(path), str(checkpoints)])
    assert rc == 0, err
    return path


@fuzz(120)
@given(data=st.data())
def test_cli_evaluate_refuses_broken_files(data, fuzz_dir, calibration_file):
    calib_path, cp_path = calibration_file, fuzz_dir / "broken checkpoints.json"
    which = data.draw(st.sampled_from(["checkpoints", "unknown ids", "calibration"]))
    cp = _base_checkpoints()
    if which == "checkpoints":
        _mutate_checkpoints(cp, data)
    elif which == "unknown ids":
        keep = data.draw(st.integers(0, 2))  # fewer than 3 among the adjusted targets
        for t in cp["targets"][keep:]:
            t["id"] = "X" + t["id"]
    cp_path.write_text(json.dumps(cp))
    if which == "calibration":
        calib_path = fuzz_dir / "broken calib.json"
        text = json.dumps(_calibration_doc())
        how = data.draw(st.sampled_from(["truncate", "format", "camera-field", "camera"]))
        doc = json.loads(text)
        if how == "truncate":
            calib_path.write_text(text[: data.draw(st.integers(0, len(text) - 2))])
        else:
            if how == "format":
                doc["format"] = data.draw(
                    st.one_of(st.sampled_from(["gtsam-sphere/calibration@7", ""]), json_values)
                )
            elif how == "camera":
                doc["camera"] = data.draw(
                    st.one_of(st.sampled_from([{}, [], None, "sphere"]), st.just({"xp_px": 1}))
                )
            else:
                key = data.draw(st.sampled_from(["width", "height", "xp_px", "yp_px", "c_px"]))
                value = data.draw(st.one_of(st.none(), st.text(max_size=5), st.just([1, 2])))
                doc["camera"][key] = value
            calib_path.write_text(json.dumps(doc))
    else:
        try:
            ids, _, _ = load_checkpoints(cp_path)
            assume(which == "unknown ids" or sum(i.startswith("T") for i in ids) < 3)
        except DatasetError:
            pass
    CASES["cli"] += 1
    rc, _, err = _run_cli(["evaluate", str(calib_path), str(cp_path)])
    _assert_one_line_error(rc, err)


def _small_room_doc(n_images: int = 3, seed: int = 3, **overrides) -> dict:
    from gtsam_sphere.simulate import SimulationOptions, simulate_room

    opts = dict(
        lens="sphere",
        fov_deg=200,
        noise_px=0.3,
        n_images=n_images,
        n_targets=40,
        n_checkpoints=5,
        width=800,
        height=600,
        seed=seed,
    )
    return simulate_room(SimulationOptions(**{**opts, **overrides})).dataset


def _degenerate(kind: str) -> dict:
    doc = _small_room_doc()
    if kind == "coincident targets":
        for t in doc["targets"]:
            t["xyz"] = [1.0, 2.0, 3.0]
    elif kind == "one image with 4 points":
        doc["images"] = [dict(doc["images"][0], observations=doc["images"][0]["observations"][:4])]
    elif kind == "one weighted target":
        for t in doc["targets"][1:]:
            del t["sigma"]
    elif kind == "every observation outside":
        for im in doc["images"]:
            for o in im["observations"]:
                o["uv"] = [-5.0, o["uv"][1]]
    elif kind == "huge coordinates":
        for t in doc["targets"]:
            t["xyz"] = [v * 1e200 for v in t["xyz"]]
    return doc


@pytest.mark.parametrize(
    "kind",
    [
        "coincident targets",
        "one image with 4 points",
        "one weighted target",
        "every observation outside",
        "huge coordinates",
    ],
)
@pytest.mark.slow  # end-to-end
def test_cli_calibrate_degenerate_but_well_formed_datasets(kind, tmp_path):
    path = write_json_atomic(tmp_path / "dataset.json", _degenerate(kind))
    out = tmp_path / "calib.json"
    CASES["cli"] += 1
    rc, _, err = _run_cli(["calibrate", str(path), "-o", str(out), "--quiet", *FAST])
    _assert_one_line_error(rc, err)
    assert not out.exists()


def test_output_that_cannot_be_written_names_the_destination(tmp_path):
    with pytest.raises(IsADirectoryError) as info:
        write_json_atomic(tmp_path, {"a": 1})
    assert info.value.filename == str(tmp_path)  # not the temporary file
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OSError) as info:
        write_json_atomic(blocker / "out.json", {"a": 1})  # parent is a file
    assert info.value.filename == str(blocker / "out.json")
    with pytest.raises(ValueError, match=r"NaN or inf .*at statistics\.rms\[1\]"):
        write_json_atomic(tmp_path / "nan.json", {"statistics": {"rms": [1.0, math.nan]}})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]
    # on the command line: exit 2, one line naming the path
    CASES["cli"] += 1
    argv = ["simulate", "--n-images", "2", "--n-targets", "60", "--width", "400", "--height", "300"]
    rc, _, err = _run_cli([*argv, "-o", str(blocker)])
    _assert_one_line_error(rc, err, str(blocker))


# -- bugs found outside dataset.py (not fixed here): minimal reproductions -------------------


def test_bug_project_of_a_huge_point():
    cam = SphereCamera(800, 600, 399.5, 299.5, 300.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # today: RuntimeWarning overflow, then uv == pp
        uv = cam.project(np.array([[1e300, 0.0, 1e300]]))
    np.testing.assert_allclose(uv, [[399.5 + 300 / math.sqrt(2), 299.5]])


def test_bug_project_of_a_tiny_point():
    cam = SphereCamera(800, 600, 399.5, 299.5, 300.0)
    uv = cam.project(np.array([[1e-200, 0.0, 1e-200]]))  # today: [[inf, nan]]
    np.testing.assert_allclose(uv, [[399.5 + 300 / math.sqrt(2), 299.5]])


def test_bug_unproject_at_90_degrees():
    cam = SphereCamera(800, 600, 399.5, 299.5, 300.0)
    p = np.array([[0.8714765864585173, 0.4904371130236428, 0.0]])  # 90 deg incidence
    rays = cam.unproject(cam.project(p))  # today: [[0.871, 0.490, nan]]
    np.testing.assert_allclose(rays, p, atol=1e-7)


def test_bug_unproject_of_a_nan_pixel():
    cam = SphereCamera(800, 600, 399.5, 299.5, 300.0)
    rays = cam.unproject(np.array([[math.nan, 299.5]]))  # today: [[nan, 0.0, nan]]
    assert np.isnan(rays).all()


@pytest.mark.parametrize("c", [0.0, -300.0, math.nan])
def test_bug_camera_accepts_a_non_positive_principal_distance(c):
    with pytest.raises(ValueError, match="c"):
        SphereCamera(800, 600, 399.5, 299.5, c)


@pytest.mark.parametrize(
    "breakage",
    [
        "images is a number",
        "image without id",
        "image without pose",
        "R of the wrong shape",
        "target without xyz",
        "target xyz NaN",
        "brown is a list",
        "knn correction incomplete",
        "c_px NaN",
    ],
)
def test_bug_load_calibration_on_malformed_entries(breakage, fuzz_dir, calibration_file):
    doc = _calibration_doc()
    if breakage == "images is a number":
        doc["images"] = 5  # TypeError: 'int' object is not iterable
    elif breakage == "image without id":
        del doc["images"][0]["id"]  # KeyError: 'id'
    elif breakage == "image without pose":
        del doc["images"][0]["cam_from_world"]  # KeyError: 'cam_from_world'
    elif breakage == "R of the wrong shape":
        doc["images"][0]["cam_from_world"]["R"] = [1, 2]  # numpy: inhomogeneous shape
    elif breakage == "target without xyz":
        del doc["targets"][0]["xyz"]  # KeyError: 'xyz'
    elif breakage == "target xyz NaN":
        doc["targets"][0]["xyz"] = [math.nan, 0.0, 0.0]  # accepted; evaluate: "src contains NaN"
    elif breakage == "brown is a list":
        doc["camera"]["brown"] = [1]  # AttributeError: 'list' object has no attribute 'items'
    elif breakage == "knn correction incomplete":
        doc["camera"]["correction"] = {"kind": "knn"}  # KeyError: 'n_neighbors'
    elif breakage == "c_px NaN":
        doc["camera"]["c_px"] = math.nan  # accepted silently
    path = fuzz_dir / "malformed calib.json"
    path.write_text(json.dumps(doc))
    CASES["cli"] += 1
    rc, _, err = _run_cli(["evaluate", str(path), str(fuzz_dir / "good checkpoints.json")])
    _assert_one_line_error(rc, err, str(path))


def test_bug_evaluate_with_partial_statistics(fuzz_dir, calibration_file):
    doc = _calibration_doc()
    del doc["statistics"]["rms_px"]  # a calibration file from another tool, or hand-edited
    path = write_json_atomic(fuzz_dir / "partial stats.json", doc)
    CASES["cli"] += 1
    rc, _, err = _run_cli(["evaluate", str(path), str(fuzz_dir / "good checkpoints.json")])
    _assert_one_line_error(rc, err)


def test_bug_single_image_of_free_targets_is_refused(tmp_path):
    doc = _small_room_doc(n_images=1, sigma_mode="free")
    path = write_json_atomic(tmp_path / "one.json", doc)
    out = tmp_path / "calib.json"
    CASES["cli"] += 1
    rc, _, err = _run_cli(["calibrate", str(path), "-o", str(out), "--quiet", *FAST])
    _assert_no_nan_file(out)
    _assert_one_line_error(rc, err, "single-image")
