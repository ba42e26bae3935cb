"""``gpocc train``: inputs -> samples -> learned model file."""

from __future__ import annotations

import dataclasses
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from pathlib import Path

import typer

from gpocc.commands.options import (
    ConfigFile,
    Force,
    InputNoise,
    Inputs,
    Seed,
    Switch,
    TrainScheduler,
    scheduler_errors,
)
from gpocc.config import Config, load_config
from gpocc.gp.bounds import GUIDE_SECTION, values_on_bounds
from gpocc.gp.growth import Growth
from gpocc.gp.model import (
    GPModel,
    build_model,
    kernel_parameters,
    patch_summary,
    save_model,
)
from gpocc.gp.train import load_optimiser
from gpocc.io.atomic import prepare_output
from gpocc.io.inputs import read_inputs
from gpocc.io.records import content_hash, input_records, warn_repeated_content
from gpocc.io.scans import scan_stamps
from gpocc.limits import check_seed
from gpocc.parallel import dask_client
from gpocc.progress import log, progress_bar
from gpocc.samples.beams import build_pool, finish_samples
from gpocc.samples.coverage import beam_coverage
from gpocc.samples.heldout import calibration_points


def train(
    inputs: Inputs,
    out: Path = typer.Option(..., "--out", help="Model file to write (.npz)."),
    config: ConfigFile = None,
    input_noise: InputNoise = None,
    seed: Seed = None,
    scheduler: TrainScheduler = None,
    force: Force = False,
) -> None:
    """Learn a GP occupancy model (hyperparameters and classifier) from robot logs."""
    prepare_output(out, force, folder=False, inputs=[*inputs, config])
    cfg = job_config(config, input_noise, seed)
    started = time.perf_counter()
    model = learn_model(inputs, cfg, scheduler)
    save_model(model, out, force=force)
    echo_model(model, out, time.perf_counter() - started)


def job_config(config: Path | None, input_noise: Switch | None, seed: int | None) -> Config:
    """The config file ``config`` (or the defaults) with the command-line overrides."""
    cfg = load_config(config)
    if input_noise is not None:
        cfg = dataclasses.replace(
            cfg, model=dataclasses.replace(cfg.model, input_noise=input_noise is Switch.on)
        )
    check_seed(seed)
    if seed is not None:
        cfg = dataclasses.replace(cfg, seed=seed)
    return cfg


def learn_model(inputs: list[Path], cfg: Config, scheduler: str | None = None) -> GPModel:
    """Read ``inputs``, build their samples and learn a model; its ``training`` records
    the stages' wall seconds under ``timings_s``. ``scheduler``: the address of a Dask
    cluster that computes the likelihood patches and the classifier's predictions (the
    model is the same as without it)."""
    started = time.perf_counter()
    batches = read_inputs(inputs, cfg)
    # The model records each input's content hash; computed here, before learning, it
    # also tells of a log given twice under two names.
    hashes = [content_hash(p) for p in inputs]
    warn_repeated_content(inputs, hashes, cfg)
    read_s = time.perf_counter() - started
    log(f"read {sum(b.n_scans for b in batches)} scans from {len(inputs)} input(s)")
    # The coverage raster is built beside the samples (both mostly numpy and compiled
    # loops that release the GIL; campus: 1 s less), and the optimiser is imported
    # meanwhile (Intel: 0.1-0.2 s less). The threads have ended before the learner forks
    # its workers: a fork during an import could leave the children its lock.
    with ThreadPoolExecutor(2, thread_name_prefix="gpocc-samples-helper") as helper:
        coverage_of_beams = helper.submit(beam_coverage, batches, cfg)
        optimiser = helper.submit(load_optimiser)
        pool = build_pool(batches, cfg)
        samples = finish_samples(pool, cfg)
        coverage = coverage_of_beams.result()
        optimiser.result()
    training_cfg = cfg.model.training
    calibration = (calibration_points(
        batches, cfg, training_cfg.calibration_every,
        max_position_std_m=training_cfg.calibration_max_position_std_m)
        if training_cfg.uses_beam_points else None)
    samples_s = time.perf_counter() - started - read_s
    log(f"built {len(samples)} samples; learning hyperparameters")
    occupied = int((samples.labels > 0).sum())
    if len(samples) and occupied in (0, len(samples)):
        kind, why = (("free", "no beam hit anything within range") if occupied == 0 else
                     ("occupied", "no beam crossed free space"))
        log(f"warning: every sample is {kind} ({why}): the map can only say {kind}; check "
            "the ranges and the sensors' range_min_m / range_max_m")
    budget = 2 + training_cfg.anneal_maxfun + 2 * training_cfg.lbfgs_maxiter
    with scheduler_errors(), (dask_client(scheduler) if scheduler else nullcontext()) as client, \
            progress_bar(budget, "likelihood evaluations (at most)") as advance:
        model = build_model(samples, cfg, inputs=tuple(str(p) for p in inputs),
                            on_evaluation=advance, coverage=coverage,
                            calibration=calibration, client=client)
    learn_s = time.perf_counter() - started - read_s - samples_s
    on_bounds = values_on_bounds(model)
    for on_bound in on_bounds:
        log(f"warning: {on_bound.message()}: the fit stopped at the bound, not at an optimum")
    if on_bounds:
        log(f"note: what each warning above means and what widening it does: {GUIDE_SECTION}")
    timings = {"read": round(read_s, 3), "samples": round(samples_s, 3),
               "learn": round(learn_s, 3)}
    growth = Growth(pool, input_records(inputs, batches, cfg, hashes), calibration)
    # The scans' time span: a map of this model is stamped with the last scan's time.
    return dataclasses.replace(model, training={**model.training, "timings_s": timings,
                                                "scan_stamps_s": list(scan_stamps(batches))},
                               growth=growth)


