"""A trained occupancy model and its self-contained file format.

The model file is a compressed ``.npz`` holding the training samples (means,
covariances, pose factors, labels, scan ids) and one JSON document with the format
version, hyperparameters, classifier, thresholds, the job's config and the versions of
the software that wrote it. It never needs pickle.
"""

from __future__ import annotations

import dataclasses
import json
import math
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gpocc.blas import single_threaded_blas
from gpocc.config import Config, config_to_dict
from gpocc.errors import GpoccError, check_regular_file
from gpocc.gp import backends
from gpocc.gp.classify import (
    C_BOUND,
    MapFunction,
    PlattClassifier,
    beam_holdout_predictions,
    fit_classifier,
    fit_offset,
    fit_offset_and_temperature,
    fit_temperature,
    offset_bound,
    temperature_undetermined,
)
from gpocc.gp.growth import Growth
from gpocc.gp.inputscale import scale_input_noise
from gpocc.gp.kernels import Kernel, make_kernel
from gpocc.gp.local import NeighbourIndex
from gpocc.gp.modelfile import (
    ARRAY_LAYOUT,
    GROWTH_ARRAYS,
    pool_rows,
    samples_of_pool,
    validate_contents,
    validate_coverage,
    validate_growth,
    validate_noise_factors,
)
from gpocc.gp.train import TrainingResult, learn_hyperparameters, make_patches
from gpocc.io.atomic import atomic_output_file
from gpocc.parallel import cluster_map
from gpocc.progress import log
from gpocc.samples.coverage import Coverage
from gpocc.samples.heldout import CalibrationPoints
from gpocc.samples.sampleset import SampleSet, has_both_labels
from gpocc.versions import model_versions

FORMAT_NAME = "gpocc-model"
#: 2: the classifier is stored as (offset, extra_variance); files of format 1 (a, b)
#: still load. The samples' covariances and pose factors are stored already scaled by
#: ``input_noise_scale`` (absent: 1). 3: the growth state for ``gpocc update`` (optional
#: ``pool_*``, ``vote_*`` and ``calibration_*`` arrays and a ``growth`` record); files of
#: formats 1 and 2 load without it. 4: the classifier's temperature; earlier files load
#: with temperature 1 (and ``classifier_temperature: none`` in their config). 5: an
#: optional ``noise_factors`` array (``samples.label_weights``), which a format 4
#: reader would ignore; earlier files load with every factor 1. 6: the samples may be
#: stored as ``sample_index``, their rows in the growth pool (:func:`_rows_in_pool`),
#: instead of their own arrays: about half the file, and half the time to write it.
FORMAT_VERSION = 6
_ARRAYS = tuple(ARRAY_LAYOUT)
#: Rows of samples that :func:`_rows_in_pool` checks at a time.
_CHECK_ROWS = 1 << 16
#: Arrays written without compression (float64 noise, see :func:`write_model`).
_STORED_ARRAYS = frozenset({"means", "covariances", "pool_means", "pool_covariances",
                            "calibration_points"})


@dataclass(frozen=True)
class GPModel:
    """Everything ``gpocc map`` needs: samples, kernel, noise, classifier, settings.

    ``samples`` are the samples the model predicts from: with ``input_noise`` off their
    covariances are zero (the baseline GP), and with it on they are already scaled by
    the learned ``input_noise_scale`` g (:mod:`gpocc.gp.inputscale`; 1 when not learned
    and in files written before it existed), so prediction code needs no switch; their
    ``sensor_names`` name the sensors they came from. ``versions``: the software that
    trained the model (:func:`gpocc.versions.model_versions`). ``training``: the
    learning's record (likelihoods, evaluations, patches, ``timings_s``).
    ``coverage``: the cells the training beams crossed (None for models built from
    samples alone); maps are nodata far from it. ``growth``: what adding logs to the
    model needs (:mod:`gpocc.gp.growth`; None for models built from samples alone and
    files written before format 3).
    """

    kernel: Kernel
    noise_variance: float
    classifier: PlattClassifier
    samples: SampleSet
    config: Config
    input_noise: bool
    training: dict[str, Any] = field(default_factory=dict)
    inputs: tuple[str, ...] = ()
    versions: dict[str, str] = field(default_factory=model_versions)
    coverage: Coverage | None = None
    input_noise_scale: float = 1.0
    growth: Growth | None = None

    @property
    def level(self) -> int:
        return self.config.model.quadrature_level

    @property
    def backend(self) -> str | backends.Choice:
        """``backend=`` of every expected-kernel call: ``model.backend`` with
        ``model.diagonal`` and ``model.covariance_precision``
        (:func:`gpocc.gp.backends.choose`)."""
        m = self.config.model
        return backends.choose(m.backend, m.diagonal, m.covariance_precision)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of the sample means, metres."""
        lo = self.samples.means.min(axis=0)
        hi = self.samples.means.max(axis=0)
        return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))


def kernel_parameters(kernel: Kernel) -> dict[str, Any]:
    """The kernel's hyperparameters as plain data (name plus fields)."""
    values = {k: (list(v) if isinstance(v, tuple) else v)
              for k, v in dataclasses.asdict(kernel).items()}  # type: ignore[call-overload]
    return {"class": type(kernel).__name__, **values}


