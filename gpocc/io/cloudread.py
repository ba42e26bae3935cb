"""A PointCloud2 topic as a planar laser: one scan per cloud, posed like a LaserScan.

Each cloud is decoded (:mod:`gpocc.io.pointcloud`), moved into the robot's base frame
with the full 3-D TF ``base <- lidar`` at its stamp, and projected into one scan around
the lidar's origin on the ground plane (:mod:`gpocc.io.cloudscan`). The projected scans
get a frame of their own, ``<lidar frame>:plane``: the lidar's origin dropped onto the
base frame's x-y plane, with the base frame's axes. It is added to the TF buffer as a
child of the base frame, so :func:`gpocc.io.laserpose.assemble` poses these scans exactly
as it poses a LaserScan (TF chain from ``map``, pose covariance carried through the
lever arm; or a pose topic with the offset as the sensor's ``mount``).

The base frame is ``sensors[].base_frame`` when set, else the frame the last moving TF
edge of the chain ``map -> lidar`` moves (``base_footprint`` or ``base_link``), else
``base_footprint`` or ``base_link`` when TF reaches the lidar from it.

Defaults of a 3-D lidar (used unless the config sets the key): ``range_min_m`` 0.3 m
(returns nearer than that horizontally are the robot's own body), ``range_max_m``
100 m, ``range_variance_m2`` 0.0009 (3 cm, the accuracy VLP-16, Ouster OS1 and Hesai
XT datasheets give), ``bearing_variance_deg2`` 0.01 plus the bearing bin's width^2 / 12
(the hit lies anywhere in its bin). The horizontal resolution comes from the layout:
the width of an organised cloud, else the fullest ring's returns; else 0.4 degrees.

A bin with no return in the height band is a no-return (cleared up to
``no_return_free_m``) when its rays returned from the floor or ceiling at least that far
away horizontally (nearer, clearing it would pass where its rays stopped: it is
unknown, as for a lidar pitched down or a depth camera); a bin with no
return at any height is invalid (no information), so a camera's or a masked lidar's
blind sector, or a bin the binning left empty, is never cleared. When the band's returns
alone fill :data:`FULL_TURN_SHARE` of the bins, the floor and ceiling returns are not
binned (their cost), and the bins left are invalid too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from gpocc.config import MountConfig, SensorConfig
from gpocc.errors import GpoccError
from gpocc.io.cloudscan import height_histogram, rotation_matrix, scan_from_cloud
from gpocc.io.laserpose import ScanTopic, find_chain, in_map_frame, mount_chain
from gpocc.io.pointcloud import (
    Cloud,
    decode_cloud,
    horizontal_bins,
    returns_mask,
    ring_count,
)
from gpocc.io.poses import PoseSeries
from gpocc.io.tf import Chain, Edge, TfBuffer, frame_name, quat_multiply, yaw_of

CLOUD_RANGE_MIN_M = 0.3
CLOUD_RANGE_MAX_M = 100.0
CLOUD_RANGE_VARIANCE_M2 = 0.0009
CLOUD_BEARING_VARIANCE_DEG2 = 0.01
DEFAULT_RESOLUTION_DEG = 0.4
#: Bin counts from a layout are kept within these (a 10-degree to a 0.09-degree step).
MIN_BINS, MAX_BINS = 36, 4096
#: Share of bins with a return in the band above which the floor and ceiling returns
#: are not binned (the bins left are then invalid; see the module docs).
FULL_TURN_SHARE = 0.9
#: Base-frame heights (m) of the fine histogram that finds the floor's peak.
FLOOR_EDGES = np.round(np.arange(-3.01, 0.51, 0.02), 2)  # centres on even centimetres
#: The floor's peak must hold this share of the returns to be named in ``gpocc info``.
FLOOR_SHARE = 0.05
#: Heights above the floor (m) of the ``gpocc info`` histogram's bin edges.
HISTOGRAM_EDGES = np.array([-0.5, -0.1, 0.1, 0.3, 0.5, 0.75, 1.0, 1.25, 1.5, 2.0, 2.5, 3.0])
#: ``gpocc info``'s shares (returns, kept by the band, the height histograms) are counted
#: on one point in this many of each cloud: percent-level shares over many clouds need no
#: more, and testing every point for a return and binning its height would cost as much
#: as the rest of the projection.
STATS_STRIDE = 16


def plane_frame(frame: str) -> str:
    return f"{frame}:plane"


@dataclass
class CloudStats:
    """What ``gpocc info`` says about a cloud topic, accumulated as clouds are read.
    ``sampled``, ``returns``, ``kept`` and the histograms count one point in
    :data:`STATS_STRIDE` of each cloud."""

    clouds: int = 0
    points: list[int] = field(default_factory=list)
    sampled: int = 0
    returns: int = 0
    kept: int = 0
    rings: int | None = None
    fields: tuple[str, ...] = ()
    layout: str = ""
    histogram: np.ndarray = field(default_factory=lambda: np.zeros(HISTOGRAM_EDGES.size + 1,
                                                                   np.int64))
    hit_bins: int = 0
    fine: np.ndarray = field(default_factory=lambda: np.zeros(FLOOR_EDGES.size + 1, np.int64))
    has_time: bool = False


@dataclass
class CloudCollector:
    """Projects the clouds of one PointCloud2 topic as they are read (TF known first).

    Args:
        path: the bag, for messages.
        sensor: the config entry; ``scan_topic`` is the cloud topic.
        tf: the bag's TF for this sensor (may be empty).
    """

    path: Path
    sensor: SensorConfig
    tf: TfBuffer | None
    scans: ScanTopic = field(default_factory=lambda: ScanTopic(levelled=True))
    stats: CloudStats = field(default_factory=CloudStats)
    base: str = ""
    #: The lidar's frame (the clouds' header.frame_id); the scans' is its plane_frame.
    lidar_frame: str = ""
    inner: Chain | None = None
    outer: Chain | None = None
    bins: int = 0
    bins_source: str = ""
    origins: list[np.ndarray] = field(default_factory=list)
    unposed: int = 0
    #: Clouds of fewer than MIN_BINS points before the first fuller one: skipped, as they
    #: would set the bins (and so the scan) of the whole topic.
    too_small: int = 0
    #: Clouds without a header.frame_id before the first one with it: skipped.
    unframed: int = 0
    #: base <- lidar when every edge between them is static: looked up once.
    mount: tuple[np.ndarray, np.ndarray] | None = None
    #: Every rotation on the chain map -> base is a yaw (a planar robot's TF): the base
    #: is level at every stamp and :meth:`_level` needs no lookup.
    yaw_only: bool = False

    @property
    def topic(self) -> str:
        return self.sensor.scan_topic or ""

    @property
    def band_base(self) -> tuple[float, float]:
        """The height band in base-frame z, metres."""
        low, high = self.sensor.height_band_m
        return low - self.sensor.base_height_m, high - self.sensor.base_height_m

    @property
    def range_min(self) -> float:
        s = self.sensor.range_min_m
        return CLOUD_RANGE_MIN_M if s is None else float(s)

    def _start(self, frame: str, cloud: Cloud) -> None:
        """Base frame, the chain base -> lidar and the bin count, from the first cloud."""
        sensor, tf = self.sensor, self.tf
        where = f"{self.path}: topic {self.topic}"
        if not tf or frame not in tf.frames():
            raise GpoccError(
                f"{where}: TF has no frame '{frame}' (the cloud's frame_id), so the lidar's "
                "height and tilt on the robot are unknown; record its mount on /tf_static "
                "(static_transform_publisher from the base frame to that frame)")
        base = sensor.base_frame
        if base is None:
            chain, _ = find_chain(tf, sensor, frame)
            body = chain.body_frame() if chain is not None else None
            if body is not None and body != frame and chain is not None and chain.steps:
                base = body
            else:
                # base_footprint itself too: a cloud already moved into it (a filter's
                # output) is taken as seen from the base's origin, as one in base_link
                # above it already was. (A lidar frame that TF moves is not a base.)
                base = next((b for b in ("base_footprint", "base_link")
                             if tf.chain(b, frame) is not None
                             and (b != frame or b == "base_footprint")), None)
        if base is None:
            raise GpoccError(
                f"{where}: cannot tell the robot's base frame under the cloud's frame "
                f"'{frame}' (its TF parents: {', '.join(tf.parents(frame)) or 'none'}); "
                "set sensors[].base_frame to the frame whose x-y plane is the ground")
        inner = tf.chain(base, frame)
        if inner is None:
            raise GpoccError(
                f"{where}: no TF chain from sensors[].base_frame '{base}' to the cloud's frame "
                f"'{frame}'; set base_frame to a frame TF connects to it")
        if any(upward and not edge.static for edge, upward in inner.steps):
            # Up from the base through a moving edge: the cloud is in the world (a
            # registered cloud), and its frame's origin is not the sensor's.
            raise GpoccError(
                f"{where}: the cloud's frame '{frame}' is not on the robot: TF reaches it from "
                f"the base frame '{base}' only through the robot's motion ({inner.describe()}),"
                " as for a registered cloud in the map frame; give the lidar's own cloud "
                "topic, in its sensor frame")
        self.base, self.inner, self.lidar_frame = base, inner, frame
        self.scans.frame_id = plane_frame(frame)
        self.outer, _ = find_chain(tf, sensor, base)
        self.yaw_only = self.outer is not None and all(
            not np.any(edge.quaternions[:, :2]) for edge, _ in self.outer.steps)
        res = sensor.horizontal_resolution_deg
        if res is not None:
            self.bins, self.bins_source = int(round(360.0 / res)), "sensors[]." \
                "horizontal_resolution_deg"
        else:
            layout = horizontal_bins(cloud)
            if layout is None:
                self.bins = int(round(360.0 / DEFAULT_RESOLUTION_DEG))
                self.bins_source = (f"default {DEFAULT_RESOLUTION_DEG:g} deg: no ring field and "
                                    "not organised; set sensors[].horizontal_resolution_deg")
            else:
                self.bins = int(np.clip(layout, MIN_BINS, MAX_BINS))
                self.bins_source = ("the cloud's width" if cloud.organised
                                    else "the points per ring")
        inc = 2.0 * math.pi / self.bins
        self.scans.geometry = (self.bins, -math.pi + 0.5 * inc, inc)
        max_m = sensor.range_max_m
        self.scans.range_limits = (self.range_min,
                                   CLOUD_RANGE_MAX_M if max_m is None else float(max_m))
        self.stats.fields = cloud.fields
        self.stats.layout = (f"organised {cloud.height} x {cloud.width}" if cloud.organised
                             else "unorganised")

    def add(self, msg: Any, t: float, log_time: float | None = None) -> None:
        """Decode, move into the base frame and project one cloud stamped ``t`` seconds
        (logged at ``log_time``: with it, the scans' clock is chosen as a LaserScan's,
        :func:`gpocc.io.stamps.choose_stamps`)."""
        where = f"{self.path}: topic {self.topic} at t={t:.6f} s"
        cloud = decode_cloud(msg, where)
        frame = frame_name(msg.header.frame_id)
        if not frame and self.inner is not None:  # as a LaserScan's: the topic's frame
            frame = self.lidar_frame
        if not frame:  # before any cloud with a frame: nothing places it on the robot
            self.unframed += 1
            return
        if self.inner is None and cloud.n_points < MIN_BINS:
            self.too_small += 1  # a driver's first, partial clouds
            return
        if self.inner is None:
            self._start(frame, cloud)
        elif frame != self.lidar_frame:
            raise GpoccError(f"{where}: the cloud's frame_id changes from "
                             f"'{self.lidar_frame}' to '{frame}'; split the bag at that time")
        mount = self._mount(t)
        if mount is None:
            self.unposed += 1
            return
        translation, rotation = mount
        level = self._level(t)
        reach = np.full(self.bins, np.inf)
        ranges, heard, z = scan_from_cloud(cloud.points, rotation, translation, level,
                                           self.band_base, self.bins, self.range_min,
                                           FULL_TURN_SHARE, reach=reach)
        # A bin whose rays met only floor or ceiling, all nearer than the free extent a
        # no-return clears (a lidar pitched down, a depth camera): clearing it would pass
        # the place its rays stopped, so it is unknown.
        ranges[np.isinf(ranges) & (reach < self.sensor.no_return_free_m)] = np.nan
        # A bin no return fell into, at any height, is unknown: a masked sector, or a gap
        # of the binning (a random-pattern lidar, columns on bin edges). Clearing it as a
        # no-return cleared free space through walls.
        ranges[~heard & np.isinf(ranges)] = np.nan
        self.scans.stamps.append(t)
        if log_time is not None:
            self.scans.log_times.append(log_time)
        self.scans.ranges.append(ranges)
        self.origins.append(translation)
        st = self.stats
        st.clouds += 1
        st.points.append(cloud.n_points)
        sample = cloud.points[::STATS_STRIDE]
        z = z[::STATS_STRIDE][returns_mask(sample)]
        st.sampled += sample.shape[0]
        st.returns += z.size
        low, high = self.band_base
        st.kept += int(np.count_nonzero((z >= low) & (z <= high)))
        st.histogram += height_histogram(z + self.sensor.base_height_m, HISTOGRAM_EDGES)
        st.fine += height_histogram(z, FLOOR_EDGES)
        st.hit_bins += int(np.count_nonzero(np.isfinite(ranges)))
        if st.clouds == 1:
            st.rings = ring_count(cloud)
        st.has_time = st.has_time or cloud.has_time

    def _mount(self, t: float) -> tuple[np.ndarray, np.ndarray] | None:
        """(translation (3,) m, rotation (3, 3)) base <- lidar at ``t``, or None without
        TF there."""
        if self.mount is not None:
            return self.mount
        assert self.tf is not None and self.inner is not None
        trans, quat, ok, _ = self.tf.transforms(self.inner, np.array([t]),
                                                self.sensor.max_pose_gap_s)
        if not ok[0]:
            return None
        mount = trans[0], rotation_matrix(quat[0])
        if all(edge.static for edge, _ in self.inner.steps):
            self.mount = mount
        return mount

    def _level(self, t: float) -> np.ndarray | None:
        """(3, 3) the rotation undoing the base's roll and pitch in the map frame at ``t``
        (its yaw kept), or None for a level base or without TF to the map: a base tilted
        on a ramp then sees vertical walls at their true horizontal distance."""
        if self.outer is None or self.tf is None or self.yaw_only:
            return None
        _, q, ok, _ = self.tf.transforms(self.outer, np.array([t]), self.sensor.max_pose_gap_s)
        if not ok[0]:
            return None
        half = 0.5 * float(yaw_of(q[0]))
        tilt = quat_multiply(np.array([0.0, 0.0, -math.sin(half), math.cos(half)]), q[0])
        if abs(tilt[3]) > 1.0 - 1e-12:
            return None
        return rotation_matrix(tilt)

    def plane_edge(self) -> Edge:
        """The TF edge base -> ``<lidar>:plane``: static when the lidar's mount is."""
        origins = np.asarray(self.origins, float).reshape(-1, 3)
        assert self.inner is not None
        static = all(edge.static for edge, _ in self.inner.steps)
        stamps = np.asarray(self.scans.stamps, float)
        if static:
            stamps, origins = stamps[:1], origins[:1]
        order = np.argsort(stamps, kind="stable")
        stamps, first = np.unique(stamps[order], return_index=True)
        flat = origins[order][first] * np.array([1.0, 1.0, 0.0])
        return Edge(parent=self.base, child=self.scans.frame_id, static=static,
                    topic=f"{self.topic} projected", stamps=stamps, translations=flat,
                    quaternions=np.tile([0.0, 0.0, 0.0, 1.0], (stamps.size, 1)))

    def resolved(self, series: PoseSeries | None = None
                 ) -> tuple[ScanTopic, TfBuffer, SensorConfig, tuple[str, ...]]:
        """The projected scans, TF with their frame, the sensor entry with the cloud
        defaults filled in, and the ``gpocc info`` lines. ``series``: the sensor's pose
        topic; when it poses the base without TF, the projected scans' offset on the base
        becomes the entry's ``mount``.

        Raises:
            GpoccError: no clouds, or none with TF from the base frame at its stamp.
        """
        where = f"{self.path}: topic {self.topic}"
        if self.inner is None and self.unframed:
            raise GpoccError(f"{where}: none of its {self.unframed} clouds has a "
                             "header.frame_id, so TF cannot place the lidar on the robot; fix "
                             "the driver's frame_id")
        if self.inner is None and self.too_small:
            raise GpoccError(f"{where}: none of its {self.too_small} clouds has {MIN_BINS} "
                             "points or more; check the driver, or pick another scan_topic")
        if self.inner is None:
            raise GpoccError(f"{where} has no messages; pick another scan_topic")
        if not self.scans.stamps:
            fix = (self.inner.published_once_fix("a mount")
                   or "check the TF stamps or raise sensors[].max_pose_gap_s")
            raise GpoccError(
                f"{where}: none of its {self.unposed} clouds has TF from '{self.base}' to the "
                f"cloud's frame within max_pose_gap_s={self.sensor.max_pose_gap_s} s; {fix}")
        assert self.tf is not None
        edge = self.plane_edge()
        tf = TfBuffer({**self.tf.edges, edge.child: edge}, dict(self.tf.conflicts),
                      self.tf.normalised_quaternions, self.tf.repeated_stamps)
        sensor = self.sensor
        defaults = SensorConfig()
        inc_deg = 360.0 / self.bins
        changes: dict[str, Any] = {"range_min_m": self.scans.range_limits[0],
                                   "range_max_m": self.scans.range_limits[1]}
        if sensor.range_variance_m2 == defaults.range_variance_m2:
            changes["range_variance_m2"] = CLOUD_RANGE_VARIANCE_M2
        if sensor.bearing_variance_deg2 == defaults.bearing_variance_deg2:
            changes["bearing_variance_deg2"] = CLOUD_BEARING_VARIANCE_DEG2 + inc_deg**2 / 12
        chain = find_chain(tf, sensor, self.scans.frame_id)[0] if sensor.position_from_tf else None
        from_tf = chain is not None or (
            sensor.position_from_tf and series is not None
            and in_map_frame(series.frame_id, sensor)
            and mount_chain(tf, series, self.scans.frame_id) is not None)
        if not from_tf and sensor.mount == MountConfig():
            # Poses from a pose topic give the base: the projected lidar is mounted on it.
            x, y, _ = edge.translations[0]
            changes["mount"] = MountConfig(x_m=float(x), y_m=float(y))
        return self.scans, tf, replace(sensor, **changes), self.summary(inc_deg)

    def summary(self, inc_deg: float) -> tuple[str, ...]:
        st = self.stats
        pts = np.asarray(st.points)
        low, high = self.sensor.height_band_m
        rings = st.rings or "unknown (no ring field)"
        lines = [
            f"point cloud {self.topic}: {st.clouds} clouds, {pts.mean():.0f} points per message "
            f"({pts.min()}..{pts.max()}), {100 * st.returns / max(st.sampled, 1):.0f}% returns, "
            f"{st.layout}, rings {rings}",
            f"  fields: {', '.join(st.fields)}",
            f"  base frame '{self.base}' ({self.inner.describe() if self.inner else ''})",
            f"  heights above the floor (m) of the returns; band [{low:g}, {high:g}] keeps "
            f"{100 * st.kept / max(st.returns, 1):.1f}%:",
        ]
        total = max(int(st.histogram.sum()), 1)
        edges = HISTOGRAM_EDGES
        labels = ([f"< {edges[0]:g}"]
                  + [f"{a:g}..{b:g}" for a, b in zip(edges[:-1], edges[1:], strict=True)]
                  + [f">= {edges[-1]:g}"])
        for label, count in zip(labels, st.histogram, strict=True):
            share = count / total
            lines.append(f"    {label:>12}  {100 * share:5.1f}%  {'#' * int(round(40 * share))}")
        lines.append(
            f"  equivalent scan: {self.bins} bins of {inc_deg:.3f} deg (from {self.bins_source}), "
            f"range {self.scans.range_limits[0]:g}..{self.scans.range_limits[1]:g} m, "
            f"{100 * st.hit_bins / max(st.clouds * self.bins, 1):.0f}% of bins hit")
        lines += self._floor_hint()
        if st.has_time:
            lines.append("  per-point time field present: the sweep is not de-skewed (every "
                         "point is taken at the cloud's stamp)")
        if self.unposed:
            lines.append(f"  {self.unposed} clouds without TF from '{self.base}' at their stamp "
                         "skipped")
        if self.unframed:
            lines.append(f"  {self.unframed} clouds without a header.frame_id before the first "
                         "one with it skipped")
        if self.too_small:
            lines.append(f"  {self.too_small} clouds of fewer than {MIN_BINS} points before the "
                         "first fuller one skipped (they would set the bearing bins)")
        return tuple(lines)

    def _floor_hint(self) -> list[str]:
        """A line naming ``base_height_m`` when the returns' densest height (the floor,
        in a room) is not where the config puts the floor."""
        inner = self.stats.fine[1:-1]
        total = max(int(self.stats.fine.sum()), 1)
        k = int(np.argmax(inner))
        if inner[k] < FLOOR_SHARE * total:
            return []
        floor = 0.5 * (FLOOR_EDGES[k] + FLOOR_EDGES[k + 1])
        if abs(floor + self.sensor.base_height_m) <= 0.05:
            return []
        return [f"  {100 * inner[k] / total:.0f}% of the returns lie at {floor:+.2f} m in "
                f"'{self.base}', not at the floor the config gives "
                f"({0.0 - self.sensor.base_height_m + 0.0:+.2f} m): if that is the floor, set "
                f"sensors[].base_height_m: {-floor:.2f}"]
