"""``map.mcap``: a map's layers as ROS 2 ``nav_msgs/msg/OccupancyGrid`` messages in MCAP.

Foxglove opens the file beside the input bag, ``ros2 bag play`` publishes it as a map
topic, and any MCAP or rosbags reader reads it back. Three topics, all in frame ``map``
and stamped with the last scan's time:

- ``/map``: ``round(100 p)``, -1 where the map has no data;
- ``/map_class``: 0 free, 100 occupied, -1 unsure or no data;
- ``/map_variance``: ``round(100 variance / scale)``, -1 where the map has no data; the
  ``scale`` (the map's largest variance) is in the channel's metadata
  (``variance_scale``), so ``variance = value / 100 * variance_scale``.

Channels offer a latched QoS (reliable, transient local, depth 1: :func:`map_qos_profiles`),
so a played-back map reaches subscribers that start later, as a map server's does.

The variance is an OccupancyGrid too (not ``foxglove.Grid``): one message type that
rosbags, RViz, Nav2 tools and Foxglove all read without a schema package, at a cost of
101 levels (1 % of the scale).

Geometry: ``info.origin`` is the lower-left corner of the lower-left cell (yaw 0), data
row 0 is the southmost row (ROS), ``info.resolution`` is the map's cell size as float32
(the message type's own precision).

Size: an OccupancyGrid holds ``width x height`` int8 cells with uint32 sides and a uint32
sequence length, so one message holds under 2^32 cells; MCAP's own limits are far
beyond that (64-bit record lengths; a message larger than a chunk gets a chunk of its
own), but readers hold a message whole. A map wider or taller than ``MAX_MESSAGE_SIDE``
cells (64 MiB a message) is therefore split into tiles of at most that side, each on its
own topic ``<topic>/tile_<row>_<col>`` (row 0 north, as the map's tiles), so that a
viewer shows them side by side rather than one replacing the other.
"""

from __future__ import annotations

import math
import os
import struct
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from gpocc.errors import GpoccError, check_regular_file
from gpocc.gridspec import GridSpec
from gpocc.io.atomic import atomic_path

MAP_TOPIC, CLASS_TOPIC, VARIANCE_TOPIC = "/map", "/map_class", "/map_variance"
FRAME_ID = "map"
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
#: Largest side of one message, cells: 8192^2 int8 cells = 64 MiB.
MAX_MESSAGE_SIDE = 8192
UNKNOWN = -1


def occupancy_values(probability: np.ndarray) -> np.ndarray:
    """(h, w) int8 ``round(100 p)`` of p(occupied) in [0, 1], -1 where NaN."""
    p = np.asarray(probability)
    out = np.full(p.shape, UNKNOWN, dtype=np.int8)
    known = np.isfinite(p)
    # Only the known cells in double precision (most of a city is no data).
    out[known] = np.rint(100.0 * np.clip(p[known].astype(np.float64), 0.0, 1.0)
                         ).astype(np.int8)
    return out


def class_values(classes: np.ndarray) -> np.ndarray:
    """(h, w) int8 of gpocc classes: 0 free, 100 occupied, -1 unsure (2) or no data (255)."""
    from gpocc.gp.classify import FREE, OCCUPIED

    c = np.asarray(classes)
    out = np.full(c.shape, UNKNOWN, dtype=np.int8)
    out[c == FREE] = 0
    out[c == OCCUPIED] = 100
    return out


def variance_values(variance: np.ndarray, scale: float) -> np.ndarray:
    """(h, w) int8 ``round(100 variance / scale)`` clipped to 0..100, -1 where NaN."""
    v = np.asarray(variance)
    out = np.full(v.shape, UNKNOWN, dtype=np.int8)
    known = np.isfinite(v)
    out[known] = np.rint(np.clip(100.0 * v[known].astype(np.float64) / scale, 0.0, 100.0)
                         ).astype(np.int8)
    return out


def variance_scale(largest: float) -> float:
    """The variance that maps to 100: the map's largest (1 when it has none above 0)."""
    return float(largest) if math.isfinite(largest) and largest > 0.0 else 1.0


@dataclass(frozen=True)
class GridLayer:
    """One topic of ``map.mcap``.

    Attributes:
        topic: e.g. ``/map``.
        values: (window) -> (h, w) int8 cells of that window of the map, row 0 north.
        metadata: the channel's metadata (strings), e.g. what the values mean.
    """

    topic: str
    values: Callable[[GridSpec], np.ndarray]
    metadata: dict[str, str] = field(default_factory=dict)


