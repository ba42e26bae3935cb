"""``gpocc grid``: inputs -> classic log-odds occupancy grid, written as a map folder."""

from __future__ import annotations

import time

import numpy as np
import typer

from gpocc.baselines.grid import occupancy_grid
from gpocc.commands.baseline import baseline_job, write_baseline
from gpocc.commands.options import (
    Bounds,
    ConfigFile,
    ConfigResolution,
    Force,
    Inputs,
    OutFolder,
)
from gpocc.config import config_to_dict
from gpocc.io.rasters import BERNOULLI_VARIANCE_BAND
from gpocc.progress import log


def grid_command(
    inputs: Inputs,
    config: ConfigFile = None,
    resolution: ConfigResolution = None,
    out: OutFolder = ...,
    bounds: Bounds = None,
    force: Force = False,
) -> None:
    """Build the classic log-odds occupancy grid (the baseline) and write a map folder."""
    job = baseline_job(inputs, config, resolution, bounds, out, force, "the grid")
    spec = job.spec
    log(f"grid: {spec.width} x {spec.height} cells at {spec.resolution} m")
    t0 = time.perf_counter()
    grid = occupancy_grid(job.batches, job.cfg, spec)
    grid_s = time.perf_counter() - t0
    write_baseline(
        job, out, force, "grid", "log-odds occupancy grid", BERNOULLI_VARIANCE_BAND,
        grid.probability.astype(np.float32), grid.variance.astype(np.float32),
        {"probability": "p(occupied) = 1 - 1/(1 + exp(log-odds)), float32",
         "variance": "Bernoulli variance p (1 - p), float32"},
        {"grid": grid_s},
        grid=config_to_dict(job.cfg)["grid"],
        observed_cells=int(grid.observed.sum()),
    )
    typer.echo(f"time: {time.perf_counter() - job.started:.1f} s")
