"""Benchmark harness: wall time, CPU time and peak memory of each stage on the Intel log,
against OctoMap on the same scans, and a campus-sized case.

``gpocc build`` (train and map in one process) is measured beside the two commands.
Run ``make bench`` (or ``.venv/bin/python bench/run_bench.py [--quick] [--no-campus]
[--repeats N]``).
Each command runs as its own process, as a user would run it; peak memory is the sampled
maximum of the physical memory of the process and its children (map workers included):
their summed proportional set size (PSS), which counts a page that forked workers share
with their parent once, not once per process. The OctoMap rows
(``bench/octomap_build.py``, pyoctomap from the ``bench`` extra) are measured in the same
run and give the ratio columns. The campus case (``bench/campus.py``) is mapped with
local worker processes and again on a Dask LocalCluster of 2 workers, whose output must
be identical. Prints markdown tables for docs/benchmarks.md. ``GPOCC_CARMEN_DIR``
overrides where the CARMEN logs are (default ``../shared/data/carmen``).
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from campus import write_campus  # noqa: E402
from proctree import process_tree  # noqa: E402

CARMEN = Path(os.environ.get("GPOCC_CARMEN_DIR", ROOT.parent / "shared" / "data" / "carmen"))
INTEL = CARMEN / "intel.gfs.log"
BASE_CONFIG = ROOT / "configs" / "carmen_intel.yaml"
GPOCC = [sys.executable, "-m", "gpocc"]
_PAGE = os.sysconf("SC_PAGE_SIZE")


@dataclass(frozen=True)
class Measurement:
    wall_s: float
    cpu_s: float
    peak_mib: float
    stdout: str


def _process_memory(pid: int) -> int:
    """Proportional resident bytes of one process (PSS: each shared page divided among
    the processes that map it), or its resident set where the kernel gives no PSS
    (Linux before 4.14: then a forked worker's shared pages count once per process)."""
    try:
        with open(f"/proc/{pid}/smaps_rollup") as fh:
            for line in fh:
                if line.startswith("Pss:"):
                    return int(line.split()[1]) * 1024
    except (FileNotFoundError, PermissionError):
        pass
    with open(f"/proc/{pid}/statm") as fh:
        return int(fh.read().split()[1]) * _PAGE


def _tree_memory(pid: int) -> int:
    """Physical bytes of ``pid`` and all its descendants: their summed PSS.

    Forked workers share the parent's pages until they write to them; summing resident
    sets counted those pages once per process (campus training with 2 workers: 1024 MiB
    summed resident sets against 426 MiB PSS at the same instant)."""
    total = 0
    for p in process_tree(pid):
        try:
            total += _process_memory(p)
        except (FileNotFoundError, ProcessLookupError, PermissionError):  # it has ended
            continue
    return total


#: Seconds between two memory samples of a measured command. Reading a process's PSS
#: walks its page tables: 4.8 ms for a 480 MB process (statm: 0.06 ms). Sampling a
#: map's three processes of 300-500 MB every 20 ms would take about half a core from the
#: command it measures; every 0.25 s, about 5%.
MEMORY_SAMPLE_S = 0.25


def measure(args: list[str]) -> Measurement:
    """Run a command (its end noticed within 20 ms), sampling its process tree's memory
    every :data:`MEMORY_SAMPLE_S`."""
    before = os.times()
    start = time.perf_counter()
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=ROOT)
    peak = 0
    sampled = -MEMORY_SAMPLE_S
    while proc.poll() is None:
        now = time.perf_counter()
        if now - sampled >= MEMORY_SAMPLE_S:
            peak, sampled = max(peak, _tree_memory(proc.pid)), now
        time.sleep(0.02)
    out, err = proc.communicate()
    wall = time.perf_counter() - start
    after = os.times()
    if proc.returncode != 0:
        raise SystemExit(f"command failed ({proc.returncode}): {' '.join(args)}\n{err}")
    cpu = (after.children_user - before.children_user) + (after.children_system
                                                          - before.children_system)
    return Measurement(wall, cpu, peak / 2**20, out)


def write_config(folder: Path, name: str, **overrides) -> Path:
    """The base Intel config with dotted-key overrides (e.g. samples.scan_stride=2)."""
    data = yaml.safe_load(BASE_CONFIG.read_text()) or {}
    for dotted, value in overrides.items():
        node = data
        keys = dotted.split(".")
        for key in keys[:-1]:
            node = node.setdefault(key, {})
        node[keys[-1]] = value
    path = folder / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def stage_times(stdout: str) -> str:
    """The ``stages:`` line(s) of a command's stdout, as one (``gpocc build`` prints the
    training's and the map's)."""
    return "; ".join(re.findall(r"^stages: (.*)$", stdout, re.MULTILINE))


