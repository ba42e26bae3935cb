"""Time the 3-D lidar projection against building the samples of the scans it gives.

Registered as the benchmark ``cloud-projection`` (``python -m bench.run_bench --only
cloud-projection``). For lidars of 16 to 128 rings at 10 and 20 Hz (columns per turn as
Velodyne / Ouster drivers give them), a robot drives a circle in a 20 x 14 m room with a
2.6 m ceiling;
each cloud is packed as an organised float32 PointCloud2 (x, y, z, intensity, t, ring;
a tenth of the points no return) and goes through what ``gpocc`` does per message:
:meth:`gpocc.io.cloudread.CloudCollector.add` (decode, 3-D TF into the base frame,
levelling, height band, bearing bins). Then the scans are posed
(:func:`gpocc.io.laserpose.assemble`) and :func:`gpocc.samples.beams.build_samples`
turns them into training samples with the default config. One row per lidar: points per
second, projection seconds, samples seconds, and their ratio, in wall time and in this
process's CPU time (steadier on a shared machine).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from gpocc.config import Config, SensorConfig
from gpocc.io.cloudread import CloudCollector
from gpocc.io.laserpose import assemble
from gpocc.io.tf import Edge, TfBuffer
from gpocc.samples.beams import build_samples

from .registry import Context, Result, Table, benchmark

LIDARS = [  # (name, rings, columns, Hz, vertical field of view in degrees, pitch degrees)
    ("VLP-16 10 Hz", 16, 1800, 10.0, (-15.0, 15.0), 0.0),
    ("VLP-16 20 Hz", 16, 900, 20.0, (-15.0, 15.0), 0.0),
    ("OS1-32 10 Hz", 32, 1024, 10.0, (-22.5, 22.5), 0.0),
    ("OS1-64 10 Hz", 64, 2048, 10.0, (-22.5, 22.5), 0.0),
    ("OS1-128 10 Hz", 128, 1024, 10.0, (-22.5, 22.5), 0.0),
    ("OS1-128 20 Hz", 128, 512, 20.0, (-22.5, 22.5), 0.0),
    # A mount pitched 10 degrees down: every point's height needs the whole rotation row.
    ("VLP-16 10 Hz pitched 10 deg", 16, 1800, 10.0, (-15.0, 15.0), 10.0),
    ("OS1-128 10 Hz pitched 10 deg", 128, 1024, 10.0, (-22.5, 22.5), 10.0),
    ("OS1-128 20 Hz pitched 10 deg", 128, 512, 20.0, (-22.5, 22.5), 10.0),
]
HALF = (10.0, 7.0)  # the room's half sizes, metres
CEILING, HEIGHT = 2.6, 0.5


def room_ranges(origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(N,) distance along unit ``dirs`` (N, 3) from ``origin`` (3,) to the box room."""
    with np.errstate(divide="ignore", invalid="ignore"):
        walls = [np.where(dirs[:, i] > 0, (HALF[i] - origin[i]) / dirs[:, i],
                          (-HALF[i] - origin[i]) / dirs[:, i]) for i in range(2)]
        floor = np.where(dirs[:, 2] < 0, -origin[2] / dirs[:, 2], np.inf)
        ceiling = np.where(dirs[:, 2] > 0, (CEILING - origin[2]) / dirs[:, 2], np.inf)
    return np.minimum.reduce([np.abs(walls[0]), np.abs(walls[1]), floor, ceiling])


