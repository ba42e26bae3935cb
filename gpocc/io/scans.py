"""The readers' output: laser scans with the robot's pose and pose covariance."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gpocc.config import SensorConfig

#: Largest |x| or |y| a pose may have, metres: beyond any planetary frame (UTM northings
#: stay below 1e7), and far below where squaring a coordinate overflows.
MAX_POSITION_M = 1e8


def position_in_range(*coordinates: float) -> bool:
    """Whether every coordinate (metres) is finite and within :data:`MAX_POSITION_M`.

    Plain Python on purpose: readers call it once per pose message or TF transform, where
    building a numpy array cost 23 us against under 1 us.
    """
    return all(abs(v) <= MAX_POSITION_M for v in coordinates)  # NaN compares False


@dataclass(frozen=True)
class Provenance:
    """Where a batch's poses and covariances came from, for ``gpocc info`` and warnings.

    Attributes:
        pose_source: e.g. ``TF map->laser`` or ``topic /amcl_pose``.
        frame_chain: the TF chain used (empty without TF).
        covariance_source: e.g. ``/amcl_pose (held up to 30 s)`` or ``config``.
        skipped: (reason, config key, count) of dropped scans.
        notes: counted repairs and fallbacks.
        stamps: which clock times each topic used (``/scan: header stamps; ...``).
        sensor_lines: what the reader saw of the sensor, for ``gpocc info`` (a point
            cloud's points, fields, rings, heights and equivalent scan).
    """

    pose_source: str
    frame_chain: str = ""
    covariance_source: str = ""
    skipped: tuple[tuple[str, str, int], ...] = ()
    notes: tuple[str, ...] = field(default=())
    stamps: str = ""
    sensor_lines: tuple[str, ...] = ()


@dataclass(frozen=True)
class ScanBatch:
    """All scans of one sensor (one robot's laser), aligned on the scan index.

    Ranges are kept raw, as recorded (REP 117): NaN invalid, ``-inf`` too close, ``+inf``
    no return. Values outside ``[range_min, range_max]`` are classified later, by the
    samples stage. A reader converts a format's own no-return code (CARMEN's 81.8 m) to
    ``+inf``.

    Attributes:
        sensor: sensor name (the config entry's ``name``).
        source: file the scans came from (for messages).
        stamps: (S,) seconds.
        angles: (B,) beam bearings in the laser frame, radians, counter-clockwise.
        ranges: (S, B) metres.
        poses: (S, 3) robot base pose (x m, y m, yaw rad) in the map frame.
        pose_covariances: (S, 3, 3) covariance of (x, y, yaw), m^2 / rad^2.
        range_min: metres; ranges below are not hits.
        range_max: metres; ranges above are not hits.
        has_pose_covariance: whether the covariances came from the input (False: the
            input had none, or the config overrides them, and the reader filled in the
            sensor config's ``pose_covariance``).
        skipped_scans: scans dropped for want of a pose within the allowed gap.
        sensor_config: the config entry the reader resolved for this sensor (topics
            filled in); None for a batch not made by a reader, which
            :func:`gpocc.samples.beam_rules.sensor_config` then matches by name.
        provenance: pose and covariance sources of a bag's batch (None: not recorded).
    """

    sensor: str
    source: str
    stamps: np.ndarray
    angles: np.ndarray
    ranges: np.ndarray
    poses: np.ndarray
    pose_covariances: np.ndarray
    range_min: float
    range_max: float
    has_pose_covariance: bool = True
    skipped_scans: int = 0
    sensor_config: SensorConfig | None = None
    provenance: Provenance | None = None

    @property
    def n_scans(self) -> int:
        return int(self.ranges.shape[0])

    @property
    def n_beams(self) -> int:
        return int(self.ranges.shape[1])


def scan_stamps(batches: list[ScanBatch]) -> tuple[float | None, float | None]:
    """(first, last) scan stamp of ``batches``, seconds; (None, None) without scans.

    CARMEN logs whose logger stamps do not increase are read in line order, and their
    stamps are scan numbers (:mod:`gpocc.io.carmen`).
    """
    stamps = [np.asarray(b.stamps, dtype=float) for b in batches if b.n_scans]
    if not stamps:
        return None, None
    return (float(min(s.min() for s in stamps)), float(max(s.max() for s in stamps)))
