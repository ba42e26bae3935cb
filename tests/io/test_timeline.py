"""The shared bracket search against a per-stamp brute force."""

from __future__ import annotations

import numpy as np

from gpocc.io.timeline import blend_poses, brackets


def _brute(known: np.ndarray, t: float, max_gap: float) -> tuple[bool, float | None]:
    """(served, value of the linear interpolant of known stamps' indices) for one stamp."""
    if np.any(known == t):
        return True, float(np.flatnonzero(known == t)[0])
    lower = known[known < t]
    upper = known[known > t]
    if lower.size == 0 or upper.size == 0:
        return False, None
    a, b = lower.max(), upper.min()
    if b - a > max_gap:
        return False, None
    i = int(np.flatnonzero(known == a)[0])
    return True, i + (t - a) / (b - a)


def test_brackets_match_a_brute_force():
    rng = np.random.default_rng(3)
    known = np.cumsum(rng.uniform(0.05, 1.0, 40))
    stamps = np.concatenate([rng.uniform(known[0] - 1, known[-1] + 1, 300), known[::7]])
    at = brackets(known, stamps, 0.6)
    index = np.arange(known.size, dtype=float)
    interpolated = (1 - at.weight) * index[at.before] + at.weight * index[at.after]
    for k, t in enumerate(stamps):
        served, value = _brute(known, t, 0.6)
        assert at.served[k] == served
        if served:
            assert interpolated[k] == np.float64(value) or abs(interpolated[k] - value) < 1e-9


def test_yaw_follows_the_shorter_arc():
    known = np.array([0.0, 1.0])
    poses = np.array([[0.0, 0.0, np.pi - 0.1], [2.0, 4.0, -np.pi + 0.1]])
    out = blend_poses(poses, brackets(known, np.array([0.5]), 2.0))
    np.testing.assert_allclose(out[0, :2], [1.0, 2.0])
    assert abs(abs(out[0, 2]) - np.pi) < 1e-12  # through +-pi, not through 0


def _brute_tolerant(known: np.ndarray, t: float, max_gap: float,
                    tol: float) -> tuple[bool, float | None]:
    """Interpolation where two known stamps around ``t`` are at most ``max_gap`` apart;
    else the nearest known stamp's index if within ``tol``; else not served."""
    lower, upper = known[known <= t], known[known > t]
    if lower.size and upper.size and upper.min() - lower.max() <= max_gap:
        a, b = lower.max(), upper.min()
        i = int(np.flatnonzero(known == a)[0])
        return True, i + (t - a) / (b - a)
    d = np.abs(known - t)
    if d.min() <= tol:
        return True, float(np.argmin(d))
    return False, None


def test_a_stamp_within_the_tolerance_takes_the_nearest_known_value():
    rng = np.random.default_rng(5)
    known = np.cumsum(rng.uniform(0.05, 1.0, 40))
    # Stamps a little off the known ones (as log time is from header stamps), and others.
    stamps = np.concatenate([known + rng.uniform(-0.03, 0.03, known.size),
                             rng.uniform(known[0] - 1, known[-1] + 1, 300)])
    at = brackets(known, stamps, 0.3, tolerance_s=0.02)
    index = np.arange(known.size, dtype=float)
    got = (1 - at.weight) * index[at.before] + at.weight * index[at.after]
    served = 0
    for k, t in enumerate(stamps):
        ok, value = _brute_tolerant(known, t, 0.3, 0.02)
        assert at.served[k] == ok, t
        if ok:
            served += 1
            assert abs(got[k] - value) < 1e-9
    assert 0 < served < stamps.size