def pitch_matrix(pitch: float) -> np.ndarray:
    """(3, 3) base <- lidar of a mount pitched ``pitch`` degrees (positive: nose down)."""
    c, s = math.cos(math.radians(pitch)), math.sin(math.radians(pitch))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def message(rings: int, cols: int, fov: tuple[float, float], pose: np.ndarray,
            rng: np.random.Generator, pitch: float = 0.0) -> SimpleNamespace:
    el = np.radians(np.linspace(*fov, rings))[:, None]
    az = np.linspace(-math.pi, math.pi, cols, endpoint=False)[None, :]
    local = np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                         np.sin(el)), -1).reshape(-1, 3)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    world = local @ pitch_matrix(pitch).T @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])
    r = room_ranges(np.array([pose[0], pose[1], HEIGHT]), world)
    r[rng.random(r.size) < 0.1] = np.nan
    dt = np.dtype({"names": ["x", "y", "z", "intensity", "t", "ring"],
                   "formats": ["<f4", "<f4", "<f4", "<f4", "<u4", "<u2"],
                   "offsets": [0, 4, 8, 16, 20, 24], "itemsize": 32})
    arr = np.zeros(r.size, dt)
    arr["x"], arr["y"], arr["z"] = (local * r[:, None]).T
    arr["ring"] = np.repeat(np.arange(rings), cols)
    fields = [SimpleNamespace(name=n, offset=o, datatype=d, count=1) for n, o, d in
              (("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7), ("t", 20, 6),
               ("ring", 24, 4))]
    return SimpleNamespace(header=SimpleNamespace(frame_id="lidar"), height=rings, width=cols,
                           fields=fields, is_bigendian=False, point_step=32,
                           row_step=32 * cols, data=np.frombuffer(arr.tobytes(), np.uint8))


def tf_for(stamps: np.ndarray, poses: np.ndarray, pitch: float = 0.0) -> TfBuffer:
    q = np.column_stack([np.zeros((stamps.size, 2)), np.sin(poses[:, 2] / 2),
                         np.cos(poses[:, 2] / 2)])
    move = Edge("map", "base_footprint", False, "/tf", stamps,
                np.column_stack([poses[:, :2], np.zeros(stamps.size)]), q)
    mount = Edge("base_footprint", "lidar", True, "/tf_static", np.zeros(1),
                 np.array([[0.1, 0.0, HEIGHT]]),
                 np.array([[0.0, math.sin(math.radians(pitch) / 2), 0.0,
                            math.cos(math.radians(pitch) / 2)]]))
    return TfBuffer({"base_footprint": move, "lidar": mount})


def run(name: str, rings: int, cols: int, hz: float, fov: tuple[float, float],
        pitch: float, seconds: float) -> list[str]:
    rng = np.random.default_rng(0)
    stamps = np.arange(0.0, seconds, 1.0 / hz)
    w = 2 * math.pi / 40.0
    poses = np.column_stack([4 * np.cos(w * stamps), 4 * np.sin(w * stamps),
                             w * stamps + math.pi / 2])
    tf_stamps = np.arange(0.0, seconds + 0.05, 0.02)
    tf_poses = np.column_stack([4 * np.cos(w * tf_stamps), 4 * np.sin(w * tf_stamps),
                                w * tf_stamps + math.pi / 2])
    sensor = SensorConfig(name="lidar", scan_topic="/points", pose_topic="/tf")
    collector = CloudCollector(Path("bench"), sensor, tf_for(tf_stamps, tf_poses, pitch))
    msgs = [message(rings, cols, fov, p, rng, pitch) for p in poses]
    t0, c0 = time.perf_counter(), time.process_time()
    for t, msg in zip(stamps, msgs, strict=True):
        collector.add(msg, float(t))
    scans, tf, resolved, _ = collector.resolved()
    project_s, project_cpu = time.perf_counter() - t0, time.process_time() - c0
    batch = assemble(Path("bench"), resolved, scans, tf, None)
    from dataclasses import replace

    batch = replace(batch, sensor_config=resolved)
    t0, c0 = time.perf_counter(), time.process_time()
    samples = build_samples([batch], Config())
    samples_s, samples_cpu = time.perf_counter() - t0, time.process_time() - c0
    return [name, f"{rings * cols * hz / 1e3:.0f} k", f"{stamps.size} x {batch.n_beams}",
            f"{project_s:.2f}", f"{samples_s:.2f}", f"{project_s / samples_s:.2f}",
            f"{project_cpu:.2f}", f"{samples_cpu:.2f}", f"{project_cpu / samples_cpu:.2f}",
            str(len(samples))]


@benchmark("cloud-projection", "3-D lidar projection against building samples")
def cloud_projection(ctx: Context) -> Result:
    """PointCloud2 messages of 16- to 128-ring lidars at 10 and 20 Hz, mounted level and
    pitched 10 degrees down (a robot circling a 20 x 14 m room) projected into planar
    scans (decode, 3-D TF, levelling, height band, bearing bins), against building the
    training samples of those scans: 10 s of data per lidar (2 s, and the 16- and 64-ring
    and the pitched 128-ring lidars only, in a quick run)."""
    seconds = 2.0 if ctx.quick else 10.0
    lidars = [LIDARS[0], LIDARS[3], LIDARS[7]] if ctx.quick else LIDARS
    result = Result()
    result.add(Table(("lidar", "points/s", "scans x bins", "projection s", "samples s",
                      "ratio", "projection CPU s", "samples CPU s", "CPU ratio", "samples"),
                     [run(*spec, seconds=seconds) for spec in lidars]))
    return result
