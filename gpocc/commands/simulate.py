"""``gpocc simulate``: the two-robot experiment as a bag, its ground truth and a config."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import typer
import yaml

import gpocc
from gpocc.commands.options import Force, check_resolution
from gpocc.constants import FREE, NO_DATA, OCCUPIED, SIMULATION_FILE
from gpocc.errors import GpoccError
from gpocc.evaluation.simulate import (
    PoseNoise,
    Simulation,
    sim_config,
    simulate,
    truth_raster,
    truth_spec,
)
from gpocc.evaluation.world import WORLD_NAMES, is_world_name, make_world
from gpocc.gridspec import GridSpec
from gpocc.io.atomic import atomic_directory, atomic_path, prepare_output
from gpocc.io.bags import write_bag
from gpocc.io.rasters import TRUTH_BAND, write_geotiff
from gpocc.limits import check_cells, check_seed, max_cells
from gpocc.progress import log

_CONFIG_HEADER = """\
# gpocc config for a simulated two-robot log (written by `gpocc simulate`).
# Each sensor's noise settings are exactly those the simulator used; the pose
# messages in sim.mcap carry the simulated pose covariance. Use it as:
#   gpocc train sim.mcap --config sim.yaml --out model.npz
"""


def _metadata(sim: Simulation, truth_spec: GridSpec, truth_counts: dict[str, int],
              seconds: float) -> dict:
    runs = []
    for run in sim.runs:
        p = run.platform
        runs.append({
            "name": p.name,
            "scan_topic": p.scan_topic,
            "pose_topic": p.pose_topic,
            "speed_m_s": p.speed_m_s,
            "scan_rate_hz": p.scan_rate_hz,
            "max_range_m": p.max_range_m,
            "range_min_m": p.range_min_m,
            "range_variance_m2": p.range_variance_m2,
            "bearing_variance_deg2": p.bearing_variance_deg2,
            "beams": p.n_beams,
            "fov_deg": p.fov_deg,
            "route_length_m": round(run.route_length_m, 3),
            "duration_s": round(run.duration_s, 3),
            "scans": run.n_scans,
            "pose_covariance": run.pose_covariance.tolist(),
        })
    return {
        "gpocc_version": gpocc.__version__,
        "world": sim.world.name,
        "world_description": sim.world.description,
        "seed": sim.seed,
        "pose_noise": {"sigma_xy_m": sim.pose_noise.sigma_xy_m,
                       "sigma_yaw_deg": sim.pose_noise.sigma_yaw_deg},
        "robots": runs,
        "truth": {"resolution_m": truth_spec.resolution, "bounds_m": list(truth_spec.bounds),
                  "cells": truth_counts,
                  "labels": "uint8: 1 occupied, 0 free, 255 no data (never observed)"},
        "timings_s": {"simulate": round(seconds, 3)},
    }


def simulate_command(
    out: Path = typer.Option(
        ..., "--out", help="Folder to write: sim.mcap (topics /robot1/scan, /robot1/pose, "
        "/robot2/scan, /robot2/pose), truth.tif (1 occupied, 0 free, 255 never observed), "
        "sim.yaml (the matching config) and simulation.json."
    ),
    seed: int = typer.Option(0, "--seed", help="Random seed of all noise."),
    world: str = typer.Option(
        "default", "--world",
        help=f"Ground-truth world: {', '.join(WORLD_NAMES)}, grown-<seed> (a random "
        f"corridor building grown from that seed), or a building of another generator: "
        f"offices-<seed>, hall-<seed>, clutter-<seed> (platform noise drawn around Table "
        f"I's from the seed).",
    ),
    pose_noise: tuple[float, float] | None = typer.Option(
        None, "--pose-noise", metavar="SIGMA_XY SIGMA_YAW_DEG",
        help="Localisation error: x/y standard deviation (m) and yaw (deg); default none.",
    ),
    resolution: float = typer.Option(0.1, "--resolution", help="Truth raster cell size, m."),
    force: Force = False,
) -> None:
    """Simulate the two-robot experiment: a slow accurate and a fast noisy robot."""
    prepare_output(out, force)
    if not is_world_name(world):
        raise GpoccError(f"--world: unknown world {world!r}; choose one of: "
                         f"{', '.join(WORLD_NAMES)}, grown-<seed>, offices-<seed>, "
                         f"hall-<seed> or clutter-<seed>")
    check_resolution(resolution)
    if pose_noise is not None and not all(v >= 0 and math.isfinite(v) for v in pose_noise):
        raise GpoccError(f"--pose-noise needs two non-negative numbers (SIGMA_XY metres, "
                         f"SIGMA_YAW degrees), got {pose_noise[0]} {pose_noise[1]}")
    check_seed(seed)
    truth = truth_spec(make_world(world), resolution)
    check_cells(truth.width, truth.height, resolution, max_cells(), "the truth raster",
                fix="use a coarser --resolution")
    noise = PoseNoise(*pose_noise) if pose_noise is not None else PoseNoise()
    started = time.perf_counter()
    sim = simulate(world, seed=seed, pose_noise=noise)
    labels, spec = truth_raster(sim.world, sim.runs, resolution)
    seconds = time.perf_counter() - started
    for run in sim.runs:
        log(f"{run.platform.name}: {run.n_scans} scans of {run.platform.n_beams} beams")
    counts = {"occupied": int((labels == OCCUPIED).sum()), "free": int((labels == FREE).sum()),
              "no_data": int((labels == NO_DATA).sum())}
    with atomic_directory(out, force=force) as tmp:
        batches = [run.batch(source=str(out / "sim.mcap")) for run in sim.runs]
        topics = [(run.platform.scan_topic, run.platform.pose_topic) for run in sim.runs]
        write_bag(tmp / "sim.mcap", batches, topics, "mcap")
        write_geotiff(tmp / "truth.tif", labels, spec, nodata=NO_DATA, band=TRUTH_BAND)
        with atomic_path(tmp / "sim.yaml") as path:
            path.write_text(_CONFIG_HEADER + yaml.safe_dump(sim_config(sim, resolution),
                                                            sort_keys=False))
        with atomic_path(tmp / SIMULATION_FILE) as path:
            path.write_text(json.dumps(_metadata(sim, spec, counts, seconds), indent=2) + "\n")
    typer.echo(f"simulation: {out}")
    typer.echo(f"world: {sim.world.name} ({sim.world.description}), seed {seed}")
    for run in sim.runs:
        typer.echo(f"{run.platform.name}: {run.n_scans} scans on {run.platform.scan_topic}")
    typer.echo(f"truth: {counts['occupied']} occupied, {counts['free']} free cells at "
               f"{resolution} m")
