"""``gpocc build``: inputs -> model -> map folder in one process (train, then map).

The same work as ``gpocc train`` followed by ``gpocc map``, with the same model file and
the same map, but the interpreter start, the imports and the compiled kernels' set-up
are paid once instead of twice, and the map's workers start with the compiled kernels
already loaded. The model is kept in the map folder as ``model.npz``, so the map can be
re-sampled later with ``gpocc map OUT/model.npz``.
"""

from __future__ import annotations

import time

import typer

from gpocc.commands.map import (
    check_map_options,
    check_map_size,
    echo_map,
    map_spec,
    warn_if_no_data,
    write_map,
)
from gpocc.commands.options import (
    Bounds,
    ConfigFile,
    Force,
    InputNoise,
    Inputs,
    OutFolder,
    Resolution,
    Scheduler,
    Seed,
    Workers,
)
from gpocc.commands.train import echo_model, job_config, learn_model
from gpocc.gp.model import write_model
from gpocc.gridspec import GridSpec
from gpocc.io.atomic import atomic_directory, prepare_output

#: The model's file name inside the map folder.
MODEL_FILE = "model.npz"


def build(
    inputs: Inputs,
    resolution: Resolution,
    out: OutFolder,
    config: ConfigFile = None,
    input_noise: InputNoise = None,
    seed: Seed = None,
    bounds: Bounds = None,
    workers: Workers = None,
    scheduler: Scheduler = None,
    force: Force = False,
) -> None:
    """Train a model and map it in one run: the map folder, with the model as model.npz."""
    prepare_output(out, force, inputs=[*inputs, config])
    check_map_options(resolution, workers)
    cfg = job_config(config, input_noise, seed)
    what = f"the map of {', '.join(map(str, inputs))}"
    if bounds is not None:  # the map's size is known before training: check it first
        check_map_size(GridSpec.from_bounds(*bounds, resolution), cfg, what, True)
    started = time.perf_counter()
    model = learn_model(inputs, cfg, scheduler)
    model_path = out / MODEL_FILE
    spec = map_spec(model, resolution, bounds, what, configurable=True)
    mapping_started = time.perf_counter()
    with atomic_directory(out, force=force) as tmp:
        # The model file (0.1-0.2 s on Intel, mostly compression, which releases the GIL)
        # is written beside the map's own files, when the workers are done and a core is
        # free: beside the workers it slowed them.
        summary = write_map(model, str(model_path), spec, tmp, workers, scheduler,
                            while_writing=lambda: write_model(model, tmp / MODEL_FILE))
    echo_model(model, model_path, None)
    echo_map(summary, out, resolution, time.perf_counter() - mapping_started)
    warn_if_no_data(summary, model)
    typer.echo(f"total time: {time.perf_counter() - started:.1f} s")
