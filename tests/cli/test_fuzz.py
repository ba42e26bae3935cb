"""Property-based fuzzing of the input boundaries: "a clean GpoccError or a valid result".

CARMEN logs, YAML configs and model files come from outside; whatever they hold, the
readers must either raise :class:`GpoccError` (which the CLI prints as one line) or
return data the next stage can trust. Example counts are kept small so the suite stays
fast; ``derandomize`` makes every run explore the same examples.
"""

from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from fuzzing import fuzz_settings
from hypothesis import given
from hypothesis import strategies as st

from gpocc.config import (
    Config,
    ModelConfig,
    SensorConfig,
    TrainingConfig,
    config_from_dict,
    config_to_dict,
    load_config,
)
from gpocc.errors import GpoccError
from gpocc.gp.model import build_model, load_model, save_model
from gpocc.io.carmen import read_carmen
from gpocc.samples.beams import build_samples
from gpocc.samples.sampleset import SampleSet

_SENSOR = SensorConfig(name="fuzz")
FUZZ = fuzz_settings(40)

# ------------------------------------------------------------------ CARMEN logs

_numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(-100, 100),
    st.integers(-5, 400),
    st.sampled_from([0, 81.9, 1e6, 1e20, -1e20]),
)
_tokens = st.one_of(_numbers.map(str), st.text("0123456789.-eEnaif x", max_size=6))


@st.composite
def _flaser(draw) -> str:
    n = draw(st.integers(0, 12))
    count = draw(st.one_of(st.just(str(n)), _tokens))
    ranges = [str(draw(st.one_of(st.floats(0, 90), _numbers))) for _ in range(n)]
    tail = [str(draw(st.one_of(st.floats(-50, 50), _numbers))) for _ in range(6)]
    stamp = str(draw(st.one_of(st.floats(0, 1e4), _numbers)))
    tokens = ["FLASER", count, *ranges, *tail, stamp, "host", stamp]
    if draw(st.booleans()):  # sometimes drop or add a token
        i = draw(st.integers(0, len(tokens) - 1))
        tokens.insert(i, draw(_tokens)) if draw(st.booleans()) else tokens.pop(i)
    return " ".join(tokens)


_carmen_line = st.one_of(
    _flaser(),
    st.builds(lambda t: "ODOM " + " ".join(t), st.lists(_tokens, max_size=9)),
    st.sampled_from(["", "# comment", "PARAM robot_laser_max_range 50", "NEFF 3"]),
    st.text(max_size=30),
)


@FUZZ
@given(lines=st.lists(_carmen_line, min_size=1, max_size=12))
def test_carmen_reader_gives_a_clean_error_or_usable_scans(lines):
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "fuzz.log"
        path.write_bytes("\n".join(lines).encode("utf-8", "surrogatepass"))
        try:
            batch = read_carmen(path, _SENSOR)
        except GpoccError as exc:
            assert str(path) in str(exc)
            return
    s, b = batch.ranges.shape
    assert batch.stamps.shape == (s,) and batch.angles.shape == (b,)
    assert batch.poses.shape == (s, 3) and np.isfinite(batch.poses).all()
    assert np.isfinite(batch.angles).all() and np.isfinite(batch.stamps).all()
    assert batch.range_min < batch.range_max
    try:
        samples = build_samples([batch], Config())
    except GpoccError:
        return
    assert np.isfinite(samples.means).all() and np.isfinite(samples.covariances).all()
    assert set(np.unique(samples.labels)) <= {-1.0, 1.0}


# ------------------------------------------------------------------ configs

_leaf = st.one_of(
    st.none(), st.booleans(), st.integers(-3, 2**40), st.floats(allow_nan=True),
    st.text(max_size=8), st.lists(st.floats(-1, 1), max_size=4),
    st.lists(st.lists(st.floats(-1, 1), min_size=3, max_size=3), min_size=3, max_size=3),
)
_KEYS = {
    "": ["seed", "sensors", "samples", "model", "classify", "map", "grid", "bogus"],
    "model": ["kernel", "quadrature_level", "neighbours", "block_size_m", "hyperparameters"],
    "map": ["resolution_m", "margin_m", "epsg", "tile_pixels", "max_cells"],
    "classify": ["occupied", "free", "max_variance_ratio"],
    "samples": ["free_spacing_m", "thin_cell_m", "beam_stride", "unscented"],
}


@st.composite
def _config_document(draw) -> object:
    doc: dict = {}
    for key in draw(st.lists(st.sampled_from(_KEYS[""]), max_size=4, unique=True)):
        if key in _KEYS and draw(st.booleans()):
            doc[key] = {k: draw(_leaf) for k in
                        draw(st.lists(st.sampled_from(_KEYS[key]), max_size=3, unique=True))}
        elif key == "sensors" and draw(st.booleans()):
            doc[key] = [{"name": draw(st.text(max_size=4)), "pose_covariance": draw(_leaf),
                         "range_max_m": draw(_leaf)}]
        else:
            doc[key] = draw(_leaf)
    if draw(st.integers(0, 9)) == 0:  # keys YAML allows that are not strings
        doc[draw(st.one_of(st.none(), st.integers(), st.booleans()))] = draw(_leaf)
    return doc if draw(st.integers(0, 9)) else draw(_leaf)