def patch_summary(training: dict[str, Any]) -> str:
    """``"; N patches of M samples"`` of a model's training record (``""`` where it
    records none: a model whose values were not learned)."""
    count, size = training.get("patches") or (0, 0)
    return f"; {count} patches of {size} samples" if count else ""


def build_model(
    samples: SampleSet, config: Config, inputs: tuple[str, ...] = (),
    on_evaluation: Callable[[int], None] | None = None,
    coverage: Coverage | None = None,
    calibration: CalibrationPoints | None = None,
    client: Any = None,
    warm_start: GPModel | None = None, refine_iterations: int | None = None,
) -> GPModel:
    """Learn hyperparameters and the classifier from ``samples`` under ``config``.

    ``on_evaluation(1)`` is called after each likelihood evaluation (progress display).
    ``client``: a ``distributed.Client`` (:func:`gpocc.parallel.dask_client`) whose
    cluster computes the likelihood patches and the classifier's predictions; the model
    is the same as without it.
    ``calibration``: labelled points of held-out scans for ``classifier_offset: beams``
    (:func:`gpocc.samples.heldout.calibration_points`); without them, or if they lack
    either class, the offset stays that of the hold-out fit.
    ``warm_start``: a model whose hyperparameters learning refines instead of searching
    from the config's initial values (:func:`gpocc.gp.train.learn_hyperparameters`);
    ``training["warm_started"]`` then says whether it did (false: they fitted worse than
    the initial values and learning searched as without them). ``refine_iterations``:
    at most this many refinement steps from it (default
    ``model.training.lbfgs_maxiter``).
    Samples without label-noise factors (made without counting each cell's labels, not
    by :func:`gpocc.samples.beams.finish_samples`) weigh once each, and the model's config
    says so (``samples.label_weights: none``) whatever ``config`` asked.
    """
    if config.samples.weighs_labels and samples.noise_factors is None:
        config = dataclasses.replace(
            config, samples=dataclasses.replace(config.samples, label_weights="none"))
    model_cfg = config.model
    if not model_cfg.input_noise:
        samples = samples.without_input_noise()
    kernel = make_kernel(model_cfg.kernel, model_cfg.hyperparameters)
    backend = backends.choose(model_cfg.backend, model_cfg.diagonal,
                              model_cfg.covariance_precision)
    # One tree of the sample means for the likelihood's patches and the classifier's.
    index = NeighbourIndex(samples)
    start = None if warm_start is None else TrainingResult(
        warm_start.kernel, warm_start.noise_variance, math.nan, math.nan, 0, (0, 0),
        warm_start.input_noise_scale)
    with single_threaded_blas():
        result: TrainingResult = learn_hyperparameters(
            kernel, model_cfg.hyperparameters.noise_variance, samples,
            model_cfg.quadrature_level, model_cfg.effective_training, config.seed,
            on_evaluation,
            backend=backend, client=client, warm_start=start,
            refine_iterations=refine_iterations, index=index,
        )
        # The model predicts from the samples as the likelihood saw them: scaled by g.
        samples = scale_input_noise(samples, result.input_noise_scale,
                                    model_cfg.training.input_noise_scale_part)
        map_fn = map if client is None else cluster_map(client)
        classifier, offset, points, bound = _fit_classifier(result, samples, config,
                                                            calibration, map_fn, index)
    training = {
        "log_marginal_likelihood": result.log_marginal_likelihood,
        "initial_log_marginal_likelihood": result.initial_log_marginal_likelihood,
        "evaluations": result.evaluations,
        "patches": list(result.patches),
        "classifier_holdout": model_cfg.training.classifier_holdout,
        "classifier_offset": offset,
        "classifier_offset_bound": bound,
        "classifier_temperature": model_cfg.training.classifier_temperature,
        "classifier_points": points,
    }
    if warm_start is not None:
        training["warm_started"] = result.warm_started
    return GPModel(
        kernel=result.kernel, noise_variance=result.noise_variance, classifier=classifier,
        samples=samples, config=config, input_noise=model_cfg.input_noise,
        training=training, inputs=tuple(inputs), coverage=coverage,
        input_noise_scale=result.input_noise_scale,
    )


