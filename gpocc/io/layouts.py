"""One beam layout for a laser topic whose scans do not share one.

A LaserScan's beams lie at ``angle_min + k angle_increment`` (k < the number of ranges).
Some drivers publish a different layout in every scan: rplidar_ros and sllidar_ros2 with
``angle_compensate: false`` give each revolution its own beam count and first angle. A
:class:`gpocc.io.scans.ScanBatch` holds one layout, so such scans are placed on a common
lattice of bearings, ``step`` apart, ``step`` the finest increment of any scan (for scans
that together cover a full turn, the lattice is one turn of the nearest whole number of
steps not longer than that): each beam goes to the lattice bearing nearest its own (at
most ``step / 2`` away), bearings no beam of a scan fell on hold NaN (no measurement) in
that scan. Since no scan's beams are closer than ``step``, two beams of a scan share a
bearing only when they point the same way (a full turn's first and last); the first is
kept. The mean square of the bearing
shifts is returned, to be added to the sensor's bearing variance: the samples stage then
widens each sample by the rounding it did not see.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gpocc.errors import GpoccError

#: A lattice longer than this many times the longest scan means the layouts are not one
#: sensor's jitter (a second laser on the topic, a driver's mode change): refused.
MAX_LATTICE_GROWTH = 2.0


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

    def describe(self) -> str:
        """One line for the batch's notes."""
        low, high = int(self.beam_counts.min()), int(self.beam_counts.max())
        counts = f"{low}" if low == high else f"{low}-{high}"
        step = abs(float(self.angles[1] - self.angles[0])) if self.angles.size > 1 else 0.0
        return (f"the beam layout varies from scan to scan ({counts} beams): beams placed on "
                f"one layout of {self.angles.size} bearings {math.degrees(step):.3g} deg apart, "
                f"each moved at most {math.degrees(self.max_shift_rad):.2g} deg; the shifts' "
                f"mean square ({math.degrees(math.sqrt(self.shift_variance_rad2)):.2g} deg "
                "rms) is added to the bearing variance")


def common_layout(where: str, ranges: list[np.ndarray],
                  layouts: list[tuple[int, float, float]]) -> CommonLayout:
    """Place scans of differing layouts on one lattice (see the module docstring).

    Args:
        where: ``"file: topic name"`` for messages.
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
    k = np.arange(int(counts.max()))
    valid = k[None, :] < counts[:, None]  # (S, K)
    # Every scan's bearings measured along the scans' direction from the lattice's start.
    along = sign * (first[:, None] + k[None, :] * np.where(several, increment, 0.0)[:, None])
    start = float(along[valid].min())
    turn = float(along[valid].max()) - start + step > 2 * math.pi - 1e-9
    if turn:
        # A 360-degree scanner whose first angle moves: bearings a turn apart are one
        # direction, so the lattice is one turn of whole steps (no longer than the finest
        # increment, so a scan's beams still find distinct bearings).
        # (Within float32 rounding of the message fields: 2 pi / 180 may come out 180.00001.)
        size = math.ceil(2 * math.pi / step * (1.0 - 1e-6))
        step = 2 * math.pi / size
    position = (along - start) / step
    slot = np.rint(position).astype(np.int64)
    shift = (slot - position) * step
    if turn:
        slot %= size
    else:
        size = int(slot[valid].max()) + 1
        if size > MAX_LATTICE_GROWTH * counts.max() + 1:
            raise GpoccError(
                f"{where}: the scans' beam layouts ({counts.min()}-{counts.max()} beams, "
                f"angle_min {math.degrees(first.min()):.1f}..{math.degrees(first.max()):.1f} "
                f"deg, finest increment {math.degrees(step):.3g} deg) do not fit one layout "
                f"of at most {MAX_LATTICE_GROWTH:g} times the longest scan; split the bag "
                "where the layout changes, or give each laser its own topic")
    padded = np.full(slot.shape, np.nan)
    for s, r in enumerate(ranges):
        padded[s, :r.shape[0]] = r
    # Two beams of a scan on one bearing (a full turn's first and last, or increments
    # within rounding of the step): the first is kept.
    rows = np.broadcast_to(np.arange(len(ranges))[:, None], slot.shape)
    _, kept = np.unique((rows * size + slot)[valid], return_index=True)
    out = np.full((len(ranges), size), np.nan)
    out[rows[valid][kept], slot[valid][kept]] = padded[valid][kept]
    shift = shift[valid][kept]
    return CommonLayout(
        angles=sign * (start + np.arange(size) * step),
        ranges=out,
        shift_variance_rad2=float(np.mean(shift ** 2)) if shift.size else 0.0,
        max_shift_rad=float(np.abs(shift).max()) if shift.size else 0.0,
        beam_counts=counts,
    )
