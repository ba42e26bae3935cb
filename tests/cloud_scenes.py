"""3-D rooms seen by a simulated spinning lidar, and bags of its PointCloud2 messages.

The room: vertical walls (segments, floor to a 2.6 m ceiling), an optional table top
(a 3 cm slab whose top is at 0.75 m, no legs), a floor that may slope along x (the robot
then tilts with it, and the ceiling rises with it). Rays are cast exactly in 3-D here
(walls through the 2-D caster of gpocc.evaluation.world, planes and the slab in closed
form); mount rotations use scipy's
Rotation, not gpocc's quaternions. Messages are packed with numpy structured arrays in
every layout drivers use (float32/float64, padding, big-endian, organised or not, NaN
or zero for no return), and written with rosbags' own writers (tests/rosbag_scenes.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from rosbag_scenes import T0, BagWriter
from scipy.spatial.transform import Rotation

from gpocc.evaluation.world import cast_rays

CEILING = 2.6
TABLE_Z = (0.72, 0.75)


def rect(x0: float, y0: float, x1: float, y1: float) -> list:
    return [[(x0, y0), (x1, y0)], [(x1, y0), (x1, y1)], [(x1, y1), (x0, y1)],
            [(x0, y1), (x0, y0)]]


@dataclass
class Room:
    """Walls (K, 2, 2), an optional table footprint (x0, y0, x1, y1), a floor slope."""

    walls: np.ndarray
    table: tuple[float, float, float, float] | None = None
    slope: float = 0.0

    def floor_z(self, x: np.ndarray) -> np.ndarray:
        return self.slope * np.asarray(x, float)

    def cast(self, origin: np.ndarray, dirs: np.ndarray, max_range: float) -> np.ndarray:
        """(N,) 3-D range along unit ``dirs`` (N, 3) from ``origin`` (3,); NaN: no return."""
        o = np.asarray(origin, float)
        h = np.hypot(dirs[:, 0], dirs[:, 1])
        az = np.arctan2(dirs[:, 1], dirs[:, 0])
        best = np.full(dirs.shape[0], np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            dw = cast_rays(self.walls, np.zeros((0, 3)), np.repeat(o[None, :2], az.size, 0), az)
            s = dw / h
            z = o[2] + s * dirs[:, 2]
            x = o[0] + s * dirs[:, 0]
            ok = np.isfinite(s) & (z >= self.floor_z(x)) & (z <= self.floor_z(x) + CEILING)
            best = np.where(ok, s, best)
            # floor z = slope x + c: o_z + s d_z = slope (o_x + s d_x) + c; the ceiling
            # is parallel to the floor (a ramp's ceiling rises with it).
            for c in (0.0, CEILING):
                s = (self.slope * o[0] + c - o[2]) / (dirs[:, 2] - self.slope * dirs[:, 0])
                best = np.where((s > 0) & (s < best), s, best)
            if self.table is not None:
                x0, y0, x1, y1 = self.table
                side = cast_rays(np.array(rect(*self.table), float), np.zeros((0, 3)),
                                 np.repeat(o[None, :2], az.size, 0), az) / h
                z = o[2] + side * dirs[:, 2]
                hit = np.isfinite(side) & (z >= TABLE_Z[0]) & (z <= TABLE_Z[1])
                best = np.where(hit & (side < best), side, best)
                for face in TABLE_Z:
                    s = (face - o[2]) / dirs[:, 2]
                    px, py = o[0] + s * dirs[:, 0], o[1] + s * dirs[:, 1]
                    inside = (s > 0) & (px > x0) & (px < x1) & (py > y0) & (py < y1)
                    best = np.where(inside & (s < best), s, best)
        return np.where(best <= max_range, best, np.nan)


ROOM_RECT = (0.0, 0.0, 8.0, 6.0)
BOX = (5.5, 3.8, 6.5, 4.6)      # a full-height box (a cupboard)
TABLE = (1.2, 4.2, 2.4, 5.0)    # a table top at 0.75 m


def room(table: bool = True, slope: float = 0.0) -> Room:
    walls = np.array(rect(*ROOM_RECT) + rect(*BOX), float)
    return Room(walls, TABLE if table else None, slope)


@dataclass
class Lidar:
    """A spinning lidar: ``rings`` elevations over ``fov_deg``, ``columns`` azimuths, on
    the base at ``xyz`` turned by roll / pitch / yaw (radians)."""

    rings: int = 16
    columns: int = 900
    fov_deg: tuple[float, float] = (-15.0, 15.0)
    xyz: tuple[float, float, float] = (0.15, 0.0, 0.45)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    max_range: float = 30.0
    range_sd: float = 0.0
    azimuth_deg: tuple[float, float] = (-180.0, 180.0)

    @property
    def rotation(self) -> Rotation:
        return Rotation.from_euler("ZYX", self.rpy[::-1])

    def directions(self) -> np.ndarray:
        """(rings, columns, 3) unit rays in the lidar frame."""
        el = np.radians(np.linspace(*self.fov_deg, self.rings))[:, None]
        az = np.radians(np.linspace(*self.azimuth_deg, self.columns, endpoint=False))[None, :]
        return np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                                            np.sin(el)), axis=-1)


def base_rotation(yaw: float, slope: float) -> Rotation:
    """The base on a floor sloping along x: its z axis the floor's normal, heading yaw."""
    return Rotation.from_euler("y", -math.atan(slope)) * Rotation.from_euler("z", yaw)