@FUZZ
@given(doc=_config_document(), raw=st.one_of(st.none(), st.binary(max_size=64)))
def test_config_loader_gives_a_clean_error_or_a_valid_config(doc, raw):
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "job.yaml"
        path.write_bytes(raw if raw is not None else yaml.safe_dump(doc).encode())
        try:
            config = load_config(path)
        except GpoccError as exc:
            assert str(path) in str(exc)
            return
    assert isinstance(config, Config)
    assert 0 <= config.seed < 2**32
    for value in _numbers_in(config_to_dict(config)):
        assert math.isfinite(value)
    assert config_from_dict(config_to_dict(config)) == config  # a valid config round-trips


def _numbers_in(data) -> list[float]:
    if isinstance(data, dict):
        return [v for x in data.values() for v in _numbers_in(x)]
    if isinstance(data, list):
        return [v for x in data for v in _numbers_in(x)]
    if isinstance(data, (int, float)) and not isinstance(data, bool):
        return [data]
    return []


# ------------------------------------------------------------------ model files


@pytest.fixture(scope="module")
def good_model(tmp_path_factory) -> tuple[dict, dict]:
    rng = np.random.default_rng(3)
    n = 60
    means = rng.uniform(-2, 2, (n, 2))
    samples = SampleSet(means, np.einsum("n,ij->nij", np.full(n, 1e-3), np.eye(2)),
                        np.where(np.abs(means[:, 0]) > 1.5, 1.0, -1.0),
                        np.arange(n, dtype=np.int64), np.zeros((n, 2, 3)),
                        np.zeros(n, dtype=np.int16))
    path = tmp_path_factory.mktemp("fuzzmodel") / "good.npz"
    save_model(build_model(samples, Config(model=ModelConfig(
        neighbours=30, training=TrainingConfig(learn=False, patches=1, patch_size=20)))), path)
    with np.load(path) as data:
        arrays = dict(data)
    return json.loads(bytes(arrays.pop("metadata")).decode()), arrays


_json = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-10, 10), st.floats(allow_nan=True),
              st.text(max_size=5)),
    lambda inner: st.one_of(st.lists(inner, max_size=3),
                            st.dictionaries(st.text(max_size=5), inner, max_size=3)),
    max_leaves=6,
)
_array = st.one_of(
    st.builds(lambda shape, v: np.full(shape, v),
              st.lists(st.integers(0, 4), max_size=3).map(tuple),
              st.one_of(st.floats(allow_nan=True), st.integers(-3, 3))),
    st.just(np.array(["a", "b"])),
    st.just(np.zeros(3, dtype=np.complex128)),
)


@st.composite
def _mutations(draw) -> list:
    ops = []
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["meta", "meta-deep", "array", "truncate", "drop"]))
        ops.append((kind, draw(st.sampled_from(
            ["kernel", "kernel_name", "noise_variance", "classifier", "input_noise",
             "training", "inputs", "config", "format_version"])),
            draw(st.sampled_from(["means", "covariances", "labels", "scan_ids",
                                  "pose_factors", "sensor_ids"])),
            draw(_json), draw(_array), draw(st.integers(0, 59))))
    return ops


@FUZZ
@given(ops=_mutations())
def test_model_loader_gives_a_clean_error_or_a_usable_model(good_model, ops):
    meta, arrays = json.loads(json.dumps(good_model[0])), dict(good_model[1])
    for kind, key, name, value, array, cut in ops:
        if kind == "meta":
            meta[key] = value
        elif kind == "meta-deep" and isinstance(meta.get(key), dict) and meta[key]:
            meta[key][sorted(meta[key])[cut % len(meta[key])]] = value
        elif kind == "array":
            arrays[name] = array
        elif kind == "truncate" and name in arrays and arrays[name].ndim:
            arrays[name] = arrays[name][:cut]
        elif kind == "drop":
            arrays.pop(name, None)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "m.npz"
        np.savez(path, metadata=np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays)
        try:
            model = load_model(path)
        except GpoccError as exc:
            assert str(path) in str(exc) and "gpocc train" in str(exc)
            return
    n = len(model.samples)
    assert n > 0
    assert model.samples.means.shape == (n, 2) and model.samples.covariances.shape == (n, 2, 2)
    assert model.samples.pose_factors.shape == (n, 2, 3)
    for a in (model.samples.labels, model.samples.scan_ids, model.samples.sensor_ids):
        assert a.shape == (n,)
    assert np.isfinite(model.samples.means).all()
    assert math.isfinite(model.noise_variance) and model.noise_variance > 0
    assert model.classifier.a > 0 and math.isfinite(model.classifier.b)
