"""Validation of a model file's contents, once, where it is read.

A model file is data from outside (copied, edited, truncated, written by another
version): every field of its JSON metadata and every array's dtype, shape, finiteness
and consistency is checked here, so that prediction code can trust a loaded model. Any
problem is one :class:`GpoccError` naming the file and saying to re-create it.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gpocc.config import Config, config_from_dict
from gpocc.errors import GpoccError
from gpocc.gp.classify import PlattClassifier
from gpocc.gp.inputscale import scale_input_noise
from gpocc.gp.kernels import KERNELS, Kernel
from gpocc.limits import max_cells
from gpocc.samples.coverage import Coverage
from gpocc.samples.sampleset import MAX_NOISE_FACTOR, SampleSet

#: name -> (dtype it is stored as, shape after the sample axis N)
ARRAY_LAYOUT: dict[str, tuple[type, tuple[int, ...]]] = {
    "means": (np.float64, (2,)),
    "covariances": (np.float64, (2, 2)),
    "labels": (np.float64, ()),
    "scan_ids": (np.int64, ()),
    "pose_factors": (np.float64, (2, 3)),
    "sensor_ids": (np.int16, ()),
}


@dataclass(frozen=True)
class ModelContents:
    """The validated pieces of a model file, ready to build a ``GPModel``."""

    kernel: Kernel
    noise_variance: float
    classifier: PlattClassifier
    samples: SampleSet
    config: Config
    input_noise: bool
    training: dict[str, Any]
    inputs: tuple[str, ...]
    versions: dict[str, str]
    input_noise_scale: float = 1.0


class _Damaged(Exception):
    """One problem found in the file (turned into a GpoccError naming the file)."""


def _finite_number(value: Any, what: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _Damaged(f"{what} is {value!r}, not a number")
    if not math.isfinite(value):
        raise _Damaged(f"{what} is {value!r}")
    if positive and value <= 0:
        raise _Damaged(f"{what} is {value!r}, not positive")
    return float(value)


def _kernel(meta: dict[str, Any]) -> Any:
    name = meta.get("kernel_name")
    if not isinstance(name, str) or name not in KERNELS:
        raise _Damaged(f"kernel_name is {name!r}, not one of {sorted(KERNELS)}")
    cls = KERNELS[name]
    params = meta.get("kernel")
    if not isinstance(params, dict):
        raise _Damaged("the kernel parameters are missing")
    if params.get("class") != cls.__name__:
        raise _Damaged(f"kernel class {params.get('class')!r} does not match kernel_name "
                       f"{name!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    given = set(params) - {"class"}
    if given != set(fields):
        missing, unknown = sorted(set(fields) - given), sorted(given - set(fields))
        raise _Damaged(f"kernel parameters: missing {missing}, unknown {unknown}")
    values: dict[str, Any] = {}
    for key in fields:
        value = params[key]
        if isinstance(value, list):
            if len(value) != 2:
                raise _Damaged(f"kernel parameter {key!r} must have 2 entries, got {value!r}")
            values[key] = tuple(_finite_number(v, f"kernel parameter {key!r}", True)
                                for v in value)
        else:
            values[key] = _finite_number(value, f"kernel parameter {key!r}", True)
    default = cls()  # pair-valued parameters (per axis) must be pairs, scalars scalars
    for key in fields:
        if isinstance(getattr(default, key), tuple) != isinstance(values[key], tuple):
            raise _Damaged(f"kernel parameter {key!r} has the wrong form: {params[key]!r}")
    return cls(**values)


def _samples(arrays: dict[str, np.ndarray]) -> SampleSet:
    n = None
    checked: dict[str, np.ndarray] = {}
    for name, (dtype, tail) in ARRAY_LAYOUT.items():
        array = arrays[name]
        if array.dtype.kind not in "fiu" or array.dtype.itemsize > 8:
            raise _Damaged(f"array {name!r} has dtype {array.dtype}, not a number type")
        if array.ndim != 1 + len(tail) or tuple(array.shape[1:]) != tail:
            want = "(N" + "".join(f", {d}" for d in tail) + ")"
            raise _Damaged(f"array {name!r} has shape {array.shape}, expected {want}")
        if n is None:
            n = array.shape[0]
        elif array.shape[0] != n:
            raise _Damaged(f"array {name!r} has {array.shape[0]} rows but 'means' has {n}")
        if array.dtype.kind == "f" and not np.isfinite(array).all():
            raise _Damaged(f"array {name!r} holds NaN or infinite values")
        converted = array.astype(dtype)
        if dtype is not np.float64 and not np.array_equal(converted, array):
            raise _Damaged(f"array {name!r} holds values that are not {np.dtype(dtype)}")
        checked[name] = converted
    if not n:
        raise _Damaged("it holds no training samples")
    if not np.isin(checked["labels"], (-1.0, 1.0)).all():
        raise _Damaged("array 'labels' holds values other than +1 and -1")
    cov = checked["covariances"]
    if (cov[:, 0, 0] < 0).any() or (cov[:, 1, 1] < 0).any() or \
            not np.allclose(cov[:, 0, 1], cov[:, 1, 0], rtol=1e-6, atol=1e-12):
        raise _Damaged("array 'covariances' holds matrices that are not covariances")
    if (checked["sensor_ids"] < 0).any():
        raise _Damaged("array 'sensor_ids' holds negative values")
    return SampleSet(**checked)


def samples_of_pool(pool: SampleSet, index: np.ndarray, input_noise: bool, scale: float,
                    part: str) -> SampleSet:
    """A model's samples made from its growth pool as training makes them: the pool's rows
    ``index`` (ascending), every covariance zero without ``input_noise``, then scaled by
    the learned g ``scale`` (:func:`gpocc.gp.inputscale.scale_input_noise`, ``part``).
    Label-noise factors are not part of it (the model file stores them apart)."""
    samples = dataclasses.replace(pool, noise_factors=None).subset(index)
    if not input_noise:
        samples = samples.without_input_noise()
    return scale_input_noise(samples, scale, part)


def _row_keys(samples: SampleSet) -> np.ndarray:
    """(N,) uint64 hash of each sample's mean (bit pattern), label, scan and sensor: equal
    rows give equal keys; :func:`pool_rows` checks the rows themselves after matching."""
    bits = np.ascontiguousarray(samples.means).view(np.uint64).reshape(-1, 2)
    with np.errstate(over="ignore"):
        key = bits[:, 0] * np.uint64(0x9E3779B97F4A7C15)
        key ^= (bits[:, 1] + np.uint64(0x632BE59BD9B4E019)) * np.uint64(0xC2B2AE3D27D4EB4F)
        key ^= samples.scan_ids.astype(np.uint64) * np.uint64(0x165667B19E3779F9)
        key ^= (samples.sensor_ids.astype(np.uint64) << np.uint64(1)) | (
            samples.labels > 0).astype(np.uint64)
    return key


def pool_rows(pool: SampleSet, samples: SampleSet) -> np.ndarray | None:
    """The ascending (M,) indices of ``pool`` whose rows are ``samples`` (M of them, in
    order: means, labels, scan and sensor ids equal), or None if they are not such a
    subsequence of the pool."""
    if len(samples) == 0 or len(samples) > len(pool):
        return None
    pool_keys = _row_keys(pool)
    order = np.argsort(pool_keys)
    sorted_keys = pool_keys[order]
    keys = _row_keys(samples)
    # Looked up in key order: twice as fast as in sample order (memory access in order).
    by_key = np.argsort(keys)
    at = np.empty(len(keys), dtype=np.int64)
    at[by_key] = np.searchsorted(sorted_keys, keys[by_key])
    np.minimum(at, len(pool) - 1, out=at)
    index = order[at]
    if not (np.array_equal(sorted_keys[at], keys) and (np.diff(index) > 0).all()):
        return None
    # One array at a time: a site's samples are hundreds of MB.
    if not all(np.array_equal(getattr(pool, name)[index], getattr(samples, name))
               for name in ("means", "labels", "scan_ids", "sensor_ids")):
        return None
    return index


def _sample_index(index: np.ndarray, pool_size: int) -> np.ndarray:
    if (index.dtype.kind not in "iu" or index.ndim != 1 or index.size == 0
            or (index < 0).any() or (index >= pool_size).any()
            or (np.diff(index.astype(np.int64)) <= 0).any()):
        raise _Damaged(f"array 'sample_index' is not ascending rows of the {pool_size} in "
                       "the growth pool")
    return index.astype(np.int64)


def _classifier(record: Any, version: Any) -> PlattClassifier:
    """Format 1 stored the published (a, b); formats 2 and 3 (offset, extra_variance);
    format 4 adds the temperature."""
    if version == 1:
        if not isinstance(record, dict) or set(record) != {"a", "b"}:
            raise _Damaged(f"the classifier must hold exactly 'a' and 'b', got {record!r}")
        a = _finite_number(record["a"], "classifier 'a'", positive=True)
        b = _finite_number(record["b"], "classifier 'b'")
        return PlattClassifier.from_ab(a, b)
    keys = {"offset", "extra_variance"} | ({"temperature"} if version >= 4 else set())
    if not isinstance(record, dict) or set(record) != keys:
        raise _Damaged(f"the classifier must hold exactly {sorted(keys)}, got {record!r}")
    return PlattClassifier(
        offset=_finite_number(record["offset"], "classifier 'offset'"),
        extra_variance=_finite_number(record["extra_variance"], "classifier 'extra_variance'",
                                      positive=True),
        temperature=(_finite_number(record["temperature"], "classifier 'temperature'",
                                    positive=True) if version >= 4 else 1.0))


#: Settings whose default changed after model files were written without them: the value
#: such a file was trained with (dotted key, value).
_OLDER_DEFAULTS = (("samples.free_clearance_m", 0.0), ("model.training.patch_centres", "samples"),
                   ("model.training.classifier_temperature", "none"),
                   ("samples.label_weights", "none"),
                   ("model.training.classifier_offset_range", "wide"),
                   ("model.training.classifier_targets", "hard"),
                   ("model.training.isotropic", False),
                   ("model.covariance_precision", "double"),
                   ("model.training.patch_offset_m", 0.0))


def _with_settings_of_older_files(config: dict) -> dict:
    """The embedded config with each key of ``_OLDER_DEFAULTS`` it lacks set to the value
    its file was trained with, so that rebuilding its patches or samples gives the same."""
    config = copy.deepcopy(config)
    for key, value in _OLDER_DEFAULTS:
        *parents, last = key.split(".")
        node = config
        for name in parents:
            node = node.get(name) if isinstance(node, dict) else None
        if isinstance(node, dict):
            node.setdefault(last, value)
    return config


def _contents(meta: Any, arrays: dict[str, np.ndarray], source: str,
              pool: SampleSet | None = None) -> ModelContents:
    if not isinstance(meta, dict):
        raise _Damaged("its metadata is not a JSON object")
    if not isinstance(meta.get("config"), dict):
        raise _Damaged("the embedded config is missing")
    config = config_from_dict(_with_settings_of_older_files(meta["config"]),
                              f"{source} (embedded config)", limits=False)
    kernel = _kernel(meta)
    noise = _finite_number(meta.get("noise_variance"), "noise_variance", positive=True)
    platt = _classifier(meta.get("classifier"), meta.get("format_version"))
    input_noise = meta.get("input_noise")
    if not isinstance(input_noise, bool):
        raise _Damaged(f"input_noise is {input_noise!r}, not true or false")
    # Absent in files written before it was learned: the stated covariances (g = 1).
    scale = _finite_number(meta.get("input_noise_scale", 1.0), "input_noise_scale",
                           positive=True)
    training = meta.get("training", {})
    if not isinstance(training, dict):
        raise _Damaged("the training record is not a JSON object")
    inputs = meta.get("inputs", [])
    if not isinstance(inputs, list) or not all(isinstance(i, str) for i in inputs):
        raise _Damaged("inputs is not a list of file names")
    names = meta.get("sensor_names", [])
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise _Damaged("sensor_names is not a list of names")
    versions = meta.get("versions", {})
    if not isinstance(versions, dict) or not all(isinstance(v, str) for v in versions.values()):
        raise _Damaged("versions is not a mapping of package names to versions")
    if "sample_index" in arrays:
        if pool is None:
            raise _Damaged("its samples are stored as rows of a growth pool it lacks")
        # Rows of the pool, which validate_growth has checked as _samples checks arrays.
        samples = samples_of_pool(pool, _sample_index(arrays["sample_index"], len(pool)),
                                  input_noise, scale,
                                  config.model.training.input_noise_scale_part)
    else:
        samples = _samples(arrays)
    if names and (samples.sensor_ids >= len(names)).any():
        raise _Damaged(f"array 'sensor_ids' names sensors beyond the {len(names)} in "
                       "sensor_names")
    return ModelContents(
        kernel=kernel, noise_variance=noise, classifier=platt,
        samples=dataclasses.replace(samples, sensor_names=tuple(names)), config=config,
        input_noise=input_noise, training=training, inputs=tuple(inputs),
        versions=dict(versions), input_noise_scale=scale,
    )


def validate_noise_factors(factors: np.ndarray | None, config: Config, n: int,
                           path: str | Path) -> np.ndarray | None:
    """The samples' (N,) label-noise factors, checked: present exactly when the model's
    config weighs labels (``samples.label_weights`` ``share`` or ``count``, with thinning),
    and numbers in [1 / :data:`MAX_NOISE_FACTOR`, :data:`MAX_NOISE_FACTOR`], one per
    sample."""
    expected = config.samples.weighs_labels
    if factors is None:
        if expected:
            raise GpoccError(f"{path}: damaged model file: its config weighs labels "
                             f"(samples.label_weights: {config.samples.label_weights}) but the "
                             "array 'noise_factors' is missing; re-create it with `gpocc train`")
        return None
    converted = (factors.astype(np.float64)
                 if factors.dtype.kind == "f" and factors.dtype.itemsize <= 8 else None)
    if not expected or converted is None or converted.shape != (n,) \
            or not np.isfinite(converted).all() \
            or (converted < 1.0 / MAX_NOISE_FACTOR).any() \
            or (converted > MAX_NOISE_FACTOR).any():
        raise GpoccError(f"{path}: damaged model file: array 'noise_factors' is not "
                         f"{n} numbers in [{1.0 / MAX_NOISE_FACTOR:g}, {MAX_NOISE_FACTOR:g}] "
                         "of a config that weighs labels (samples.label_weights); re-create "
                         "it with `gpocc train`")
    return converted


def validate_contents(meta: Any, arrays: dict[str, np.ndarray], path: str | Path,
                      pool: SampleSet | None = None) -> ModelContents:
    """Check a model file's metadata and arrays; return them as typed pieces.

    Args:
        meta: the decoded JSON metadata (format and version already checked).
        arrays: name -> array for every name in :data:`ARRAY_LAYOUT`, or (format 6)
            ``sample_index`` alone: the samples are then rows of ``pool``
            (:func:`samples_of_pool`).
        path: the model file, for messages.
        pool: the samples of the file's growth pool (validated), if it has one.

    Raises:
        GpoccError: naming ``path`` and what is wrong, and saying to re-train.
    """
    try:
        return _contents(meta, arrays, str(path), pool)
    except _Damaged as exc:
        raise GpoccError(
            f"{path}: damaged model file: {exc}; re-create it with `gpocc train`"
        ) from None
    except GpoccError as exc:
        # The embedded config or a kernel constructor: the fix is re-training, not a config.
        raise GpoccError(
            f"{path}: damaged model file ({exc}); re-create it with `gpocc train`"
        ) from None


def _coverage(meta: Any, bits: np.ndarray, limit: int) -> Coverage:
    if not isinstance(meta, dict):
        raise _Damaged("its coverage record is not a JSON object")
    x0 = _finite_number(meta.get("x0"), "coverage x0")
    y0 = _finite_number(meta.get("y0"), "coverage y0")
    cell = _finite_number(meta.get("cell_m"), "coverage cell_m", positive=True)
    step = _finite_number(meta.get("step_m"), "coverage step_m", positive=True)
    shape = meta.get("shape")
    if (not isinstance(shape, list) or len(shape) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0
                       for v in shape)):
        raise _Damaged(f"coverage shape is {shape!r}, not two non-negative whole numbers")
    rows, cols = shape
    if rows * cols > limit:
        raise _Damaged(f"coverage raster of {rows} x {cols} cells is over the cell limit")
    if bits.dtype != np.uint8 or bits.ndim != 1 or bits.size != -(-rows * cols // 8):
        raise _Damaged(f"coverage bits have dtype {bits.dtype} and shape {bits.shape}, "
                       f"not {-(-rows * cols // 8)} bytes for {rows} x {cols} cells")
    covered = np.unpackbits(bits, count=rows * cols).astype(bool).reshape(rows, cols)
    return Coverage(x0, y0, cell, step, covered)


def validate_coverage(meta: Any, bits: np.ndarray | None, config: Config,
                      path: str | Path) -> Coverage | None:
    """The model file's coverage raster (cells the training beams crossed), checked.

    None when the file has none (files written before it existed): maps then fall back
    to the cells holding training samples.

    Raises:
        GpoccError: naming ``path`` and what is wrong, and saying to re-train.
    """
    if meta is None and bits is None:
        return None
    try:
        if meta is None or bits is None:
            raise _Damaged("it holds half of a coverage raster (record or bits missing)")
        return _coverage(meta, bits, max_cells(config.map.max_cells))
    except _Damaged as exc:
        raise GpoccError(
            f"{path}: damaged model file: {exc}; re-create it with `gpocc train`"
        ) from None


#: The optional arrays of a model's growth state (format 3; :mod:`gpocc.gp.growth`).
GROWTH_ARRAYS = (*(f"pool_{name}" for name in ARRAY_LAYOUT), "vote_keys", "vote_counts",
                 "calibration_points", "calibration_labels", "calibration_scan_ids")


def _integers(array: np.ndarray, name: str) -> np.ndarray:
    if array.dtype.kind not in "iu" or array.ndim != 1:
        raise _Damaged(f"array {name!r} has dtype {array.dtype} and shape {array.shape}, "
                       "not a list of integers")
    return array.astype(np.int64)


def _growth(meta: Any, arrays: dict[str, np.ndarray]) -> Any:
    # Imported here: the growth state's modules import the samples stage, which the
    # map's workers (loading models) do not otherwise need.
    from gpocc.gp.growth import Growth
    from gpocc.io.records import record_from_dict
    from gpocc.samples.beams import SamplePool
    from gpocc.samples.heldout import CalibrationPoints

    if not isinstance(meta, dict):
        raise _Damaged("its growth record is not a JSON object")
    missing = [n for n in GROWTH_ARRAYS[:8] if n not in arrays]
    if missing:
        raise _Damaged(f"its growth state lacks the arrays {missing}")
    try:
        pool = _samples({name: arrays[f"pool_{name}"] for name in ARRAY_LAYOUT})
    except _Damaged as exc:
        raise _Damaged(f"growth state (pool): {exc}") from None
    names = meta.get("sensor_names")
    if (not isinstance(names, list) or not all(isinstance(n, str) for n in names)
            or (pool.sensor_ids >= len(names)).any()):
        raise _Damaged("the growth record's sensor_names do not name the pool's sensors")
    n_scans = meta.get("n_scans")
    if (isinstance(n_scans, bool) or not isinstance(n_scans, int)
            or n_scans <= int(pool.scan_ids.max())):
        raise _Damaged(f"the growth record's n_scans is {n_scans!r}, not above every scan id")
    keys = _integers(arrays["vote_keys"], "vote_keys")
    counts = _integers(arrays["vote_counts"], "vote_counts")
    if keys.shape != counts.shape or (counts <= 0).any() or (np.diff(keys) <= 0).any():
        raise _Damaged("the label votes are not ascending keys with positive counts")
    records = meta.get("inputs")
    if not isinstance(records, list):
        raise _Damaged("the growth record's inputs are not a list")
    try:
        parsed = tuple(record_from_dict(r) for r in records)
    except ValueError as exc:
        raise _Damaged(str(exc)) from None
    calibration = None
    parts = [n for n in GROWTH_ARRAYS[8:] if n in arrays]
    if parts:
        if len(parts) != 3:
            raise _Damaged("it holds part of the calibration points")
        points = arrays["calibration_points"]
        labels = arrays["calibration_labels"]
        if (points.dtype.kind != "f" or points.ndim != 2 or points.shape[1:] != (2,)
                or labels.shape != points.shape[:1] or not np.isfinite(points).all()
                or not np.isin(labels, (-1.0, 1.0)).all()):
            raise _Damaged("its calibration points are malformed")
        calibration = CalibrationPoints(points.astype(np.float64), labels.astype(np.float64),
                                        _integers(arrays["calibration_scan_ids"],
                                                  "calibration_scan_ids"))
    pool = dataclasses.replace(pool, sensor_names=tuple(names))
    return Growth(SamplePool(pool, keys, counts, n_scans), parsed, calibration)


def validate_growth(meta: Any, arrays: dict[str, np.ndarray], path: str | Path) -> Any:
    """The model file's growth state (:class:`gpocc.gp.growth.Growth`), checked; None
    when the file has none (format 2 and older, models built from samples alone).

    Raises:
        GpoccError: naming ``path`` and what is wrong, and saying to re-train.
    """
    if meta is None and not arrays:
        return None
    try:
        if meta is None:
            raise _Damaged("it holds growth arrays without their record")
        return _growth(meta, arrays)
    except _Damaged as exc:
        raise GpoccError(
            f"{path}: damaged model file: {exc}; re-create it with `gpocc train`"
        ) from None
