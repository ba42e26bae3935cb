"""The cloud projection's fast path against a brute-force reference.

:func:`gpocc.io.cloudscan.scan_from_cloud` computes heights for every point but positions,
bearings and the returns test only for the points in the band, and bins bearings with a
polynomial arctan checked against arctan2 near the bins' edges. Oracles: a per-point
Python loop in float64 (``math.atan2`` per point, the nearest in-band return per bin) on
clouds decoded from PointCloud2 bytes, organised and not, with NaN and all-zero points,
a tilted and yawed mount and a tilted base; and numpy's arctan2 for the bins themselves.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gpocc.io.cloudscan import (
    HEARD_STRIDE,
    _bin_index,
    _exact_bin_index,
    rotation_matrix,
    scan_from_cloud,
)
from gpocc.io.pointcloud import decode_cloud

BAND, BINS, RANGE_MIN = (0.1, 2.0), 360, 0.3
#: Points this close (bin units, metres) to a bin's edge, the band's limits or range_min
#: may fall either side in float32: the reference drops them (they become NaN points).
AMBIGUOUS = 1e-4


def _message(xyz: np.ndarray, height: int, width: int, float64: bool) -> SimpleNamespace:
    """A PointCloud2 of ``xyz`` (height * width, 3) with a ring field and padding."""
    kind = "<f8" if float64 else "<f4"
    size = 8 if float64 else 4
    dt = np.dtype({"names": ["x", "y", "z", "ring"], "formats": [kind, kind, kind, "<u2"],
                   "offsets": [0, size, 2 * size, 3 * size], "itemsize": 3 * size + 6})
    arr = np.zeros(len(xyz), dt)
    arr["x"], arr["y"], arr["z"] = xyz.T
    arr["ring"] = np.arange(len(xyz)) // width
    code = 8 if float64 else 7
    fields = [SimpleNamespace(name=n, offset=o, datatype=d, count=1) for n, o, d in
              (("x", 0, code), ("y", size, code), ("z", 2 * size, code), ("ring", 3 * size, 4))]
    return SimpleNamespace(height=height, width=width, point_step=dt.itemsize,
                           row_step=dt.itemsize * width, is_bigendian=False, fields=fields,
                           data=np.frombuffer(arr.tobytes(), np.uint8))


def _reference_point(p, rotation, translation, level):
    """(bin, horizontal distance, height, ambiguous) of one lidar-frame point, float64."""
    base = rotation @ p + translation
    ground = translation * np.array([1.0, 1.0, 0.0])
    flat = base if level is None else level @ (base - ground) + ground
    dx, dy = flat[0] - ground[0], flat[1] - ground[1]
    u = (math.atan2(dy, dx) + math.pi) * BINS / (2 * math.pi)
    d = math.hypot(dx, dy)
    z = base[2]
    ambiguous = (abs(u - round(u)) < AMBIGUOUS or min(abs(z - BAND[0]), abs(z - BAND[1]))
                 < AMBIGUOUS or abs(d - RANGE_MIN) < AMBIGUOUS)
    return int(u) % BINS, d, z, ambiguous


def _reference_scan(points, rotation, translation, level, enough):
    """Ranges, heard, per bin by a loop over the points (the projection's definition)."""
    ranges = np.full(BINS, np.inf)
    heard = np.zeros(BINS, bool)
    others = []
    for p in points:
        if not np.all(np.isfinite(p)) or not np.any(p):
            continue  # no return
        k, d, z, _ = _reference_point(p, rotation, translation, level)
        if BAND[0] <= z <= BAND[1]:
            heard[k] = True
            if d >= RANGE_MIN:
                ranges[k] = min(ranges[k], d)
        else:
            others.append(k)
    if heard.sum() < enough * BINS:
        heard[others[::HEARD_STRIDE]] = True
    return ranges, heard


def _lidar_points(organised: bool, narrow: bool, rng: np.random.Generator) -> np.ndarray:
    """(16 * 200, 3) returns of a 16-ring lidar in a cluttered scene (ranges 0.2..9 m),
    azimuths jittered off any grid; one point in ten NaN and one in twenty all zero.
    ``narrow``: a 100-degree field of view (the floor's returns are then binned too)."""
    rings, cols = 16, 200
    el = np.radians(np.linspace(-15.0, 15.0, rings))[:, None]
    span = math.radians(50.0) if narrow else math.pi
    az = np.linspace(-span, span, cols, endpoint=False)[None, :]
    az = az + rng.uniform(-0.01, 0.01, (rings, cols))
    el = el + np.zeros_like(az)
    r = rng.uniform(0.2, 9.0, (rings, cols))
    pts = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                    r * np.sin(el)], -1).reshape(-1, 3)
    if not organised:
        pts = pts[rng.permutation(len(pts))]
    pts[rng.random(len(pts)) < 0.1] = np.nan
    pts[rng.random(len(pts)) < 0.05] = 0.0
    return pts


