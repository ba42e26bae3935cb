"""A 3-D lidar cloud as one planar scan: height band, bearing bins, nearest return.

The cloud is first moved into the robot's base frame with the full 3-D transform at its
stamp (:func:`to_base`), so a tilted or rolled mount, or a base tilted on a ramp, still
measures heights above the base frame's ground plane (its x-y plane). Then
(:func:`project`):

* points whose height is inside the band ``[low, high]`` are obstacles (tables, walls,
  people), those below are the floor and those above the ceiling: neither is ever a hit;
* bearings are measured around the lidar's origin projected on the ground plane, with
  axes parallel to the base frame, and binned in ``bins`` equal sectors of a full turn;
* the nearest obstacle of a bin, at least ``range_min`` away horizontally, is its hit
  (range = horizontal distance); a bin with no obstacle (its rays saw only floor,
  ceiling or nothing) is a no-return (``+inf``), which the beam rules clear up to
  ``no_return_free_m`` as for a planar laser.

The result is a LaserScan-like row of ranges at bearings
``-pi + (i + 1/2) 2 pi / bins``. All points of a sweep are taken at the cloud's stamp:
a per-point time field is read but the sweep is not de-skewed (at 1 m/s and 10 Hz a
point is at most 0.1 m from where a de-skewed point would be).
"""

from __future__ import annotations

import math

import numpy as np

from gpocc.io.tf import quat_rotate


def bin_angles(bins: int) -> np.ndarray:
    """(bins,) bearing of each bin's centre, radians, ``-pi + (i + 1/2) 2 pi / bins``."""
    inc = 2.0 * math.pi / bins
    return -math.pi + (np.arange(bins) + 0.5) * inc


def to_base(xyz: np.ndarray, translation: np.ndarray, quaternion: np.ndarray) -> np.ndarray:
    """(N, 3) points moved by the transform base <- lidar (translation (3,), unit
    quaternion (x, y, z, w) (4,)), metres."""
    q = np.broadcast_to(np.asarray(quaternion, float), (xyz.shape[0], 4))
    return quat_rotate(q, xyz) + np.asarray(translation, float)


def project(points: np.ndarray, origin: np.ndarray, band: tuple[float, float], bins: int,
            range_min: float) -> np.ndarray:
    """One scan from a cloud in the base frame (see the module docs).

    Args:
        points: (N, 3) returns in the base frame, metres (no NaN).
        origin: (2,) or (3,) the lidar's origin in the base frame; only x, y are used.
        band: (low, high) heights above the base frame's x-y plane, metres.
        bins: bearing bins in a full turn.
        range_min: horizontal distance, metres, below which returns are ignored (the
            robot's own body).

    Returns:
        (bins,) ranges, metres, ``+inf`` for bins without an obstacle return.
    """
    z = points[:, 2]
    keep = (z >= band[0]) & (z <= band[1])
    dx = points[keep, 0] - float(origin[0])
    dy = points[keep, 1] - float(origin[1])
    dist = np.hypot(dx, dy)
    near = dist >= range_min
    dx, dy, dist = dx[near], dy[near], dist[near]
    scale = bins / (2.0 * math.pi)
    index = np.floor((np.arctan2(dy, dx) + math.pi) * scale).astype(np.int64) % bins
    ranges = np.full(bins, np.inf)
    np.minimum.at(ranges, index, dist)
    return ranges


def height_histogram(z: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Counts of heights ``z`` (N,) in the bins ``edges`` (K + 1,), the outer bins open:
    (K + 2,) = [below edges[0], the K bins, above edges[-1]]."""
    inner = np.histogram(z, bins=edges)[0]
    return np.concatenate([[np.count_nonzero(z < edges[0])], inner,
                           [np.count_nonzero(z > edges[-1])]])
