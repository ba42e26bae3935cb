"""Sensors of a bag when the config names none: one per laser, paired by namespace.

Every LaserScan topic becomes a sensor named after the topic (``/robot1/scan`` ->
``robot1/scan``); a bag without any takes its PointCloud2 topics (3-D lidars)
instead. Its pose topic is looked for in its own namespace first, then in each
enclosing one up to the root (``/robot1/front/scan`` looks in ``/robot1/front``, ``/robot1``,
``/``), so namespaced robots pair with their own topics and several lasers of one robot
share its pose. The usual multi-level names count as one name: ``/odometry/filtered``,
``/odometry/global``, ``/odometry/local`` and ``/slam_toolbox/pose`` are in the root
namespace (``/robot1/odometry/global`` in ``robot1``). A ``nav_msgs/Odometry`` whose
``header.frame_id`` is ``map`` is a map pose source whatever its topic name: it belongs to
the namespace of the frame it moves (``child_frame_id``: ``robot1/base_link`` ->
``robot1``), else to the nearest namespace of its topic that holds lasers
(``/robot1/ekf/fused`` -> ``robot1``), else to the root (``/ekf/fused``). Within a
namespace the best source wins: a map pose (PoseWithCovarianceStamped from AMCL or SLAM,
Odometry in ``map``) over Odometry in another frame over PoseStamped.
With TF reaching the laser from ``map`` the pose topic supplies only the covariance, so a
tie is settled by name (``amcl_pose`` first, then alphabetically) and said in ``gpocc
info``; without TF a tie is an error that names the candidates and prints a
ready-to-paste ``sensors:`` entry. A laser with no pose topic but TF takes ``pose_topic:
/tf`` (covariance from the config).
"""

from __future__ import annotations

from collections.abc import Sequence

from gpocc.config import SensorConfig
from gpocc.errors import GpoccError
from gpocc.io.bags import SCAN_TYPES, TF_POSE, BagContents, TopicSummary, tf_topics_for
from gpocc.io.laserpose import namespace
from gpocc.io.poses import POSE_TYPES
from gpocc.io.tf import TF_TYPES

#: Pose topic names of more than one level, taken as one name (their namespace is the
#: part before them).
KNOWN_NAMES = ("odometry/filtered", "odometry/global", "odometry/local", "slam_toolbox/pose")
_ODOMETRY = "nav_msgs/msg/Odometry"


def sensor_name(scan_topic: str) -> str:
    return scan_topic.strip("/") or "scan"


def _in_scope(pose_ns: str, scan_ns: str) -> bool:
    return not pose_ns or pose_ns == scan_ns or scan_ns.startswith(pose_ns + "/")


def scan_topics(topics: Sequence[TopicSummary]) -> list[str]:
    """The topics that become sensors without a config: every LaserScan topic, or when
    there is none every PointCloud2 topic (a 3-D lidar; a depth camera's cloud beside a
    laser is not picked up unless named in the config)."""
    lasers = [t.name for t in topics if t.msgtype == SCAN_TYPES[0]]
    return lasers or [t.name for t in topics if t.msgtype in SCAN_TYPES[1:]]


def _is_map(frame: str) -> bool:
    return frame == "map" or frame.endswith("/map")


def pose_namespace(contents: BagContents, topic: str, msgtype: str) -> str:
    """The namespace a pose topic serves (see the module docs)."""
    name = topic.strip("/")
    by_name = namespace(topic)
    for known in KNOWN_NAMES:
        if name == known or name.endswith("/" + known):
            by_name = name[: -len(known)].rstrip("/")
            break
    frame, child = contents.frame_of(topic)
    if msgtype == _ODOMETRY and _is_map(frame):
        # A map pose of the frame it moves: that frame's namespace, else the nearest
        # enclosing namespace of the topic that holds lasers (/robot1/ekf/fused ->
        # robot1), else the root (/ekf/fused).
        by_frame = child.rpartition("/")[0]
        if by_frame:
            return by_frame
        scans = [namespace(t.name) for t in contents.topics if t.msgtype in SCAN_TYPES]
        parts = by_name.split("/") if by_name else []
        for k in range(len(parts), 0, -1):
            prefix = "/".join(parts[:k])
            if any(ns == prefix or ns.startswith(prefix + "/") for ns in scans):
                return prefix
        return ""
    return by_name


def _rank(contents: BagContents, topic: str, msgtype: str) -> int:
    """0 a map pose, 1 Odometry in another (or an unknown) frame, 2 no covariance."""
    if msgtype == _ODOMETRY:
        return 0 if _is_map(contents.frame_of(topic)[0]) else 1
    return 0 if POSE_TYPES[msgtype] else 2


