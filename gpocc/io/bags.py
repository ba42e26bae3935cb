"""ROS bags as :class:`ScanBatch`: ROS1 ``.bag``, ROS2 bag folders, bare ``.mcap`` files.

Reading goes through ``rosbags.highlevel.AnyReader`` with the message definitions the
bag carries; bags without any (older ROS2 sqlite3 bags) fall back to the ROS2 Humble
definitions. Scans come from ``sensor_msgs/msg/LaserScan``; poses from
``geometry_msgs/msg/PoseWithCovarianceStamped``, ``nav_msgs/msg/Odometry`` or
``geometry_msgs/msg/PoseStamped`` (no covariance), and TF (``/tf``, ``/tf_static``): see
:mod:`gpocc.io.laserpose` for how the laser pose and its covariance are chosen. Times are
header stamps in seconds, or the log time for a topic whose header stamps are zero,
constant or not increasing (:mod:`gpocc.io.stamps`).

LaserScan messages are checked as read: ``angle_min``, ``angle_max`` and
``angle_increment`` must be finite and agree with the number of ranges (within two
increments: drivers differ by one beam) and a scan must have ranges; each is a one-line
error naming file, topic, stamp and field. A topic whose beam layout changes from scan to
scan is placed on one layout (:mod:`gpocc.io.layouts`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import functools
import math
import os
import tempfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from gpocc.config import SensorConfig
from gpocc.errors import GpoccError
from gpocc.io import laserpose
from gpocc.io.atomic import atomic_directory, atomic_path, check_can_write
from gpocc.io.cloudread import CloudCollector
from gpocc.io.laserpose import ScanTopic as _ScanTopic
from gpocc.io.laserpose import namespace
from gpocc.io.pointcloud import CLOUD_TYPE
from gpocc.io.poses import POSE_TYPES, XY_YAW, PoseCollector
from gpocc.io.scans import ScanBatch
from gpocc.io.tf import TF_TYPES, TfBuffer, TfCollector, frame_name, merge_buffers
from gpocc.io.timeline import blend_poses, brackets

SCAN_TYPE = "sensor_msgs/msg/LaserScan"
#: Message types a sensor's ``scan_topic`` may have: a planar laser or a 3-D lidar's cloud
#: (projected into one scan per cloud, :mod:`gpocc.io.cloudread`).
SCAN_TYPES = (SCAN_TYPE, CLOUD_TYPE)
#: ``pose_topic`` value meaning: positions from TF only, covariance from the config.
TF_POSE = "/tf"
#: ``write_bag`` formats; also what ``bag_format`` reports.
FORMATS = ("ros1", "ros2-sqlite3", "ros2-mcap", "mcap")
FORMAT_NAMES = {
    "ros1": "ROS1 bag",
    "ros2-sqlite3": "ROS2 bag (sqlite3)",
    "ros2-mcap": "ROS2 bag (mcap)",
    "mcap": "MCAP file",
}


@dataclass(frozen=True)
class TopicSummary:
    """One topic of an input: name, message type and message count."""

    name: str
    msgtype: str
    count: int


@dataclass(frozen=True)
class BagContents:
    """What a bag holds: its format, topics and record-time span (seconds).

    ``frames``: ``(topic, frame_id, child_frame_id)`` of each pose topic's first message
    (child empty when the type has none), which pose-source choice needs.
    """

    format: str
    topics: tuple[TopicSummary, ...]
    start_s: float | None
    end_s: float | None
    frames: tuple[tuple[str, str, str], ...] = ()

    def frame_of(self, topic: str) -> tuple[str, str]:
        """``(frame_id, child_frame_id)`` of a pose topic, ``("", "")`` when unknown."""
        return next(((f, c) for t, f, c in self.frames if t == topic), ("", ""))

    def topic(self, name: str) -> TopicSummary | None:
        return next((t for t in self.topics if t.name == name), None)

    def topics_of_type(self, *msgtypes: str) -> list[TopicSummary]:
        return [t for t in self.topics if t.msgtype in msgtypes]

    def listing(self) -> str:
        """``/scan (sensor_msgs/msg/LaserScan), ...`` for error messages."""
        if not self.topics:
            return "none"
        return ", ".join(f"{t.name} ({t.msgtype})" for t in self.topics)


# --------------------------------------------------------------------------- reading


def bag_format(path: Path) -> str | None:
    """The bag format of ``path`` from its name (and a ROS2 folder's metadata), or None."""
    if path.is_dir():
        meta = path / "metadata.yaml"
        if not meta.is_file():
            return None
        try:
            info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
            storage = str(info.get("storage_identifier", "sqlite3"))
        except (OSError, yaml.YAMLError, KeyError, TypeError, AttributeError):
            return "ros2-sqlite3"  # the reader reports what exactly is wrong
        return "ros2-mcap" if storage == "mcap" else "ros2-sqlite3"
    if path.suffix == ".bag":
        return "ros1"
    if path.suffix == ".mcap":
        return "mcap"
    if path.suffix == ".db3":
        return "ros2-sqlite3"
    return None


@functools.cache
def _typestore(store: str) -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores[store])


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def _corrupt(path: Path, exc: BaseException) -> GpoccError:
    hint = "re-record or re-export it"
    if path.suffix == ".mcap" or (path.is_dir() and any(path.glob("*.mcap"))):
        hint += " (`mcap recover` can often save a cut-off MCAP file)"
    return GpoccError(
        f"{path}: cannot read the bag ({_one_line(exc)}); it may be truncated or corrupt, "
        f"or not a bag at all: {hint}"
    )


