"""One beam layout for a laser topic whose scans do not share one.

A LaserScan's beams lie at ``angle_min + k angle_increment`` (k < the number of ranges).
Some drivers publish a different layout in every scan: rplidar_ros and sllidar_ros2 with
``angle_compensate: false`` give each revolution its own beam count and first angle. A
:class:`gpocc.io.scans.ScanBatch` holds one layout, so such scans are placed on a common
lattice of bearings, ``step`` apart, ``step`` the finest increment of any scan (for scans
that together cover a full turn, the lattice is one turn of the nearest whole number of
steps not longer than that): each beam goes to the lattice bearing nearest its own (at
most ``step / 2`` away), bearings no beam of a scan fell on hold NaN (no measurement) in
that scan; a beam half a step off takes the lower of its two. No scan's beams are closer
than ``step``, so along a scan the bearings increase, and two beams of a scan share one
only when they point the same way (a full turn's first and last): the first is kept.
The mean square of the bearing shifts is returned, to be added to the sensor's bearing
variance: the samples stage then widens each sample by the rounding it did not see.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from gpocc.config import SensorConfig
from gpocc.errors import GpoccError

#: A lattice longer than this many times the longest scan means the layouts are not one
#: sensor's jitter (a second laser on the topic, a driver's mode change): refused.
MAX_LATTICE_GROWTH = 2.0
#: Scans placed at a time (bounds the temporary arrays of a long log).
_SCANS_PER_BLOCK = 2048
#: Positions within this many steps of a half step round down (ties, float noise).
_TIE = 1e-6
#: Shifts below this (radians) are float rounding: the beams kept their bearings.
_EXACT_RAD = 1e-9


@dataclass(frozen=True)
class CommonLayout:
    """Scans on one lattice of bearings.

    Attributes:
        angles: (B,) bearings in the laser frame, radians, in the scans' direction.
        ranges: (S, B) metres; NaN where no beam of that scan fell.
        shift_variance_rad2: mean square of the beams' bearing shifts, rad^2.
        max_shift_rad: the largest shift, rad.
        beam_counts: (S,) beams per scan as recorded.
    """

    angles: np.ndarray
    ranges: np.ndarray
    shift_variance_rad2: float
    max_shift_rad: float
    beam_counts: np.ndarray

    def widened(self, sensor: SensorConfig) -> SensorConfig:
        """``sensor`` with the shifts' mean square added to its bearing variance."""
        return dataclasses.replace(
            sensor, bearing_variance_deg2=sensor.bearing_variance_deg2
            + self.shift_variance_rad2 * (180.0 / math.pi) ** 2)

    def describe(self) -> str:
        """One line for the batch's notes."""
        low, high = int(self.beam_counts.min()), int(self.beam_counts.max())
        counts = f"{low}" if low == high else f"{low}-{high}"
        step = abs(float(self.angles[1] - self.angles[0])) if self.angles.size > 1 else 0.0
        placed = (f"the beam layout varies from scan to scan ({counts} beams): beams placed on "
                  f"one layout of {self.angles.size} bearings {math.degrees(step):.3g} deg "
                  "apart")
        if self.max_shift_rad < _EXACT_RAD:
            return placed + ", each on its own bearing"
        return (f"{placed}, each moved at most {math.degrees(self.max_shift_rad):.2g} deg; the "
                f"shifts' mean square ({math.degrees(math.sqrt(self.shift_variance_rad2)):.2g} "
                "deg rms) is added to the bearing variance")