def pose_candidates(contents: BagContents, scan_topic: str) -> list[str]:
    """The best pose topics for a scan topic: nearest namespace, best type; may tie."""
    ns = namespace(scan_topic)
    poses = [(t.name, pose_namespace(contents, t.name, t.msgtype),
              _rank(contents, t.name, t.msgtype))
             for t in contents.topics if t.msgtype in POSE_TYPES]
    poses = [p for p in poses if _in_scope(p[1], ns)]
    if not poses:
        return []
    depth = max(len(p[1]) for p in poses)
    near = [p for p in poses if len(p[1]) == depth]
    best = min(p[2] for p in near)
    return sorted(p[0] for p in near if p[2] == best)


def _flow_yaml(entries: list[tuple[str, str, str]]) -> str:
    """A one-line ``sensors:`` block (YAML flow style) that pastes into a config."""
    items = ", ".join(f"{{name: {n}, scan_topic: {s}, pose_topic: {p}}}" for n, s, p in entries)
    return f"sensors: [{items}]"


class PoseSourceError(GpoccError):
    """No pose source can be chosen for a laser: ``problem`` (what is wrong, naming the
    input) and ``fix`` (a config line for that laser), printed as ``problem; fix``. A
    bag with several lasers replaces the fix by one config line for all of them."""

    def __init__(self, problem: str, fix: str) -> None:
        super().__init__(f"{problem}; {fix}")
        self.problem = problem
        self.fix = fix


def pose_topic_for(contents: BagContents, scan_topic: str, path: object,
                   name: str | None = None) -> str:
    """The pose topic to use with ``scan_topic`` (``/tf`` when only TF gives the pose).

    Raises:
        GpoccError: no pose topic and no TF, or a tie without TF; the message carries a
            ready-to-paste ``sensors:`` line.
    """
    name = name or sensor_name(scan_topic)
    cands = pose_candidates(contents, scan_topic)
    has_tf = bool(tf_topics_for(contents, scan_topic))
    if len(cands) == 1:
        return cands[0]
    if not cands:
        if has_tf:
            return TF_POSE
        others = [f"{t.name} ({t.msgtype})" for t in contents.topics
                  if t.msgtype in POSE_TYPES or t.msgtype in TF_TYPES]
        raise PoseSourceError(
            f"{path}: no pose source for the laser {scan_topic}: no pose topic pairs with it "
            f"and no TF (candidate topics: {', '.join(others) or 'none'}; all topics: "
            f"{contents.listing()})",
            f"set sensors[].pose_topic to its pose topic (or record /tf): "
            f"{_flow_yaml([(name, scan_topic, 'POSE_TOPIC')])}")
    if has_tf:
        amcl = [c for c in cands if c.rstrip("/").endswith("amcl_pose")]
        return (amcl or cands)[0]
    raise PoseSourceError(
        f"{path}: cannot choose the pose topic for {scan_topic} among {', '.join(cands)} "
        f"(no TF to settle it)",
        f"put this in the config, keeping the right one: "
        f"{_flow_yaml([(name, scan_topic, cands[0])])}")


def detect_sensors(contents: BagContents, path: object) -> list[SensorConfig]:
    """One sensor per LaserScan topic, each with its pose topic (see the module docs).

    Raises:
        GpoccError: no LaserScan topic, or a laser whose pose source cannot be chosen;
            the message ends with a ``sensors:`` line for every laser, ready to paste.
    """
    scans = scan_topics(contents.topics)
    if not scans:
        raise GpoccError(
            f"{path}: cannot choose the LaserScan topic (found: none; all topics: "
            f"{contents.listing()}); record a sensor_msgs/LaserScan or PointCloud2 topic, "
            "or set sensors[].scan_topic")
    sensors, problems = [], []
    for scan in scans:
        try:
            pose = pose_topic_for(contents, scan, path)
        except PoseSourceError as exc:
            problems.append((scan, exc.problem))
            continue
        sensors.append(SensorConfig(name=sensor_name(scan), scan_topic=scan, pose_topic=pose))
    if problems:
        entries = []
        for scan in scans:
            done = next((s for s in sensors if s.scan_topic == scan), None)
            cands = pose_candidates(contents, scan)
            pose = done.pose_topic if done else (cands[0] if cands else "POSE_TOPIC")
            entries.append((sensor_name(scan), scan, pose))
        raise GpoccError(f"{problems[0][1]}; set sensors[].pose_topic in a config for "
                         f"all its lasers: {_flow_yaml(entries)}")
    return sensors
