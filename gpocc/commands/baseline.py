"""What the baseline commands (``gpocc grid``, ``gpocc bhm``) share: the job (config,
inputs read, the raster laid out and checked before any work) and the map folder of one
whole-map set of layers."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import typer

from gpocc.baselines.grid import default_grid_spec
from gpocc.commands.options import check_resolution
from gpocc.config import Config, load_config
from gpocc.gp.classify import classify
from gpocc.gridspec import GridSpec
from gpocc.io.atomic import atomic_directory, prepare_output
from gpocc.io.inputs import read_inputs
from gpocc.io.mapserver import check_map_server_size
from gpocc.io.rasters import Band
from gpocc.io.scans import ScanBatch, scan_stamps
from gpocc.limits import check_cells, max_cells
from gpocc.mapping.folder import MapFolder, folder_metadata, write_metadata
from gpocc.progress import log


@dataclass(frozen=True)
class BaselineJob:
    """A baseline command's inputs: the config, the scans read, the map's raster, and
    ``started`` / ``read_s`` (``time.perf_counter`` seconds) for its time lines."""

    inputs: tuple[Path, ...]
    cfg: Config
    batches: list[ScanBatch]
    spec: GridSpec
    started: float
    read_s: float


def baseline_job(inputs: list[Path], config: Path | None, resolution: float | None,
                 bounds: tuple[float, float, float, float] | None, out: Path, force: bool,
                 what: str) -> BaselineJob:
    """Claim ``out``, read the config and ``inputs`` and lay out the map's raster
    (``what``: its name in the size error), checked against the cell and PGM limits
    before any work."""
    prepare_output(out, force, inputs=[*inputs, config])
    cfg = load_config(config)
    res = cfg.map.resolution_m if resolution is None else check_resolution(resolution)
    started = time.perf_counter()
    batches = read_inputs(inputs, cfg)
    read_s = time.perf_counter() - started
    log(f"read {sum(b.n_scans for b in batches)} scans from {len(inputs)} input(s)")
    spec = default_grid_spec(batches, cfg, res, bounds)
    check_cells(spec.width, spec.height, res, max_cells(cfg.map.max_cells), what,
                fix="use a coarser --resolution or smaller --bounds")
    check_map_server_size(spec, cfg.map.max_pgm_pixels)
    return BaselineJob(tuple(inputs), cfg, batches, spec, started, read_s)


def write_baseline(job: BaselineJob, out: Path, force: bool, method: str, title: str,
                   variance_band: Band, probability: np.ndarray, variance: np.ndarray,
                   layers: dict[str, str], timings: dict[str, float], **extra: object,
                   ) -> dict[str, int]:
    """Write the map folder of one whole-map layer set (probability and variance (H, W)
    float32, NaN no data; classes from the config's thresholds) atomically at ``out``;
    ``layers`` describe the layers and ``extra`` the method in ``metadata.json``, whose
    timings gain the write. Returns the class counts."""
    cfg, spec, batches = job.cfg, job.spec, job.batches
    classes = classify(probability, cfg.classify.occupied, cfg.classify.free)
    t0 = time.perf_counter()
    with atomic_directory(out, force=force) as tmp:
        folder = MapFolder(tmp, spec, cfg, bands={"variance": variance_band},
                           stamp_s=scan_stamps(batches)[1])
        folder.add(0, 0, spec, probability, variance, classes)
        counts = folder.finish(title)
        write_metadata(tmp, folder_metadata(
            method, spec, cfg, counts, layers,
            {"read": job.read_s, **timings, "write": time.perf_counter() - t0},
            ros=folder.ros_outputs,
            inputs=[str(p) for p in job.inputs],
            sensors=[{"name": b.sensor, "source": b.source, "scans": b.n_scans,
                      "beams": b.n_beams} for b in batches],
            **extra,
        ))
    typer.echo(f"{method}: {out}")
    typer.echo(f"cells: {spec.width} x {spec.height} at {spec.resolution} m, bounds {spec.bounds}")
    typer.echo(f"classes: {counts['occupied']} occupied, {counts['free']} free, "
               f"{counts['unsure']} unsure")
    if not np.isfinite(probability).any():  # as gpocc map warns: the bounds miss the data
        log(f"warning: every cell of the map is nodata: no beam reaches it; check --bounds "
            f"against the data's extent ({_scans_extent(batches)})")
    return counts


def _scans_extent(batches: list[ScanBatch]) -> str:
    """``x .. , y .. m`` of the scans' poses, for a message."""
    poses = np.concatenate([b.poses[:, :2] for b in batches if b.n_scans])
    (x0, y0), (x1, y1) = poses.min(axis=0), poses.max(axis=0)
    return f"the robot drove x {x0:.1f} .. {x1:.1f} m, y {y0:.1f} .. {y1:.1f} m"