def base_path(t: np.ndarray) -> np.ndarray:
    """(N, 3) x, y, yaw: an ellipse around (3.5, 2.5), a lap in 20 s."""
    w = 2 * math.pi / 20.0
    t = np.asarray(t, float)
    return np.column_stack([3.5 + 2.0 * np.cos(w * t), 2.5 + 1.3 * np.sin(w * t),
                            np.arctan2(1.3 * np.cos(w * t), -2.0 * np.sin(w * t))])


def scan_cloud(world: Room, lidar: Lidar, pose: np.ndarray,
               rng: np.random.Generator | None = None) -> np.ndarray:
    """(rings, columns, 3) points in the lidar frame, NaN where no return."""
    x, y, yaw = pose
    body = base_rotation(yaw, world.slope)
    base = np.array([x, y, float(world.floor_z(x))])
    origin = base + body.apply(lidar.xyz)
    local = lidar.directions().reshape(-1, 3)
    ranges = world.cast(origin, (body * lidar.rotation).apply(local), lidar.max_range)
    if rng is not None and lidar.range_sd:
        ranges = ranges + rng.normal(0.0, lidar.range_sd, ranges.shape)
    return (local * ranges[:, None]).reshape(lidar.rings, lidar.columns, 3)


@dataclass(frozen=True)
class Layout:
    """How a driver packs points."""

    float64: bool = False
    pad: int = 0                 # bytes before x and at the end of each point
    bigendian: bool = False
    organised: bool = True
    zero_no_return: bool = False  # organised no-returns as (0, 0, 0) instead of NaN
    ring: bool = True
    extras: bool = True          # intensity and t fields


def pack_cloud(points: np.ndarray, layout: Layout) -> dict:
    """PointCloud2 fields (without header) for (rings, columns, 3) points."""
    e = ">" if layout.bigendian else "<"
    f = e + ("f8" if layout.float64 else "f4")
    size = 8 if layout.float64 else 4
    names, formats, offsets, fields = [], [], [], []

    def add(name: str, fmt: str, datatype: int, nbytes: int, offset: int) -> int:
        names.append(name)
        formats.append(fmt)
        offsets.append(offset)
        fields.append((name, offset, datatype))
        return offset + nbytes

    off = layout.pad
    for axis in "xyz":
        off = add(axis, f, 8 if layout.float64 else 7, size, off)
    if layout.extras:
        off = add("intensity", e + "f4", 7, 4, off)
        off = add("t", e + "u4", 6, 4, off)
    if layout.ring:
        off = add("ring", e + "u2", 4, 2, off)
    step = off + layout.pad
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    rings, cols = points.shape[:2]
    pts = points.reshape(-1, 3)
    ring = np.repeat(np.arange(rings), cols)
    col = np.tile(np.arange(cols), rings)
    ok = np.isfinite(pts).all(axis=1)
    if not layout.organised:
        pts, ring, col = pts[ok], ring[ok], col[ok]
    elif layout.zero_no_return:
        pts = np.where(ok[:, None], pts, 0.0)
    arr = np.zeros(pts.shape[0], dtype)
    arr["x"], arr["y"], arr["z"] = pts.T
    if layout.extras:
        arr["intensity"] = 100.0
        arr["t"] = col * 50_000
    if layout.ring:
        arr["ring"] = ring
    height, width = (rings, cols) if layout.organised else (1, pts.shape[0])
    return dict(height=height, width=width, fields=fields, is_bigendian=layout.bigendian,
                point_step=step, row_step=step * width,
                data=np.frombuffer(arr.tobytes(), np.uint8), is_dense=not layout.organised)


