"""Time build_samples on all of intel.gfs.log (910 scans x 180 beams).

Run: ``.venv/bin/python bench/bench_samples.py [path/to/intel.gfs.log]``. Prints a table
of scans, samples before and after thinning, and seconds.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

from gpocc.config import Config, SamplesConfig, SensorConfig, replace
from gpocc.io.scans import ScanBatch
from gpocc.samples.beams import build_samples

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
DEFAULT_LOG = DATA / "carmen" / "intel.gfs.log"
NO_RETURN_M = 81.8  # CARMEN's no-return code is 81.83 m in this log


def read_flaser(path: Path, sensor: str) -> ScanBatch:
    """A minimal FLASER parser, used when gpocc.io.inputs is not available."""
    rows = []
    for line in path.read_text().splitlines():
        tokens = line.split()
        if tokens and tokens[0] == "FLASER":
            rows.append(tokens)
    n = int(rows[0][1])
    values = np.array([[float(t) for t in row[2 : 2 + n + 3]] for row in rows])
    ranges = values[:, :n]
    ranges[ranges >= NO_RETURN_M] = np.inf
    poses = values[:, n : n + 3]
    return ScanBatch(
        sensor=sensor,
        source=str(path),
        stamps=np.arange(len(rows), dtype=float),
        angles=-math.pi / 2 + np.arange(n) * math.pi / n,
        ranges=ranges,
        poses=poses,
        pose_covariances=np.zeros((len(rows), 3, 3)),
        range_min=0.0,
        range_max=NO_RETURN_M,
        has_pose_covariance=False,
    )


def main() -> None:
    path = Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT_LOG
    if not path.is_file():
        sys.exit(f"{path}: not found; pass the path to intel.gfs.log")
    t0 = time.perf_counter()
    try:
        from gpocc.io.inputs import read_inputs

        (batch,) = read_inputs([path], Config())
        reader = "gpocc.io.inputs.read_inputs"
    except ImportError:
        batch = read_flaser(path, "intel")
        reader = "the bench's own FLASER parser"
    t_read = time.perf_counter() - t0
    base = Config(sensors=(SensorConfig(name=batch.sensor),))
    print(f"read {batch.n_scans} scans x {batch.n_beams} beams in {t_read:.2f} s with {reader}")
    print(f"{'thin_cell_m':>11} {'scans':>6} {'samples':>10} {'kept':>9} {'seconds':>8}")
    unthinned = None
    for thin in (0.0, 0.15):
        config = replace(base, samples=SamplesConfig(free_spacing_m=0.4, thin_cell_m=thin))
        t0 = time.perf_counter()
        samples = build_samples([batch], config)
        dt = time.perf_counter() - t0
        if thin == 0.0:
            unthinned = len(samples)
        print(f"{thin:>11.2f} {batch.n_scans:>6d} {unthinned:>10d} {len(samples):>9d} {dt:>8.2f}")


if __name__ == "__main__":
    main()