def refit_model(
    samples: SampleSet, config: Config, kept: GPModel, inputs: tuple[str, ...] = (),
    coverage: Coverage | None = None, calibration: CalibrationPoints | None = None,
) -> GPModel:
    """A model of ``samples`` with ``kept``'s hyperparameters (kernel, label noise,
    input-noise scale) and a classifier fitted anew on ``samples``, as
    :func:`build_model` fits it after learning; ``training`` keeps ``kept``'s record of
    the learning."""
    if not config.model.input_noise:
        samples = samples.without_input_noise()
    result = TrainingResult(
        kept.kernel, kept.noise_variance,
        kept.training.get("log_marginal_likelihood", math.nan),
        kept.training.get("initial_log_marginal_likelihood", math.nan), 0, (0, 0),
        kept.input_noise_scale)
    with single_threaded_blas():
        samples = scale_input_noise(samples, kept.input_noise_scale,
                                    config.model.training.input_noise_scale_part)
        classifier, offset, points, bound = _fit_classifier(result, samples, config,
                                                            calibration)
    training = {**kept.training, "classifier_holdout": config.model.training.classifier_holdout,
                "classifier_offset": offset, "classifier_offset_bound": bound,
                "classifier_temperature": config.model.training.classifier_temperature,
                "classifier_points": points}
    return GPModel(
        kernel=kept.kernel, noise_variance=kept.noise_variance, classifier=classifier,
        samples=samples, config=config, input_noise=config.model.input_noise,
        training=training, inputs=tuple(inputs), coverage=coverage,
        input_noise_scale=kept.input_noise_scale,
    )


def _fit_classifier(result: TrainingResult, samples: SampleSet, config: Config,
                    calibration: CalibrationPoints | None, map_fn: MapFunction = map,
                    index: NeighbourIndex | None = None,
                    ) -> tuple[PlattClassifier, str, int, float]:
    """The Platt classifier of the learned GP, where its offset came from (``holdout`` or
    ``beams``), the number of held-out beam points it was fitted on (0 for holdout) and
    the largest |offset| its fit allowed (:func:`gpocc.gp.classify.offset_bound`).
    ``index``: a neighbour index of samples with the same means, for its patches."""
    model_cfg = config.model
    training = model_cfg.effective_training
    backend = backends.choose(model_cfg.backend, model_cfg.diagonal,
                              model_cfg.covariance_precision)
    # Fresh patches (another seed) for the classifier: a and b fitted on the very
    # neighbourhoods whose likelihood chose the hyperparameters would be optimistic.
    patches = make_patches(samples, training, config.seed + 1, index)
    classifier = fit_classifier(result.kernel, result.noise_variance, patches,
                                model_cfg.quadrature_level, training.classifier_holdout,
                                backend, map_fn, training.classifier_variance == "latent",
                                training.classifier_temperature == "samples",
                                training.classifier_targets)
    if training.classifier_variance == "label-map":
        # Fitted on the label's variance, applied to a cell's latent variance plus the
        # label noise: the same quantity.
        classifier = dataclasses.replace(
            classifier, extra_variance=classifier.extra_variance + result.noise_variance)
    if not training.uses_beam_points:
        return classifier, "holdout", 0, C_BOUND
    if calibration is None or not calibration.usable:
        log("note: too few labelled points of held-out scans (every "
            f"{training.calibration_every}th scan) to fit the classifier's "
            + ("offset and temperature" if training.classifier_offset == "beams"
               else "temperature") + " on; kept the held-out samples' fit")
        return classifier, "holdout", 0, C_BOUND
    mean, variance, labels = beam_holdout_predictions(
        result.kernel, result.noise_variance, samples, calibration,
        model_cfg.quadrature_level, model_cfg.neighbours, model_cfg.block_size_m,
        training.calibration_blocks, np.random.default_rng(config.seed + 2),
        backend, map_fn)
    if not has_both_labels(labels):  # the chosen blocks may hold one class only
        return classifier, "holdout", 0, C_BOUND
    offset, bound = "holdout", offset_bound(mean, training.classifier_offset_range)
    targets = training.classifier_targets
    if training.classifier_temperature == "beams":
        if temperature_undetermined(classifier, mean, labels, targets):
            log(f"note: the classifier puts all {labels.size} labelled points of held-out "
                "scans on their label's side, which leaves its temperature undetermined "
                "with hard targets; kept the held-out samples' fit (temperature 1)")
        elif training.classifier_offset == "beams":
            classifier, offset = fit_offset_and_temperature(
                mean, variance, labels, classifier.extra_variance, bound, targets), "beams"
        else:
            classifier = fit_temperature(classifier, mean, variance, labels, targets)
    elif training.classifier_offset == "beams":
        classifier, offset = fit_offset(
            mean, variance, labels, classifier.extra_variance, classifier.temperature,
            bound, targets), "beams"
    return classifier, offset, int(labels.size), bound if offset == "beams" else C_BOUND


