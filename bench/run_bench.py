"""Benchmark harness: wall time, CPU time and peak memory of each stage on the Intel log.

Run ``make bench`` (or ``.venv/bin/python bench/run_bench.py [--quick]``). Each command
runs as its own process, as a user would run it; peak memory is the sampled maximum of the
summed resident set of the process and its children (map workers included). Prints
markdown tables for docs/benchmarks.md.
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

import yaml

ROOT = Path(__file__).resolve().parents[1]
INTEL = ROOT.parent / "shared" / "data" / "carmen" / "intel.gfs.log"
BASE_CONFIG = ROOT / "configs" / "carmen_intel.yaml"
GPOCC = [sys.executable, "-m", "gpocc"]
_PAGE = os.sysconf("SC_PAGE_SIZE")


@dataclass(frozen=True)
class Measurement:
    wall_s: float
    cpu_s: float
    peak_mib: float
    stdout: str


def _tree_rss(pid: int) -> int:
    """Summed resident bytes of ``pid`` and all its descendants."""
    total = 0
    stack = [pid]
    while stack:
        p = stack.pop()
        try:
            with open(f"/proc/{p}/statm") as fh:
                total += int(fh.read().split()[1]) * _PAGE
            with open(f"/proc/{p}/task/{p}/children") as fh:
                stack.extend(int(c) for c in fh.read().split())
        except (FileNotFoundError, ProcessLookupError, PermissionError):
            continue
    return total


def measure(args: list[str]) -> Measurement:
    """Run a command, sampling its process tree's memory every 20 ms."""
    before = os.times()
    start = time.perf_counter()
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=ROOT)
    peak = 0
    while proc.poll() is None:
        peak = max(peak, _tree_rss(proc.pid))
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
    match = re.search(r"^stages: (.*)$", stdout, re.MULTILINE)
    return match.group(1) if match else ""


def run_method(work: Path, method: str, config: Path, resolution: float) -> list[tuple]:
    """Rows (stage, Measurement, detail) for one method: grid, gp-no-noise or gp."""
    out = work / f"{method}-{config.stem}-{resolution}"
    if method == "grid":
        m = measure([*GPOCC, "grid", str(INTEL), "--config", str(config), "--resolution",
                     str(resolution), "--out", str(out), "--force"])
        return [("grid", m, "")]
    noise = "off" if method == "gp-no-noise" else "on"
    model = work / f"{method}-{config.stem}.npz"
    train = measure([*GPOCC, "train", str(INTEL), "--config", str(config), "--out", str(model),
                     "--input-noise", noise, "--force"])
    mapped = measure([*GPOCC, "map", str(model), "--resolution", str(resolution), "--out",
                      str(out), "--force"])
    return [("train", train, stage_times(train.stdout)), ("map", mapped, "")]


def table(rows: list[list[str]], header: list[str]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="skip the scaling tables")
    args = parser.parse_args()
    if not INTEL.is_file():
        raise SystemExit(f"{INTEL} not found: the benchmark needs ../shared/data/carmen/")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python "
          f"{platform.python_version()}, {platform.platform()}")
    with tempfile.TemporaryDirectory(prefix="gpocc-bench-") as tmp:
        work = Path(tmp)
        base = write_config(work, "intel")
        rows, totals = [], {}
        for method in ("grid", "gp-no-noise", "gp"):
            for stage, m, detail in run_method(work, method, base, 0.1):
                rows.append([method, stage, f"{m.wall_s:.1f}", f"{m.cpu_s:.1f}",
                             f"{m.peak_mib:.0f}", detail])
                totals[method] = totals.get(method, 0.0) + m.wall_s
        for method in ("grid", "gp-no-noise", "gp"):
            rows.append([method, "**total**", f"{totals[method]:.1f}", "", "",
                         f"{totals[method] / totals['grid']:.1f} x grid"])
        print("\n## Intel, 0.1 m, all scans\n")
        print(table(rows, ["method", "stage", "wall s", "CPU s", "peak MiB", "detail"]))
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