def echo_model(model: GPModel, out: Path, seconds: float | None) -> None:
    """The summary of a learned model on stdout; ``seconds``: the command's time line."""
    occupied = int((model.samples.labels > 0).sum())
    params = kernel_parameters(model.kernel)
    typer.echo(f"model: {out}")
    typer.echo(f"samples: {len(model.samples)} ({occupied} occupied, "
               f"{len(model.samples) - occupied} free)")
    typer.echo(f"input noise: {'on' if model.input_noise else 'off'}")
    typer.echo("kernel: " + ", ".join(f"{k}={v}" for k, v in params.items()))
    typer.echo(f"noise_variance: {model.noise_variance:.6g}")
    if model.training.get("hyperparameters") == "kept":  # gpocc update --keep
        typer.echo(f"log marginal likelihood: {model.training['log_marginal_likelihood']:.3f} "
                   "(kept with the hyperparameters: the model's own, on its own patches)")
    else:
        typer.echo(f"log marginal likelihood: {model.training['log_marginal_likelihood']:.3f} "
                   f"(initial {model.training['initial_log_marginal_likelihood']:.3f}"
                   + patch_summary(model.training) + ")")
    if model.input_noise_scale != 1.0:
        part = model.config.model.training.input_noise_scale_part
        typer.echo(f"input noise scale (learned): {model.input_noise_scale:.4g}"
                   + (" (pose part of the input covariances)" if part == "pose" else ""))
    typer.echo(f"classifier: {model.classifier.summary()}; "
               f"{_fitted_on(model.training, model.classifier.temperature)})")
    timings = model.training["timings_s"]
    typer.echo(f"stages: read {timings['read']:.1f} s, samples {timings['samples']:.1f} s, "
               f"hyperparameters+classifier {timings['learn']:.1f} s")
    if seconds is not None:
        typer.echo(f"time: {seconds:.1f} s")


def _fitted_on(training: dict, temperature: float) -> str:
    """What the classifier was fitted on, for the summary line (``temperature``: the
    classifier's; exactly 1 under ``classifier_temperature: beams`` when none was fitted,
    :func:`gpocc.gp.classify.fit_temperature`)."""
    how = ("fitted leaving one scan out" if training.get("classifier_holdout") == "scan"
           else "fitted leaving one sample out")
    beams = []
    if training.get("classifier_offset") == "beams":
        beams.append("offset")
    if (training.get("classifier_temperature") == "beams" and training.get("classifier_points")
            and temperature != 1.0):
        beams.append("temperature")
    if beams:
        how += (f"; {' and '.join(beams)} from {training['classifier_points']} points of "
                "held-out scans")
    return how
