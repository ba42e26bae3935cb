"""Whole commands on real logs: the Intel log against the grid baseline and OctoMap,
back-to-back repeats against OctoMap on both logs, the campus case, and scaling with
data and map size."""

from __future__ import annotations

import importlib.util
import sys

import numpy as np

from .campus import write_campus
from .harness import Measurement, gpocc, measure, printed, stage_times, write_config
from .paths import FREIBURG, FREIBURG_CONFIG, INTEL, INTEL_CONFIG
from .registry import Context, Result, Table, benchmark, require

MEASURED = ("method", "stage", "wall s", "CPU s", "peak MiB", "detail")


def _row(method: str, stage: str, m: Measurement, detail: str = "") -> list[str]:
    return [method, stage, f"{m.wall_s:.1f}", f"{m.cpu_s:.1f}", f"{m.peak_mib:.0f}", detail]


def _octomap_missing() -> str | None:
    if importlib.util.find_spec("pyoctomap") is None:
        return "OctoMap rows left out: pyoctomap is not installed (the `bench` extra, " \
               "which `make bench` installs)"
    return None


def octomap(logs, config, resolution: float) -> Measurement:
    """OctoMap (pyoctomap) built from the same logs with gpocc's reader, as its own
    process (``bench/octomap_build.py``)."""
    return measure([sys.executable, "-m", "bench.octomap_build", "--config", config,
                    "--resolution", str(resolution), *logs])


def _train_and_map(ctx: Context, name: str, config, noise: str = "on",
                   resolution: float = 0.1) -> tuple[Measurement, Measurement]:
    model = ctx.work / f"{name}.npz"
    train = gpocc("train", INTEL, "--config", config, "--out", model, "--input-noise", noise,
                  "--force")
    mapped = gpocc("map", model, "--resolution", resolution, "--out", ctx.work / name,
                   "--force")
    return train, mapped


def _build(ctx: Context, name: str, config, resolution: float = 0.1,
           log=INTEL) -> Measurement:
    return gpocc("build", log, "--config", config, "--resolution", resolution, "--out",
                 ctx.work / name, "--force")


@benchmark("intel", "Intel, 0.1 m, all scans: each method's stages")
def intel(ctx: Context) -> Result:
    """The whole Intel log (910 scans x 180 beams, about 30 x 30 m) mapped at 0.1 m with
    `configs/carmen_intel.yaml`: the log-odds grid, the GP without and with input noise
    (`gpocc train` + `gpocc map`), `gpocc build` (both in one process) and OctoMap on the
    same scans. Each command is its own process; peak memory is the sampled maximum of
    the summed proportional set size (PSS) of the process and its workers."""
    require(INTEL)
    config = write_config(ctx.work, "intel")
    rows, totals = [], {}
    grid = gpocc("grid", INTEL, "--config", config, "--resolution", "0.1", "--out",
                 ctx.work / "intel-grid", "--force")
    rows.append(_row("grid", "grid", grid))
    totals["grid"] = grid.wall_s
    for method, noise in (("gp-no-noise", "off"), ("gp", "on")):
        train, mapped = _train_and_map(ctx, f"intel-{method}", config, noise)
        rows += [_row(method, "train", train, stage_times(train.stdout)),
                 _row(method, "map", mapped, stage_times(mapped.stdout))]
        totals[method] = train.wall_s + mapped.wall_s
    built = _build(ctx, "intel-build", config)
    rows.append(_row("gp (build)", "train + map, one process", built,
                     stage_times(built.stdout)))
    totals["gp (build)"] = built.wall_s
    result = Result()
    no_octomap = _octomap_missing()
    if no_octomap:
        result.notes.append(no_octomap)
    else:
        octo = octomap([INTEL], config, 0.1)
        rows.append(_row("octomap", "build", octo, stage_times(octo.stdout)))
        totals["octomap"] = octo.wall_s
    for method, total in totals.items():
        ratios = [f"{total / totals['grid']:.1f} x grid"]
        if "octomap" in totals:
            ratios.append(f"{total / totals['octomap']:.1f} x OctoMap")
        rows.append([method, "**total**", f"{total:.1f}", "", "", ", ".join(ratios)])
    result.add(Table(MEASURED, rows))
    return result


