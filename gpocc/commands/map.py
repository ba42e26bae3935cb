"""``gpocc map``: model -> probability, variance and class rasters, map_server, preview."""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated

import typer

from gpocc.commands.options import (
    Bounds,
    Force,
    MapScheduler,
    OutFolder,
    Resolution,
    Workers,
    check_at_least,
    check_resolution,
    scheduler_errors,
)
from gpocc.config import Config
from gpocc.gp.model import GPModel, kernel_parameters, load_model
from gpocc.gridspec import GridSpec
from gpocc.io.atomic import atomic_directory, prepare_output
from gpocc.io.mapserver import check_map_server_size
from gpocc.limits import check_cells, max_cells
from gpocc.mapping.folder import write_metadata
from gpocc.mapping.mapper import (
    MapSummary,
    block_count,
    make_map,
    map_metadata,
    whole_map,
)
from gpocc.parallel import default_workers
from gpocc.progress import debug, log, progress_bar


def map_command(
    model_path: Annotated[Path, typer.Argument(
        metavar="MODEL", help="Model file from `gpocc train`.")],
    resolution: Resolution,
    out: OutFolder,
    bounds: Bounds = None,
    workers: Workers = None,
    scheduler: MapScheduler = None,
    force: Force = False,
) -> None:
    """Sample a trained model at any resolution and write the map folder."""
    prepare_output(out, force)
    check_map_options(resolution, workers)
    model = load_model(model_path)
    spec = map_spec(model, resolution, bounds, f"the map of {model_path}")
    # A folder from `gpocc build` holds its model: mapping into it again (--force) must
    # keep that file, which the new folder replaces the old one with.
    kept = _path_inside(model_path, out)
    started = time.perf_counter()
    with atomic_directory(out, force=force) as tmp:
        if kept is not None:
            (tmp / kept).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(model_path, tmp / kept)
        summary = write_map(model, str(model_path), spec, tmp, workers, scheduler)
    echo_map(summary, out, resolution, time.perf_counter() - started)
    warn_if_no_data(summary, model)


def warn_if_no_data(summary: MapSummary, model: GPModel) -> None:
    """A warning on stderr when every cell of a written map is nodata: the bounds miss
    the data (cells farther than ``map.max_beam_distance_m`` from every beam), which the
    class counts on stdout show only as zeros."""
    if sum(summary.class_counts.values()) > 0:
        return
    x0, y0, x1, y1 = model.extent
    log(f"warning: every cell of the map is nodata: no cell lies within "
        f"map.max_beam_distance_m ({model.config.map.max_beam_distance_m} m) of a beam; "
        f"the samples span x {x0:.1f} .. {x1:.1f} m, y {y0:.1f} .. {y1:.1f} m: "
        f"check --bounds")


def _path_inside(path: Path, folder: Path) -> Path | None:
    """``path`` relative to ``folder`` if it lies inside it, else None."""
    try:
        return path.resolve().relative_to(folder.resolve())
    except ValueError:
        return None


def check_map_options(resolution: float, workers: int | None) -> None:
    """Refuse a bad --resolution or --workers before any work."""
    check_resolution(resolution)
    if workers is not None:
        check_at_least("--workers", workers, 1)


def map_spec(model: GPModel, resolution: float, bounds: tuple[float, ...] | None,
             what: str, configurable: bool = False) -> GridSpec:
    """The raster of a map of ``model``: ``bounds`` or the model's whole map
    (:func:`gpocc.mapping.mapper.whole_map`), checked by :func:`check_map_size`."""
    debug(f"model: {len(model.samples)} samples from sensors "
          f"{', '.join(model.samples.sensor_names) or '(unnamed)'}; kernel "
          f"{kernel_parameters(model.kernel)}, noise variance {model.noise_variance:.6g}")
    if bounds is not None:
        spec = GridSpec.from_bounds(*bounds, resolution)
    else:
        spec = whole_map(model, resolution)
    check_map_size(spec, model.config, what, configurable)
    return spec


def check_map_size(spec: GridSpec, config: Config, what: str, configurable: bool) -> None:
    """Refuse a raster above ``map.max_cells`` or ``map.max_pgm_pixels`` of ``config``;
    ``what`` names the map, ``configurable``: the config is the user's to edit (not one
    embedded in a model file)."""
    check_cells(spec.width, spec.height, spec.resolution, max_cells(config.map.max_cells),
                what, fix="use a coarser --resolution or smaller --bounds",
                configurable=configurable)
    check_map_server_size(spec, config.map.max_pgm_pixels)


def local_workers(workers: int | None) -> int:
    """The map's local processes: ``--workers``, at most the cores this process may use
    (with a note on stderr), or all of them. Anchors are CPU-bound and single-threaded:
    more processes than cores add no speed, and each holds its own neighbour index and
    compiled kernels (``--workers 100000`` started one process per chunk of anchors)."""
    cores = default_workers()
    if workers is None:
        return cores
    if workers > cores:
        log(f"note: --workers {workers} is more than the {cores} core(s) this process may "
            f"use; using {cores}")
        return cores
    return workers


def write_map(model: GPModel, model_name: str, spec: GridSpec, folder: Path,
              workers: int | None, scheduler: str | None,
              while_writing: Callable[[], None] | None = None,
              whole: GridSpec | None = None) -> MapSummary:
    """Map ``model`` over ``spec`` into ``folder`` (private to this run) with its
    metadata, which names the model ``model_name``; ``while_writing()``: other work of
    the caller, done beside the map's own writing; ``whole``: the whole map whose local
    problems to use (:func:`gpocc.mapping.mapper.make_map`)."""
    n_workers = local_workers(workers) if not scheduler else (workers or default_workers())
    total = block_count(model, spec, whole)
    log(f"mapping {spec.width} x {spec.height} cells at {spec.resolution} m in {total} "
        f"blocks ({'dask ' + scheduler if scheduler else f'{n_workers} worker(s)'})")
    with scheduler_errors(), progress_bar(total, "blocks") as advance:
        summary = make_map(model, spec, folder, n_workers, scheduler, advance,
                           while_writing=while_writing, whole=whole)
    write_metadata(folder, map_metadata(model_name, model, summary,
                                        workers=n_workers, scheduler=scheduler))
    return summary


def echo_map(summary: MapSummary, out: Path, resolution: float, seconds: float) -> None:
    """The summary of a written map on stdout."""
    spec = summary.spec
    typer.echo(f"map: {out}")
    typer.echo(f"cells: {spec.width} x {spec.height} at {resolution} m, bounds {spec.bounds}")
    counts = summary.class_counts
    typer.echo(f"classes: {counts['occupied']} occupied, {counts['free']} free, "
               f"{counts['unsure']} unsure")
    stages = ", ".join(f"{k} {v:.1f} s" for k, v in summary.stage_seconds.items())
    typer.echo(f"stages: {stages}")
    typer.echo(f"time: {seconds:.1f} s")
