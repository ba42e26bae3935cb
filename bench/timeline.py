"""Where a command's wall time goes: cores in use per process over time, with its log lines.

Usage: ``.venv/bin/python -m bench.timeline [--bin SECONDS] -- COMMAND...``, e.g.::

    .venv/bin/python -m bench.timeline -- .venv/bin/gpocc build \\
        ../shared/data/carmen/intel.gfs.log --config configs/carmen_intel.yaml \\
        --resolution 0.1 --out /tmp/intel-map --force

Every 50 ms the CPU time of the command's process tree is read from ``/proc``; each line
of the output covers one bin (0.25 s by default) and gives the cores in use, in all and
per process (the last three digits of its pid), and the command's stderr lines appear, time-
stamped, where they were printed. A stage that runs on one core while the other is idle
shows as ``total 1.0`` with a single process. Linux only.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time

from .harness import process_tree

_TICKS = os.sysconf("SC_CLK_TCK")


def _cpu_seconds(pid: int) -> float | None:
    """User plus system CPU seconds of ``pid``, or None once it has gone."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / _TICKS


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bin", type=float, default=0.25, help="seconds per output line")
    parser.add_argument("command", nargs=argparse.REMAINDER)
    args = parser.parse_args()
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("give the command to run after --")

    started = time.perf_counter()
    proc = subprocess.Popen(command, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL,
                            text=True)
    lines: list[tuple[float, str]] = []

    def read_stderr() -> None:
        for line in proc.stderr:
            lines.append((time.perf_counter() - started, line.rstrip()))

    reader = threading.Thread(target=read_stderr)
    reader.start()
    samples: list[tuple[float, dict[int, float]]] = []
    while proc.poll() is None:
        now = time.perf_counter() - started
        row = {p: c for p in process_tree(proc.pid) if (c := _cpu_seconds(p)) is not None}
        samples.append((now, row))
        time.sleep(0.05)
    reader.join()
    print(f"wall {time.perf_counter() - started:.2f} s, exit status {proc.returncode}")

    pending = list(lines)
    previous: dict[int, float] = {}
    bin_start, used = 0.0, {}
    for now, row in samples:
        for p, c in row.items():
            if p in previous:
                used[p] = used.get(p, 0.0) + c - previous[p]
        previous = row
        if now - bin_start < args.bin:
            continue
        while pending and pending[0][0] <= now:
            at, text = pending.pop(0)
            print(f"   {at:6.2f} | {text[:110]}")
        busy = {p: v / (now - bin_start) for p, v in used.items() if v > 0}
        per_process = " ".join(f"{p % 1000}:{v:.2f}" for p, v in sorted(busy.items()))
        print(f"{bin_start:5.2f}-{now:5.2f} total {sum(busy.values()):4.2f} {per_process}")
        bin_start, used = now, {}
    for at, text in pending:
        print(f"   {at:6.2f} | {text[:110]}")
    sys.exit(proc.returncode)


if __name__ == "__main__":
    main()
