"""``gpocc update``: add new logs to a saved model without reading its old logs."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import typer

from gpocc.commands.options import Force, Inputs, check_at_least
from gpocc.commands.train import echo_model
from gpocc.config import config_from_dict, read_config_mapping
from gpocc.errors import GpoccError
from gpocc.gp.model import load_model, save_model
from gpocc.gp.update import REFINE_ITERATIONS, model_growth, update_config, update_model
from gpocc.io.atomic import prepare_output
from gpocc.io.inputs import read_inputs
from gpocc.io.records import check_new_inputs, content_hash, input_records
from gpocc.io.scans import scan_stamps
from gpocc.progress import log, progress_bar


def update(
    model_path: Path = typer.Argument(..., metavar="MODEL",
                                      help="Model file to add to (.npz from `gpocc train`)."),
    inputs: Inputs = ...,  # type: ignore[assignment]
    out: Path = typer.Option(..., "--out", help="Model file to write (.npz)."),
    config: Path | None = typer.Option(
        None, "--config", help="YAML config for the new logs (sensors, inputs transforms); "
        "its samples and model keys must be the model's. Default: the model's config."),
    relearn: bool = typer.Option(
        False, "--relearn", help="Learn the hyperparameters again on all samples from the "
        "config's initial values, as `gpocc train` does (default: refine the model's "
        "values on all samples by Fisher scoring, without learning's global search)."),
    keep: bool = typer.Option(
        False, "--keep", help="Keep the model's hyperparameters and only refit the "
        "classifier (fastest; they were learned on the old logs' patches alone)."),
    refine_iterations: int | None = typer.Option(
        None, "--refine-iterations",
        help=f"Steps of the refinement, at most, one likelihood evaluation each (L-BFGS-B "
        "iterations for a kernel whose loops give no input-noise-scale derivative); "
        "it stops earlier where the gain still to come is estimated under 0.01 nats. "
        f"Default {REFINE_ITERATIONS}; "
        "not with --relearn or --keep."),
    force: Force = False,
) -> None:
    """Add new logs to a model: their samples join the model's, its hyperparameters are
    refined and the classifier refitted on all of them; the old logs are not read again."""
    if relearn and keep:
        raise GpoccError("--relearn and --keep exclude each other; give one of them")
    if refine_iterations is not None and (relearn or keep):
        raise GpoccError(f"--refine-iterations sets the refinement, which --"
                         f"{'relearn' if relearn else 'keep'} does not run; give one of them")
    if refine_iterations is None:
        refine_iterations = REFINE_ITERATIONS
    check_at_least("--refine-iterations", refine_iterations, 1)
    prepare_output(out, force, folder=False, inputs=[model_path, *inputs, config])
    started = time.perf_counter()
    model = load_model(model_path)
    given, stated = None, None
    if config is not None:
        stated = read_config_mapping(config)
        given = config_from_dict(stated, str(config))
        stated = stated or {}  # an empty file states nothing
    cfg = update_config(model, given, model_path, config, stated)
    growth, lacking = model_growth(model)
    for note in lacking:
        log(f"note: {model_path} (model format of an older gpocc) does not keep {note}")
    # Checked before reading: a repeated log costs nothing.
    hashes = [content_hash(p) for p in inputs]
    check_new_inputs(growth.records, inputs, hashes, str(model_path))
    batches = read_inputs(inputs, cfg)
    read_s = time.perf_counter() - started
    log(f"read {sum(b.n_scans for b in batches)} scans from {len(inputs)} input(s)")
    records = input_records(inputs, batches, cfg, hashes)
    if keep:
        grown = update_model(model, growth, batches, records, cfg, "kept")
    else:
        training = cfg.model.training
        budget = (2 + (training.anneal_maxfun if relearn else 1)
                  + 2 * (training.lbfgs_maxiter if relearn else refine_iterations))
        with progress_bar(budget, "likelihood evaluations (at most)") as advance:
            grown = update_model(model, growth, batches, records, cfg,
                                 "relearned" if relearn else "refined", advance,
                                 refine_iterations)
    grown = dataclasses.replace(grown, training={
        **grown.training,
        "timings_s": {"read": round(read_s, 3), **grown.training["timings_s"]},
        "scan_stamps_s": _span(model.training.get("scan_stamps_s"), scan_stamps(batches)),
        "updates": [*model.training.get("updates", []),
                    {"inputs": [str(p) for p in inputs],
                     "hyperparameters": grown.training["hyperparameters"]}]})
    save_model(grown, out, force=force)
    added = len(grown.samples) - len(model.samples)
    typer.echo(f"added {len(inputs)} input(s), {sum(b.n_scans for b in batches)} scans; "
               f"samples {len(model.samples)} -> {len(grown.samples)} ({added:+d}); "
               f"hyperparameters {grown.training['hyperparameters']}")
    echo_model(grown, out, time.perf_counter() - started)



def _span(old: object, new: tuple[float | None, float | None]) -> list[float | None]:
    """The (first, last) scan stamps of the model's scans and the new ones'; the new
    ones' alone when the model did not record its own."""
    if not (isinstance(old, list) and len(old) == 2
            and all(isinstance(v, int | float) for v in old)):
        return list(new)
    if new[0] is None or new[1] is None:
        return [float(old[0]), float(old[1])]
    return [min(float(old[0]), new[0]), max(float(old[1]), new[1])]
