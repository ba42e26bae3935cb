"""The stamp of a generated page: date, git commit and machine.

Shared by the benchmark suite (``bench.run_bench``) and the accuracy suite
(``bench.experiment``).
"""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _git(*args: str) -> str:
    try:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return ""


def commit() -> str:
    """The short commit hash, with ``+ uncommitted changes`` when tracked files other than
    markdown pages (which change no measurement) differ from it."""
    head = _git("rev-parse", "--short", "HEAD") or "unknown"
    changed = [line for line in _git("status", "--porcelain", "--untracked-files=no")
               .splitlines() if not line.endswith(".md")]
    return f"{head} + uncommitted changes" if changed else head


def machine() -> str:
    """CPU model, cores, memory, OS, Python and numpy with its BLAS, in one line."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next(line.split(":", 1)[1].strip() for line in fh
                       if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    memory = ""
    try:
        with open("/proc/meminfo") as fh:
            kib = next(int(line.split()[1]) for line in fh if line.startswith("MemTotal"))
        memory = f", {kib / 2**20:.0f} GiB memory"
    except (OSError, StopIteration):
        pass
    usable = usable_cores()
    cores = f"{os.cpu_count()} cores" + (f" ({usable} usable)" if usable != os.cpu_count()
                                         else "")
    import numpy as np
    from threadpoolctl import threadpool_info

    # numpy's own BLAS (scipy may load another copy, listed in no fixed order).
    found = [i for i in threadpool_info() if i.get("user_api") == "blas"]
    found.sort(key=lambda i: "numpy" not in str(i.get("filepath", "")))
    blas = (f"{found[0].get('internal_api')} {found[0].get('version')}" if found
            else "unknown BLAS")
    return (f"{cpu} ({platform.machine()}), {cores}{memory}; {platform.system()} "
            f"{platform.release()}, Python {platform.python_version()}, numpy "
            f"{np.__version__} with {blas}")


def load() -> float | None:
    """The 1-minute load average (None where the system gives none)."""
    try:
        return os.getloadavg()[0]
    except OSError:
        return None


def usable_cores() -> int:
    """The cores this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def stamp(when: datetime.datetime | None = None) -> str:
    """``Generated on DATE UTC at commit `HASH` on MACHINE.`` for a page's head."""
    when = when or datetime.datetime.now(datetime.UTC)
    return f"Generated on {when:%Y-%m-%d %H:%M} UTC at commit `{commit()}` on {machine()}."