def message_windows(spec: GridSpec, max_side: int = MAX_MESSAGE_SIDE
                    ) -> list[tuple[int, int, GridSpec]]:
    """(tile row, tile col, window) of each message of a layer, row 0 north; one window
    (the whole map) when it fits in one message."""
    if max_side < 1:
        raise ValueError("max_side must be at least 1")
    return [(r // max_side, c // max_side, spec.window(r, c, max_side, max_side))
            for r in range(0, spec.height, max_side) for c in range(0, spec.width, max_side)]


def tile_topic(topic: str, row: int, col: int) -> str:
    """The topic of tile (row, col) of a split layer."""
    return f"{topic}/tile_{row}_{col}"


@cache
def map_qos_profiles() -> str:
    """The channels' ``offered_qos_profiles`` (required by MCAP's ros2 profile): reliable,
    transient local, keep last 1, as Nav2's map_server offers a map, so ``ros2 bag play``
    latches it for the subscribers that ask for that (RViz, Nav2's costmaps). Integer
    enums (rosbag2 metadata version 8) are read by every ROS 2 release since Humble."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )
    from rosbags.rosbag2.metadata import dump_qos_v8

    default = QosTime(sec=0, nsec=0)  # unspecified: the middleware's default (infinite)
    return dump_qos_v8([Qos(
        history=QosHistory.KEEP_LAST, depth=1, reliability=QosReliability.RELIABLE,
        durability=QosDurability.TRANSIENT_LOCAL, deadline=default, lifespan=default,
        liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=default,
        avoid_ros_namespace_conventions=False)])


#: The definitions (ROS 2 Humble's fields) of OccupancyGrid and the types it holds: the
#: only types a map file needs. rosbags' whole Humble store (every message type of ROS 2,
#: a dataclass each) cost 0.1-0.2 s CPU of every map, on the map's critical path.
MAP_MESSAGE_DEFINITIONS = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/msg/Pose": "Point position\nQuaternion orientation\n",
    "nav_msgs/msg/MapMetaData": "builtin_interfaces/Time map_load_time\nfloat32 resolution\n"
                                "uint32 width\nuint32 height\ngeometry_msgs/Pose origin\n",
    OCCUPANCY_GRID: "std_msgs/Header header\nMapMetaData info\nint8[] data\n",
}


@cache
def _typestore() -> Any:
    """A rosbags type store of :data:`MAP_MESSAGE_DEFINITIONS` alone (the same CDR bytes
    and message definition as the Humble store's, tests/io/test_ros_outputs.py)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    types: dict[str, Any] = {}
    for name, text in MAP_MESSAGE_DEFINITIONS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def _stamp(ts: Any, stamp_ns: int) -> Any:
    return ts.types["builtin_interfaces/msg/Time"](
        sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)


def grid_message(window: GridSpec, values: np.ndarray, stamp_ns: int) -> bytes:
    """The CDR bytes of one OccupancyGrid of ``values`` (h, w) int8 (row 0 north) on
    ``window``, frame ``map``, stamped ``stamp_ns`` (header and ``map_load_time``)."""
    ts = _typestore()
    t = ts.types
    cells = np.asarray(values, dtype=np.int8)
    if cells.shape != window.shape:
        raise ValueError(f"values {cells.shape} do not match the window {window.shape}")
    stamp = _stamp(ts, stamp_ns)
    info = t["nav_msgs/msg/MapMetaData"](
        map_load_time=stamp,
        resolution=float(window.resolution),
        width=window.width,
        height=window.height,
        origin=t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=float(window.x0), y=float(window.y0), z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)),
    )
    msg = t[OCCUPANCY_GRID](
        header=t["std_msgs/msg/Header"](stamp=stamp, frame_id=FRAME_ID),
        info=info,
        # ROS: data row 0 is the southmost row; ours is the northmost.
        data=np.ascontiguousarray(cells[::-1]).reshape(-1),
    )
    return bytes(ts.serialize_cdr(msg, OCCUPANCY_GRID))


def stamp_nanoseconds(stamp_s: float | None) -> int:
    """A stamp in seconds as integer nanoseconds (None or negative: 0)."""
    if stamp_s is None or not math.isfinite(stamp_s) or stamp_s < 0:
        return 0
    return int(round(stamp_s * 1e9))


def write_map_mcap(path: str | os.PathLike[str], spec: GridSpec, layers: Sequence[GridLayer],
                   stamp_ns: int, max_side: int = MAX_MESSAGE_SIDE) -> list[str]:
    """Write ``layers`` of the map on ``spec`` as OccupancyGrid messages, atomically.

    Each layer is one message on its topic, or, when the map is more than ``max_side``
    cells a side, one message per tile on :func:`tile_topic` topics. Every message is
    logged and published at ``stamp_ns``. Only one message's cells are in memory at a
    time.

    Returns:
        the topics written, in order.
    """
    from mcap.writer import CompressionType, Writer

    import gpocc

    ts = _typestore()
    msgdef, _ = ts.generate_msgdef(OCCUPANCY_GRID, ros_version=2)
    windows = message_windows(spec, max_side)
    tiled = len(windows) > 1
    topics = []
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        writer = Writer(fh, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library=f"gpocc {gpocc.__version__}")
        schema = writer.register_schema(name=OCCUPANCY_GRID, encoding="ros2msg",
                                        data=msgdef.encode())
        for layer in layers:
            for row, col, window in windows:
                topic = tile_topic(layer.topic, row, col) if tiled else layer.topic
                channel = writer.register_channel(
                    topic=topic, message_encoding="cdr", schema_id=schema,
                    metadata={**layer.metadata, "offered_qos_profiles": map_qos_profiles()})
                data = grid_message(window, layer.values(window), stamp_ns)
                writer.add_message(channel, log_time=stamp_ns, data=data,
                                   publish_time=stamp_ns, sequence=0)
                topics.append(topic)
        writer.finish()
    return topics