#: The first bytes of an MCAP file.
MCAP_MAGIC = b"\x89MCAP0\r\n"


#: Above this many bytes of MCAP files a failed read is reported as it is: checking every
#: record in Python would keep the user waiting minutes for the error.
MAX_CORRUPTION_CHECK_BYTES = 1 << 30


def mcap_corruption(path: Path) -> str | None:
    """How an MCAP file, or an MCAP file of a ROS 2 bag folder, is corrupt, read record
    by record with the mcap library: a chunk or the data section failing its stored CRC,
    or records that do not parse (a length past the file, a cut-off end, bytes no record
    holds), as ``"FILE: what failed"``; None if every file reads whole (CRCs are checked
    where the writer stored them), is not MCAP, or is too large to check
    (:data:`MAX_CORRUPTION_CHECK_BYTES`). It reads every file whole: a check for after a
    read has failed, to tell corruption from bad data."""
    import struct

    from mcap import exceptions
    from mcap.stream_reader import CRCValidationError, StreamReader

    # Not corruption: what this installation cannot decode (classes of recent releases).
    unsupported = tuple(getattr(exceptions, name) for name in
                        ("UnsupportedCompressionError", "DecoderNotFoundError")
                        if hasattr(exceptions, name))
    files = [path] if path.is_file() else sorted(path.glob("*.mcap"))
    if sum(f.stat().st_size for f in files) > MAX_CORRUPTION_CHECK_BYTES:
        return None
    for file in files:
        try:
            with open(file, "rb") as stream:
                if stream.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                    continue
                stream.seek(0)
                for _ in StreamReader(stream, validate_crcs=True).records:
                    pass
        except CRCValidationError as exc:
            return f"{file.name}: {exc}"
        except unsupported:
            continue
        except (exceptions.McapError, UnicodeDecodeError, struct.error, ValueError) as exc:
            return f"{file.name}: its records do not parse ({_one_line(exc)})"
        except OSError:
            continue
    return None


@contextlib.contextmanager
def _corruption_named(path: Path) -> Iterator[None]:
    """An error while reading a bag's messages is the bag's corruption when its MCAP
    records say so (:func:`mcap_corruption`): a flipped byte otherwise shows as whatever
    field it lands in (an angle that disagrees with its count, a NaN pose), with that
    field's fix."""
    try:
        yield
    except Exception:
        try:
            failure = mcap_corruption(path)
        except Exception:  # noqa: BLE001 - the check must never hide the read's own error
            failure = None
        if failure is None:
            raise
        raise GpoccError(
            f"{path}: the file is corrupt ({failure}); re-record or re-export it "
            "(`mcap recover` can often save an MCAP file)"
        ) from None


