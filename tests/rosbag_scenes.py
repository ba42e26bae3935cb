"""Realistic robot bags for the TF / pose-source tests, written with rosbags directly.

A robot drives a smooth route of the simulated default world; its laser scans the world
from the true laser pose. Bags hold what real recordings hold: ``/tf`` (map -> odom from a
localiser, odom -> base_footprint from odometry at 50 Hz), ``/tf_static`` (base_footprint
-> base_link -> laser with 3-D offsets), optionally ``/amcl_pose`` at AMCL's
motion-triggered cadence and ``/odom`` with "do not trust" covariances. Independent of
gpocc's own bag writer: every message is built here from the typestore.
"""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline

from gpocc.evaluation.world import make_world

WORLD = make_world("default")
T0 = 1_700_000_000.0


def quat(roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> tuple[float, ...]:
    """ZYX Euler angles to a quaternion (x, y, z, w)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy)


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SE(2) ``a (+) b`` for (N, 3) or (3,) poses."""
    a, b = np.atleast_2d(a), np.atleast_2d(b)
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack([a[:, 0] + c * b[:, 0] - s * b[:, 1],
                            a[:, 1] + s * b[:, 0] + c * b[:, 1],
                            np.angle(np.exp(1j * (a[:, 2] + b[:, 2])))])


def inverse(a: np.ndarray) -> np.ndarray:
    a = np.atleast_2d(a)
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack([-c * a[:, 0] - s * a[:, 1], s * a[:, 0] - c * a[:, 1], -a[:, 2]])


class Route:
    """A smooth path (cubic spline through route 0's waypoints) at constant speed."""

    def __init__(self, speed: float, route: int = 0, offset: tuple[float, float] = (0, 0)):
        pts = WORLD.routes[route][:6] + np.asarray(offset)
        d = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        self.spline = CubicSpline(d, pts, bc_type="natural")
        self.speed = speed
        self.length = d[-1]

    def base(self, t: np.ndarray) -> np.ndarray:
        """(N, 3) true base pose at times ``t`` (seconds after T0)."""
        s = np.clip(self.speed * np.asarray(t, float), 0, self.length)
        xy = self.spline(s)
        dx, dy = self.spline(s, 1).T
        return np.column_stack([xy, np.arctan2(dy, dx)])


@dataclass
class Laser:
    """A laser on the base: topic, frame, SE(2) mount, 3-D extras, beams."""

    topic: str
    frame: str
    mount: tuple[float, float, float] = (0.25, 0.05, 0.1)   # x, y, yaw on base_footprint
    upside_down: bool = False
    pitch: float = 0.0      # rad, of the mount (the simulated scans stay level)
    n_beams: int = 90
    max_range: float = 15.0

    @property
    def angles(self) -> np.ndarray:
        return np.linspace(-2.0, 2.0, self.n_beams)


@dataclass
class Robot:
    """One robot's truth and what its bag topics carry."""

    route: Route
    lasers: list[Laser]
    prefix: str = ""             # frame prefix ("robot1/") and topic namespace
    duration: float = 12.0
    scan_rate: float = 10.0
    drift: tuple[float, float, float] = (0.6, -0.4, 0.15)  # map->odom at the end
    scans: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=dict)

    def frame(self, name: str) -> str:
        return self.prefix + name

    def topic(self, name: str) -> str:
        return "/" + (self.prefix + name).lstrip("/")

    def correction(self, t: np.ndarray) -> np.ndarray:
        """(N, 3) map -> odom: grows linearly, as a localiser corrects odometry drift."""
        return np.asarray(self.drift)[None] * (np.asarray(t, float)[:, None] / self.duration)

    def odometry(self, t: np.ndarray) -> np.ndarray:
        """(N, 3) the drifting odom -> base_footprint pose."""
        return compose(inverse(self.correction(t)), self.route.base(t))

    def laser_pose(self, laser: Laser, t: np.ndarray) -> np.ndarray:
        return compose(self.route.base(t), np.asarray(laser.mount))

    def simulate(self) -> None:
        """Scans of each laser at ``scan_rate``, stamps offset from the TF stamps."""
        for k, laser in enumerate(self.lasers):
            t = np.arange(0.2, self.duration - 0.2, 1 / self.scan_rate) + 0.013 + 0.004 * k
            pose = self.laser_pose(laser, t)
            sign = -1.0 if laser.upside_down else 1.0
            phi = pose[:, 2:3] + sign * laser.angles[None, :]
            origins = np.repeat(pose[:, :2], laser.n_beams, axis=0)
            ranges = WORLD.cast(origins, phi.ravel(), laser.max_range)
            self.scans[laser.topic] = (t, pose, ranges.reshape(t.size, -1))


