"""CARMEN text logs (``FLASER`` and ``ROBOTLASER1`` lines) as :class:`ScanBatch`.

CARMEN logs record the world pose of the laser with every scan, so the pose is the
laser pose and the mount offset is zero unless the config says otherwise. They carry no
pose covariance: the sensor config's covariance is filled in and
``has_pose_covariance`` is False.

Time stamps: the logger time stamp (last token of a line) when it strictly increases
over the whole log, else the line order (scan k at k seconds). Logs post-processed by a
SLAM front end (``intel.gfs.log``) have a few out-of-order stamps, so they get line order.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gpocc.config import SensorConfig
from gpocc.errors import GpoccError
from gpocc.io.layouts import CommonLayout, common_layout
from gpocc.io.scans import MAX_POSITION_M, ScanBatch, position_in_range
from gpocc.progress import log

#: Readings at or above this are CARMEN's "no return" code (81.83 m, 81.91 m in practice).
NO_RETURN_M = 81.8

#: First tokens of CARMEN log lines; used to recognise a log whatever its suffix.
MESSAGE_TYPES = frozenset({
    "FLASER", "RLASER", "LASER3", "LASER4", "ROBOTLASER1", "ROBOTLASER2", "RAWLASER1",
    "RAWLASER2", "RAWLASER3", "RAWLASER4", "ODOM", "TRUEPOS", "PARAM", "SYNC", "NEFF",
    "GPSNMEA", "SONAR", "BUMPER", "SCANMARK", "POSITIONLASER", "IMU", "VECTORMOVE",
})

_SKIPPED = ("#",)


@dataclass(frozen=True)
class CarmenContents:
    """What a CARMEN log holds: message counts and the logger time span (seconds)."""

    counts: dict[str, int]
    start_s: float | None
    end_s: float | None
    #: Scan lines whose logger stamp does not increase (the scans are then timed by line
    #: order, scan k at k seconds: :func:`read_carmen`).
    out_of_order: int = 0


def _flaser_bearings(n: int) -> np.ndarray:
    """(n,) bearings of a FLASER scan: a 180 degree fan starting at the robot's right.

    Even counts (180, 360: CARMEN's usual) step pi/n from -pi/2; odd counts (181, 361)
    include both ends of the fan, so they step pi/(n - 1).
    """
    step = math.pi / (n - 1) if n % 2 == 1 and n > 1 else math.pi / n
    return -math.pi / 2 + np.arange(n) * step


def is_carmen_text(head: bytes) -> bool:
    """Whether the first bytes of a file look like a CARMEN log."""
    try:
        text = head.decode("ascii")
    except UnicodeDecodeError:
        return False
    for line in text.splitlines():
        tokens = line.split()
        if not tokens or tokens[0].startswith(_SKIPPED):
            continue
        return tokens[0] in MESSAGE_TYPES
    return False


def _lines(path: Path) -> list[str]:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise GpoccError(f"{path}: cannot read the file ({exc.strerror}); check the path") from None
    if not data.strip():
        raise GpoccError(f"{path}: the file is empty; pass a CARMEN log with FLASER lines")
    try:
        return data.decode("ascii").splitlines()
    except UnicodeDecodeError as exc:
        raise GpoccError(
            f"{path}: not a text CARMEN log (binary byte at offset {exc.start}); "
            "pass a .log/.clf text file, or a .bag/.mcap with a matching suffix"
        ) from None


def _not_increasing(stamps: np.ndarray) -> int:
    """Steps of ``stamps`` (N,) s, in line order, that do not increase (NaN included):
    with any, a log's scans are timed by line order."""
    return int(np.count_nonzero(~(np.diff(stamps) > 0)))


def describe_carmen(path: str | Path) -> CarmenContents:
    """Count the message types of a CARMEN log and its logger time span."""
    path = Path(path)
    counts: Counter[str] = Counter()
    stamps: list[float] = []
    by_type: dict[str, list[float]] = {"FLASER": [], "ROBOTLASER1": []}
    for line in _lines(path):
        # Only the first and last tokens matter: splitting whole lines took 0.04 s of
        # every Intel job (and its reader splits them again).
        head = line.split(None, 1)
        if not head or head[0].startswith(_SKIPPED):
            continue
        counts[head[0]] += 1
        if head[0] in ("FLASER", "ROBOTLASER1"):
            try:
                stamps.append(float(line.rsplit(None, 1)[-1]))
                by_type[head[0]].append(stamps[-1])
            except ValueError:
                pass
    # Of the line type the reader reads (FLASER where there are any: read_carmen); a log
    # may write a FLASER and a ROBOTLASER1 line of one scan.
    read = by_type["FLASER"] or by_type["ROBOTLASER1"]
    return CarmenContents(
        counts=dict(counts),
        start_s=min(stamps) if stamps else None,
        end_s=max(stamps) if stamps else None,
        out_of_order=_not_increasing(np.asarray(read, dtype=float)),
    )


def _parse_numbers(path: Path, lineno: int, tokens: list[str], expected: str) -> np.ndarray:
    try:
        return np.asarray(tokens, dtype=float)
    except ValueError:
        bad = next(t for t in tokens if not is_number(t))
        raise GpoccError(
            f"{path}: line {lineno}: non-numeric value {bad!r} in a {expected} line; "
            "fix or delete that line"
        ) from None


def is_number(token: str) -> bool:
    """Whether ``token`` parses as a float."""
    try:
        float(token)
    except ValueError:
        return False
    return True


@dataclass(frozen=True)
class _Scan:
    lineno: int
    ranges: np.ndarray
    angles: np.ndarray
    pose: np.ndarray
    logger_stamp: float
    no_return_m: float = NO_RETURN_M


def _parse_flaser(path: Path, lineno: int, tokens: list[str]) -> _Scan:
    # FLASER n r_0 .. r_{n-1} x y th odom_x odom_y odom_th ipc_ts host logger_ts
    try:
        n = int(tokens[1])
    except (IndexError, ValueError):
        raise GpoccError(
            f"{path}: line {lineno}: FLASER needs the beam count as its second token; "
            "fix or delete that line"
        ) from None
    if n <= 0:
        raise GpoccError(
            f"{path}: line {lineno}: FLASER with {n} beams (the second token); a scan needs "
            "at least one beam: fix or delete that line"
        )
    if len(tokens) != n + 11:
        raise GpoccError(
            f"{path}: line {lineno}: FLASER with {n} beams needs {n + 11} tokens, got "
            f"{len(tokens)} ({'truncated line' if len(tokens) < n + 11 else 'extra tokens'}?); "
            "fix or delete that line"
        )
    values = _parse_numbers(path, lineno, tokens[2 : n + 8] + [tokens[-1]], "FLASER")
    return _Scan(lineno, values[:n], _flaser_bearings(n), values[n : n + 3], float(values[-1]))


def _parse_robotlaser(path: Path, lineno: int, tokens: list[str]) -> _Scan:
    # ROBOTLASER1 type start fov res max_range accuracy remission_mode n r_0..r_{n-1}
    #   m rem_0..rem_{m-1} laser_x laser_y laser_th robot_x robot_y robot_th tv rv
    #   forward_safety side_safety turn_axis ipc_ts host logger_ts
    try:
        n = int(tokens[8])
        m = int(tokens[9 + n])
    except (IndexError, ValueError):
        raise GpoccError(
            f"{path}: line {lineno}: ROBOTLASER1 line is truncated or its reading counts are "
            "not integers; fix or delete that line"
        ) from None
    if n <= 0 or m < 0 or len(tokens) != 10 + n + m + 14:
        raise GpoccError(
            f"{path}: line {lineno}: ROBOTLASER1 with {n} readings and {m} remissions needs "
            f"{24 + n + m} tokens, got {len(tokens)}; fix or delete that line"
        )
    start, _fov, res, max_range = _parse_numbers(path, lineno, tokens[2:6], "ROBOTLASER1")
    if not (np.isfinite(start) and np.isfinite(res) and 0.0 < abs(res) <= np.pi):
        raise GpoccError(
            f"{path}: line {lineno}: ROBOTLASER1 start angle {start} and angular resolution "
            f"{res} must be finite, with the resolution in (0, pi] radians; fix or delete "
            "that line")
    ranges = _parse_numbers(path, lineno, tokens[9 : 9 + n], "ROBOTLASER1")
    tail = tokens[10 + n + m :]
    pose = _parse_numbers(path, lineno, tail[0:3] + [tail[-1]], "ROBOTLASER1")
    angles = start + np.arange(n) * res
    return _Scan(lineno, ranges, angles, pose[:3], float(pose[3]), float(max_range))


def read_carmen(path: str | Path, sensor: SensorConfig) -> ScanBatch:
    """Read the laser scans of a CARMEN log.

    ``FLASER`` lines are used; a log without them falls back to ``ROBOTLASER1`` (whose
    laser pose, beam fan and maximum range are read from the line). Ranges at or above
    81.8 m (FLASER) or the line's maximum range (ROBOTLASER1) become ``+inf`` (no
    return); ``range_max`` is that value unless the config sets ``range_max_m``. Scans
    of several layouts (FLASER beam counts, ROBOTLASER1 fans) are placed on one, their
    bearing shifts added to the bearing variance (:mod:`gpocc.io.layouts`; the batch's
    ``sensor_config``).

    Args:
        path: the log file.
        sensor: the config entry for this log (name, covariance, range limits).

    Returns:
        One batch: ``poses`` (S, 3) are the laser poses (x m, y m, yaw rad).

    Raises:
        GpoccError: empty or binary file, a malformed scan line (its line number), no
            scans, or scan layouts that do not fit one laser (:mod:`gpocc.io.layouts`).
    """
    path = Path(path)
    lines = _lines(path)
    # The usual log (FLASER lines of one beam count) in one compiled pass; anything else,
    # a malformed line included, line by line, which names it.
    table = _flaser_table(lines) or _scan_table(path, lines)
    ranges, poses = table.ranges, table.poses
    ranges[ranges >= table.no_return_m] = np.inf
    if not np.isfinite(poses).all():
        bad = table.linenos[int(np.flatnonzero(~np.isfinite(poses).all(axis=1))[0])]
        raise GpoccError(f"{path}: line {bad}: the pose is not finite; fix or delete that line")
    far = next((k for k, pose in enumerate(poses) if not position_in_range(*pose[:2])), None)
    if far is not None:
        raise GpoccError(f"{path}: line {table.linenos[far]}: the pose has a coordinate beyond "
                         f"{MAX_POSITION_M:g} m; fix or delete that line")
    logger = table.logger_stamps
    monotonic = bool(np.isfinite(logger).all()) and _not_increasing(logger) == 0
    n_scans = len(table.linenos)
    stamps = logger if monotonic else np.arange(n_scans, dtype=float)
    covariance = np.broadcast_to(sensor.pose_covariance_matrix, (n_scans, 3, 3)).copy()
    resolved = None
    if table.layout is not None:
        log(f"note: {path}: {table.layout.describe()}")
        resolved = table.layout.widened(sensor)
    return ScanBatch(
        sensor=sensor.name,
        source=str(path),
        stamps=stamps,
        # An upside-down laser sweeps clockwise seen from above: mirrored bearings.
        angles=-table.angles if sensor.mount.upside_down else table.angles.copy(),
        ranges=ranges,
        poses=poses,
        pose_covariances=covariance,
        range_min=sensor.range_min_m if sensor.range_min_m is not None else 0.0,
        range_max=sensor.range_max_m if sensor.range_max_m is not None else table.no_return_m,
        has_pose_covariance=False,
        skipped_scans=0,
        # The bearing variance grown by the layouts' rounding (None: the entry as given).
        sensor_config=resolved,
    )


@dataclass(frozen=True)
class _ScanTable:
    """A log's scans: line numbers (S,), ranges (S, n) m, bearings (n,) rad, laser poses
    (S, 3) (x m, y m, yaw rad), logger stamps (S,) s and the no-return range, m."""

    linenos: list[int]
    ranges: np.ndarray
    angles: np.ndarray
    poses: np.ndarray
    logger_stamps: np.ndarray
    no_return_m: float
    # The scans' several layouts placed on one (None: they share one).
    layout: CommonLayout | None = None


def _flaser_table(lines: list[str]) -> _ScanTable | None:
    """The FLASER scans of a log whose every FLASER line is well formed, with one beam
    count, and which has no ROBOTLASER1 line; else None (:func:`_scan_table` then reads
    it line by line and names what is wrong).

    The lines' numbers are read in one compiled pass (:func:`gpocc.compiled.parse_rows`:
    the doubles ``float`` reads from each token, a fifth of the time or less).
    """
    linenos: list[int] = []
    bodies: list[str] = []
    stamps: list[str] = []
    beams = 0
    for lineno, line in enumerate(lines, start=1):
        head = line.split(None, 2)
        if not head or head[0] != "FLASER":
            if head and head[0] == "ROBOTLASER1":
                return None
            continue
        # FLASER n r_0 .. r_{n-1} x y th odom_x odom_y odom_th ipc_ts host logger_ts
        try:
            n = int(head[1])
            body, _ipc, _host, stamp = head[2].rsplit(None, 3)
        except (IndexError, ValueError):
            return None
        if n <= 0 or (beams and n != beams) or n + 6 > (len(body) + 1) // 2:
            return None
        beams = n
        linenos.append(lineno)
        bodies.append(body)
        stamps.append(stamp)
    if not bodies:
        return None
    try:
        from gpocc import compiled  # here: reading logs must not need the compiled loops
    except ImportError:
        return None
    values = compiled.parse_rows("\n".join(bodies).encode("ascii"), beams + 6, len(bodies))
    if values is None:
        return None
    try:
        logger = np.asarray(stamps, dtype=float)
    except ValueError:
        return None
    return _ScanTable(linenos, np.ascontiguousarray(values[:, :beams]), _flaser_bearings(beams),
                      np.ascontiguousarray(values[:, beams:beams + 3]), logger, NO_RETURN_M)


def _scan_table(path: Path, lines: list[str]) -> _ScanTable:
    """The scans of a log read line by line: FLASER lines, else ROBOTLASER1 lines; a
    malformed line, no scan or two beam counts is a :class:`GpoccError` naming it."""
    flaser: list[_Scan] = []
    robotlaser: list[_Scan] = []
    for lineno, line in enumerate(lines, start=1):
        tokens = line.split()
        if not tokens:
            continue
        if tokens[0] == "FLASER":
            flaser.append(_parse_flaser(path, lineno, tokens))
        elif tokens[0] == "ROBOTLASER1":
            robotlaser.append(_parse_robotlaser(path, lineno, tokens))
    scans = flaser or robotlaser
    if not scans:
        raise GpoccError(
            f"{path}: no FLASER or ROBOTLASER1 lines, so no laser scans; pass a CARMEN log "
            "with laser data"
        )
    # FLASER's bearings follow from the beam count; ROBOTLASER1 lines state their own.
    # Scans of several layouts (beam counts, or ROBOTLASER1 resolutions) go on one
    # (gpocc.io.layouts).
    first = scans[0].angles
    same = all(s.angles.shape == first.shape and np.abs(s.angles - first).max() <= 1e-9
               for s in scans)
    layout = None if same else common_layout(
        str(path), [s.ranges for s in scans],
        [(s.angles.shape[0], float(s.angles[0]),
          float(s.angles[1] - s.angles[0]) if s.angles.shape[0] > 1 else 0.0) for s in scans])
    return _ScanTable([s.lineno for s in scans],
                      np.stack([s.ranges for s in scans]) if same else layout.ranges,
                      first if same else layout.angles, np.stack([s.pose for s in scans]),
                      np.array([s.logger_stamp for s in scans]),
                      min(s.no_return_m for s in scans), layout)