@benchmark("intel-repeats", "Intel, 0.1 m: `gpocc build` and OctoMap back to back")
def intel_repeats(ctx: Context) -> Result:
    """`gpocc build` on the whole Intel log and OctoMap on the same scans, alternately,
    `--repeats` times (2 in a quick run): one run of each says little on a machine whose
    speed drifts from minute to minute, so the table gives every pair and the medians."""
    return _repeats(ctx, INTEL, "intel")


@benchmark("freiburg-repeats", "Freiburg 079, 0.1 m: `gpocc build` and OctoMap back to back")
def freiburg_repeats(ctx: Context) -> Result:
    """The same on the dense log: the whole Freiburg 079 log (4,791 scans x 360 beams,
    `configs/carmen_freiburg.yaml`), `gpocc build` and OctoMap alternately, `--repeats`
    times (2 in a quick run). OctoMap casts every beam into its tree; gpocc reads every
    beam into samples too, but learns and maps from the thinned samples, which grow with
    the area mapped rather than the beams: the Intel log (910 scans x 180 beams) and this
    one are the sparse and dense ends of the real logs here."""
    return _repeats(ctx, FREIBURG, "freiburg", FREIBURG_CONFIG)


def _repeats(ctx: Context, log, name: str, base=INTEL_CONFIG) -> Result:
    """`gpocc build` of ``log`` (with ``base``'s config) and OctoMap on the same scans,
    alternately, `--repeats` times: every pair and the medians."""
    require(log)
    no_octomap = _octomap_missing()
    config = write_config(ctx.work, name, base)
    repeats = min(ctx.repeats, 2) if ctx.quick else ctx.repeats
    rows, builds, octos = [], [], []
    for run in range(1, repeats + 1):
        built = _build(ctx, f"{name}-repeat", config, log=log)
        builds.append(built.wall_s)
        row = [str(run), f"{built.wall_s:.2f}", f"{built.peak_mib:.0f}"]
        if not no_octomap:
            octo = octomap([log], config, 0.1)
            octos.append(octo.wall_s)
            row += [f"{octo.wall_s:.2f}", f"{built.wall_s / octo.wall_s:.1f}"]
        rows.append(row)
    header = ("run", "build wall s", "build peak MiB")
    median = ["**median**", f"{np.median(builds):.2f}", ""]
    if not no_octomap:
        header += ("OctoMap wall s", "ratio")
        median += [f"{np.median(octos):.2f}", f"{np.median(np.divide(builds, octos)):.1f}"]
    result = Result()
    result.add(Table(header, [*rows, median]))
    if no_octomap:
        result.notes.append(no_octomap)
    return result


def same_rasters(a, b) -> bool:
    """Whether every GeoTIFF under map folders ``a`` and ``b`` holds the same array."""
    from gpocc.io.rasters import read_raster  # GDAL: the COGs use a float predictor

    files = sorted(p.relative_to(a) for p in a.rglob("*.tif"))
    if not files or files != sorted(p.relative_to(b) for p in b.rglob("*.tif")):
        return False
    return all(np.array_equal(read_raster(a / f)[0], read_raster(b / f)[0], equal_nan=True)
               for f in files)