class _DefaultTypestore:
    """The ROS 2 Humble typestore for bags that carry no message definitions (rosbag2
    sqlite3 bags before Iron), built on first use: building it takes 0.15 s, and ROS 1
    bags, MCAP files and newer rosbag2 bags carry their own definitions."""

    def __bool__(self) -> bool:
        return True

    def __getattr__(self, name: str) -> Any:
        return getattr(_typestore("ROS2_HUMBLE"), name)


@contextlib.contextmanager
def _open_reader(path: Path) -> Iterator[Any]:
    """An open AnyReader on ``path``; any failure of the library becomes a GpoccError."""
    from rosbags.highlevel import AnyReader

    if not path.exists():
        raise GpoccError(f"{path}: no such file or folder; check the input path")
    if path.is_file() and path.stat().st_size == 0:
        raise GpoccError(f"{path}: the file is empty; re-record or re-export the bag")
    try:
        reader = AnyReader([path], default_typestore=_DefaultTypestore())
        reader.open()
    except GpoccError:
        raise
    except Exception as exc:  # rosbags, sqlite and mcap raise many types on bad bytes
        raise _corrupt(path, exc) from None
    try:
        yield reader
    except GpoccError:
        raise
    except Exception as exc:
        raise _corrupt(path, exc) from None
    finally:
        with contextlib.suppress(Exception):
            reader.close()


def _contents(reader: Any, fmt: str) -> BagContents:
    topics = tuple(
        TopicSummary(name, info.msgtype or "(mixed types)", int(info.msgcount))
        for name, info in sorted(reader.topics.items())
    )
    count = sum(t.count for t in topics)
    start = reader.start_time * 1e-9 if count else None
    # AnyReader's end_time is one nanosecond after the last message.
    end = (reader.end_time - 1) * 1e-9 if count else None
    return BagContents(fmt, topics, start, end)


def _pose_frames(reader: Any) -> tuple[tuple[str, str, str], ...]:
    """``(topic, frame_id, child_frame_id)`` from the first message of each pose topic."""
    out = []
    for conn in reader.connections:
        if conn.msgtype not in POSE_TYPES or any(t == conn.topic for t, _, _ in out):
            continue
        for c, _, raw in reader.messages(connections=[conn]):
            msg = reader.deserialize(raw, c.msgtype)
            out.append((conn.topic, frame_name(msg.header.frame_id),
                        frame_name(getattr(msg, "child_frame_id", "") or "")))
            break
    return tuple(out)


def describe_bag(path: str | Path) -> BagContents:
    """Topics (type, message count), time span and pose topics' frames of a bag (the
    first message of each pose topic is read; no other message)."""
    path = Path(path)
    fmt = bag_format(path) or "mcap"
    with _open_reader(path) as reader:
        return dataclasses.replace(_contents(reader, fmt), frames=_pose_frames(reader))


def _stamp(msg: Any) -> float:
    """The header stamp in seconds; 0.0 when it is zero (see :mod:`gpocc.io.stamps`)."""
    stamp = msg.header.stamp
    return stamp.sec + stamp.nanosec * 1e-9


