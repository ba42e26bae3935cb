"""Adding logs to a trained model (``gpocc update``): new samples join the model's kept
state (:mod:`gpocc.gp.growth`) without reading its old logs again.

The samples are those training on all logs at once would build. The hyperparameters
(``hyperparameters``) are by default ``refined``: Fisher scoring on the union's patches
(:mod:`gpocc.gp.refine`) starts from the model's values instead of annealing from the
config's initial ones. Learning's optimum is mostly set by its patches, not by its
start, so this heads where training on all logs lands (the patches, drawn from the same
samples with the same seed, are the same) in a few evaluations, stopping once the gain
still to come is estimated under 0.01 nats (:mod:`gpocc.gp.refine`) or after
``refine_iterations`` steps (:data:`REFINE_ITERATIONS`).
``kept`` keeps the model's values (cheapest; they were learned on other patches, and ten
patches' optimum moves with the draw: Freiburg held-out AUC up to 0.008 apart);
``relearned`` learns them on the union as training does, which gives that model exactly.
The patches' likelihood can have several optima: where training's annealing ends in
another basin than the model's values, the refinement finds another optimum than
training (docs/benchmarks.md, ``update-cost``, gives both log marginal likelihoods).
The classifier is always fitted anew on the union.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from gpocc.blas import single_threaded_blas
from gpocc.config import Config, config_to_dict
from gpocc.errors import GpoccError
from gpocc.gp import backends
from gpocc.gp.growth import Growth, growth_of_older_model, join_calibration
from gpocc.gp.kernels import make_kernel
from gpocc.gp.model import GPModel, build_model, refit_model
from gpocc.gp.train import load_optimiser, make_patches, negative_log_likelihood
from gpocc.io.records import InputRecord
from gpocc.io.scans import ScanBatch
from gpocc.progress import log
from gpocc.samples.beams import build_pool, finish_samples, merge_pools
from gpocc.samples.coverage import beam_coverage, sample_coverage, union_coverage
from gpocc.samples.heldout import calibration_points
from gpocc.samples.sampleset import SampleSet

#: Steps of a refinement, at most (``gpocc update --refine-iterations``): the real logs'
#: cuts converge in fewer (docs/benchmarks.md, "Updating a model against training on all
#: logs", counts their evaluations).
REFINE_ITERATIONS = 20

#: Config sections an update takes from the model: its samples were built and its
#: hyperparameters learned with them.
MODEL_SECTIONS = ("samples", "model")


def _differences(kept: object, given: object, stated: object, prefix: str) -> list[str]:
    """The dotted keys that the config file states (``stated``, its parsed YAML) with a
    value (``given``, validated) other than the model's (``kept``)."""
    if isinstance(kept, dict) and isinstance(stated, dict):
        given = given if isinstance(given, dict) else {}
        return [d for key in stated if key in kept
                for d in _differences(kept[key], given.get(key), stated[key],
                                      f"{prefix}.{key}")]
    return [] if kept == given else [prefix]


def update_config(model: GPModel, given: Config | None, model_path: str | Path,
                  config_path: str | Path | None, stated: object = None) -> Config:
    """The config of an update: the model's, with ``given``'s job settings (``seed``,
    ``sensors`` added to the model's, ``inputs``, ``classify``, ``map``, ``grid``; the
    model's ``map.anchor_origin_m`` unless the file states one).
    ``stated``: the config file's parsed YAML (:func:`gpocc.config.read_config_mapping`):
    only the ``samples`` and ``model`` keys it states are checked against the model's,
    so that a default changed since the model was trained is no conflict (without it,
    every key is checked).

    Raises:
        GpoccError: ``given`` states a ``samples`` or ``model`` key (the kernel, say)
            other than the model's, or changes a sensor the model already holds.
    """
    kept = model.config
    if given is None:
        return kept
    kept_dict, given_dict = config_to_dict(kept), config_to_dict(given)
    stated_dict = stated if isinstance(stated, dict) else given_dict
    for section in MODEL_SECTIONS:
        changed = _differences(kept_dict[section], given_dict[section],
                               stated_dict.get(section) or {}, section)
        if changed:
            raise GpoccError(
                f"{config_path}: key '{changed[0]}' differs from the model {model_path}'s "
                f"({_value(kept_dict, changed[0])!r} there): an update keeps the model's "
                f"samples and model settings; remove the key or train a new model")
    sensors = {s.name: s for s in kept.sensors}
    for i, sensor in enumerate(given.sensors):
        if sensor.name in sensors and sensor != sensors[sensor.name]:
            raise GpoccError(
                f"{config_path}: sensors[{i}] ('{sensor.name}') differs from the sensor of "
                f"that name in the model {model_path}; give it the model's settings "
                f"(`gpocc info {model_path}`) or another name")
    added = tuple(s for s in given.sensors if s.name not in sensors)
    inputs = {e.path: e for e in kept.inputs}
    inputs.update({e.path: e for e in given.inputs})
    map_cfg = given.map
    stated_map = stated_dict.get("map")
    if kept.map.anchor_origin_m is not None and not (
            isinstance(stated_map, dict) and "anchor_origin_m" in stated_map):
        # A pinned anchor lattice is what lets the model's maps and its update's agree.
        map_cfg = dataclasses.replace(map_cfg, anchor_origin_m=kept.map.anchor_origin_m)
    return dataclasses.replace(given, samples=kept.samples, model=kept.model, map=map_cfg,
                               sensors=kept.sensors + added, inputs=tuple(inputs.values()))


def _value(data: dict, dotted: str) -> object:
    for key in dotted.split("."):
        data = data.get(key) if isinstance(data, dict) else None  # type: ignore[assignment]
    return data