@pytest.mark.parametrize(("organised", "float64", "tilted_base", "narrow"), [
    (True, False, False, False),
    (False, False, True, False),
    (True, False, True, True),
    (False, True, False, False),
    (False, False, False, True),
])
def test_fast_projection_equals_brute_force_reference(organised, float64, tilted_base,
                                                      narrow):
    rng = np.random.default_rng(7)
    pts = _lidar_points(organised, narrow, rng)
    # Tilted 10 degrees forward and turned 30 degrees on the base, 0.6 m up.
    rotation = Rotation.from_euler("zyx", [30.0, 10.0, 0.0], degrees=True).as_matrix()
    translation = np.array([0.2, -0.1, 0.6])
    level = (Rotation.from_euler("x", 3.0, degrees=True).as_matrix() if tilted_base
             else None)
    # The reference's float64 and the projection's float32 may disagree on points at
    # a bin's edge, the band's limits or range_min: those become NaN points.
    for i, p in enumerate(pts):
        if np.all(np.isfinite(p)) and np.any(p):
            pts[i] = np.nan if _reference_point(p, rotation, translation, level)[3] else p
    enough = 0.9
    height, width = (16, 200) if organised else (1, len(pts))
    cloud = decode_cloud(_message(pts, height, width, float64), "test")
    assert cloud.points.dtype == (np.float64 if float64 else np.float32)
    ranges, heard, z = scan_from_cloud(cloud.points, rotation, translation, level, BAND,
                                       BINS, RANGE_MIN, enough)
    want_ranges, want_heard = _reference_scan(pts, rotation, translation, level, enough)
    assert np.isfinite(want_ranges).sum() > BINS // 4  # the scene has hits to compare
    assert (want_heard.sum() < enough * BINS) == narrow  # the floor was binned when narrow
    np.testing.assert_array_equal(np.isinf(ranges), np.isinf(want_ranges))
    np.testing.assert_allclose(ranges, want_ranges, rtol=1e-5)
    np.testing.assert_array_equal(heard, want_heard)
    returns = np.all(np.isfinite(pts), axis=1) & np.any(pts != 0, axis=1)
    np.testing.assert_allclose(z[returns], (pts[returns] @ rotation.T + translation)[:, 2],
                               atol=1e-5)


@pytest.mark.parametrize("bins", [36, 512, 1024, 1800, 4096])
def test_fast_bins_equal_arctan2_bins_on_and_off_the_edges(bins):
    rng = np.random.default_rng(bins)
    n = 20000
    edges = -math.pi + np.arange(bins) * 2 * math.pi / bins
    a = rng.uniform(-math.pi, math.pi, n)
    a[:500] = rng.choice(edges, 500) + rng.normal(0.0, 1e-6, 500)  # within rounding
    r = np.exp(rng.uniform(-6.0, 6.0, n))
    dx, dy = (r * np.cos(a)).astype(np.float32), (r * np.sin(a)).astype(np.float32)
    dx[500:520], dy[520:540] = 0.0, 0.0  # on the axes
    dx[540:550], dy[540:550] = -0.0, 0.0  # the origin, both signs of zero
    dx[550:560], dy[550:560] = 0.0, -0.0
    dy[560:570], dx[560:570] = -0.0, -1.0  # at -pi
    mixed = rng.permutation(n)  # a few percent near the edges: the polynomial's path
    for order in (mixed, np.arange(n)):  # and arctan2 for all (starts on the edges)
        np.testing.assert_array_equal(_bin_index(dx[order], dy[order], bins),
                                      _exact_bin_index(dx[order], dy[order], bins))
    # A lidar whose columns are the bins: every bearing on an edge.
    cols = -math.pi + np.arange(bins) * 2 * math.pi / bins
    gx, gy = (np.cos(cols) * 3.7).astype(np.float32), (np.sin(cols) * 3.7).astype(np.float32)
    np.testing.assert_array_equal(_bin_index(gx, gy, bins), _exact_bin_index(gx, gy, bins))


def test_rotation_matrix_matches_scipy():
    q = Rotation.from_euler("zyx", [30.0, 10.0, -5.0], degrees=True)
    np.testing.assert_allclose(rotation_matrix(q.as_quat()), q.as_matrix(), atol=1e-12)