def common_layout(where: str, ranges: list[np.ndarray],
                  layouts: list[tuple[int, float, float]]) -> CommonLayout:
    """Place scans of differing layouts on one lattice (see the module docstring).

    Args:
        where: the file (and topic) for messages.
        ranges: S arrays of metres, the n_s ranges of each scan as recorded.
        layouts: S tuples (n_s, angle_min rad, angle_increment rad), already checked
            (finite, nonzero increment where n_s > 1, agreeing with the ranges).

    Raises:
        GpoccError: scans turning both ways, or layouts too far apart to be one sensor's.
    """
    counts = np.array([n for n, _, _ in layouts], dtype=np.int64)
    first = np.array([a for _, a, _ in layouts])
    increment = np.array([d for _, _, d in layouts])
    several = counts > 1
    if not several.any():
        raise GpoccError(f"{where}: every scan has one beam, at differing angles; a "
                         "single-beam range finder is not a laser scanner gpocc can map with")
    signs = np.sign(increment[several])
    if not (signs == signs[0]).all():
        raise GpoccError(f"{where}: some scans' angle_increment is positive and some negative "
                         "(the beams turn both ways); fix the driver's angle settings")
    sign = float(signs[0])
    step = float(np.abs(increment[several]).min())
    increment = np.where(several, increment, 0.0)
    # Each scan's bearings measured along the scans' direction: its first and last.
    lows = sign * first
    start = float(lows.min())
    end = float((lows + sign * (counts - 1) * increment).max())
    turn = end - start + step > 2 * math.pi - 1e-9
    if turn:
        # A 360-degree scanner whose first angle moves: bearings a turn apart are one
        # direction, so the lattice is one turn of whole steps (no longer than the finest
        # increment, so a scan's beams still find distinct bearings).
        # (Within float32 rounding of the message fields: 2 pi / 180 may come out 180.00001.)
        size = math.ceil(2 * math.pi / step * (1.0 - 1e-6))
        step = 2 * math.pi / size
    else:
        # The last scan's last beam, and one more bearing for a beam that a tie before it
        # pushes on (below); an unused last bearing is dropped at the end.
        size = int(math.floor((end - start) / step + 0.5)) + 2
    if size > MAX_LATTICE_GROWTH * counts.max() + 2:
        raise GpoccError(
            f"{where}: the scans' beam layouts ({counts.min()}-{counts.max()} beams, "
            f"angle_min {math.degrees(first.min()):.1f}..{math.degrees(first.max()):.1f} "
            f"deg, finest increment {math.degrees(step):.3g} deg) do not fit one layout "
            f"of at most {MAX_LATTICE_GROWTH:g} times the longest scan; split the recording "
            "where the layout changes, or give each laser its own topic or log")
    out = np.full((len(ranges), size), np.nan)
    squares, kept_beams, largest = 0.0, 0, 0.0
    # A block of scans at a time: a long log of a dense lidar has 1e8 beams.
    for lo in range(0, len(ranges), _SCANS_PER_BLOCK):
        hi = min(len(ranges), lo + _SCANS_PER_BLOCK)
        k = np.arange(int(counts[lo:hi].max()))
        valid = k[None, :] < counts[lo:hi, None]
        position = (lows[lo:hi, None] + k[None, :] * np.abs(increment[lo:hi, None])
                    - start) / step
        # Nearest bearings, a tie (half a step) to the lower one, alike for every beam of a
        # scan whatever the float noise (rint's half to even would put two beams on one
        # bearing); floor(p + c) grows by at least one per step, so along a scan they
        # increase. A turn's step may exceed an increment by float32 rounding: a beam
        # whose bearing would still repeat its predecessor's takes the next one.
        slot = np.floor(position + (0.5 - _TIE)).astype(np.int64)
        slot = k[None, :] + np.maximum.accumulate(np.where(valid, slot - k[None, :],
                                                           np.iinfo(np.int64).min), axis=1)
        shift = (slot - position) * step
        rows = np.broadcast_to(np.arange(lo, hi)[:, None], slot.shape)
        if turn:
            slot %= size
            # A full turn's first and last beams point the same way: the first is kept.
            _, keep = np.unique((rows * size + slot)[valid], return_index=True)
            chosen = np.zeros(int(valid.sum()), dtype=bool)
            chosen[keep] = True
            kept = np.zeros(valid.shape, dtype=bool)
            kept[valid] = chosen
        else:
            kept = valid
        padded = np.full(slot.shape, np.nan)
        for s in range(lo, hi):
            padded[s - lo, :ranges[s].shape[0]] = ranges[s]
        out[rows[kept], slot[kept]] = padded[kept]
        squares += float(np.sum(shift[kept] ** 2))
        kept_beams += int(kept.sum())
        largest = max(largest, float(np.abs(shift[kept]).max(initial=0.0)))
    if not turn and np.isnan(out[:, -1]).all():
        out, size = out[:, :-1], size - 1
    return CommonLayout(
        angles=sign * (start + np.arange(size) * step),
        ranges=out,
        shift_variance_rad2=squares / kept_beams if kept_beams else 0.0,
        max_shift_rad=largest,
        beam_counts=counts,
    )