def add_cloud(bag: BagWriter, topic: str, frame: str, t: float, packed: dict) -> None:
    T = bag.T
    fields = [T["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=1)
              for n, o, d in packed["fields"]]
    msg = T["sensor_msgs/msg/PointCloud2"](header=bag.header(t, frame),
                                           **{**packed, "fields": fields})
    bag.add(topic, "sensor_msgs/msg/PointCloud2", t, msg)


def tf_item(parent: str, child: str, xyz, rotation: Rotation) -> tuple:
    return (parent, child, tuple(float(v) for v in xyz), tuple(rotation.as_quat()))


@dataclass
class LidarRun:
    """A robot driving the ellipse with a lidar (and optionally a planar laser)."""

    world: Room
    lidar: Lidar
    layout: Layout = field(default_factory=Layout)
    cloud_t: np.ndarray = field(default_factory=lambda: 0.31 + np.arange(20) * 1.0)
    seed: int = 0

    def write(self, bag: BagWriter, topic: str = "/velodyne_points",
              frame: str = "velodyne", base: str = "base_footprint", base_height: float = 0.0,
              amcl: bool = False) -> None:
        """TF map -> ``base`` (``base_height`` above the floor) at 30 Hz, or with ``amcl``
        a PoseWithCovarianceStamped /amcl_pose instead; the lidar's mount on /tf_static."""
        rng = np.random.default_rng(self.seed)
        for t in np.arange(0.0, 20.6, 1 / 30):
            x, y, yaw = base_path(np.array([t]))[0]
            rot = base_rotation(yaw, self.world.slope)
            xyz = (x, y, float(self.world.floor_z(x)) + base_height)
            if amcl:
                c = np.diag([0.004, 0.003, 1e-6, 1e-6, 1e-6, 0.001])
                bag.pose_cov("/amcl_pose", T0 + t, "map", xyz, tuple(rot.as_quat()), c)
            else:
                bag.tf("/tf", T0 + t, [tf_item("map", base, xyz, rot)])
        mount = np.asarray(self.lidar.xyz) - np.array([0.0, 0.0, base_height])
        bag.tf("/tf_static", T0, [tf_item(base, frame, mount, self.lidar.rotation)])
        for t, pose in zip(self.cloud_t, base_path(self.cloud_t), strict=True):
            pts = scan_cloud(self.world, self.lidar, pose, rng)
            add_cloud(bag, topic, frame, T0 + t, pack_cloud(pts, self.layout))


def add_planar_laser(bag: BagWriter, run: LidarRun, beams: int = 900,
                     topic: str = "/scan", frame: str = "laser") -> None:
    """The same run seen by a level 360-degree laser where the lidar is (same noise)."""
    rng = np.random.default_rng(run.seed + 1)
    angles = np.linspace(-math.pi, math.pi, beams, endpoint=False)
    level = Lidar(rings=1, columns=beams, fov_deg=(0.0, 0.0), xyz=run.lidar.xyz,
                  max_range=run.lidar.max_range, range_sd=run.lidar.range_sd)
    bag.tf("/tf_static", T0, [tf_item("base_footprint", frame, level.xyz, level.rotation)])
    for t, pose in zip(run.cloud_t, base_path(run.cloud_t), strict=True):
        pts = scan_cloud(run.world, level, pose, rng)[0]
        r = np.linalg.norm(pts, axis=1)
        bag.scan(topic, frame, T0 + t, angles, np.where(np.isfinite(r), r, np.inf),
                 level.max_range)


def obstacle_distance(p: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """(N,) distance from each (N, 2) point to the nearest of the (K, 2, 2) segments."""
    a, e = segments[:, 0], segments[:, 1] - segments[:, 0]
    rel = p[:, None] - a[None]
    u = np.clip((rel * e[None]).sum(-1) / (e * e).sum(-1)[None], 0.0, 1.0)
    return np.linalg.norm(rel - u[..., None] * e[None], axis=-1).min(axis=1)


def inside(p: np.ndarray, r: tuple) -> np.ndarray:
    """Points strictly inside the rectangle ``r = (x0, y0, x1, y1)``."""
    return (p[:, 0] > r[0]) & (p[:, 0] < r[2]) & (p[:, 1] > r[1]) & (p[:, 1] < r[3])