# --------------------------------------------------------------------------- reading


def _messages(path: Path) -> Iterator[tuple[str, dict[str, str], str, bytes]]:
    """(topic, channel metadata, schema name, data) of every message of an MCAP file."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        try:
            reader = make_reader(fh)
            for schema, channel, message in reader.iter_messages(log_time_order=True):
                yield (channel.topic, dict(channel.metadata),
                       schema.name if schema is not None else "", message.data)
        # A truncated file makes the reader seek before its start (OSError EINVAL).
        except (McapError, ValueError, EOFError, KeyError, OSError, struct.error) as exc:
            raise GpoccError(f"{path}: not a readable MCAP file ({exc}); pass a map.mcap "
                             f"written by gpocc or another MCAP map") from None


def read_map_mcap(path: str | os.PathLike[str], topic: str = MAP_TOPIC
                  ) -> tuple[np.ndarray, GridSpec, float]:
    """The occupancy map on ``topic`` of an MCAP file, as p(occupied) on a grid.

    Reads the last OccupancyGrid on ``topic`` or, for a map split into tiles, the last
    message of each ``<topic>/tile_*`` topic, mosaicked. Values 0..100 become ``v / 100``;
    -1 (unknown) becomes NaN.

    Returns:
        ``(p (H, W) float32, grid, nan)``; row 0 is north, as :func:`read_raster`.

    Raises:
        GpoccError: unreadable file, no such topic, another message type, values outside
            -1..100, a rotated origin, or tiles of differing resolutions.
    """
    path = Path(path)
    check_regular_file(path, "map", "check the path")
    prefix = f"{topic}/tile_"
    last: dict[str, bytes] = {}
    for name, _, schema, data in _messages(path):
        if name == topic or name.startswith(prefix):
            if schema != OCCUPANCY_GRID:
                raise GpoccError(f"{path}: topic {name} holds {schema or 'schemaless'} "
                                 f"messages, not {OCCUPANCY_GRID}")
            last[name] = data
    if topic in last:
        chosen = [last[topic]]
    elif last:
        chosen = list(last.values())
    else:
        raise GpoccError(f"{path}: no {OCCUPANCY_GRID} on topic {topic}; pass a map.mcap "
                         f"written by gpocc")
    ts = _typestore()
    grids = [_grid_of(path, ts.deserialize_cdr(data, OCCUPANCY_GRID)) for data in chosen]
    spec = _union(path, [g for _, g in grids])
    values = np.full(spec.shape, np.nan, dtype=np.float32)
    for cells, window in grids:
        row = round((spec.y1 - window.y1) / spec.resolution)
        col = round((window.x0 - spec.x0) / spec.resolution)
        p = np.where(cells < 0, np.nan, cells / 100.0).astype(np.float32)
        values[row:row + window.height, col:col + window.width] = p
    return values, spec, float("nan")


def _grid_of(path: Path, msg: Any) -> tuple[np.ndarray, GridSpec]:
    info = msg.info
    q = info.origin.orientation
    if abs(q.x) > 1e-9 or abs(q.y) > 1e-9 or abs(q.z) > 1e-9:
        raise GpoccError(f"{path}: the map's origin is rotated; only maps aligned with "
                         f"their frame (yaw 0) are supported")
    width, height = int(info.width), int(info.height)
    data = np.asarray(msg.data, dtype=np.int8)
    if data.size != width * height:
        raise GpoccError(f"{path}: an OccupancyGrid holds {data.size} cells, not its "
                         f"{width} x {height}")
    if data.size and (data.min() < -1 or data.max() > 100):
        raise GpoccError(f"{path}: OccupancyGrid values outside -1..100 "
                         f"({data.min()} .. {data.max()})")
    # float32 on the wire: its shortest repr is the cell size the writer meant (0.1).
    resolution = float(str(np.float32(info.resolution)))
    try:
        window = GridSpec(float(info.origin.position.x), float(info.origin.position.y),
                          resolution, width, height)
    except GpoccError as exc:
        raise GpoccError(f"{path}: {exc}") from None
    return data.reshape(height, width)[::-1], window


def _union(path: Path, windows: list[GridSpec]) -> GridSpec:
    res = windows[0].resolution
    if any(not math.isclose(w.resolution, res, rel_tol=1e-9) for w in windows):
        raise GpoccError(f"{path}: the map's tiles have different resolutions")
    x0 = min(w.x0 for w in windows)
    y0 = min(w.y0 for w in windows)
    width = round((max(w.x1 for w in windows) - x0) / res)
    height = round((max(w.y1 for w in windows) - y0) / res)
    return GridSpec(x0, y0, res, width, height)