def run_method(work: Path, method: str, config: Path, resolution: float) -> list[tuple]:
    """Rows (stage, Measurement, detail) for one method: grid, gp-no-noise or gp."""
    out = work / f"{method}-{config.stem}-{resolution}"
    if method == "grid":
        m = measure([*GPOCC, "grid", str(INTEL), "--config", str(config), "--resolution",
                     str(resolution), "--out", str(out), "--force"])
        return [("grid", m, "")]
    if method == "gp (build)":
        m = measure([*GPOCC, "build", str(INTEL), "--config", str(config), "--resolution",
                     str(resolution), "--out", str(work / f"build-{config.stem}-{resolution}"),
                     "--force"])
        return [("build (train + map, one process)", m, stage_times(m.stdout))]
    noise = "off" if method == "gp-no-noise" else "on"
    model = work / f"{method}-{config.stem}.npz"
    train = measure([*GPOCC, "train", str(INTEL), "--config", str(config), "--out", str(model),
                     "--input-noise", noise, "--force"])
    mapped = measure([*GPOCC, "map", str(model), "--resolution", str(resolution), "--out",
                      str(out), "--force"])
    return [("train", train, stage_times(train.stdout)),
            ("map", mapped, stage_times(mapped.stdout))]


def run_octomap(logs: list[Path], config: Path, resolution: float) -> Measurement:
    """OctoMap (pyoctomap) built from the same logs with gpocc's reader, as its own process."""
    return measure([sys.executable, str(ROOT / "bench" / "octomap_build.py"), "--config",
                    str(config), "--resolution", str(resolution), *map(str, logs)])


def same_rasters(a: Path, b: Path) -> bool:
    """Whether every GeoTIFF under map folders ``a`` and ``b`` holds the same array."""
    from gpocc.io.rasters import read_raster  # GDAL: the COGs use a float predictor

    files = sorted(p.relative_to(a) for p in a.rglob("*.tif"))
    if not files or files != sorted(p.relative_to(b) for p in b.rglob("*.tif")):
        return False
    return all(np.array_equal(read_raster(a / f)[0], read_raster(b / f)[0], equal_nan=True)
               for f in files)


def campus(work: Path) -> None:
    """The campus case: train, map with local processes and on a Dask LocalCluster."""
    from dask.distributed import LocalCluster

    logs, config, scans = write_campus(work / "campus")
    model = work / "campus.npz"
    train = measure([*GPOCC, "train", *map(str, logs), "--config", str(config), "--out",
                     str(model), "--force"])
    local_out, dask_out = work / "campus-map", work / "campus-map-dask"
    mapped = measure([*GPOCC, "map", str(model), "--resolution", "0.1", "--out",
                      str(local_out), "--force", "--workers", "2"])
    cells = re.search(r"^cells: (\d+) x (\d+)", mapped.stdout, re.MULTILINE)
    octo = run_octomap(logs, config, 0.1)
    # Before the Dask cluster: in two runs measured after it, build's samples stage took
    # twice train's (10.4 against 5.0 s; 13.2 against 7.8 s), and as long as train's
    # when run alone.
    built = measure([*GPOCC, "build", *map(str, logs), "--config", str(config), "--resolution",
                     "0.1", "--out", str(work / "campus-build"), "--force", "--workers", "2"])
    # Loopback only, dashboard on a free port: nothing leaves this machine.
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0") as cluster:
        on_dask = measure([*GPOCC, "map", str(model), "--resolution", "0.1", "--out",
                           str(dask_out), "--force", "--scheduler", cluster.scheduler_address])
    identical = same_rasters(local_out, dask_out)
    total = train.wall_s + mapped.wall_s
    rows = [
        ["gp", "train", f"{train.wall_s:.1f}", f"{train.cpu_s:.1f}", f"{train.peak_mib:.0f}",
         stage_times(train.stdout)],
        ["gp", "map (2 processes)", f"{mapped.wall_s:.1f}", f"{mapped.cpu_s:.1f}",
         f"{mapped.peak_mib:.0f}", (f"{cells.group(1)} x {cells.group(2)} cells; " if cells
                                     else "") + stage_times(mapped.stdout)],
        ["gp", "map (Dask LocalCluster, 2 workers)", f"{on_dask.wall_s:.1f}", "",
         f"{on_dask.peak_mib:.0f}", f"identical output: {'yes' if identical else 'NO'}"],
        ["octomap", "build", f"{octo.wall_s:.1f}", f"{octo.cpu_s:.1f}", f"{octo.peak_mib:.0f}",
         stage_times(octo.stdout)],
        ["gp", "**train + map**", f"{total:.1f}", "", "",
         f"{total / octo.wall_s:.1f} x OctoMap"],
        ["gp", "**build (train + map, one process)**", f"{built.wall_s:.1f}",
         f"{built.cpu_s:.1f}", f"{built.peak_mib:.0f}",
         f"{built.wall_s / octo.wall_s:.1f} x OctoMap; " + stage_times(built.stdout)],
    ]
    print(f"\n## Campus: {len(logs)} buildings, {scans} scans, 0.1 m\n")
    print("Dask CPU time and memory are the client's only (the cluster runs in the bench's "
          "own process tree).\n")
    print(table(rows, ["method", "stage", "wall s", "CPU s", "peak MiB", "detail"]))


