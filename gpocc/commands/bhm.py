"""``gpocc bhm``: inputs -> Bayesian Hilbert map (a baseline), written as a map folder."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import typer

from gpocc.baselines.bhm import fit_bhm, predict_grid, training_points
from gpocc.baselines.grid import default_grid_spec
from gpocc.commands.options import Bounds, ConfigFile, Force, Inputs, OutFolder, check_resolution
from gpocc.config import load_config
from gpocc.gp.classify import classify
from gpocc.io.atomic import atomic_directory, prepare_output
from gpocc.io.inputs import read_inputs
from gpocc.io.mapserver import check_map_server_size
from gpocc.io.rasters import Band
from gpocc.io.scans import scan_stamps
from gpocc.limits import check_cells, max_cells
from gpocc.mapping.folder import MapFolder, folder_metadata, write_metadata
from gpocc.mapping.support import Support
from gpocc.progress import log
from gpocc.samples.coverage import beam_coverage

#: The variance layer of a BHM map.
BHM_VARIANCE_BAND = Band("posterior variance of the BHM logit w . phi(x)", "logit^2")

#: Most inducing points (weights) a BHM may have.
MAX_INDUCING_POINTS = 20_000_000

# Cells per group of the nodata mask's distance look-ups (gpocc.mapping.support).
_MASK_GROUP = 16


def bhm_command(
    inputs: Inputs,
    config: ConfigFile = None,
    resolution: float | None = typer.Option(
        None, "--resolution", help="Cell size, metres (default: the config's map.resolution_m)."
    ),
    out: OutFolder = ...,
    bounds: Bounds = None,
    force: Force = False,
) -> None:
    """Build a Bayesian Hilbert map (Senanayake and Ramos 2017, a baseline) and write a map
    folder. Settings: the config's bhm section."""
    prepare_output(out, force, inputs=[*inputs, config])
    cfg = load_config(config)
    res = cfg.map.resolution_m if resolution is None else check_resolution(resolution)
    started = time.perf_counter()
    batches = read_inputs(inputs, cfg)
    read_s = time.perf_counter() - started
    log(f"read {sum(b.n_scans for b in batches)} scans from {len(inputs)} input(s)")
    spec = default_grid_spec(batches, cfg, res, bounds)
    check_cells(spec.width, spec.height, res, max_cells(cfg.map.max_cells), "the map",
                fix="use a coarser --resolution or smaller --bounds")
    check_map_server_size(spec, cfg.map.max_pgm_pixels)  # before any work
    t0 = time.perf_counter()
    points = training_points(batches, cfg)
    b = cfg.bhm
    extent = points.points.max(axis=0) - points.points.min(axis=0)
    check_cells(extent[0] / b.inducing_spacing_m, extent[1] / b.inducing_spacing_m,
                b.inducing_spacing_m, MAX_INDUCING_POINTS, "the BHM's inducing lattice",
                fix="raise bhm.inducing_spacing_m in the config", configurable=False)
    log(f"bhm: {len(points)} training points ({int(points.weights.sum())} before counting "
        f"per {b.sample_cell_m:g} m cell)")
    model = fit_bhm(points, b)
    fit_s = time.perf_counter() - t0
    log(f"bhm: {model.grid.nx} x {model.grid.ny} inducing points, lower bound per EM pass "
        + ", ".join(f"{v:.6g}" for v in model.posterior.bounds))
    t0 = time.perf_counter()
    limit = cfg.map.max_beam_distance_m
    inside = None
    if limit is not None:
        inside = Support(beam_coverage(batches, cfg), limit).mask(spec, _MASK_GROUP)
    probability, variance = predict_grid(model, spec, inside)
    predict_s = time.perf_counter() - t0
    classes = classify(probability, cfg.classify.occupied, cfg.classify.free)
    t0 = time.perf_counter()
    with atomic_directory(out, force=force) as tmp:
        folder = MapFolder(tmp, spec, cfg, bands={"variance": BHM_VARIANCE_BAND},
                           stamp_s=scan_stamps(batches)[1])
        folder.add(0, 0, spec, probability, variance, classes)
        counts = folder.finish("Bayesian Hilbert map")
        write_s = time.perf_counter() - t0
        write_metadata(tmp, folder_metadata(
            "bhm", spec, cfg, counts,
            {"probability": "p(occupied) = sigmoid(m / sqrt(1 + pi v / 8)), m and v the "
                            "logit's posterior mean and variance, float32",
             "variance": "posterior variance v of the logit w . phi(x), float32"},
            {"read": read_s, "fit": fit_s, "predict": predict_s, "write": write_s},
            ros=folder.ros_outputs,
            inputs=[str(p) for p in inputs],
            sensors=[{"name": bt.sensor, "source": bt.source, "scans": bt.n_scans,
                      "beams": bt.n_beams} for bt in batches],
            bhm={**dataclasses.asdict(b),
                 "inducing_points": [model.grid.nx, model.grid.ny],
                 "training_points": model.n_points, "raw_points": model.n_raw,
                 "lower_bounds": [float(v) for v in model.posterior.bounds]},
            max_beam_distance_m=limit,
            data_cells=int(np.isfinite(probability).sum()),
        ))
    typer.echo(f"bhm: {out}")
    typer.echo(f"cells: {spec.width} x {spec.height} at {spec.resolution} m, bounds {spec.bounds}")
    typer.echo(f"classes: {counts['occupied']} occupied, {counts['free']} free, "
               f"{counts['unsure']} unsure")
    typer.echo(f"time: {time.perf_counter() - started:.1f} s")
