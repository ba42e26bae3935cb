"""``gpocc grid``: inputs -> classic log-odds occupancy grid, written as a map folder."""

from __future__ import annotations

import time

import numpy as np
import typer

from gpocc.baselines.grid import default_grid_spec, occupancy_grid
from gpocc.commands.options import Bounds, ConfigFile, Force, Inputs, OutFolder, check_resolution
from gpocc.config import config_to_dict, load_config
from gpocc.gp.classify import classify
from gpocc.io.atomic import atomic_directory, prepare_output
from gpocc.io.inputs import read_inputs
from gpocc.io.mapserver import check_map_server_size
from gpocc.io.rasters import BERNOULLI_VARIANCE_BAND
from gpocc.io.scans import scan_stamps
from gpocc.limits import check_cells, max_cells
from gpocc.mapping.folder import MapFolder, folder_metadata, write_metadata
from gpocc.progress import log


def grid_command(
    inputs: Inputs,
    config: ConfigFile = None,
    resolution: float | None = typer.Option(
        None, "--resolution", help="Cell size, metres (default: the config's map.resolution_m)."
    ),
    out: OutFolder = ...,
    bounds: Bounds = None,
    force: Force = False,
) -> None:
    """Build the classic log-odds occupancy grid (the baseline) and write a map folder."""
    prepare_output(out, force, inputs=[*inputs, config])
    cfg = load_config(config)
    res = cfg.map.resolution_m if resolution is None else check_resolution(resolution)
    started = time.perf_counter()
    batches = read_inputs(inputs, cfg)
    read_s = time.perf_counter() - started
    n_scans = sum(b.n_scans for b in batches)
    log(f"read {n_scans} scans from {len(inputs)} input(s)")
    spec = default_grid_spec(batches, cfg, res, bounds)
    check_cells(spec.width, spec.height, res, max_cells(cfg.map.max_cells), "the grid",
                fix="use a coarser --resolution or smaller --bounds")
    check_map_server_size(spec, cfg.map.max_pgm_pixels)  # before any work
    log(f"grid: {spec.width} x {spec.height} cells at {res} m")
    t0 = time.perf_counter()
    grid = occupancy_grid(batches, cfg, spec)
    grid_s = time.perf_counter() - t0
    probability = grid.probability.astype(np.float32)
    variance = grid.variance.astype(np.float32)
    classes = classify(probability, cfg.classify.occupied, cfg.classify.free)
    t0 = time.perf_counter()
    with atomic_directory(out, force=force) as tmp:
        folder = MapFolder(tmp, spec, cfg, bands={"variance": BERNOULLI_VARIANCE_BAND},
                           stamp_s=scan_stamps(batches)[1])
        folder.add(0, 0, spec, probability, variance, classes)
        counts = folder.finish("log-odds occupancy grid")
        write_s = time.perf_counter() - t0
        write_metadata(tmp, folder_metadata(
            "grid", spec, cfg, counts,
            {"probability": "p(occupied) = 1 - 1/(1 + exp(log-odds)), float32",
             "variance": "Bernoulli variance p (1 - p), float32"},
            {"read": read_s, "grid": grid_s, "write": write_s},
            ros=folder.ros_outputs,
            inputs=[str(p) for p in inputs],
            sensors=[{"name": b.sensor, "source": b.source, "scans": b.n_scans,
                      "beams": b.n_beams} for b in batches],
            grid=config_to_dict(cfg)["grid"],
            observed_cells=int(grid.observed.sum()),
        ))
    typer.echo(f"grid: {out}")
    typer.echo(f"cells: {spec.width} x {spec.height} at {spec.resolution} m, bounds {spec.bounds}")
    typer.echo(f"classes: {counts['occupied']} occupied, {counts['free']} free, "
               f"{counts['unsure']} unsure")
    typer.echo(f"time: {time.perf_counter() - started:.1f} s")