class BagWriter:
    """Messages collected then written in time order as ROS1, ROS2 (sqlite3/mcap) or MCAP."""

    def __init__(self, fmt: str) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.fmt = fmt
        self.ros1 = fmt == "ros1"
        self.ts = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if self.ros1:  # rosbags' Noetic store lacks tf2_msgs; a real bag carries its msgdef
            from rosbags.typesys import get_types_from_msg

            self.ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                                "tf2_msgs/msg/TFMessage"))
        self.T = self.ts.types
        self.messages: list[tuple[float, str, str, object]] = []

    def header(self, t: float, frame: str) -> object:
        sec = int(math.floor(t))
        stamp = self.T["builtin_interfaces/msg/Time"](sec=sec, nanosec=round((t - sec) * 1e9))
        if self.ros1:
            return self.T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
        return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def add(self, topic: str, msgtype: str, t: float, msg: object) -> None:
        self.messages.append((t, topic, msgtype, msg))

    def pose(self, xyz: tuple, q: tuple) -> object:
        T = self.T
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=xyz[0], y=xyz[1], z=xyz[2]),
            orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))

    def scan(self, topic: str, frame: str, t: float, angles: np.ndarray, ranges: np.ndarray,
             max_range: float, **override: float) -> None:
        fields = dict(angle_min=float(angles[0]), angle_max=float(angles[-1]),
                      angle_increment=float(angles[1] - angles[0]), time_increment=0.0,
                      scan_time=0.1, range_min=0.05, range_max=max_range)
        fields.update(override)
        msg = self.T["sensor_msgs/msg/LaserScan"](
            header=self.header(t, frame), ranges=np.asarray(ranges, np.float32),
            intensities=np.zeros(0, np.float32), **fields)
        self.add(topic, "sensor_msgs/msg/LaserScan", t, msg)

    def tf(self, topic: str, t: float, items: list[tuple[str, str, tuple, tuple]]) -> None:
        T = self.T
        transforms = [
            T["geometry_msgs/msg/TransformStamped"](
                header=self.header(t, parent), child_frame_id=child,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2]),
                    rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))
            for parent, child, xyz, q in items]
        self.add(topic, "tf2_msgs/msg/TFMessage", t,
                 T["tf2_msgs/msg/TFMessage"](transforms=transforms))

    def pose_cov(self, topic: str, t: float, frame: str, xyz: tuple, q: tuple,
                 cov6: np.ndarray) -> None:
        T = self.T
        msg = T["geometry_msgs/msg/PoseWithCovarianceStamped"](
            header=self.header(t, frame),
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(xyz, q),
                                                           covariance=np.ravel(cov6)))
        self.add(topic, "geometry_msgs/msg/PoseWithCovarianceStamped", t, msg)

    def odom(self, topic: str, t: float, frame: str, child: str, xyz: tuple, q: tuple,
             cov6: np.ndarray) -> None:
        T = self.T
        v = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        msg = T["nav_msgs/msg/Odometry"](
            header=self.header(t, frame), child_frame_id=child,
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(xyz, q),
                                                           covariance=np.ravel(cov6)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=v, angular=v),
                covariance=np.zeros(36)))
        self.add(topic, "nav_msgs/msg/Odometry", t, msg)

    def write(self, path: Path, compress: bool = False) -> Path:
        msgs = sorted(self.messages, key=lambda m: m[0])
        types = dict.fromkeys((topic, msgtype) for _, topic, msgtype, _ in msgs)
        if self.ros1:
            from rosbags.rosbag1 import Writer as Writer1

            writer1 = Writer1(path)
            if compress:
                writer1.set_compression(Writer1.CompressionFormat.LZ4)
            with writer1 as writer:
                conns = {k: writer.add_connection(k[0], k[1], typestore=self.ts) for k in types}
                for t, topic, msgtype, msg in msgs:
                    writer.write(conns[(topic, msgtype)], round(t * 1e9),
                                 bytes(self.ts.serialize_ros1(msg, msgtype)))
            return path
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

        plugin = StoragePlugin.SQLITE3 if self.fmt == "ros2-sqlite3" else StoragePlugin.MCAP
        folder = path if self.fmt != "mcap" else path.parent / (path.stem + "_folder")
        writer2 = Writer(folder, version=9, storage_plugin=plugin)
        if compress:
            writer2.set_compression(CompressionMode.FILE, CompressionFormat.ZSTD)
        with writer2 as writer:
            conns = {k: writer.add_connection(k[0], k[1], typestore=self.ts) for k in types}
            for t, topic, msgtype, msg in msgs:
                writer.write(conns[(topic, msgtype)], round(t * 1e9),
                             bytes(self.ts.serialize_cdr(msg, msgtype)))
        if self.fmt == "mcap":
            shutil.move(next(folder.glob("*.mcap")), path)
            shutil.rmtree(folder)
        return path


