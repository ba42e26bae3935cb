"""Turn a CARMEN log into two ROS 2 bags: a clean one and a TF-only one (issue 11).

clean.mcap: /scan and /pose (PoseWithCovarianceStamped, the log's corrected laser poses).
tf/: /scan (frame ``laser``) and TF only, as a real robot records it: the base 0.15 m
behind the laser (``/tf_static`` base_link -> laser), odometry ``odom -> base_link`` 3 ms
before and after each scan, and a localiser's ``map -> odom`` at 2 Hz that grows linearly to
(1.0 m, -0.7 m, 0.2 rad) over the log (the odometry drifts by that much). Mapping the
odometry frame would be badly off; the chain map -> laser gives back the corrected pose.

    python bench/tf_bag_from_carmen.py ../shared/data/carmen/intel.gfs.log OUTDIR
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from gpocc.config import SensorConfig
from gpocc.io.bags import write_bag
from gpocc.io.carmen import read_carmen

MOUNT_X = 0.15
DRIFT = (1.0, -0.7, 0.2)


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack([a[:, 0] + c * b[:, 0] - s * b[:, 1],
                            a[:, 1] + s * b[:, 0] + c * b[:, 1], a[:, 2] + b[:, 2]])


def _inverse(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack([-c * a[:, 0] - s * a[:, 1], s * a[:, 0] - c * a[:, 1], -a[:, 2]])


def main(log: str, out: str) -> None:
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    sensor = SensorConfig(name="intel", range_max_m=40.0,
                          pose_covariance=((0.0009, 0, 0), (0, 0.0009, 0), (0, 0, 7.6154e-5)))
    batch = read_carmen(log, sensor)
    batch = batch.__class__(**{**batch.__dict__, "pose_covariances": np.broadcast_to(
        sensor.pose_covariance_matrix, (batch.n_scans, 3, 3)).copy()})
    write_bag(out_dir / "clean.mcap", [batch], [("/scan", "/pose")], "mcap", force=True)

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    t0, t1 = float(batch.stamps[0]), float(batch.stamps[-1])

    def header(t: float, frame: str) -> object:
        ns = round(t * 1e9)
        return T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
            frame_id=frame)

    def tf(t: float, parent: str, child: str, x: float, y: float, yaw: float) -> object:
        return T["tf2_msgs/msg/TFMessage"](transforms=[T["geometry_msgs/msg/TransformStamped"](
            header=header(t, parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=x, y=y, z=0.0),
                rotation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2),
                                                           w=math.cos(yaw / 2))))])

    def correction(t: np.ndarray) -> np.ndarray:
        return np.asarray(DRIFT)[None] * ((t - t0) / (t1 - t0))[:, None]

    base = _compose(batch.poses, np.array([[-MOUNT_X, 0.0, 0.0]]))
    # The log's scans are 1 s apart (logger stamps): odometry is published 3 ms before
    # and after each scan, at the scan's pose (a 50 Hz stream would need motion between
    # scans the log does not have).
    msgs = []
    for dt in (-0.003, 0.003):
        t_odom = batch.stamps + dt
        odom = _compose(_inverse(correction(t_odom)), base)
        for t, p in zip(t_odom, odom, strict=True):
            if t >= 0:
                msgs.append((t, "/tf", tf(t, "odom", "base_link", *p)))
    for t in np.arange(t0, t1 + 1.0, 0.5):
        c = correction(np.array([t]))[0]
        msgs.append((t, "/tf", tf(t, "map", "odom", *c)))
    static = tf(t0, "base_link", "laser", MOUNT_X, 0.0, 0.0)
    msgs.append((t0, "/tf_static", static))
    inc = float(batch.angles[1] - batch.angles[0])
    for t, r in zip(batch.stamps, batch.ranges, strict=True):
        msgs.append((t, "/scan", T["sensor_msgs/msg/LaserScan"](
            header=header(t, "laser"), angle_min=float(batch.angles[0]),
            angle_max=float(batch.angles[-1]), angle_increment=inc, time_increment=0.0,
            scan_time=0.0, range_min=float(batch.range_min), range_max=float(batch.range_max),
            ranges=np.asarray(r, np.float32), intensities=np.zeros(0, np.float32))))
    msgs.sort(key=lambda m: m[0])
    types = {"/tf": "tf2_msgs/msg/TFMessage", "/tf_static": "tf2_msgs/msg/TFMessage",
             "/scan": "sensor_msgs/msg/LaserScan"}
    bag = out_dir / "tf"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {k: writer.add_connection(k, v, typestore=ts) for k, v in types.items()}
        for t, topic, msg in msgs:
            writer.write(conns[topic], round(t * 1e9), ts.serialize_cdr(msg, types[topic]))
    print(f"{out_dir}/clean.mcap and {bag}: {batch.n_scans} scans")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
