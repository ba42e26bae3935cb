"""The OctoMap baseline of ``make bench``: build an OctoMap tree from the same scans.

Run ``.venv/bin/python -m bench.octomap_build --config CONFIG --resolution 0.1 LOG...``
(needs the ``bench`` extra: pyoctomap). The logs are read with gpocc's own reader (the
same read code and time as gpocc's), every scan is inserted as a planar point cloud
(z = 0) from its laser pose with ray casting of the free space, and the tree's leaves are
counted. Inner nodes are updated once at the end (``lazy_eval``), as OctoMap's batch
users do. No-return beams (+inf) are inserted as free rays of ``no_return_free_m`` (as
gpocc's samples do) by passing a point that far with a ``max_range`` just short of it.
CARMEN poses are the laser's pose (mount offset zero), which is what every bench input is.

Prints ``read`` and ``insert`` seconds and the tree size; wall, CPU and peak memory are
measured from outside (``bench/harness.py``), like every other row.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from gpocc.config import load_config
from gpocc.io.inputs import read_inputs


def scan_points(ranges: np.ndarray, angles: np.ndarray, pose: np.ndarray, range_max: float,
                free_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(hits (H, 3), no-return ends (F, 3)) of one scan in the map frame, metres, z = 0."""
    x, y, yaw = pose
    bearing = yaw + angles
    hit = np.isfinite(ranges) & (ranges > 0.0) & (ranges < range_max)
    miss = np.isposinf(ranges) | (np.isfinite(ranges) & (ranges >= range_max))
    out = []
    for mask, dist in ((hit, ranges[hit]), (miss, np.full(int(miss.sum()), free_m))):
        b = bearing[mask]
        out.append(np.column_stack([x + dist * np.cos(b), y + dist * np.sin(b),
                                    np.zeros(b.shape[0])]))
    return out[0], out[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("logs", nargs="+", type=Path)
    parser.add_argument("--config", type=Path, required=True)
    parser.add_argument("--resolution", type=float, default=0.1)
    args = parser.parse_args()
    import pyoctomap  # bench-only dependency (the `bench` extra)

    started = time.perf_counter()
    config = load_config(args.config)
    batches = read_inputs(args.logs, config)
    read_s = time.perf_counter() - started
    sensors = {s.name: s for s in config.sensors}
    tree = pyoctomap.OcTree(args.resolution)
    scans = 0
    for batch in batches:
        sensor = sensors.get(batch.sensor)
        free_m = float(sensor.no_return_free_m) if sensor and sensor.no_return_free_m else 0.0
        for ranges, pose in zip(batch.ranges, batch.poses, strict=True):
            hits, misses = scan_points(ranges, batch.angles, pose, batch.range_max, free_m)
            origin = np.array([pose[0], pose[1], 0.0])
            if hits.shape[0]:
                tree.insertPointCloud(hits, origin, lazy_eval=True)
            if misses.shape[0] and free_m > 0.0:
                # max_range shorter than the points: OctoMap marks the ray free, no hit.
                tree.insertPointCloud(misses, origin, max_range=free_m - 1e-3, lazy_eval=True)
            scans += 1
    tree.updateInnerOccupancy()  # once, as OctoMap's batch users do (lazy_eval above)
    insert_s = time.perf_counter() - started - read_s
    print(f"octomap: {scans} scans, {tree.getNumLeafNodes()} leaves, resolution "
          f"{args.resolution} m")
    print(f"stages: read {read_s:.1f} s, insert {insert_s:.1f} s")


if __name__ == "__main__":
    main()
