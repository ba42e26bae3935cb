"""``sensor_msgs/msg/PointCloud2`` messages as numpy arrays, without per-point Python loops.

A cloud's bytes are viewed through a numpy structured dtype built from the message's
own field list (name, offset, datatype), its ``point_step`` (padding between points),
``row_step`` (padding at the end of a row of an organised cloud) and ``is_bigendian``:
``x``, ``y``, ``z`` as float32 or float64 at any offset, and the optional ``ring``,
per-point time (``t``, ``time``, ``timestamp``, ``time_offset``) and ``intensity``.

Points whose ``x``, ``y`` or ``z`` is not finite, or which are exactly at the sensor
origin (drivers such as Ouster's and Velodyne's organised output write zeros for "no
return"), are no returns: they are dropped here and never become obstacles.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from gpocc.errors import GpoccError

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"

#: sensor_msgs/PointField datatype codes -> numpy kinds.
POINTFIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
#: Names drivers use for the per-point time field (Ouster ``t``, Velodyne ``time``,
#: Hesai ``timestamp``, Livox ``time_offset`` / ``offset_time``).
TIME_FIELDS = ("t", "time", "timestamp", "time_offset", "offset_time")
RING_FIELDS = ("ring", "channel", "line", "laser_id")


@dataclass(frozen=True)
class Cloud:
    """The returns of one PointCloud2 message.

    Attributes:
        points: (P, 3) every point of the message, metres in its frame (a view into the
            message's bytes where the layout allows); float32 unless a coordinate is
            float64. P = ``n_points``.
        n_points: points in the message, returns and no-returns (``height * width``).
        height, width: the message's layout (``height > 1``: organised, one row per ring).
        fields: the message's field names, in order.
        columns: the message's points (structured, all of them), from which
            :attr:`ring`, :attr:`time` and :attr:`intensity` are read when asked for
            (the projection needs none of them).
    """

    points: np.ndarray
    n_points: int
    height: int
    width: int
    fields: tuple[str, ...]
    columns: np.ndarray | None = None

    @cached_property
    def returns(self) -> np.ndarray:
        """(P,) bool, the points that are returns (:func:`returns_mask`). Computed when
        first asked for: the projection tests only the points in its height band."""
        return returns_mask(self.points)

    @property
    def organised(self) -> bool:
        return self.height > 1

    @property
    def xyz(self) -> np.ndarray:
        """(N, 3) the returns only (a copy)."""
        return self.points[self.returns]

    def _column(self, names: tuple[str, ...]) -> np.ndarray | None:
        if self.columns is None:
            return None
        points = self.columns
        name = next((n for n in names if n in (points.dtype.names or ())), None)
        if name is None:
            return None
        values = points[name]
        return (values[:, 0] if values.ndim > 1 else values)[self.returns]

    @property
    def ring(self) -> np.ndarray | None:
        """(N,) laser ring of each return (the field's type; an organised cloud's row
        without a ring field), or None."""
        ring = self._column(RING_FIELDS)
        if ring is None and self.organised and self.columns is not None:
            ring = np.repeat(np.arange(self.height), self.width)[self.returns]
        return ring

    @property
    def time(self) -> np.ndarray | None:
        """(N,) per-point time field as recorded (its type and units), or None."""
        return self._column(TIME_FIELDS)

    @property
    def has_time(self) -> bool:
        return any(n in self.fields for n in TIME_FIELDS)

    @property
    def intensity(self) -> np.ndarray | None:
        return self._column(("intensity",))


def _field_dtype(datatype: int, count: int, endian: str, where: str, name: str) -> np.dtype:
    kind = POINTFIELD_TYPES.get(int(datatype))
    if kind is None:
        raise GpoccError(f"{where}: field {name} has datatype {datatype}, not a "
                         "sensor_msgs/PointField type (1..8); fix the driver")
    base = np.dtype(endian + kind)
    return base if count <= 1 else np.dtype((base, (int(count),)))


def decode_cloud(msg: Any, where: str) -> Cloud:
    """The returns of one PointCloud2 message (see the module docs).

    Args:
        msg: a deserialised ``sensor_msgs/msg/PointCloud2``.
        where: ``file: topic T at t=...`` for error messages.

    Raises:
        GpoccError: no ``x``/``y``/``z`` field or a non-float one, fields beyond
            ``point_step``, or fewer bytes than the layout needs; naming the field.
    """
    height, width = int(msg.height), int(msg.width)
    step, row_step = int(msg.point_step), int(msg.row_step)
    endian = ">" if msg.is_bigendian else "<"
    fields = {f.name: f for f in msg.fields}
    names = tuple(f.name for f in msg.fields)
    if not names and height * width == 0:  # a default-constructed, empty message
        return Cloud(np.zeros((0, 3), np.float32), 0, height, width, names)
    for axis in ("x", "y", "z"):
        f = fields.get(axis)
        if f is None:
            raise GpoccError(f"{where}: the cloud has no field {axis} (fields: "
                             f"{', '.join(names) or 'none'}); it is not an x, y, z point "
                             "cloud: pick another scan_topic")
        if int(f.datatype) not in (7, 8):
            raise GpoccError(f"{where}: field {axis} has datatype {f.datatype}, not FLOAT32 (7) "
                             "or FLOAT64 (8); fix the driver's output")
    wanted = ["x", "y", "z"]
    wanted += [n for n in RING_FIELDS if n in fields][:1]
    wanted += [n for n in TIME_FIELDS if n in fields][:1]
    wanted += [n for n in ("intensity",) if n in fields]
    formats, offsets = [], []
    for name in wanted:
        f = fields[name]
        dt = _field_dtype(f.datatype, int(f.count), endian, where, name)
        if int(f.offset) < 0 or int(f.offset) + dt.itemsize > step:
            raise GpoccError(f"{where}: field {name} at offset {f.offset} ({dt.itemsize} bytes) "
                             f"does not fit in point_step={step}; fix the driver's output")
        formats.append(dt)
        offsets.append(int(f.offset))
    dtype = np.dtype({"names": wanted, "formats": formats, "offsets": offsets,
                      "itemsize": step})
    data = np.asarray(msg.data, dtype=np.uint8)
    n = height * width
    if height > 1 and row_step < width * step:
        raise GpoccError(f"{where}: row_step={row_step} is less than width * point_step = "
                         f"{width * step}; fix the driver's output")
    rows = row_step if height > 1 else width * step
    need = (height - 1) * rows + width * step if n else 0
    if data.size < need:
        raise GpoccError(f"{where}: the cloud holds {data.size} bytes, its layout "
                         f"({height} x {width} points of {step} bytes, row_step {row_step}) "
                         f"needs {need}; the message is cut off: drop it or re-record")
    if n == 0:
        return Cloud(np.zeros((0, 3)), 0, height, width, names)
    points = np.ndarray((height, width), dtype=dtype, buffer=data.data,
                        strides=(rows, step)).reshape(-1)
    # float32 clouds stay float32 (millimetres at a kilometre): the projection's matrix
    # product and arctan2 run twice as fast on them.
    kind = np.float64 if 8 in (int(fields[a].datatype) for a in "xyz") else np.float32
    xyz = _xyz_view(data, fields, n, step, rows, width, endian)
    if xyz is None:
        xyz = np.empty((n, 3), kind)
        for k, axis in enumerate("xyz"):
            xyz[:, k] = points[axis]
    return Cloud(xyz, n, height, width, names, points)


def returns_mask(xyz: np.ndarray) -> np.ndarray:
    """(N,) bool: which points (N, 3) of a cloud, in the lidar's own frame, are returns:
    finite and not all zero (beyond about 1e19 m, where the square overflows in float32,
    is no return either)."""
    return is_return(xyz[:, 0], xyz[:, 1], xyz[:, 2])


def is_return(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """:func:`returns_mask` of the points' coordinates (N,) each."""
    with np.errstate(over="ignore", invalid="ignore"):
        square = x * x
        square += y * y
        square += z * z
        # One comparison each side: NaN fails both, as isfinite(square) & (square > 0).
        return (square > 0) & (square < np.inf)


def _xyz_view(data: np.ndarray, fields: dict, n: int, step: int, rows: int, width: int,
              endian: str) -> np.ndarray | None:
    """(n, 3) a strided view of x, y, z when they are consecutive native floats of one
    type in rows without padding (the common driver layout), else None."""
    types = {int(fields[a].datatype) for a in "xyz"}
    size = 4 if types == {7} else 8 if types == {8} else 0
    x = int(fields["x"].offset)
    if (not size or endian != "<" or np.little_endian is False or step % size or x % size
            or int(fields["y"].offset) != x + size or int(fields["z"].offset) != x + 2 * size
            or rows != width * step):
        return None
    flat = data[: n * step].view(np.float32 if size == 4 else np.float64)
    return flat.reshape(n, step // size)[:, x // size: x // size + 3]


def ring_count(cloud: Cloud) -> int | None:
    """The number of rings: rows of an organised cloud, distinct ``ring`` values, or None."""
    if cloud.organised:
        return cloud.height
    if cloud.ring is not None and cloud.ring.size:
        return int(np.unique(cloud.ring).size)
    return None


def horizontal_bins(cloud: Cloud) -> int | None:
    """Bins of a full turn at the lidar's horizontal resolution, from the cloud's layout.

    An organised cloud has one column per firing (``width``); an unorganised one with a
    ``ring`` field has as many firings per turn as its fullest ring has returns (no-returns
    dropped by the driver make this a lower bound). None when neither tells.
    """
    if cloud.organised:
        return cloud.width
    if cloud.ring is not None and cloud.ring.size:
        _, counts = np.unique(cloud.ring, return_counts=True)
        return int(counts.max())
    return None
