"""Values known at some stamps, wanted at others: the bracket search every reader shares.

Poses from pose topics (:mod:`gpocc.io.bags`), TF edges (:mod:`gpocc.io.tf`) and odometry
anchored by pose fixes (:mod:`gpocc.io.laserpose`) are all interpolated to scan stamps by
the same rule: a stamp is served when it lies between two known stamps at most
``max_gap_s`` apart, or within ``tolerance_s`` of a known stamp (whose value it then
takes): never by exact float equality, as two clocks (header stamps of two drivers, or
log times) rarely agree to the nanosecond.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class Brackets:
    """For each wanted stamp: the known samples around it and its interpolation weight.

    Attributes:
        before, after: (S,) indices of the known samples at or before / after the stamp
            (equal when the stamp is a known stamp; the nearest one when not served).
        weight: (S,) in [0, 1]: value = (1 - weight) v[before] + weight v[after].
        served: (S,) bool: the stamp may be interpolated (see the module docstring).
    """

    before: np.ndarray
    after: np.ndarray
    weight: np.ndarray
    served: np.ndarray


def brackets(known: np.ndarray, stamps: np.ndarray, max_gap_s: float,
             tolerance_s: float = 1e-6) -> Brackets:
    """Bracket ``stamps`` (S,) seconds in ``known`` (K,) seconds, strictly increasing.

    ``tolerance_s`` defaults to 1 us: a float second near 1.7e9 s holds about 0.2 us, so
    two renderings of one nanosecond stamp agree to that.
    """
    n = known.shape[0]
    right = np.searchsorted(known, stamps, side="right")
    before = np.clip(right - 1, 0, n - 1)
    after = np.clip(right, 0, n - 1)
    d_before = np.where(right > 0, stamps - known[before], np.inf)
    d_after = np.where(right < n, known[after] - stamps, np.inf)
    gap = known[after] - known[before]
    inside = (right > 0) & (right < n) & (gap <= max_gap_s)
    nearest = np.where(d_before <= d_after, before, after)
    close = ~inside & (np.minimum(d_before, d_after) <= tolerance_s)
    before = np.where(close, nearest, before)
    after = np.where(close, nearest, after)
    gap = known[after] - known[before]
    with np.errstate(invalid="ignore", divide="ignore"):
        weight = np.where(gap > 0, (stamps - known[before]) / np.where(gap > 0, gap, 1.0), 0.0)
    return Brackets(before, after, np.clip(weight, 0.0, 1.0), inside | close)


def blend_poses(poses: np.ndarray, at: Brackets) -> np.ndarray:
    """(S, 3) poses (x m, y m, yaw rad) at the bracketed stamps: x, y linear in time, yaw
    along the shorter arc, from ``poses`` (K, 3) at the known stamps."""
    p0, p1, w = poses[at.before], poses[at.after], at.weight
    dyaw = np.angle(np.exp(1j * (p1[:, 2] - p0[:, 2])))
    out = p0 + w[:, None] * (p1 - p0)
    out[:, 2] = np.angle(np.exp(1j * (p0[:, 2] + w * dyaw)))
    return out
