"""``gpocc grid``: inputs -> classic log-odds occupancy grid, written as a map folder."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import typer

import gpocc
from gpocc.cli import command
from gpocc.config import config_to_dict, load_config
from gpocc.errors import GpoccError
from gpocc.evaluation.grid import default_grid_spec, occupancy_grid
from gpocc.evaluation.grid_folder import write_grid_folder
from gpocc.io.atomic import atomic_directory, atomic_path, prepare_output
from gpocc.io.inputs import read_inputs
from gpocc.limits import check_cells, max_cells
from gpocc.progress import log


@command("grid")
def grid_command(
    inputs: list[Path] = typer.Argument(
        ..., metavar="INPUT", help="Bags, bag folders, .mcap files or CARMEN logs."
    ),
    config: Path | None = typer.Option(None, "--config", help="YAML job config."),
    resolution: float | None = typer.Option(
        None, "--resolution", help="Cell size, metres (default: the config's map.resolution_m)."
    ),
    out: Path = typer.Option(..., "--out", help="Map folder to write."),
    bounds: tuple[float, float, float, float] | None = typer.Option(
        None, "--bounds", metavar="XMIN YMIN XMAX YMAX",
        help="Map area, metres; default: the observed extent plus map.margin_m.",
    ),
    force: bool = typer.Option(False, "--force", help="Replace an existing map folder."),
) -> None:
    """Build the classic log-odds occupancy grid (the baseline) and write a map folder."""
    prepare_output(out, force)
    cfg = load_config(config)
    res = cfg.map.resolution_m if resolution is None else resolution
    if not (res > 0 and math.isfinite(res)):
        raise GpoccError(f"--resolution must be a positive number of metres, got {res}")
    started = time.perf_counter()
    batches = read_inputs(inputs, cfg)
    read_s = time.perf_counter() - started
    n_scans = sum(b.n_scans for b in batches)
    log(f"read {n_scans} scans from {len(inputs)} input(s)")
    spec = default_grid_spec(batches, cfg, res, bounds)
    check_cells(spec.width, spec.height, res, max_cells(cfg.map.max_cells), "the grid")
    log(f"grid: {spec.width} x {spec.height} cells at {res} m")
    t0 = time.perf_counter()
    grid = occupancy_grid(batches, cfg, spec)
    grid_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    with atomic_directory(out, force=force) as tmp:
        counts = write_grid_folder(tmp, grid, cfg)
        write_s = time.perf_counter() - t0
        meta = {
            "gpocc_version": gpocc.__version__,
            "method": "grid",
            "inputs": [str(p) for p in inputs],
            "sensors": [{"name": b.sensor, "source": b.source, "scans": b.n_scans,
                         "beams": b.n_beams} for b in batches],
            "resolution_m": spec.resolution,
            "bounds_m": list(spec.bounds),
            "size_cells": [spec.width, spec.height],
            "epsg": cfg.map.epsg,
            "thresholds": {"occupied": cfg.classify.occupied, "free": cfg.classify.free},
            "grid": config_to_dict(cfg)["grid"],
            "class_counts": counts,
            "observed_cells": int(grid.observed.sum()),
            "timings_s": {"read": round(read_s, 3), "grid": round(grid_s, 3),
                          "write": round(write_s, 3)},
            "layers": {"probability": "p(occupied) = 1 - 1/(1 + exp(log-odds)), float32",
                       "variance": "Bernoulli variance p (1 - p), float32",
                       "class": "uint8: 0 free, 1 occupied, 2 unsure, 255 no data"},
        }
        with atomic_path(tmp / "metadata.json") as path:
            path.write_text(json.dumps(meta, indent=2) + "\n")
    typer.echo(f"grid: {out}")
    typer.echo(f"cells: {spec.width} x {spec.height} at {spec.resolution} m, bounds {spec.bounds}")
    typer.echo(f"classes: {counts['occupied']} occupied, {counts['free']} free, "
               f"{counts['unsure']} unsure")
    typer.echo(f"time: {time.perf_counter() - started:.1f} s")
