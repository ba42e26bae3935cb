"""Input dispatch: recognise each input's format and pick the config's sensors for it.

Formats: a folder with ``metadata.yaml`` is a ROS2 bag; ``*.bag`` a ROS1 bag; ``*.mcap``
a bare MCAP file (``*.db3`` a bare ROS2 sqlite3 file); ``*.log``, ``*.clf``, ``*.gfs``, or
text whose first message is a CARMEN type, a CARMEN log.

Sensors: each ``sensors`` entry of the config names a robot's laser (``scan_topic``)
and pose source (``pose_topic``). An entry with ``inputs`` (globs on the file name)
applies only to matching inputs and its topics must be there; an entry without applies
to every input that has its scan topic. With no ``sensors`` in the config, each
LaserScan topic of a bag becomes a sensor named after it, paired with a pose topic by
namespace (:mod:`gpocc.io.autodetect`); a CARMEN log gives one sensor named after the
file stem. An entry without ``pose_topic`` gets one the same way.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from gpocc.config import Config, SensorConfig
from gpocc.errors import GpoccError, check_distinct, check_regular_file
from gpocc.io import autodetect, bags, carmen
from gpocc.io.bags import BagContents, TopicSummary
from gpocc.io.frames import entry_matches, input_transform, transform_batch
from gpocc.io.scans import ScanBatch
from gpocc.progress import debug, log

FORMAT_NAMES = {**bags.FORMAT_NAMES, "carmen": "CARMEN log"}
CARMEN_SUFFIXES = (".log", ".clf", ".gfs")
_ROS1_MAGIC = b"#ROSBAG V2.0"
_SQLITE_MAGIC = b"SQLite format 3\x00"


@dataclass(frozen=True)
class InputSummary:
    """What one input holds, for ``gpocc info`` and for choosing sensors.

    ``topics`` lists a bag's topics; for a CARMEN log, its message types (type
    ``carmen/FLASER`` etc.). ``start_s``/``end_s``: record-time span, seconds.
    """

    path: Path
    format: str
    topics: tuple[TopicSummary, ...]
    start_s: float | None
    end_s: float | None
    frames: tuple[tuple[str, str, str], ...] = ()  # see BagContents.frames
    clock_note: str = ""  # how the scans are timed when not by the span's clock

    @property
    def format_name(self) -> str:
        return FORMAT_NAMES[self.format]

    def listing(self) -> str:
        return BagContents(self.format, self.topics, self.start_s, self.end_s).listing()


def _head(path: Path, size: int = 4096) -> bytes:
    try:
        with path.open("rb") as f:
            return f.read(size)
    except OSError as exc:
        raise GpoccError(f"{path}: cannot read the file ({exc.strerror}); check the path") from None


def detect_format(path: str | Path) -> str:
    """``ros1``, ``ros2-sqlite3``, ``ros2-mcap``, ``mcap`` or ``carmen``.

    Raises:
        GpoccError: missing path, empty file, or an unknown format.
    """
    path = Path(path)
    if not path.exists():
        raise GpoccError(f"{path}: no such file or folder; check the input path")
    if path.is_dir():
        fmt = bags.bag_format(path)
        if fmt is None:
            raise GpoccError(
                f"{path}: a folder without metadata.yaml is not a ROS2 bag; pass the bag "
                "folder itself (the one holding metadata.yaml)"
            )
        return fmt
    check_regular_file(path, "recording", "check the input path")
    if path.stat().st_size == 0:
        raise GpoccError(f"{path}: the file is empty; pass a bag, an MCAP file or a CARMEN log")
    fmt = bags.bag_format(path)
    if fmt is not None:
        return fmt
    head = _head(path)
    if path.suffix in CARMEN_SUFFIXES or carmen.is_carmen_text(head):
        return "carmen"
    for magic, suffix in ((bags.MCAP_MAGIC, ".mcap"), (_ROS1_MAGIC, ".bag"),
                          (_SQLITE_MAGIC, ".db3")):
        if head.startswith(magic):
            raise GpoccError(f"{path}: looks like a {suffix} file; rename it to *{suffix}")
    raise GpoccError(
        f"{path}: unknown input format; pass a ROS1 .bag, a ROS2 bag folder (with "
        "metadata.yaml), an .mcap file or a CARMEN log (.log/.clf)"
    )


def describe_input(path: str | Path) -> InputSummary:
    """Format, topics with message counts, and time span of one input."""
    path = Path(path)
    fmt = detect_format(path)
    if fmt == "carmen":
        contents = carmen.describe_carmen(path)
        topics = tuple(
            TopicSummary(name, f"carmen/{name}", count)
            for name, count in sorted(contents.counts.items())
        )
        n = contents.out_of_order
        note = (f"{n} logger stamp{' does' if n == 1 else 's do'} not increase, so scans "
                "are timed by line order (scan k at k s)" if n else "")
        return InputSummary(path, fmt, topics, contents.start_s, contents.end_s,
                            clock_note=note)
    bag = bags.describe_bag(path)
    return InputSummary(path, fmt, bag.topics, bag.start_s, bag.end_s, bag.frames)


def _matches(sensor: SensorConfig, path: Path) -> bool:
    return any(
        fnmatch.fnmatchcase(path.name, glob) or fnmatch.fnmatchcase(path.as_posix(), glob)
        for glob in sensor.inputs
    )


def _scan_topics(summary: InputSummary) -> list[str]:
    return autodetect.scan_topics(summary.topics)


def _only(path: Path, summary: InputSummary, names: list[str], what: str,
          sensor: str | None) -> str:
    if len(names) == 1:
        return names[0]
    found = "none" if not names else ", ".join(names)
    key = "scan_topic" if what == "LaserScan" else "pose_topic"
    whose = f" for sensor '{sensor}'" if sensor else ""
    fix = (f"set {key} in that sensors entry" if sensor
           else f"add a `sensors:` entry with {key} to the config")
    raise GpoccError(
        f"{path}: cannot choose the {what} topic{whose} (found: {found}; all topics: "
        f"{summary.listing()}); {fix}"
    )


def default_sensor(summary: InputSummary) -> SensorConfig:
    """The sensor used for an input when the config has no ``sensors``.

    A CARMEN log: one sensor named after the file stem. A bag: its only LaserScan topic
    and its only pose topic, the sensor named after the scan topic (``/scan`` ->
    ``scan``).

    Raises:
        GpoccError: a bag with no or several LaserScan or pose topics, listing the topics.
    """
    path = summary.path
    if summary.format == "carmen":
        return SensorConfig(name=path.stem)
    scan = _only(path, summary, _scan_topics(summary), "LaserScan", None)
    pose = autodetect.pose_topic_for(_contents(summary), scan, path)
    return SensorConfig(name=autodetect.sensor_name(scan), scan_topic=scan, pose_topic=pose)


def _contents(summary: InputSummary) -> BagContents:
    return BagContents(summary.format, summary.topics, summary.start_s, summary.end_s,
                       summary.frames)


def _resolve_bag_sensor(summary: InputSummary, sensor: SensorConfig) -> SensorConfig:
    path = summary.path
    scan = sensor.scan_topic or _only(path, summary, _scan_topics(summary), "LaserScan",
                                      sensor.name)
    contents = _contents(summary)
    pose = bags.TF_POSE if sensor.pose_topic in ("tf", bags.TF_POSE) else sensor.pose_topic
    if pose is None and contents.topic(scan) is not None:  # else check_topics names scan
        pose = autodetect.pose_topic_for(contents, scan, path, sensor.name)
    return replace(sensor, scan_topic=scan, pose_topic=pose)


def sensors_for_input(summary: InputSummary, config: Config) -> list[SensorConfig]:
    """The config entries that apply to one input, with their topics filled in.

    Raises:
        GpoccError: no entry applies, a required topic is missing or has the wrong type,
            or a topic cannot be chosen unambiguously.
    """
    path = summary.path
    if not config.sensors:
        if summary.format == "carmen":
            return [default_sensor(summary)]
        return autodetect.detect_sensors(_contents(summary), path)
    applicable = [s for s in config.sensors if not s.inputs or _matches(s, path)]
    if not applicable:
        globs = ", ".join(f"{s.name}: {list(s.inputs)}" for s in config.sensors)
        raise GpoccError(
            f"{path}: no `sensors` entry of the config applies to this input (inputs globs: "
            f"{globs}); add a glob matching '{path.name}' to an entry's inputs"
        )
    if summary.format == "carmen":
        explicit = [s for s in applicable if s.inputs]
        chosen = explicit or applicable
        if len(chosen) > 1:
            names = ", ".join(s.name for s in chosen)
            raise GpoccError(
                f"{path}: several `sensors` entries ({names}) apply to this CARMEN log, which "
                "holds one laser; give each entry an inputs glob"
            )
        return chosen
    contents = _contents(summary)
    resolved = []
    for sensor in applicable:
        if not sensor.inputs and sensor.scan_topic and contents.topic(sensor.scan_topic) is None:
            continue  # an entry for another input's robot
        full = _resolve_bag_sensor(summary, sensor)
        bags.check_topics(path, contents, full)
        resolved.append(full)
    if not resolved:
        if len(applicable) == 1:
            bags.check_topics(path, contents, applicable[0])  # raises: names topic and file
        wanted = ", ".join(f"{s.scan_topic} ({s.name})" for s in applicable)
        raise GpoccError(
            f"{path}: none of the configured scan topics ({wanted}) is in this input; topics "
            f"present: {summary.listing()}; add a `sensors:` entry for it"
        )
    return resolved


def read_input(path: str | Path, config: Config,
               summary: InputSummary | None = None) -> list[ScanBatch]:
    """The scans of one input: one batch per sensor that applies to it.

    Each batch carries the sensor config entry resolved for it (``sensor_config``), so
    later stages never look a sensor up by name again.
    """
    path = Path(path)
    summary = summary or describe_input(path)
    sensors = sensors_for_input(summary, config)
    if summary.format == "carmen":
        batches = [carmen.read_carmen(path, sensors[0])]
    else:
        batches = bags.read_bag(path, sensors)
    # A reader may resolve more (a point cloud's defaults and layout): its entry wins.
    # A recording made in another map frame: its poses moved into the job's (config inputs).
    transform = input_transform(path, config)
    return [transform_batch(replace(b, sensor_config=b.sensor_config or s), transform)
            for b, s in zip(batches, sensors, strict=True)]


def read_inputs(paths: Sequence[str | Path], config: Config) -> list[ScanBatch]:
    """Read every input into scan batches, one per (input, sensor).

    Batches of one sensor from several inputs stay separate (their ``source`` differs).

    Raises:
        GpoccError: no inputs, any unreadable input or topic problem, or no scans at all.
    """
    if not paths:
        raise GpoccError("no inputs given; pass one or more bags, MCAP files or CARMEN logs")
    check_distinct(paths)
    batches: list[ScanBatch] = []
    for p in paths:
        batches.extend(read_input(p, config))
    for b in batches:
        debug(f"{b.source}: sensor '{b.sensor}': {b.n_scans} scans of {b.n_beams} beams, "
              f"range {b.range_min:g}..{b.range_max:g} m, pose covariance from "
              f"{'the input' if b.has_pose_covariance else 'the config'}, "
              f"{b.skipped_scans} scans skipped")
    for entry in config.inputs:
        if not any(entry_matches(entry.path, p) for p in paths):
            log(f"note: the config's inputs entry '{entry.path}' matches none of these "
                "inputs (by file name or trailing folders); its transform applies to none")
    used = {b.sensor for b in batches}
    for sensor in config.sensors:
        if sensor.name not in used:
            topic = f" ({sensor.scan_topic})" if sensor.scan_topic else ""
            log(f"note: sensor '{sensor.name}'{topic} reads nothing from these inputs")
    if sum(b.n_scans for b in batches) == 0:
        names = ", ".join(str(p) for p in paths)
        raise GpoccError(f"{names}: no laser scans in the inputs; check the topics and files")
    return batches
