"""Scans of differing beam layouts on one lattice (gpocc.io.layouts).

Oracle: brute force. Each recorded beam's bearing is compared with every lattice bearing
(as directions: a turn apart is the same bearing); its range must sit at the nearest one,
no other entry of its scan may hold a range, and the reported shift statistics are those
of the nearest-bearing distances.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gpocc.errors import GpoccError
from gpocc.io.layouts import common_layout


def _rplidar_scans(rng: np.random.Generator, scans: int, beams: int, sign: float
                   ) -> tuple[list[np.ndarray], list[tuple[int, float, float]]]:
    """A 360-degree scanner publishing each revolution as it came: a few beams more or
    fewer, the first angle jittered by up to an increment, the increment fitted to both."""
    ranges, layouts = [], []
    for _ in range(scans):
        n = beams - int(rng.integers(0, 6))
        first = -math.pi + rng.uniform(-1.0, 1.0) * 2 * math.pi / beams
        last = first + 2 * math.pi * (n - 1) / n
        if sign < 0:
            first, last = last, first
        ranges.append(rng.uniform(0.5, 8.0, n))
        layouts.append((n, first, (last - first) / (n - 1)))
    return ranges, layouts


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_each_beam_lands_on_the_nearest_lattice_bearing(sign: float) -> None:
    rng = np.random.default_rng(3)
    ranges, layouts = _rplidar_scans(rng, 40, 360, sign)
    common = common_layout("bag: topic /scan", ranges, layouts)
    # The scans cover a full turn: one turn of whole steps, none longer than the finest
    # increment (but for rounding), and no fewer.
    finest = min(abs(d) for _, _, d in layouts)
    step = 2 * math.pi / common.angles.size
    assert 2 * math.pi / (common.angles.size - 1) > finest >= step * (1 - 1e-9)
    np.testing.assert_allclose(np.diff(common.angles), sign * step, rtol=1e-12)
    shifts = []
    for s, (r, (n, first, inc)) in enumerate(zip(ranges, layouts, strict=True)):
        bearings = first + np.arange(n) * inc
        distance = np.abs(np.angle(np.exp(1j * (bearings[:, None] - common.angles[None, :]))))
        nearest = distance.argmin(axis=1)
        np.testing.assert_array_equal(common.ranges[s, nearest], r)
        others = np.ones(common.angles.size, dtype=bool)
        others[nearest] = False
        assert np.isnan(common.ranges[s, others]).all()
        assert np.count_nonzero(~np.isnan(common.ranges[s])) == n  # every beam kept
        shifts.append(distance.min(axis=1))
    shifts = np.concatenate(shifts)
    assert shifts.max() <= step / 2 + 1e-12
    assert common.max_shift_rad == pytest.approx(shifts.max(), abs=1e-12)
    assert common.shift_variance_rad2 == pytest.approx(np.mean(shifts ** 2), rel=1e-9)
    np.testing.assert_array_equal(common.beam_counts, [n for n, _, _ in layouts])
    assert "varies from scan to scan" in common.describe()


def test_scans_that_only_drop_trailing_beams_keep_their_bearings() -> None:
    # Same first angle and increment, fewer beams: the lattice is the longest scan's.
    inc = math.radians(0.5)
    layouts = [(100, -0.5, inc), (97, -0.5, inc), (100, -0.5, inc)]
    ranges = [np.full(n, 2.0 + s) for s, (n, _, _) in enumerate(layouts)]
    common = common_layout("bag: topic /scan", ranges, layouts)
    np.testing.assert_allclose(common.angles, -0.5 + np.arange(100) * inc)
    assert common.max_shift_rad < 1e-12
    assert np.isnan(common.ranges[1, 97:]).all() and (common.ranges[1, :97] == 3.0).all()


def test_scans_turning_both_ways_are_refused() -> None:
    layouts = [(10, 0.0, 0.1), (10, 0.9, -0.1)]
    with pytest.raises(GpoccError, match=r"bag: topic /scan: .*both ways"):
        common_layout("bag: topic /scan", [np.ones(10), np.ones(10)], layouts)


@pytest.mark.parametrize("layouts", [
    # A second laser's sector on the same topic: the lattice would be three times longer.
    [(10, 0.0, 0.1), (10, 2.0, 0.1)],
    # Full turns, and a few beams a milliradian apart: a turn of 6284 bearings.
    [(360, 0.0, 2 * math.pi / 360), (360, 0.01, 2 * math.pi / 360), (5, 0.0, 0.001)],
])
def test_layouts_too_far_apart_to_be_one_laser_are_refused(layouts) -> None:
    ranges = [np.ones(n) for n, _, _ in layouts]
    with pytest.raises(GpoccError, match=r"do not fit one layout.*split the recording"):
        common_layout("bag: topic /scan", ranges, layouts)


def test_a_full_turn_whose_last_beam_repeats_the_first_keeps_the_first() -> None:
    # 361 beams a degree apart: the last points where the first does. The second scan
    # lies half a degree off: each of its beams ties between two bearings, and rounding
    # half to even would put two beams on one bearing and lose a third of them.
    inc = math.radians(1.0)
    layouts = [(361, 0.0, inc), (360, 0.5 * inc, inc)]
    ranges = [np.arange(361, dtype=float), np.arange(360, dtype=float) + 1000.0]
    common = common_layout("bag: topic /scan", ranges, layouts)
    assert common.angles.size == 360
    np.testing.assert_array_equal(common.ranges[0], np.arange(360.0))
    assert np.count_nonzero(~np.isnan(common.ranges[1])) == 360
    # In order around the turn, each half a degree from its own bearing.
    start = int(np.flatnonzero(common.ranges[1] == 1000.0)[0])
    np.testing.assert_array_equal(np.roll(common.ranges[1], -start), ranges[1])
    assert common.max_shift_rad == pytest.approx(0.5 * inc)


def test_scans_half_a_step_apart_keep_every_beam() -> None:
    inc = math.radians(0.5)
    layouts = [(100, 0.0, inc), (100, 0.5 * inc, inc), (99, 1.5 * inc, inc)]
    ranges = [np.full(n, 1.0 + s) for s, (n, _, _) in enumerate(layouts)]
    common = common_layout("bag: topic /scan", ranges, layouts)
    for s, (n, _, _) in enumerate(layouts):
        row = common.ranges[s]
        assert np.count_nonzero(~np.isnan(row)) == n and (row[~np.isnan(row)] == 1.0 + s).all()
    assert common.max_shift_rad == pytest.approx(0.5 * inc, rel=1e-9)
    assert common.angles.size == 100  # ties take the lower bearing


def test_blocks_of_scans_give_the_layout_of_all_at_once(monkeypatch) -> None:
    from gpocc.io import layouts

    rng = np.random.default_rng(9)
    ranges, scans = _rplidar_scans(rng, 30, 120, 1.0)
    whole = common_layout("bag: topic /scan", ranges, scans)
    monkeypatch.setattr(layouts, "_SCANS_PER_BLOCK", 7)
    blocks = common_layout("bag: topic /scan", ranges, scans)
    np.testing.assert_array_equal(blocks.ranges, whole.ranges)
    np.testing.assert_array_equal(blocks.angles, whole.angles)
    assert blocks.shift_variance_rad2 == pytest.approx(whole.shift_variance_rad2, rel=1e-12)
    assert blocks.max_shift_rad == whole.max_shift_rad