def model_growth(model: GPModel) -> tuple[Growth, list[str]]:
    """The model's growth state, or the stand-in of an older file and what it lacks."""
    if model.growth is not None:
        return model.growth, []
    samples_cfg = model.config.samples
    return growth_of_older_model(model.samples, model.input_noise_scale, model.input_noise,
                                 model.inputs, samples_cfg.thin_cell_m,
                                 samples_cfg.min_label_share)


def update_model(model: GPModel, growth: Growth, batches: list[ScanBatch],
                 records: tuple[InputRecord, ...], config: Config,
                 hyperparameters: str = "refined",
                 on_evaluation: Callable[[int], None] | None = None,
                 refine_iterations: int = REFINE_ITERATIONS) -> GPModel:
    """``model`` with the samples of ``batches`` (from the inputs ``records``) added.

    Args:
        model: the model to grow.
        growth: its state (:func:`model_growth`).
        batches: the new logs' scans, read with ``config``.
        records: the new inputs.
        config: from :func:`update_config`.
        hyperparameters: ``refined`` (from the model's values), ``kept`` or
            ``relearned`` (from the config's initial values) on the union; see the
            module docstring.
        on_evaluation: progress of the likelihood evaluations (``refined``,
            ``relearned``).
        refine_iterations: steps of a refinement, at most.

    Model hyperparameters that fit the union worse than the config's initial values
    (:func:`kept_fit`) are learned again; ``training["hyperparameters"]`` says how they
    were found.
    """
    started = time.perf_counter()
    old = growth.pool
    # As in `gpocc train`: the new beams' coverage and the optimiser's import (the
    # classifier's fit needs it) beside the samples; both release the GIL or wait on I/O.
    with ThreadPoolExecutor(2, thread_name_prefix="gpocc-samples-helper") as helper:
        new_coverage = helper.submit(beam_coverage, batches, config)
        optimiser = helper.submit(load_optimiser)
        new = build_pool(batches, config, scan_offset=old.n_scans,
                         sensor_names=old.samples.sensor_names)
        pool = merge_pools(old, new, config)
        samples = finish_samples(pool, config)
        coverage = union_coverage(
            model.coverage if model.coverage is not None
            else sample_coverage(model.samples.means), new_coverage.result())
        optimiser.result()
    calibration = growth.calibration
    training = config.model.training
    if training.uses_beam_points:
        calibration = join_calibration(calibration, calibration_points(
            batches, config, training.calibration_every,
            max_position_std_m=training.calibration_max_position_std_m,
            scan_offset=old.n_scans))
    inputs = model.inputs + tuple(r.path for r in records)
    samples_s = time.perf_counter() - started
    if hyperparameters not in ("refined", "kept", "relearned"):
        raise ValueError(f"hyperparameters must be refined, kept or relearned, "
                         f"not {hyperparameters!r}")
    how = hyperparameters
    worse = "relearned (the model's fitted all logs worse than the initial values)"
    if how == "kept":
        fit = kept_fit(model, samples, config)
        if fit[0] < fit[1]:
            log(f"note: the model's hyperparameters explain all the logs worse than the "
                f"config's initial values do (log marginal likelihood {fit[0]:.1f} < "
                f"{fit[1]:.1f} on the same patches); learning them again")
            how = worse
    if how != "kept":
        # A refinement checks the model's values against the initial ones itself (on
        # the patches it draws anyway) and searches as training does if they fit worse.
        grown = build_model(samples, config, inputs=inputs, on_evaluation=on_evaluation,
                            coverage=coverage, calibration=calibration,
                            warm_start=model if how == "refined" else None,
                            refine_iterations=refine_iterations)
        if how == "refined" and not grown.training["warm_started"]:
            log("note: the model's hyperparameters explain all the logs worse than the "
                "config's initial values do (on the same patches); learned them again")
            how = worse
    else:
        grown = refit_model(samples, config, model, inputs=inputs, coverage=coverage,
                            calibration=calibration)
    return dataclasses.replace(grown, growth=Growth(pool, growth.records + records,
                                                    calibration),
                               training={**grown.training, "hyperparameters": how,
                                         **({"refine_iterations": refine_iterations}
                                            if how == "refined" else {}),
                                         "timings_s": {
                                             "samples": round(samples_s, 3),
                                             "learn": round(time.perf_counter() - started
                                                            - samples_s, 3)}})


def kept_fit(model: GPModel, samples: SampleSet, config: Config) -> tuple[float, float]:
    """Log marginal likelihoods (nats) of the model's hyperparameters and of the config's
    initial values, on the patches that learning on ``samples`` (unscaled) would draw.

    A model learned on a few logs may have found a poor optimum (a kernel far too smooth
    for the walls); on the union it then explains the data worse than the starting point
    of learning, which two likelihood evaluations show at a small share of a learning's
    cost.
    """
    if not config.model.input_noise:
        samples = samples.without_input_noise()
    model_cfg = config.model
    patches = make_patches(samples, model_cfg.effective_training, config.seed)
    initial = make_kernel(model_cfg.kernel, model_cfg.hyperparameters)
    with single_threaded_blas():
        values = [
            -negative_log_likelihood(
                np.append(kernel.theta, math.log(noise)), kernel, patches,
                model_cfg.quadrature_level, with_gradient=False, input_scale=scale,
                backend=backends.choose(model_cfg.backend, model_cfg.diagonal,
                                        model_cfg.covariance_precision),
                scale_part=model_cfg.training.input_noise_scale_part)[0]
            for kernel, noise, scale in (
                (model.kernel, model.noise_variance, model.input_noise_scale),
                (initial, model_cfg.hyperparameters.noise_variance, 1.0))]
    return values[0], values[1]