@benchmark("campus", "Campus: five buildings, 0.1 m", in_quick=False)
def campus(ctx: Context) -> Result:
    """A campus-sized job: four rotated and offset copies of the Intel log and one of
    Freiburg 079 on a site of about 166 x 173 m (8,431 scans, `bench/campus.py`), trained,
    mapped with 2 local worker processes and again on a Dask LocalCluster of 2 workers
    (whose output must be identical), built in one process, and OctoMap on the same
    scans. Dask CPU time and memory are the client's only."""
    from dask.distributed import LocalCluster

    require(INTEL, FREIBURG)
    logs, config, scans = write_campus(ctx.work / "campus")
    model = ctx.work / "campus.npz"
    train = gpocc("train", *logs, "--config", config, "--out", model, "--force")
    local_out, dask_out = ctx.work / "campus-map", ctx.work / "campus-map-dask"
    mapped = gpocc("map", model, "--resolution", "0.1", "--out", local_out, "--force",
                   "--workers", "2")
    cells = printed(mapped.stdout, r"cells: (\d+) x (\d+)")
    # Before the Dask cluster: build's samples stage measured after it took up to twice
    # train's, and as long as train's when run alone.
    built = gpocc("build", *logs, "--config", config, "--resolution", "0.1", "--out",
                  ctx.work / "campus-build", "--force", "--workers", "2")
    # Loopback only, dashboard on a free port: nothing leaves this machine.
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0") as cluster:
        on_dask = gpocc("map", model, "--resolution", "0.1", "--out", dask_out, "--force",
                        "--scheduler", cluster.scheduler_address)
    identical = same_rasters(local_out, dask_out)
    total = train.wall_s + mapped.wall_s
    rows = [
        _row("gp", "train", train, stage_times(train.stdout)),
        _row("gp", "map (2 processes)", mapped,
             (f"{cells.group(1)} x {cells.group(2)} cells; " if cells else "")
             + stage_times(mapped.stdout)),
        ["gp", "map (Dask LocalCluster, 2 workers)", f"{on_dask.wall_s:.1f}", "",
         f"{on_dask.peak_mib:.0f}", f"identical output: {'yes' if identical else 'NO'}"],
        ["gp", "**train + map**", f"{total:.1f}", "", "", ""],
        _row("gp", "**build (train + map, one process)**", built, stage_times(built.stdout)),
    ]
    result = Result()
    no_octomap = _octomap_missing()
    if no_octomap:
        result.notes.append(no_octomap)
    else:
        octo = octomap(logs, config, 0.1)
        rows.append(_row("octomap", "build", octo, stage_times(octo.stdout)))
        rows[3][5] = f"{total / octo.wall_s:.1f} x OctoMap"
        rows[4][5] = f"{built.wall_s / octo.wall_s:.1f} x OctoMap; " + rows[4][5]
    result.add(Table(MEASURED, rows), f"{len(logs)} logs, {scans} scans.")
    return result


@benchmark("scaling-data", "Scaling with data (GP with input noise, 0.1 m)", in_quick=False)
def scaling_data(ctx: Context) -> Result:
    """Intel with every 4th, every 2nd and every scan (`samples.scan_stride`), trained and
    mapped at 0.1 m: how training and map time grow with the samples."""
    require(INTEL)
    rows = []
    for stride, label in ((4, "1/4"), (2, "1/2"), (1, "all")):
        cfg = write_config(ctx.work, f"stride{stride}", **{"samples.scan_stride": stride})
        train, mapped = _train_and_map(ctx, f"stride{stride}", cfg)
        samples = printed(train.stdout, r"samples: (\d+)")
        rows.append([label, samples.group(1) if samples else "?", f"{train.wall_s:.1f}",
                     f"{mapped.wall_s:.1f}", f"{max(train.peak_mib, mapped.peak_mib):.0f}"])
    result = Result()
    result.add(Table(("scans", "samples", "train wall s", "map wall s", "peak MiB"), rows))
    return result


@benchmark("scaling-size", "Scaling with map size (GP with input noise, all scans)",
           in_quick=False)
def scaling_size(ctx: Context) -> Result:
    """One Intel model mapped at 0.2, 0.1 and 0.05 m: map time per cell."""
    require(INTEL)
    model = ctx.intel_model()
    rows = []
    for resolution in (0.2, 0.1, 0.05):
        m = gpocc("map", model, "--resolution", resolution, "--out",
                  ctx.work / f"res-{resolution}", "--force")
        cells = printed(m.stdout, r"cells: (\d+) x (\d+)")
        n_cells = int(cells.group(1)) * int(cells.group(2)) if cells else 0
        rows.append([f"{resolution}", f"{n_cells}", f"{m.wall_s:.1f}", f"{m.cpu_s:.1f}",
                     f"{m.peak_mib:.0f}", f"{1e6 * m.wall_s / max(n_cells, 1):.0f}"])
    result = Result()
    result.add(Table(("resolution m", "cells", "map wall s", "CPU s", "peak MiB",
                      "us per cell"), rows))
    return result