def add_robot(bag: BagWriter, robot: Robot, *, tf_topic: str = "/tf",
              static_topic: str = "/tf_static", map_to_odom: bool = True,
              odom_tf: bool = True, odom_rate: float = 50.0, map_rate: float = 10.0,
              static_tf: bool = True) -> None:
    """The robot's scans and TF: map -> odom -> base_footprint -> base_link -> lasers."""
    if not robot.scans:
        robot.simulate()
    f = robot.frame
    tf_t = np.arange(0.0, robot.duration + 1e-9, 1 / odom_rate)
    odom = robot.odometry(tf_t)
    if odom_tf:
        for t, p in zip(tf_t, odom, strict=True):
            bag.tf(tf_topic, T0 + t, [(f("odom"), f("base_footprint"), (p[0], p[1], 0.0),
                                       quat(yaw=p[2]))])
    if map_to_odom:
        for t in np.arange(0.0, robot.duration + 1e-9, 1 / map_rate) + 0.0071:
            c = robot.correction(np.array([t]))[0]
            bag.tf(tf_topic, T0 + t, [(map_frame(robot), f("odom"), (c[0], c[1], 0.0),
                                       quat(yaw=c[2]))])
    # A 3-D static chain: base_link 0.1 m up, the lasers 0.2 m above base_link.
    static = [(f("base_footprint"), f("base_link"), (0.0, 0.0, 0.1), quat())]
    for laser in robot.lasers:
        mx, my, myaw = laser.mount
        static.append((f("base_link"), laser.frame, (mx, my, 0.2),
                       quat(roll=math.pi if laser.upside_down else 0.0, pitch=laser.pitch,
                            yaw=myaw)))
    if static_tf:
        bag.tf(static_topic, T0, static)
    for laser in robot.lasers:
        t, _, ranges = robot.scans[laser.topic]
        for tk, r in zip(t, ranges, strict=True):
            bag.scan(laser.topic, laser.frame, T0 + tk, laser.angles, r, laser.max_range)


def map_frame(robot: Robot) -> str:
    return "map"


def amcl_stamps(robot: Robot, dist: float = 0.25, turn: float = 0.2) -> np.ndarray:
    """Times AMCL would publish: after ``dist`` metres or ``turn`` radians of motion."""
    t = np.arange(0.0, robot.duration, 0.01)
    p = robot.route.base(t)
    out, last = [0.0], p[0]
    for tk, pk in zip(t, p, strict=True):
        if (math.hypot(*(pk[:2] - last[:2])) >= dist
                or abs(math.remainder(pk[2] - last[2], 2 * math.pi)) >= turn):
            out.append(float(tk))
            last = pk
    return np.asarray(out) + 0.002


def cov6(x: float, y: float, yaw: float, xy: float = 0.0, z_and_tilt: float = 1e-6) -> np.ndarray:
    c = np.diag([x, y, z_and_tilt, z_and_tilt, z_and_tilt, yaw])
    c[0, 1] = c[1, 0] = xy
    return c


def heldout_grid_auc(batch) -> float:
    """AUC of a log-odds grid built from 4 of 5 scans of ``batch`` (a ScanBatch), on the
    held-out 5th scans' points: how two readings of one run are compared."""
    from sklearn.metrics import roc_auc_score

    from gpocc.baselines.grid import observed_extent, occupancy_grid
    from gpocc.config import Config, SensorConfig
    from gpocc.evaluation.split import split_batch
    from gpocc.gridspec import GridSpec

    config = Config()
    split = split_batch(batch, SensorConfig(name=batch.sensor), every=5,
                        rng=np.random.default_rng(0))
    spec = GridSpec.from_bounds(*observed_extent([split.train], config), 0.1)
    grid = occupancy_grid([split.train], config, spec)
    row, col, inside = spec.index_of(split.points)
    scores = grid.probability[row[inside], col[inside]]
    seen = np.isfinite(scores)  # cells no training beam reached have no probability
    assert seen.mean() > 0.8
    return float(roc_auc_score(split.labels[inside][seen], scores[seen]))