def _check_scan_fields(path: Path, topic: str, msg: Any, t: float, n: int) -> None:
    """LaserScan geometry sanity: a clean error naming file, topic, stamp and field."""
    where = f"{path}: topic {topic} at t={t:.6f} s"
    fields = {k: float(getattr(msg, k)) for k in ("angle_min", "angle_max", "angle_increment")}
    for key, value in fields.items():
        if not math.isfinite(value):
            raise GpoccError(f"{where}: field {key} is {value}; the scan's bearings are "
                             "unknown: fix the driver or drop these messages")
    if n == 0:
        raise GpoccError(f"{where}: field ranges is empty; drop these messages or pick "
                         "another scan_topic")
    inc = fields["angle_increment"]
    if n > 1 and (inc == 0.0 or abs(inc) * (n - 1) > 2 * math.pi + 1e-6):
        raise GpoccError(
            f"{where}: field angle_increment={inc} with {n} ranges spans "
            f"{abs(inc) * (n - 1):.3f} rad, not within (0, 2 pi]; fix the driver's settings")
    expected = fields["angle_min"] + (n - 1) * inc
    if n > 1 and abs(expected - fields["angle_max"]) > 2 * abs(inc) + 1e-6:
        raise GpoccError(
            f"{where}: field angle_max={fields['angle_max']:.6f} disagrees with angle_min + "
            f"(n - 1) angle_increment = {expected:.6f} for {n} ranges; fix the driver's "
            "angle settings")


def _add_scan(path: Path, topic: str, acc: _ScanTopic, msg: Any, record_ns: int) -> None:
    ranges = np.asarray(msg.ranges, dtype=float)
    header = _stamp(msg)
    t = header or record_ns * 1e-9
    _check_scan_fields(path, topic, msg, t, ranges.shape[0])
    geometry = (ranges.shape[0], float(msg.angle_min), float(msg.angle_increment))
    frame = frame_name(msg.header.frame_id)
    if frame and not acc.frame_id:  # the first frame given: a driver may leave some empty
        acc.frame_id = frame
    elif frame and frame != acc.frame_id and acc.frame_change is None:
        acc.frame_change = (t, acc.frame_id, frame)
    if acc.geometry is None:
        acc.geometry = geometry
        acc.range_limits = (float(msg.range_min), float(msg.range_max))
    elif acc.layouts is not None:
        acc.layouts.append(geometry)
    elif geometry[0] != acc.geometry[0] or not all(
            # np.allclose(atol=1e-6) on two finite floats, without its per-call cost (a
            # tenth of a second per 1000 scans).
            abs(a - b) <= 1e-6 + 1e-5 * abs(b)
            for a, b in zip(geometry[1:], acc.geometry[1:], strict=True)):
        # A driver that publishes each revolution as it came (gpocc.io.layouts).
        acc.layouts = [acc.geometry] * len(acc.ranges) + [geometry]
    acc.stamps.append(header)
    acc.log_times.append(record_ns * 1e-9)
    acc.ranges.append(ranges)


