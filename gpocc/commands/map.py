"""``gpocc map``: model -> probability, variance and class rasters, map_server, preview."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from gpocc.commands.options import Bounds, Force, OutFolder, check_at_least, check_resolution
from gpocc.gp.model import kernel_parameters, load_model
from gpocc.gridspec import GridSpec
from gpocc.io.atomic import atomic_directory, prepare_output
from gpocc.limits import check_cells, max_cells
from gpocc.mapping.blocks import block_cells, plan_blocks
from gpocc.mapping.folder import write_metadata
from gpocc.mapping.mapper import default_spec, make_map, map_metadata
from gpocc.parallel import default_workers
from gpocc.progress import debug, log, progress_bar


def map_command(
    model_path: Path = typer.Argument(..., metavar="MODEL", help="Model file from `gpocc train`."),
    resolution: float = typer.Option(..., "--resolution", help="Cell size, metres."),
    out: OutFolder = ...,
    bounds: Bounds = None,
    workers: int | None = typer.Option(
        None, "--workers", help="Local processes (default: all cores)."
    ),
    scheduler: str | None = typer.Option(
        None, "--scheduler", help="Dask scheduler address tcp://HOST:PORT."
    ),
    force: Force = False,
) -> None:
    """Sample a trained model at any resolution and write the map folder."""
    prepare_output(out, force)
    check_resolution(resolution)
    if workers is not None:
        check_at_least("--workers", workers, 1)
    model = load_model(model_path)
    debug(f"model {model_path}: {len(model.samples)} samples from sensors "
          f"{', '.join(model.samples.sensor_names) or '(unnamed)'}; kernel "
          f"{kernel_parameters(model.kernel)}, noise variance {model.noise_variance:.6g}")
    if bounds is not None:
        spec = GridSpec.from_bounds(*bounds, resolution)
    else:
        spec = default_spec(model, resolution, model.config.map.margin_m)
    # The model's embedded config is not the user's to edit here: name the variable.
    check_cells(spec.width, spec.height, resolution,
                max_cells(model.config.map.max_cells), f"the map of {model_path}",
                fix="use a coarser --resolution or smaller --bounds", configurable=False)
    n_workers = workers or default_workers()
    cells = block_cells(model.config.model.block_size_m, resolution)
    total = len(plan_blocks(spec, cells))
    log(f"mapping {spec.width} x {spec.height} cells at {resolution} m in {total} blocks "
        f"({'dask ' + scheduler if scheduler else f'{n_workers} worker(s)'})")
    started = time.perf_counter()
    with atomic_directory(out, force=force) as tmp, progress_bar(total, "blocks") as advance:
        summary = make_map(model, spec, tmp, n_workers, scheduler, advance)
        write_metadata(tmp, map_metadata(str(model_path), model, summary,
                                         workers=n_workers, scheduler=scheduler))
    seconds = time.perf_counter() - started
    typer.echo(f"map: {out}")
    typer.echo(f"cells: {spec.width} x {spec.height} at {resolution} m, bounds {spec.bounds}")
    counts = summary.class_counts
    typer.echo(f"classes: {counts['occupied']} occupied, {counts['free']} free, "
               f"{counts['unsure']} unsure")
    stages = ", ".join(f"{k} {v:.1f} s" for k, v in summary.stage_seconds.items())
    typer.echo(f"stages: {stages}")
    typer.echo(f"time: {seconds:.1f} s")