def save_model(model: GPModel, path: str | Path, force: bool = False) -> None:
    """Write ``model`` to ``path`` (.npz) atomically.

    An existing ``path`` is replaced only with ``force``, and only if it is a model file
    (see :func:`gpocc.io.atomic.atomic_output_file`).
    """
    with atomic_output_file(path, force=force) as tmp:
        write_model(model, tmp)


def write_model(model: GPModel, path: str | Path) -> None:
    """Write ``model`` to ``path`` (.npz) as it is: for a path private to this run (inside
    a temporary output folder); top-level model files go through :func:`save_model`."""
    meta = model_metadata(model)
    arrays = model_arrays(model)
    index = _rows_in_pool(model)
    if index is not None:
        arrays = {"sample_index": index,
                  **{k: v for k, v in arrays.items() if k not in _ARRAYS}}
    # Positions and covariances are float64 noise: deflate gained 8-26% on them at
    # 30-40 MB/s, a third of writing a large site's model.
    write_archive(path, meta, arrays, stored=_STORED_ARRAYS)


def write_archive(path: str | Path, meta: dict[str, Any], arrays: dict[str, np.ndarray],
                  stored: frozenset[str] = frozenset()) -> None:
    """Write ``meta`` (as the ``metadata`` entry) and ``arrays`` to ``path`` as the .npz
    archive numpy.load reads: each entry deflated at zlib level 1 (level 6, numpy's,
    packs 2% smaller in four times the time), those named in ``stored`` uncompressed."""
    entries = {"metadata": np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays}
    with open(path, "wb") as fh, zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED,
                                                 compresslevel=1) as archive:
        for name, array in entries.items():
            # Entries opened by name take the archive's method (and its level 1).
            archive.compression = (zipfile.ZIP_STORED if name in stored
                                   else zipfile.ZIP_DEFLATED)
            with archive.open(f"{name}.npy", "w", force_zip64=True) as entry:
                np.lib.format.write_array(entry, np.asanyarray(array), allow_pickle=False)


def model_metadata(model: GPModel) -> dict[str, Any]:
    """The JSON metadata of ``model``'s file (its arrays: :func:`model_arrays`)."""
    meta = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "versions": dict(model.versions),
        "sensor_names": list(model.samples.sensor_names),
        "kernel": kernel_parameters(model.kernel),
        "kernel_name": model.config.model.kernel,
        "noise_variance": model.noise_variance,
        "classifier": {"offset": model.classifier.offset,
                       "extra_variance": model.classifier.extra_variance,
                       "temperature": model.classifier.temperature},
        "input_noise": model.input_noise,
        "input_noise_scale": model.input_noise_scale,
        "training": model.training,
        "inputs": list(model.inputs),
        "config": config_to_dict(model.config),
    }
    if model.coverage is not None:
        cov = model.coverage
        meta["coverage"] = {"x0": cov.x0, "y0": cov.y0, "cell_m": cov.cell_m,
                            "step_m": cov.step_m, "shape": list(cov.covered.shape)}
    if model.growth is not None:
        meta["growth"] = _growth_record(model.growth)
    return meta