def table(rows: list[list[str]], header: list[str]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def repeated_build(work: Path, config: Path, repeats: int) -> None:
    """``gpocc build`` on Intel and OctoMap, alternately, ``repeats`` times: one run of each
    says little on a machine whose speed drifts by 20% within minutes, so the table gives
    every pair (measured back to back) and the median."""
    if repeats < 1:
        return
    rows, builds, octos = [], [], []
    for run in range(1, repeats + 1):
        built = run_method(work, "gp (build)", config, 0.1)[0][1]
        octo = run_octomap([INTEL], config, 0.1)
        builds.append(built.wall_s)
        octos.append(octo.wall_s)
        rows.append([str(run), f"{built.wall_s:.2f}", f"{built.peak_mib:.0f}",
                     f"{octo.wall_s:.2f}", f"{built.wall_s / octo.wall_s:.1f}"])
    rows.append(["**median**", f"{np.median(builds):.2f}", "", f"{np.median(octos):.2f}",
                 f"{np.median(np.divide(builds, octos)):.1f}"])
    print(f"\n## Intel, 0.1 m: `gpocc build` and OctoMap, {repeats} pairs back to back\n")
    print(table(rows, ["run", "build wall s", "build peak MiB", "OctoMap wall s",
                       "ratio"]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="skip the scaling tables")
    parser.add_argument("--no-campus", action="store_true", help="skip the campus case")
    parser.add_argument("--campus-only", action="store_true", help="only the campus case")
    parser.add_argument("--repeats", type=int, default=5,
                        help="pairs of Intel `gpocc build` and OctoMap runs (0: none)")
    args = parser.parse_args()
    if not INTEL.is_file():
        raise SystemExit(f"{INTEL} not found: the benchmark needs ../shared/data/carmen/")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python "
          f"{platform.python_version()}, {platform.platform()}")
    with tempfile.TemporaryDirectory(prefix="gpocc-bench-") as tmp:
        work = Path(tmp)
        if args.campus_only:
            campus(work)
            return
        base = write_config(work, "intel")
        rows, totals = [], {}
        for method in ("grid", "gp-no-noise", "gp", "gp (build)"):
            for stage, m, detail in run_method(work, method, base, 0.1):
                rows.append([method, stage, f"{m.wall_s:.1f}", f"{m.cpu_s:.1f}",
                             f"{m.peak_mib:.0f}", detail])
                totals[method] = totals.get(method, 0.0) + m.wall_s
        octo = run_octomap([INTEL], base, 0.1)
        rows.append(["octomap", "build", f"{octo.wall_s:.1f}", f"{octo.cpu_s:.1f}",
                     f"{octo.peak_mib:.0f}", stage_times(octo.stdout)])
        totals["octomap"] = octo.wall_s
        for method in ("grid", "gp-no-noise", "gp", "gp (build)", "octomap"):
            rows.append([method, "**total**", f"{totals[method]:.1f}", "", "",
                         f"{totals[method] / totals['grid']:.1f} x grid, "
                         f"{totals[method] / totals['octomap']:.1f} x OctoMap"])
        print("\n## Intel, 0.1 m, all scans\n")
        print(table(rows, ["method", "stage", "wall s", "CPU s", "peak MiB", "detail"]))
        repeated_build(work, base, args.repeats)
        if not args.no_campus:
            campus(work)
        if args.quick:
            return
        rows = []
        for stride, label in ((4, "1/4"), (2, "1/2"), (1, "all")):
            cfg = write_config(work, f"stride{stride}", **{"samples.scan_stride": stride})
            result = run_method(work, "gp", cfg, 0.1)
            samples = re.search(r"^samples: (\d+)", result[0][1].stdout, re.MULTILINE)
            rows.append([label, samples.group(1) if samples else "?",
                         f"{result[0][1].wall_s:.1f}", f"{result[1][1].wall_s:.1f}",
                         f"{max(r[1].peak_mib for r in result):.0f}"])
        print("\n## Scaling with data (GP with input noise, 0.1 m)\n")
        print(table(rows, ["scans", "samples", "train wall s", "map wall s", "peak MiB"]))
        rows = []
        model = work / "gp-intel.npz"
        for resolution in (0.2, 0.1, 0.05):
            out = work / f"res-{resolution}"
            m = measure([*GPOCC, "map", str(model), "--resolution", str(resolution), "--out",
                         str(out), "--force"])
            cells = re.search(r"^cells: (\d+) x (\d+)", m.stdout, re.MULTILINE)
            n_cells = int(cells.group(1)) * int(cells.group(2)) if cells else 0
            rows.append([f"{resolution}", f"{n_cells}", f"{m.wall_s:.1f}", f"{m.cpu_s:.1f}",
                         f"{m.peak_mib:.0f}", f"{1e6 * m.wall_s / max(n_cells, 1):.0f}"])
        print("\n## Scaling with map size (GP with input noise, all scans)\n")
        print(table(rows, ["resolution m", "cells", "map wall s", "CPU s", "peak MiB",
                           "us per cell"]))


if __name__ == "__main__":
    main()
