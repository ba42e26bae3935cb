"""``gpocc bhm``: inputs -> Bayesian Hilbert map (a baseline), written as a map folder."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import typer

from gpocc.baselines.bhm import fit_bhm, predict_grid, training_points
from gpocc.commands.baseline import baseline_job, write_baseline
from gpocc.commands.options import (
    Bounds,
    ConfigFile,
    ConfigResolution,
    Force,
    Inputs,
    OutFolder,
)
from gpocc.io.rasters import Band
from gpocc.limits import check_cells
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
    resolution: ConfigResolution = None,
    out: OutFolder = ...,
    bounds: Bounds = None,
    force: Force = False,
) -> None:
    """Build a Bayesian Hilbert map (Senanayake and Ramos 2017, a baseline) and write a map
    folder. Settings: the config's bhm section."""
    job = baseline_job(inputs, config, resolution, bounds, out, force, "the map")
    cfg, spec, batches = job.cfg, job.spec, job.batches
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
    write_baseline(
        job, out, force, "bhm", "Bayesian Hilbert map", BHM_VARIANCE_BAND,
        probability, variance,
        {"probability": "p(occupied) = sigmoid(m / sqrt(1 + pi v / 8)), m and v the "
                        "logit's posterior mean and variance, float32",
         "variance": "posterior variance v of the logit w . phi(x), float32"},
        {"fit": fit_s, "predict": predict_s},
        bhm={**dataclasses.asdict(b),
             "inducing_points": [model.grid.nx, model.grid.ny],
             "training_points": model.n_points, "raw_points": model.n_raw,
             "lower_bounds": [float(v) for v in model.posterior.bounds]},
        max_beam_distance_m=limit,
        data_cells=int(np.isfinite(probability).sum()),
    )
    typer.echo(f"time: {time.perf_counter() - job.started:.1f} s")