def _rows_in_pool(model: GPModel) -> np.ndarray | None:
    """The rows of the model's growth pool its samples are made of
    (:func:`gpocc.gp.modelfile.samples_of_pool` gives them back exactly), or None: no
    pool, or samples it does not give (a model built from samples alone)."""
    if model.growth is None:
        return None
    pool = model.growth.pool.samples
    index = pool_rows(pool, model.samples)
    if index is None:
        return None
    part = model.config.model.training.input_noise_scale_part
    # pool_rows has matched the rows' means, labels, scan and sensor ids; what making
    # them changes are the covariances and pose factors. In blocks of rows: the whole set
    # made again would add a copy of the samples (a site's: hundreds of MB) to the peak
    # memory of writing the model.
    for start in range(0, len(index), _CHECK_ROWS):
        rows = slice(start, start + _CHECK_ROWS)
        made = samples_of_pool(pool, index[rows], model.input_noise,
                               model.input_noise_scale, part)
        if not all(np.array_equal(getattr(made, name), getattr(model.samples, name)[rows])
                   for name in ("covariances", "pose_factors")):
            return None
    return index


def model_arrays(model: GPModel) -> dict[str, np.ndarray]:
    """Every array of ``model`` by its name in a model file, the samples as their own
    arrays (format 5's layout; :func:`write_model` may store them as rows of the pool)."""
    arrays = {name: getattr(model.samples, name) for name in _ARRAYS}
    if model.samples.noise_factors is not None:
        arrays["noise_factors"] = model.samples.noise_factors
    if model.coverage is not None:
        arrays["coverage"] = np.packbits(model.coverage.covered, axis=None)
    if model.growth is not None:
        pool = model.growth.pool
        arrays.update({f"pool_{name}": getattr(pool.samples, name) for name in _ARRAYS})
        arrays.update(vote_keys=pool.vote_keys, vote_counts=pool.vote_counts)
        calibration = model.growth.calibration
        if calibration is not None:
            arrays.update(calibration_points=calibration.points,
                          calibration_labels=calibration.labels,
                          calibration_scan_ids=calibration.scan_ids)
    return arrays


def _growth_record(growth: Growth) -> dict[str, Any]:
    """The growth state's JSON record (its arrays: :func:`model_arrays`)."""
    return {"n_scans": growth.pool.n_scans,
            "sensor_names": list(growth.pool.samples.sensor_names),
            "inputs": [r.as_dict() for r in growth.records]}


def load_model(path: str | Path) -> GPModel:
    """Read a model file; a missing, corrupt or newer-format file is a GpoccError."""
    p = Path(path)
    if p.is_dir() and (p / "model.npz").is_file():  # a `gpocc build` map folder
        raise GpoccError(f"{p}: is a map folder; pass its model, {p / 'model.npz'}")
    check_regular_file(p, "model file", "pass a model file (create one with `gpocc train`)")
    try:
        loaded = np.load(p, allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):  # a bare .npy array
            raise ValueError("not an .npz archive")
        with loaded as data:
            meta = json.loads(bytes(data["metadata"]).decode())
            # Format 6 may store the samples as rows of the growth pool instead.
            names = ("sample_index",) if "sample_index" in data.files else _ARRAYS
            arrays = {name: data[name] for name in names}
            coverage_bits = data["coverage"] if "coverage" in data.files else None
            factors = data["noise_factors"] if "noise_factors" in data.files else None
            growth_arrays = {name: data[name] for name in GROWTH_ARRAYS if name in data.files}
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, zlib.error,
            json.JSONDecodeError, EOFError, UnicodeDecodeError, RecursionError):
        # RecursionError: metadata nested deeper than JSON's decoder recurses.
        raise GpoccError(f"{p}: not a gpocc model file or corrupt; re-create it with "
                         "`gpocc train`") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
        raise GpoccError(f"{p}: not a gpocc model file; re-create it with `gpocc train`")
    version = meta.get("format_version")
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise GpoccError(f"{p}: damaged model file: format_version is {version!r}; "
                         "re-create it with `gpocc train`")
    if version > FORMAT_VERSION:
        raise GpoccError(
            f"{p}: model format version {version} is newer than this gpocc understands "
            f"({FORMAT_VERSION}); upgrade gpocc or re-train with this version"
        )
    growth = validate_growth(meta.get("growth"), growth_arrays, p)
    parts = validate_contents(meta, arrays, p,
                              None if growth is None else growth.pool.samples)
    checked = validate_noise_factors(factors, parts.config, len(parts.samples), p)
    if checked is not None:
        parts = dataclasses.replace(parts, samples=dataclasses.replace(
            parts.samples, noise_factors=checked))
    # ModelContents holds GPModel's fields but the coverage, field for field.
    return GPModel(
        **vars(parts),
        coverage=validate_coverage(meta.get("coverage"), coverage_bits, parts.config, p),
        growth=growth,
    )
