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
  ``no_return_free_m`` as for a planar laser; :func:`bin_returns` also says which bins
  any return fell into, and :mod:`gpocc.io.cloudread` makes the others unknown.

The result is a LaserScan-like row of ranges at bearings
``-pi + (i + 1/2) 2 pi / bins``. All points of a sweep are taken at the cloud's stamp:
a per-point time field is read but the sweep is not de-skewed (at 1 m/s and 10 Hz a
point is at most 0.1 m from where a de-skewed point would be).
"""

from __future__ import annotations

import math

import numpy as np

from gpocc.io.pointcloud import is_return, returns_mask
from gpocc.io.tf import quat_rotate


def bin_angles(bins: int) -> np.ndarray:
    """(bins,) bearing of each bin's centre, radians, ``-pi + (i + 1/2) 2 pi / bins``."""
    inc = 2.0 * math.pi / bins
    return -math.pi + (np.arange(bins) + 0.5) * inc


def rotation_matrix(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of a unit quaternion (x, y, z, w)."""
    x, y, z, w = (float(v) for v in q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


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
    return bin_returns(points[:, 0], points[:, 1], points[:, 2], origin, band, bins,
                       range_min)[0]


#: Returns outside the band are binned one in this many, only to tell which bins the
#: lidar looked into (:func:`bin_returns`); a bin holds several rings' returns.
HEARD_STRIDE = 4


def _exact_bin_index(dx: np.ndarray, dy: np.ndarray, bins: int) -> np.ndarray:
    """(N,) bin of each bearing ``arctan2(dy, dx)``: the definition :func:`_bin_index`
    reproduces."""
    index = ((np.arctan2(dy, dx) + math.pi) * (bins / (2.0 * math.pi))).astype(np.intp)
    index[index >= bins] -= bins  # arctan2 rounding up to pi
    return index


def _atan_coefficients(degree: int = 8) -> np.ndarray:
    """Coefficients, highest first, of a polynomial p(s) with ``t p(t^2) ~ arctan(t)`` on
    [0, 1] (least squares at Chebyshev nodes; largest error about 1e-9 rad)."""
    t = 0.5 + 0.5 * np.cos(np.pi * (np.arange(400) + 0.5) / 400)
    return np.polyfit(t * t, np.arctan(t) / t, degree)


_ATAN = tuple(np.float32(c) for c in _atan_coefficients())
#: Bound on |approximate - numpy float32 arctan2| in radians, with a wide margin: the
#: polynomial's error (1e-9) and float32 rounding in both (a few 1e-7).
ATAN_TOLERANCE = 1e-5


def _bin_index(dx: np.ndarray, dy: np.ndarray, bins: int) -> np.ndarray:
    """(N,) bin of each bearing, equal to :func:`_exact_bin_index` (float32 ``dx``, ``dy``).

    numpy's float32 arctan2 costs some 30 ns a point, more than the rest of the projection
    together; a polynomial arctan with octant reduction costs a few vector passes. Where
    the polynomial's bearing is within :data:`ATAN_TOLERANCE` of a bin's edge (a few
    percent of the points), or undefined (dx = dy = 0), the bin is taken from arctan2
    itself, so every bin is the one arctan2 gives.
    """
    if dx.dtype != np.float32 or dy.dtype != np.float32 or _on_edges(dx[:256], dy[:256],
                                                                     bins):
        return _exact_bin_index(dx, dy, bins)
    u = _bin_coordinate(dx, dy, bins)
    unsure = _near_edge(u, bins)
    k = np.flatnonzero(unsure)
    if k.size > dx.size // 4:
        return _exact_bin_index(dx, dy, bins)
    with np.errstate(invalid="ignore"):  # NaN (dx = dy = 0): set just below
        index = u.astype(np.intp)
    index[k] = _exact_bin_index(dx[k], dy[k], bins)
    return index


def _on_edges(dx: np.ndarray, dy: np.ndarray, bins: int) -> bool:
    """Whether more than a quarter of these bearings lie within the polynomial's
    tolerance of a bin's edge: a lidar whose columns are the bins, mounted at a yaw of a
    multiple of the bin's width. Then arctan2 decides nearly every bin."""
    return bool(np.count_nonzero(_near_edge(_bin_coordinate(dx, dy, bins), bins))
                > dx.size // 4)


def _near_edge(u: np.ndarray, bins: int) -> np.ndarray:
    """(N,) bool: bin coordinates ``u`` within the polynomial's tolerance of an integer
    (or NaN)."""
    frac = u - np.floor(u)
    margin = np.float32(max(ATAN_TOLERANCE * bins / (2.0 * math.pi), 1e-3))
    with np.errstate(invalid="ignore"):
        return ~((frac > margin) & (frac < 1 - margin))  # NaN (dx = dy = 0) is unsure


def _bin_coordinate(dx: np.ndarray, dy: np.ndarray, bins: int) -> np.ndarray:
    """(N,) float32 ``(bearing + pi) bins / (2 pi)`` with the polynomial arctan: its floor
    is the bin, but for bearings within :data:`ATAN_TOLERANCE` of a bin's edge."""
    ax, ay = np.abs(dx), np.abs(dy)
    steep = ay > ax
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.minimum(ax, ay)
        t /= np.maximum(ax, ay)
    s = t * t
    p = np.full_like(s, _ATAN[0])
    for c in _ATAN[1:]:
        p *= s
        p += c
    p *= t
    # Octants by arithmetic on 0/1 masks: numpy's masked ufuncs and np.where branch per
    # point and cost ten times as much. The result is within a few float32 ulp.
    half_pi, pi = np.float32(0.5 * math.pi), np.float32(math.pi)
    p += steep * (half_pi - 2 * p)  # pi/2 - p where steep
    p += np.signbit(dx) * (pi - 2 * p)  # pi - p where dx < 0
    p *= 1 - 2 * np.signbit(dy).view(np.int8).astype(np.float32)  # the sign of dy
    p += pi
    p *= np.float32(bins / (2.0 * math.pi))
    return p


def bin_returns(x: np.ndarray, y: np.ndarray, z: np.ndarray, origin: np.ndarray,
                band: tuple[float, float], bins: int, range_min: float,
                enough: float = 1.0,
                valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Ranges (bins,) as :func:`project`, and (bins,) bool: the lidar looked into the bin
    (a return in the band, or one in :data:`HEARD_STRIDE` of the floor and ceiling
    returns, fell in it). ``x``, ``y`` (N,) horizontal positions, ``z`` (N,) heights,
    metres; ``valid`` (N,) bool, the points to use (None: all). When the band's returns
    alone reach ``enough`` of the bins, the floor and ceiling returns are not binned (the
    caller needs no more)."""
    dx = x - x.dtype.type(origin[0])
    dy = y - y.dtype.type(origin[1])
    in_band = (z >= band[0]) & (z <= band[1])
    if valid is not None:
        in_band &= valid
    ranges, heard = _nearest_per_bin(dx[in_band], dy[in_band], bins, range_min)
    if np.count_nonzero(heard) >= enough * bins:
        return ranges, heard
    out = ~in_band if valid is None else ~in_band & valid
    heard[_bin_index(dx[out][::HEARD_STRIDE], dy[out][::HEARD_STRIDE], bins)] = True
    return ranges, heard


def scan_from_cloud(xyz: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                    level: np.ndarray | None, band: tuple[float, float], bins: int,
                    range_min: float, enough: float = 1.0,
                    valid: np.ndarray | None = None, reach: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`bin_returns` of a cloud in the lidar frame.

    The points go into the base frame (``p_base = rotation @ p + translation``); their
    height is ``p_base[2]``; their horizontal position is levelled about the lidar's
    ground point ``g = (t_x, t_y, 0)``: ``level @ (p_base - g) + g`` (``level`` (3, 3)
    undoes the base's roll and pitch; None: the base is level).

    Only the heights are computed for every point. The horizontal positions, bearings
    and the returns test are computed for the points in the band alone (a quarter to a
    half of a spinning lidar's points), and for one in :data:`HEARD_STRIDE` of the
    others only when the band's returns leave more than ``1 - enough`` of the bins
    unseen. The arithmetic per point is that of :func:`bin_returns` on the whole cloud,
    so the scan is the same to the bit.

    Args:
        xyz: (N, 3) points in the lidar frame, metres (float32 or float64; any strides).
        rotation: (3, 3) base <- lidar. translation: (3,) metres.
        valid: (N,) bool, the returns among the points; None: those that pass
            :func:`gpocc.io.pointcloud.returns_mask` (finite, not all zero).
        reach: optional (bins,) output: where the floor's and ceiling's returns were
            binned, the farthest of them per bin, metres horizontally (0: none); left
            untouched where they were not (the band's returns filled ``enough``).

    Returns:
        ``(ranges (bins,), heard (bins,), heights (N,))``: the heights of all the points
        in the base frame, metres (meaningless for points that are not returns).
    """
    rotation = np.asarray(rotation, float)
    translation = np.asarray(translation, float)
    ground = translation * np.array([1.0, 1.0, 0.0])
    m = rotation if level is None else np.asarray(level, float) @ rotation
    off = translation - ground if level is None else level @ (translation - ground)
    shift = off + ground
    kind = xyz.dtype.type

    # Three multiply-adds per output row: numpy's matmul with an inner size of 3 is
    # slower than this and rounds differently.
    def row(x: np.ndarray, y: np.ndarray, z: np.ndarray, r: np.ndarray,
            shift: float) -> np.ndarray:
        out = x * kind(r[0])
        out += y * kind(r[1])
        out += z * kind(r[2])
        out += kind(shift)
        return out

    def bearings(x: np.ndarray, y: np.ndarray, z: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        bx, by = row(x, y, z, m[0], shift[0]), row(x, y, z, m[1], shift[1])
        return bx - bx.dtype.type(ground[0]), by - by.dtype.type(ground[1])

    columns = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    with np.errstate(invalid="ignore", over="ignore"):  # NaN points fail every test
        z = _height(columns, rotation[2], translation[2])
        in_band = (z >= band[0]) & (z <= band[1])
        if valid is not None:
            in_band &= valid
        # One column at a time: numpy copies a strided column under a mask faster than
        # rows of three.
        x, y, zz = (c[in_band] for c in columns)
        if valid is None:
            ok = is_return(x, y, zz)
            if not ok.all():
                x, y, zz = x[ok], y[ok], zz[ok]
        dx, dy = bearings(x, y, zz)
        ranges, heard = _nearest_per_bin(dx, dy, bins, range_min)
        if np.count_nonzero(heard) >= enough * bins:
            return ranges, heard, z
        # The floor's and ceiling's returns, in :func:`bin_returns`'s order and stride.
        out = ~in_band & (returns_mask(xyz) if valid is None else valid)
        pick = np.flatnonzero(out)[::HEARD_STRIDE]
        dx, dy = bearings(*(c[pick] for c in columns))
        index = _bin_index(dx, dy, bins)
        heard[index] = True
        if reach is not None:
            reach[:] = 0.0
            np.maximum.at(reach, index, np.hypot(dx, dy).astype(np.float64))
    return ranges, heard, z


def _height(columns: tuple[np.ndarray, np.ndarray, np.ndarray], r: np.ndarray,
            shift: float) -> np.ndarray:
    """(N,) ``x r[0] + y r[1] + z r[2] + shift`` in the columns' float type, rounded as
    :func:`scan_from_cloud`'s rows, without the terms whose coefficient is exactly 0 nor
    the products by exactly 1: a lidar mounted level (a yaw at most) has height
    ``z + shift``, one pass over the cloud instead of six. A term dropped with a
    non-finite coordinate would have made the height NaN; such points are not returns,
    and every use of the heights tests the returns among them."""
    kind = columns[0].dtype.type
    out = None
    for c, k in zip(columns, r, strict=True):
        if k == 0.0:
            continue
        term = c if k == 1.0 else c * kind(k)
        if out is None:
            out = term.copy() if k == 1.0 else term
        else:
            out += term
    if out is None:
        out = np.zeros(columns[0].shape, columns[0].dtype)
    out += kind(shift)
    return out


def height_histogram(z: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Counts of heights ``z`` (N,) in the bins ``edges`` (K + 1,, increasing), the outer
    bins open: (K + 2,) = [below edges[0], the K bins, at or above edges[-1]]."""
    return np.bincount(np.searchsorted(edges, z, side="right"), minlength=edges.size + 1)


def _nearest_per_bin(dx: np.ndarray, dy: np.ndarray, bins: int,
                     range_min: float) -> tuple[np.ndarray, np.ndarray]:
    """Per bearing bin, the nearest return at least ``range_min`` metres away ((bins,),
    inf where none) and whether any return fell in the bin; ``dx``, ``dy`` (N,) metres
    from the lidar in the base plane."""
    index = _bin_index(dx, dy, bins)
    dist = np.hypot(dx, dy)
    near = dist >= range_min
    ranges = np.full(bins, np.inf)
    np.minimum.at(ranges, index[near], dist[near].astype(np.float64))
    heard = np.zeros(bins, bool)
    heard[index] = True
    return ranges, heard
