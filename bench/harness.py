"""Measuring commands from outside: wall time, CPU time and peak physical memory of a
process and its children, as a user would run them (Linux ``/proc``)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import yaml

from .paths import INTEL_CONFIG, ROOT

GPOCC = [sys.executable, "-m", "gpocc"]
_PAGE = os.sysconf("SC_PAGE_SIZE")

#: Seconds between two memory samples of a measured command. Reading a process's PSS
#: walks its page tables: 4.8 ms for a 480 MB process (statm: 0.06 ms). Sampling a
#: map's three processes of 300-500 MB every 20 ms would take about half a core from the
#: command it measures; every 0.25 s, about 5%.
MEMORY_SAMPLE_S = 0.25


@dataclass(frozen=True)
class Measurement:
    """One command: wall and CPU seconds (children's user + system), peak MiB, stdout."""

    wall_s: float
    cpu_s: float
    peak_mib: float
    stdout: str


def process_tree(pid: int) -> list[int]:
    """``pid`` and all its descendants, parents first. A process that ends meanwhile is
    still listed (its children, if any were left, are not); callers skip what has gone."""
    found, stack = [], [pid]
    while stack:
        p = stack.pop()
        found.append(p)
        try:
            with open(f"/proc/{p}/task/{p}/children") as fh:
                stack.extend(int(c) for c in fh.read().split())
        except OSError:  # it has ended
            pass
    return found


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


def tree_memory(pid: int) -> int:
    """Physical bytes of ``pid`` and all its descendants: their summed PSS. Forked workers
    share the parent's pages until they write to them; summed resident sets would count
    those pages once per process."""
    total = 0
    for p in process_tree(pid):
        try:
            total += _process_memory(p)
        except (FileNotFoundError, ProcessLookupError, PermissionError):  # it has ended
            continue
    return total


def measure(args: list[str]) -> Measurement:
    """Run a command in the repository (its end noticed within 20 ms), sampling its
    process tree's memory every :data:`MEMORY_SAMPLE_S`. A failure stops the suite with
    the command's stderr."""
    before = os.times()
    start = time.perf_counter()
    proc = subprocess.Popen([str(a) for a in args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=ROOT)
    peak = 0
    sampled = -MEMORY_SAMPLE_S
    while proc.poll() is None:
        now = time.perf_counter()
        if now - sampled >= MEMORY_SAMPLE_S:
            peak, sampled = max(peak, tree_memory(proc.pid)), now
        time.sleep(0.02)
    out, err = proc.communicate()
    wall = time.perf_counter() - start
    after = os.times()
    if proc.returncode != 0:
        raise RuntimeError(f"command failed ({proc.returncode}): "
                           f"{' '.join(map(str, args))}\n{err}")
    cpu = (after.children_user - before.children_user) + (after.children_system
                                                          - before.children_system)
    return Measurement(wall, cpu, peak / 2**20, out)


def gpocc(*args: object) -> Measurement:
    """``gpocc ARGS...`` as its own process, measured."""
    return measure([*GPOCC, *map(str, args)])


def write_config(folder: Path, name: str, base: Path = INTEL_CONFIG, **overrides) -> Path:
    """``base`` with dotted-key overrides (``samples.scan_stride=2`` is passed as
    ``**{"samples.scan_stride": 2}``), written to ``folder/name.yaml``."""
    data = yaml.safe_load(base.read_text()) or {}
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


def printed(stdout: str, pattern: str) -> re.Match | None:
    """The first line of ``stdout`` matching ``pattern`` (anchored at a line start)."""
    return re.search(f"^{pattern}", stdout, re.MULTILINE)