def interpolate_poses(
    pose_stamps: np.ndarray,
    poses: np.ndarray,
    covariances: np.ndarray,
    stamps: np.ndarray,
    max_gap_s: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Poses and covariances at ``stamps``, interpolated between the bracketing poses.

    x and y are linear in time, yaw follows the shorter arc, the covariance is linear.
    A stamp is served only when it lies between two poses at most ``max_gap_s`` apart,
    or within 1 us of a pose stamp (:func:`gpocc.io.timeline.brackets`); outside the
    poses' time range, or inside a longer gap, it is not.

    Args:
        pose_stamps: (P,) seconds, strictly increasing.
        poses: (P, 3) x m, y m, yaw rad.
        covariances: (P, 3, 3).
        stamps: (S,) seconds.
        max_gap_s: longest pose gap to interpolate across, seconds.

    Returns:
        ``(poses (S, 3), covariances (S, 3, 3), valid (S,) bool)``; rows where ``valid``
        is False hold the nearest pose and are to be dropped.
    """
    at = brackets(pose_stamps, stamps, max_gap_s)
    w = at.weight[:, None, None]
    cov = (1.0 - w) * covariances[at.before] + w * covariances[at.after]
    return blend_poses(poses, at), cov, at.served


def check_topics(path: Path, contents: BagContents, sensor: SensorConfig) -> None:
    """Raise a GpoccError unless the sensor's scan and pose topics exist with usable types.

    ``pose_topic`` may be ``/tf`` (positions from TF, covariance from the config), which
    needs a TF topic in the bag.
    """
    if sensor.pose_topic == TF_POSE and not contents.topics_of_type(*TF_TYPES):
        raise GpoccError(
            f"{path}: sensor '{sensor.name}' takes its pose from TF (pose_topic: {TF_POSE}), "
            f"but the bag has no TF topic; topics present: {contents.listing()}; set pose_topic "
            "to a pose topic")
    for role, name, types in (
        ("scan_topic", sensor.scan_topic, SCAN_TYPES),
        ("pose_topic", sensor.pose_topic, tuple(POSE_TYPES)),
    ):
        if role == "pose_topic" and name == TF_POSE:
            continue
        if name is None:
            raise GpoccError(f"{path}: sensor '{sensor.name}' has no {role}; set it in the config")
        topic = contents.topic(name)
        if topic is None:
            raise GpoccError(
                f"{path}: topic {name} (sensor '{sensor.name}' {role}) is not in the bag; "
                f"topics present: {contents.listing()}"
            )
        if topic.msgtype not in types:
            raise GpoccError(
                f"{path}: topic {name} is {topic.msgtype}, not {' or '.join(types)}; "
                f"pick another {role} (topics present: {contents.listing()})"
            )


def tf_topics_for(contents: BagContents, scan_topic: str) -> list[str]:
    """The TF topics of a sensor: those in its namespace or any enclosing one (``/tf``)."""
    ns = namespace(scan_topic)
    out = []
    for t in contents.topics_of_type(*TF_TYPES):
        tns = namespace(t.name)
        if not tns or ns == tns or ns.startswith(tns + "/"):
            out.append(t.name)
    return out


def odometry_topic_for(contents: BagContents, sensor: SensorConfig) -> str | None:
    """The one Odometry topic in the sensor's (nearest enclosing) namespace to anchor a
    PoseWithCovarianceStamped pose topic without TF, or None."""
    pose = contents.topic(sensor.pose_topic or "")
    if pose is None or pose.msgtype != "geometry_msgs/msg/PoseWithCovarianceStamped":
        return None
    ns = namespace(sensor.scan_topic or "")
    odoms = [t.name for t in contents.topics_of_type("nav_msgs/msg/Odometry")
             if not namespace(t.name) or ns == namespace(t.name)
             or ns.startswith(namespace(t.name) + "/")]
    if not odoms:
        return None
    depth = max(len(namespace(t)) for t in odoms)
    near = [t for t in odoms if len(namespace(t)) == depth]
    return near[0] if len(near) == 1 else None


def read_bag(path: str | Path, sensors: Sequence[SensorConfig]) -> list[ScanBatch]:
    """Read the scans of each sensor from one bag, each with its laser pose and covariance.

    Args:
        path: a ``.bag`` file, a ROS2 bag folder (one or several storage files, compressed
            or not) or a ``.mcap`` file.
        sensors: config entries with ``scan_topic`` and ``pose_topic`` set (``pose_topic``
            may be ``/tf``).

    Returns:
        One batch per sensor, in the order given. Scans are sorted by header stamp;
        scans without a pose within ``max_pose_gap_s`` are dropped and counted (see
        :mod:`gpocc.io.laserpose` for the pose and covariance sources).

    Raises:
        GpoccError: unreadable bag, missing topic or wrong message type, a bad message
            (see :mod:`gpocc.io.poses`, :mod:`gpocc.io.tf` and this module's docs), or no
            scan with a pose.
    """
    path = Path(path)
    fmt = bag_format(path) or "mcap"
    with _open_reader(path) as reader:
        contents = _contents(reader, fmt)
        for sensor in sensors:
            check_topics(path, contents, sensor)
        clouds = {s.scan_topic for s in sensors
                  if contents.topic(s.scan_topic).msgtype == CLOUD_TYPE}
        scan_acc = {s.scan_topic: _ScanTopic() for s in sensors if s.scan_topic not in clouds}
        odom_for = {s.name: odometry_topic_for(contents, s) for s in sensors}
        pose_names = [s.pose_topic for s in sensors if s.pose_topic != TF_POSE]
        pose_names += [t for t in odom_for.values() if t is not None]
        pose_acc = {t: PoseCollector(path, t, contents.topic(t).msgtype) for t in pose_names}
        # A cloud needs TF for the lidar's mount even when its position comes from a topic.
        tf_for = {s.name: tf_topics_for(contents, s.scan_topic)
                  if s.position_from_tf or s.scan_topic in clouds else [] for s in sensors}
        tf_acc = {t: TfCollector(path) for names in tf_for.values() for t in names}
        wanted = [c for c in reader.connections
                  if c.topic in scan_acc or c.topic in pose_acc or c.topic in tf_acc]
        with _corruption_named(path):
            for conn, record_ns, raw in reader.messages(connections=wanted):
                msg = reader.deserialize(raw, conn.msgtype)
                if conn.topic in scan_acc:
                    _add_scan(path, conn.topic, scan_acc[conn.topic], msg, record_ns)
                if conn.topic in pose_acc:
                    pose_acc[conn.topic].add(msg, record_ns)
                if conn.topic in tf_acc:
                    tf_acc[conn.topic].add(msg, conn.topic, record_ns)
            series = {topic: acc.build() for topic, acc in pose_acc.items()}
            built = {topic: acc.build() for topic, acc in tf_acc.items()}
        tfs = {s.name: merge_buffers([built[t] for t in tf_for[s.name]]) or None
               for s in sensors}
        # Clouds are projected as read, in a second pass once TF is known: a bag's clouds
        # would not fit in memory.
        cloud_acc = {s.scan_topic: CloudCollector(path, s, tfs[s.name]) for s in sensors
                     if s.scan_topic in clouds}
        wanted = [c for c in reader.connections if c.topic in cloud_acc]
        with _corruption_named(path):
            for conn, record_ns, raw in (reader.messages(connections=wanted) if wanted
                                         else ()):
                msg = reader.deserialize(raw, conn.msgtype)
                # The header stamp, else the log time: a cloud is projected with the TF at
                # its time as it is read, before the topic's clock could be judged whole.
                cloud_acc[conn.topic].add(msg, _stamp(msg) or record_ns * 1e-9,
                                          record_ns * 1e-9)
    with _corruption_named(path):
        return [_assemble(path, s, scan_acc, cloud_acc, tfs[s.name], series,
                          series.get(odom_for[s.name]) if odom_for[s.name] else None)
                for s in sensors]


def _assemble(path: Path, sensor: SensorConfig, scan_acc: dict[str, _ScanTopic],
              cloud_acc: dict[str, CloudCollector], tf: TfBuffer | None,
              series: dict[str, Any], odom: Any) -> ScanBatch:
    """One sensor's batch from what :func:`read_bag` collected."""
    if sensor.scan_topic in cloud_acc:
        scans, tf, resolved, lines = cloud_acc[sensor.scan_topic].resolved(
            series.get(sensor.pose_topic))
        batch = laserpose.assemble(path, resolved, scans, tf, series.get(sensor.pose_topic),
                                   odom)
        return replace(batch, sensor_config=resolved,
                       provenance=replace(batch.provenance, sensor_lines=lines))
    return laserpose.assemble(path, sensor, scan_acc[sensor.scan_topic], tf,
                              series.get(sensor.pose_topic), odom)


# --------------------------------------------------------------------------- writing


def _check_writable(
    path: Path, batches: Sequence[ScanBatch], topics: Sequence[tuple[str, str]], fmt: str
) -> None:
    if fmt not in FORMATS:
        raise GpoccError(f"unknown bag format {fmt!r}; use one of {', '.join(FORMATS)}")
    if len(batches) != len(topics):
        raise GpoccError(
            f"{path}: {len(batches)} scan batches but {len(topics)} (scan, pose) topic pairs; "
            "give one pair per batch"
        )
    if not batches:
        raise GpoccError(f"{path}: nothing to write (no scan batches)")
    suffix = {"ros1": ".bag", "mcap": ".mcap"}.get(fmt)
    if suffix and path.suffix != suffix:
        raise GpoccError(f"{path}: a {FORMAT_NAMES[fmt]} must be named *{suffix}; rename it")
    if suffix is None and path.suffix in (".bag", ".mcap"):
        raise GpoccError(
            f"{path}: a {FORMAT_NAMES[fmt]} is a folder; give it a name without .bag/.mcap"
        )
    names = [t for pair in topics for t in pair]
    if len(set(names)) != len(names):
        raise GpoccError(f"{path}: topic names must all differ, got {names}")
    for batch in batches:
        if batch.n_beams > 1:
            step = np.diff(batch.angles)
            if np.abs(step - step.mean()).max() > 1e-6:
                raise GpoccError(
                    f"{path}: sensor '{batch.sensor}' has unevenly spaced beams, which a "
                    "LaserScan message cannot hold"
                )
        if batch.n_scans and np.min(batch.stamps) < 0:
            raise GpoccError(f"{path}: sensor '{batch.sensor}' has negative time stamps")


class _Messages:
    """Builds LaserScan and PoseWithCovarianceStamped messages for one typestore."""

    def __init__(self, typestore: Any, ros1: bool) -> None:
        self.ts = typestore
        self.ros1 = ros1
        t = typestore.types
        self.Time, self.Header = t["builtin_interfaces/msg/Time"], t["std_msgs/msg/Header"]
        self.Scan = t[SCAN_TYPE]
        self.Point, self.Quat = t["geometry_msgs/msg/Point"], t["geometry_msgs/msg/Quaternion"]
        self.Pose = t["geometry_msgs/msg/Pose"]
        self.PoseCov = t["geometry_msgs/msg/PoseWithCovariance"]
        self.PoseCovStamped = t["geometry_msgs/msg/PoseWithCovarianceStamped"]

    def header(self, ns: int, frame: str, seq: int) -> Any:
        stamp = self.Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        if self.ros1:
            return self.Header(seq=seq, stamp=stamp, frame_id=frame)
        return self.Header(stamp=stamp, frame_id=frame)

    def serialize(self, msg: Any, msgtype: str) -> bytes:
        if self.ros1:
            return bytes(self.ts.serialize_ros1(msg, msgtype))
        return bytes(self.ts.serialize_cdr(msg, msgtype))

    def scan(self, batch: ScanBatch, k: int, ns: int, scan_time: float) -> bytes:
        angles = batch.angles
        inc = float((angles[-1] - angles[0]) / (angles.size - 1)) if angles.size > 1 else 0.0
        msg = self.Scan(
            header=self.header(ns, "laser", k),
            angle_min=float(angles[0]),
            angle_max=float(angles[-1]),
            angle_increment=inc,
            time_increment=0.0,
            scan_time=scan_time,
            range_min=float(batch.range_min),
            range_max=float(batch.range_max),
            ranges=np.asarray(batch.ranges[k], dtype=np.float32),
            intensities=np.zeros(0, dtype=np.float32),
        )
        return self.serialize(msg, SCAN_TYPE)

    def pose(self, batch: ScanBatch, k: int, ns: int) -> bytes:
        x, y, yaw = (float(v) for v in batch.poses[k])
        cov = np.zeros((6, 6))
        cov[np.ix_(XY_YAW, XY_YAW)] = batch.pose_covariances[k]
        pose = self.Pose(
            position=self.Point(x=x, y=y, z=0.0),
            orientation=self.Quat(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)),
        )
        msg = self.PoseCovStamped(
            header=self.header(ns, "map", k),
            pose=self.PoseCov(pose=pose, covariance=cov.reshape(36)),
        )
        return self.serialize(msg, "geometry_msgs/msg/PoseWithCovarianceStamped")


def _write_messages(writer: Any, messages: _Messages, batches: Sequence[ScanBatch],
                    topics: Sequence[tuple[str, str]]) -> None:
    pose_type = "geometry_msgs/msg/PoseWithCovarianceStamped"
    conns = [
        (writer.add_connection(scan, SCAN_TYPE, typestore=messages.ts),
         writer.add_connection(pose, pose_type, typestore=messages.ts))
        for scan, pose in topics
    ]
    # Record in time order across sensors, as a recorder would.
    ns = [np.round(np.asarray(b.stamps, dtype=float) * 1e9).astype(np.int64) for b in batches]
    which = np.concatenate([np.full(b.n_scans, i) for i, b in enumerate(batches)])
    index = np.concatenate([np.arange(b.n_scans) for b in batches])
    times = np.concatenate(ns) if ns else np.zeros(0, dtype=np.int64)
    scan_times = [float(np.median(np.diff(b.stamps))) if b.n_scans > 1 else 0.0 for b in batches]
    for j in np.lexsort((index, which, times)):
        i, k, t = int(which[j]), int(index[j]), int(times[j])
        writer.write(conns[i][0], t, messages.scan(batches[i], k, t, scan_times[i]))
        writer.write(conns[i][1], t, messages.pose(batches[i], k, t))


def write_bag(
    path: str | Path,
    batches: Sequence[ScanBatch],
    topics: Sequence[tuple[str, str]],
    fmt: str,
    *,
    force: bool = False,
) -> None:
    """Write scans and their poses as a bag, atomically.

    Each scan becomes a ``sensor_msgs/msg/LaserScan`` (frame ``laser``) and a
    ``geometry_msgs/msg/PoseWithCovarianceStamped`` (frame ``map``) at the scan's stamp,
    the pose covariance placed at the x, y, yaw entries of the 6x6 matrix. Ranges are
    stored as float32, as LaserScan holds them.

    Args:
        path: ``*.bag`` for ``ros1``, ``*.mcap`` for ``mcap``, a folder name for the
            ROS2 formats.
        batches: the scans, one batch per sensor; beams must be evenly spaced.
        topics: ``(scan_topic, pose_topic)`` for each batch.
        fmt: ``ros1``, ``ros2-sqlite3``, ``ros2-mcap`` or ``mcap`` (one bare file).
        force: replace an existing output.

    Raises:
        GpoccError: existing output without ``force``, bad arguments, or a write failure.
    """
    path = Path(path)
    _check_writable(path, batches, topics, fmt)
    check_can_write(path, force)
    try:
        if fmt == "ros1":
            from rosbags.rosbag1 import Writer as Writer1

            with atomic_path(path) as tmp:
                tmp.unlink()  # the writer refuses an existing file
                with Writer1(tmp) as writer:
                    _write_messages(writer, _Messages(_typestore("ROS1_NOETIC"), True),
                                    batches, topics)
            return
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        storage = StoragePlugin.SQLITE3 if fmt == "ros2-sqlite3" else StoragePlugin.MCAP
        messages = _Messages(_typestore("ROS2_HUMBLE"), False)
        if fmt == "mcap":
            with atomic_path(path) as tmp, tempfile.TemporaryDirectory(dir=path.parent) as work:
                bag = Path(work) / path.stem
                with Writer2(bag, version=9, storage_plugin=storage) as writer:
                    _write_messages(writer, messages, batches, topics)
                os.replace(bag / f"{path.stem}.mcap", tmp)
            return
        with atomic_directory(path, force=force) as tmp:
            # The writer creates the folder itself and names its files after it.
            bag = tmp / path.name
            with Writer2(bag, version=9, storage_plugin=storage) as writer:
                _write_messages(writer, messages, batches, topics)
            for item in bag.iterdir():
                os.replace(item, tmp / item.name)
            bag.rmdir()
    except GpoccError:
        raise
    except OSError as exc:
        if exc.errno == errno.ENOSPC:
            raise GpoccError(f"{path}: cannot write the bag: no space left on device; free "
                             "some space there, or write it elsewhere") from None
        raise GpoccError(f"{path}: cannot write the bag ({_one_line(exc)}); check the folder "
                         "exists and is writable") from None
