"""Beams to samples: REP 117 classes, free-sample spacing, strides, thinning, ids."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from gpocc import compiled
from gpocc.config import Config, MountConfig, SamplesConfig, SensorConfig
from gpocc.errors import GpoccError
from gpocc.io.scans import ScanBatch
from gpocc.samples import beams
from gpocc.samples.beams import build_samples, thin_samples
from gpocc.samples.sampleset import SampleSet

ZERO_POSE_COV = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
NOISELESS = SensorConfig(
    name="r1", range_variance_m2=0.0, bearing_variance_deg2=0.0, pose_covariance=ZERO_POSE_COV,
    no_return_free_m=2.0, mount=MountConfig(x_m=0.2, y_m=0.1, yaw_deg=30.0),
)
SAMPLES = SamplesConfig(free_spacing_m=0.5, hit_gap_m=0.25, thin_cell_m=0.0, free_clearance_m=0.0)


def _batch(ranges, angles, poses, *, sensor="r1", range_min=0.1, range_max=8.0, covs=None):
    ranges = np.asarray(ranges, dtype=float)
    s = ranges.shape[0]
    return ScanBatch(
        sensor=sensor,
        source=f"{sensor}.log",
        stamps=np.arange(s, dtype=float),
        angles=np.asarray(angles, dtype=float),
        ranges=ranges,
        poses=np.asarray(poses, dtype=float),
        pose_covariances=np.zeros((s, 3, 3)) if covs is None else np.asarray(covs, dtype=float),
        range_min=range_min,
        range_max=range_max,
        has_pose_covariance=covs is not None,
    )


def _se2(x, y, yaw):
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def _oracle(batch: ScanBatch, sensor: SensorConfig, cfg: SamplesConfig, scan_offset=0):
    """REP 117 rules, one beam at a time: rows (label, scan_id, x, y)."""
    rows = []
    m = sensor.mount
    mount = _se2(m.x_m, m.y_m, math.radians(m.yaw_deg))
    for s in range(0, batch.n_scans, cfg.scan_stride):
        laser = _se2(*batch.poses[s]) @ mount
        for b in range(0, batch.n_beams, cfg.beam_stride):
            r, bearing = batch.ranges[s, b], batch.angles[b]
            if math.isnan(r) or r < batch.range_min:
                continue
            if r >= batch.range_max:
                hit, limit = False, min(sensor.no_return_free_m, batch.range_max)
            else:
                gap = max(cfg.hit_gap_m, cfg.hit_gap_sigmas * math.sqrt(sensor.range_variance_m2))
                hit, limit = True, r - gap
            points = []
            if hit:
                points.append((1.0, r))
            k = 1
            while k * cfg.free_spacing_m <= limit + 1e-12:
                points.append((-1.0, k * cfg.free_spacing_m))
                k += 1
            for label, d in points:
                p = laser @ np.array([d * math.cos(bearing), d * math.sin(bearing), 1.0])
                rows.append((label, s + scan_offset, p[0], p[1]))
    return np.array(rows).reshape(-1, 4)


def _rows(samples: SampleSet) -> np.ndarray:
    return np.column_stack([samples.labels, samples.scan_ids, samples.means])


def _assert_same_rows(got: np.ndarray, expected: np.ndarray):
    """Same multiset of (label, scan, x, y), matched by nearest point (order-free)."""
    assert got.shape == expected.shape
    used = np.zeros(len(got), dtype=bool)
    for row in expected:
        d = np.linalg.norm(got[:, 2:] - row[2:], axis=1)
        d[(got[:, 0] != row[0]) | (got[:, 1] != row[1]) | used] = np.inf
        j = int(np.argmin(d))
        assert d[j] < 1e-9, f"no sample for {row}"
        used[j] = True


def _config(sensor=NOISELESS, **samples):
    return Config(sensors=(sensor,), samples=replace(SAMPLES, **samples))


ANGLES = [-1.2, -0.4, 0.3, 1.1]
POSES = [[1.0, -2.0, 0.3], [4.0, 0.5, -2.5]]


def test_hits_exact_and_free_samples_at_documented_distances():
    ranges = [[2.25, 0.6, 5.1, 3.3], [1.0, 7.9, 0.3, 4.75]]
    batch = _batch(ranges, ANGLES, POSES)
    samples = build_samples([batch], _config())
    _assert_same_rows(_rows(samples), _oracle(batch, NOISELESS, SAMPLES))
    # spot checks of the rules themselves, in the laser frame of scan 0, beam 0
    laser = _se2(*POSES[0]) @ _se2(0.2, 0.1, math.radians(30.0))
    local = np.linalg.solve(laser, np.column_stack([samples.means, np.ones(len(samples))]).T).T
    along = np.hypot(local[:, 0], local[:, 1])
    on_beam0 = (samples.scan_ids == 0) & np.isclose(np.arctan2(local[:, 1], local[:, 0]), -1.2)
    np.testing.assert_allclose(np.sort(along[on_beam0 & (samples.labels < 0)]),
                               [0.5, 1.0, 1.5, 2.0])  # 2.0 == 2.25 - hit_gap is included
    np.testing.assert_allclose(along[on_beam0 & (samples.labels > 0)], [2.25])
    # no noise anywhere: zero covariances and pose factors
    np.testing.assert_allclose(samples.covariances, 0.0, atol=1e-20)
    np.testing.assert_allclose(samples.pose_factors, 0.0, atol=1e-20)
    assert samples.labels.dtype == np.float64 and samples.scan_ids.dtype == np.int64
    assert samples.sensor_ids.dtype == np.int16 and (samples.sensor_ids == 0).all()


def test_invalid_ranges_give_nothing_and_no_return_gives_free_space():
    ranges = [[np.nan, -np.inf, 0.05, 2.0], [np.inf, 3.0, 9.0, 2.0]]
    batch = _batch(ranges, ANGLES, POSES, range_max=3.0)
    sensor = replace(NOISELESS, no_return_free_m=2.0)
    samples = build_samples([batch], _config(sensor))
    _assert_same_rows(_rows(samples), _oracle(batch, sensor, SAMPLES))
    per_scan = np.bincount(samples.scan_ids, minlength=2)
    # scan 0: only the 2.0 m beam: a hit + free at 0.5, 1.0, 1.5
    assert per_scan[0] == 4
    # scan 1: +inf -> 4 free up to 2.0; 3.0 (== range_max) and 9.0 -> 4 free each
    # (min(no_return_free_m, range_max) = 2.0); plus the 2.0 m beam's 4
    assert per_scan[1] == 16
    assert (samples.labels[samples.scan_ids == 1] > 0).sum() == 1

    # range_max below no_return_free_m caps the no-return free space
    capped = replace(sensor, no_return_free_m=5.0)
    samples = build_samples([batch], _config(capped))
    _assert_same_rows(_rows(samples), _oracle(batch, capped, SAMPLES))
    assert np.bincount(samples.scan_ids, minlength=2)[1] == 4 + 3 * 6


def test_strides_keep_every_sth_scan_and_bth_beam():
    rng = np.random.default_rng(0)
    ranges = rng.uniform(0.5, 6.0, size=(5, 7))
    angles = np.linspace(-1.5, 1.5, 7)
    poses = np.column_stack([rng.normal(size=5), rng.normal(size=5), rng.uniform(-3, 3, 5)])
    batch = _batch(ranges, angles, poses)
    cfg = replace(SAMPLES, scan_stride=2, beam_stride=3)
    samples = build_samples([batch], _config(scan_stride=2, beam_stride=3))
    _assert_same_rows(_rows(samples), _oracle(batch, NOISELESS, cfg))
    assert set(samples.scan_ids.tolist()) == {0, 2, 4}


def _noisy_batch(n_scans=30, seed=1):
    rng = np.random.default_rng(seed)
    angles = np.linspace(-1.5, 1.5, 40)
    ranges = rng.uniform(0.5, 4.0, size=(n_scans, 40))
    poses = np.column_stack([rng.uniform(0, 1, n_scans), rng.uniform(0, 1, n_scans),
                             rng.uniform(-3, 3, n_scans)])
    covs = np.zeros((n_scans, 3, 3))
    covs[:, 0, 0] = rng.uniform(0.001, 0.01, n_scans)
    covs[:, 1, 1] = rng.uniform(0.001, 0.01, n_scans)
    covs[:, 2, 2] = rng.uniform(1e-4, 1e-3, n_scans)
    return _batch(ranges, angles, poses, covs=covs)


def _brute_force_thin(samples: SampleSet, cell: float) -> np.ndarray:
    best: dict[tuple, int] = {}
    trace = np.trace(samples.covariances, axis1=1, axis2=2)
    for i in range(len(samples)):
        key = (samples.labels[i], math.floor(samples.means[i, 0] / cell),
               math.floor(samples.means[i, 1] / cell))
        if key not in best or trace[i] < trace[best[key]]:
            best[key] = i
    return np.sort(np.array(list(best.values())))


def test_thinning_keeps_the_most_certain_sample_per_cell_and_label(monkeypatch):
    batch = _noisy_batch()
    sensor = replace(NOISELESS, range_variance_m2=0.0004, bearing_variance_deg2=0.1)
    everything = build_samples([batch], _config(sensor))
    expected = everything.subset(_brute_force_thin(everything, 0.5))

    thinned = build_samples([batch], _config(sensor, thin_cell_m=0.5))
    assert len(thinned) == len(expected) < len(everything) / 4
    np.testing.assert_array_equal(thinned.means, expected.means)
    np.testing.assert_array_equal(thinned.covariances, expected.covariances)

    # the same when the samples arrive in many chunks (thinning as they come)
    monkeypatch.setattr(beams, "CHUNK_SAMPLES", 300)
    chunked = build_samples([batch], _config(sensor, thin_cell_m=0.5))
    _assert_same_rows(_rows(chunked), _rows(expected))
    chunked_all = build_samples([batch], _config(sensor))
    _assert_same_rows(_rows(chunked_all), _rows(everything))


def test_thinning_across_batches_and_chunks_matches_thinning_their_union(monkeypatch):
    """Three overlapping batches (two sensors) in many small chunks: the chunks are thinned
    as they come and their union re-thinned from keys alone; the result is the brute-force
    thinning of every unthinned sample, in build order."""
    sensor = replace(NOISELESS, range_variance_m2=0.0004, bearing_variance_deg2=0.1)
    other = replace(sensor, name="r2", range_variance_m2=0.0009)
    batches = [_noisy_batch(seed=1), replace(_noisy_batch(seed=2), sensor="r2",
                                              source="r2.log"), _noisy_batch(seed=3)]
    config = Config(sensors=(sensor, other), samples=replace(SAMPLES, thin_cell_m=0.3))
    monkeypatch.setattr(beams, "CHUNK_SAMPLES", 200)
    everything = build_samples(batches, replace(config, samples=SAMPLES))
    expected = everything.subset(_brute_force_thin(everything, 0.3))
    thinned = build_samples(batches, config)
    assert len(thinned) < len(everything) / 4
    for field in ("means", "covariances", "labels", "scan_ids", "pose_factors", "sensor_ids"):
        np.testing.assert_array_equal(getattr(thinned, field), getattr(expected, field))
    assert thinned.sensor_names == ("r1", "r2")


def test_a_batch_without_samples_is_named_even_between_good_ones():
    good = _noisy_batch()
    empty = replace(_noisy_batch(seed=4), source="empty.log",
                    ranges=np.full((30, 40), np.nan))
    with pytest.raises(GpoccError, match="empty.log: sensor 'r1' gave no training samples"):
        build_samples([good, empty, good], _config(thin_cell_m=0.3))


def test_errors_come_in_the_order_of_the_logs():
    """The first log's error is the one reported, though the next log is prepared while
    the first one's samples are still being made: poses 2e9 m from the origin put its
    samples past the label counts' range, and the log after it has no usable beam."""
    far = _noisy_batch()
    far = replace(far, source="far.log", poses=far.poses + [2e9, 0.0, 0.0])
    empty = replace(_noisy_batch(seed=4), source="empty.log",
                    ranges=np.full((30, 40), np.nan))
    with pytest.raises(GpoccError, match="from the map origin"):
        build_samples([far, empty], _config(thin_cell_m=0.3))
    with pytest.raises(GpoccError, match="empty.log"):
        build_samples([_noisy_batch(), empty, far], _config(thin_cell_m=0.3))


def test_thin_samples_ties_keep_the_first():
    means = np.array([[0.1, 0.1], [0.2, 0.3], [0.3, 0.2], [0.1, 0.1], [1.2, 0.1]])
    covs = np.repeat(np.eye(2)[None], 5, axis=0)
    covs[2] *= 0.5
    samples = SampleSet(
        means=means, covariances=covs, labels=np.array([1.0, 1.0, -1.0, -1.0, 1.0]),
        scan_ids=np.arange(5), pose_factors=np.zeros((5, 2, 3)),
        sensor_ids=np.zeros(5, dtype=np.int16),
    )
    kept = thin_samples(samples, 1.0)
    # +1 in cell (0, 0): 0 and 1 tie -> 0; -1 in (0, 0): 2 has the smaller trace; +1 in (1, 0)
    np.testing.assert_array_equal(kept.scan_ids, [0, 2, 4])
    assert thin_samples(samples, 0.0) is samples


@pytest.mark.parametrize("cell_m", [0.5, 1e-8])  # 1e-8: cell indices past 2**31
def test_thin_samples_matches_a_brute_force_oracle(cell_m):
    """Per (label, cell): the smallest single-precision trace, the earliest on ties; kept
    in input order. Cells on both sides of zero, many ties."""
    rng = np.random.default_rng(11)
    n = 400
    scale = 3.0 if cell_m > 1e-3 else 40.0
    means = rng.uniform(-scale, scale, (n, 2))
    if cell_m < 1e-3:  # every 7th point repeats its predecessor: same cell
        dup = np.arange(0, n - 1, 7)
        means[dup + 1] = means[dup]
    traces = rng.choice([0.01, 0.02, 0.03], n)
    covs = np.zeros((n, 2, 2))
    covs[:, 0, 0] = covs[:, 1, 1] = traces / 2
    samples = SampleSet(
        means=means, covariances=covs, labels=rng.choice([-1.0, 1.0], n),
        scan_ids=np.arange(n), pose_factors=np.zeros((n, 2, 3)),
        sensor_ids=np.zeros(n, dtype=np.int16),
    )
    best: dict[tuple, int] = {}
    cells = np.floor(means / cell_m).astype(np.int64)
    trace32 = traces.astype(np.float32)
    for i in range(n):
        group = (samples.labels[i], int(cells[i, 0]), int(cells[i, 1]))
        if group not in best or trace32[i] < trace32[best[group]]:
            best[group] = i
    assert len(best) < n  # some groups hold several samples
    kept = thin_samples(samples, cell_m)
    np.testing.assert_array_equal(kept.scan_ids, sorted(best.values()))


@pytest.mark.parametrize("n, n_keys", [(0, 1), (5, 1), (3000, 40), (40_000, 9000)])
def test_thin_groups_match_a_dictionary_oracle(n, n_keys):
    """The compiled grouping (a hash table that doubles as keys arrive: 9000 keys take
    it from 1024 slots through several doublings): per key in order of first sight, its
    count and its sample with the smallest single-precision trace, the earliest on ties.
    Keys on both sides of zero and far apart, traces with many ties."""
    rng = np.random.default_rng(n)
    pool = rng.choice(np.array([-(2**40), -7, 0, 1, 2**33], np.int64), n_keys) \
        + rng.integers(-(2**20), 2**20, n_keys)
    keys = pool[rng.integers(0, n_keys, n)]
    trace = rng.choice([0.5, 0.25, 0.125, 1.0], n).astype(np.float32)
    first: dict[int, int] = {}
    count: dict[int, int] = {}
    best: dict[int, int] = {}
    for i, key in enumerate(keys.tolist()):
        first.setdefault(key, i)
        count[key] = count.get(key, 0) + 1
        if key not in best or trace[i] < trace[best[key]]:
            best[key] = i
    order = sorted(first, key=first.get)
    group_keys, counts, kept = compiled.thin_groups(keys, trace)
    np.testing.assert_array_equal(group_keys, order)
    np.testing.assert_array_equal(counts, [count[k] for k in order])
    np.testing.assert_array_equal(kept, [best[k] for k in order])


def test_scan_ids_unique_across_batches_and_sensor_ids_by_first_appearance():
    rng = np.random.default_rng(2)
    a = _batch(rng.uniform(1, 3, (3, 4)), ANGLES, np.zeros((3, 3)), sensor="r1")
    b = _batch(rng.uniform(1, 3, (2, 4)), ANGLES, np.zeros((2, 3)), sensor="r2")
    c = _batch(rng.uniform(1, 3, (4, 4)), ANGLES, np.zeros((4, 3)), sensor="r1")
    r2 = replace(NOISELESS, name="r2", mount=MountConfig())
    config = Config(sensors=(NOISELESS, r2), samples=SAMPLES)
    samples = build_samples([a, b, c], config)
    for ids, sensor_id in ((range(0, 3), 0), (range(3, 5), 1), (range(5, 9), 0)):
        mask = samples.sensor_ids == sensor_id
        assert set(ids) <= set(samples.scan_ids[mask].tolist())
    assert set(samples.scan_ids.tolist()) == set(range(9))
    assert (samples.sensor_ids[np.isin(samples.scan_ids, [3, 4])] == 1).all()
    # the oracle with the same offsets
    _assert_same_rows(
        _rows(samples),
        np.concatenate([_oracle(a, NOISELESS, SAMPLES), _oracle(b, r2, SAMPLES, 3),
                        _oracle(c, NOISELESS, SAMPLES, 5)]),
    )


def test_pose_covariance_source_batch_config_or_override():
    """Translation-only pose noise Q moves every sample by the same Q: exact in the UT."""
    q_batch = np.array([[0.02, 0.005, 0.0], [0.005, 0.01, 0.0], [0.0, 0.0, 0.0]])
    q_config = np.array([[0.03, -0.01, 0.0], [-0.01, 0.04, 0.0], [0.0, 0.0, 0.0]])
    batch = _batch([[2.0, 3.0, np.inf, 1.5]], ANGLES, [POSES[0]], covs=[q_batch])
    sensor = replace(NOISELESS, pose_covariance=tuple(map(tuple, q_config)))

    def check(samples, q):
        expected = np.broadcast_to(q[:2, :2], (len(samples), 2, 2))
        np.testing.assert_allclose(samples.covariances, expected, atol=1e-12)
        np.testing.assert_allclose(samples.pose_factors @ np.swapaxes(samples.pose_factors, 1, 2),
                                   samples.covariances, atol=1e-12)

    check(build_samples([batch], _config(sensor)), q_batch)
    check(build_samples([batch], _config(replace(sensor, override_pose_covariance=True))), q_config)
    check(build_samples([replace(batch, has_pose_covariance=False)], _config(sensor)), q_config)


def test_unknown_sensor_uses_defaults():
    batch = _batch([[2.0, 3.0, 2.5, 1.5]], ANGLES, [POSES[0]], sensor="ghost")
    got = build_samples([batch], _config())
    expected = build_samples([batch], Config(sensors=(SensorConfig(name="ghost"),),
                                             samples=SAMPLES))
    np.testing.assert_array_equal(got.covariances, expected.covariances)
    assert got.covariances.any()  # the default noise model, not NOISELESS


def test_hits_carry_range_variance_free_samples_do_not():
    """Only the range is noisy: a hit's covariance is var_r along the beam, a free one's zero."""
    sensor = replace(NOISELESS, range_variance_m2=0.09)
    batch = _batch([[2.0]], [0.0], [[0.0, 0.0, 0.0]])
    samples = build_samples(
        [batch], _config(sensor, free_spacing_m=0.5, hit_gap_m=0.0, hit_gap_sigmas=0.0)
    )
    direction = np.array([math.cos(math.pi / 6), math.sin(math.pi / 6)])  # mount yaw 30 deg
    hit = samples.covariances[samples.labels > 0]
    np.testing.assert_allclose(hit, [0.09 * np.outer(direction, direction)], atol=1e-12)
    free = samples.covariances[samples.labels < 0]
    assert len(free) == 4  # 0.5 .. 2.0 m, hit_gap 0
    np.testing.assert_allclose(free, 0.0, atol=1e-15)


def test_free_samples_stop_a_few_range_sigmas_before_a_noisy_hit():
    """With range std 0.3 m, free samples stop 2 sigma = 0.6 m before the reading."""
    sensor = replace(NOISELESS, range_variance_m2=0.09)
    batch = _batch([[3.0]], [0.0], [[0.0, 0.0, 0.0]])
    cfg = _config(sensor, free_spacing_m=0.25, hit_gap_m=0.1, hit_gap_sigmas=2.0)
    samples = build_samples([batch], cfg)
    free = samples.means[samples.labels < 0]
    distances = np.linalg.norm(free - samples.means[samples.labels > 0][0]
                               + 3.0 * np.array([math.cos(math.pi / 6), math.sin(math.pi / 6)]),
                               axis=1)
    np.testing.assert_allclose(np.sort(distances), 0.25 * np.arange(1, 10), atol=1e-9)
    _assert_same_rows(_rows(samples), _oracle(batch, sensor, cfg.samples))


def test_no_valid_beam_is_a_clear_error():
    batch = _batch([[np.nan, -np.inf, 0.01, np.nan]], ANGLES, [POSES[0]], sensor="r9")
    with pytest.raises(GpoccError, match=r"r9\.log.*'r9'.*range_min"):
        build_samples([batch], _config())
    with pytest.raises(GpoccError, match="no scans"):
        build_samples([], _config())


def test_non_finite_poses_are_a_clear_error():
    batch = _batch([[2.0, 2.0, 2.0, 2.0]], ANGLES, [[np.nan, 0.0, 0.0]])
    with pytest.raises(GpoccError, match="r1.log.*non-finite poses"):
        build_samples([batch], _config())


def test_min_label_share_drops_labels_a_cell_rarely_saw():
    """Brute force: count every sample's label per cell over the whole log, then keep a
    thinned sample only if its label is at least the given share of its cell's samples."""
    rng = np.random.default_rng(4)
    n_scans, n_beams = 40, 24
    angles = np.linspace(-1.4, 1.4, n_beams)
    ranges = rng.uniform(1.0, 4.0, size=(n_scans, n_beams))
    ranges[rng.random(ranges.shape) < 0.1] *= 0.5  # "people": short, rare readings
    poses = np.column_stack([rng.uniform(-0.5, 0.5, n_scans), rng.uniform(-0.5, 0.5, n_scans),
                             rng.uniform(-0.3, 0.3, n_scans)])
    batch = _batch(ranges, angles, poses)
    cell = 0.3
    everything = build_samples([batch], _config(thin_cell_m=0.0))
    thinned = build_samples([batch], _config(thin_cell_m=cell))
    filtered = build_samples([batch], _config(thin_cell_m=cell, min_label_share=0.25))
    counts: dict[tuple[int, int], list[int]] = {}
    for mean, label in zip(everything.means, everything.labels, strict=True):
        key = tuple(np.floor(mean / cell).astype(int))
        counts.setdefault(key, [0, 0])[int(label > 0)] += 1
    share = np.array([counts[tuple(np.floor(m / cell).astype(int))][int(lab > 0)]
                      / sum(counts[tuple(np.floor(m / cell).astype(int))])
                      for m, lab in zip(thinned.means, thinned.labels, strict=True)])
    expected = thinned.subset(share >= 0.25)
    assert 0 < len(expected) < len(thinned)
    _assert_same_rows(_rows(filtered), _rows(expected))


def test_free_range_variance_gives_free_samples_of_hit_beams_the_range_variance():
    """With the option, free samples of a hit beam are spread along the beam like the hit;
    a no-return beam's free samples are not (its range carries no information)."""
    sensor = replace(NOISELESS, range_variance_m2=0.09)
    batch = _batch([[2.0, np.inf]], [0.0, 0.5], [[0.0, 0.0, 0.0]])
    cfg = _config(sensor, free_spacing_m=0.5, hit_gap_m=0.0, hit_gap_sigmas=0.0)
    cfg = replace(cfg, samples=replace(cfg.samples, free_range_variance=True))
    samples = build_samples([batch], cfg)
    direction = np.array([math.cos(math.pi / 6), math.sin(math.pi / 6)])  # mount yaw 30 deg
    along = 0.09 * np.outer(direction, direction)
    free = samples.covariances[samples.labels < 0]
    spread = np.array([np.allclose(c, along, atol=1e-12) for c in free])
    exact = np.array([np.allclose(c, 0.0, atol=1e-15) for c in free])
    assert spread.sum() == 4  # 0.5 .. 2.0 m on the hit beam
    assert exact.sum() == len(free) - 4 > 0  # the no-return beam


def test_clear_free_near_hits_matches_a_brute_force_oracle():
    """A free sample goes when some occupied sample lies strictly within the radius;
    occupied samples and far free samples stay, in order."""
    rng = np.random.default_rng(5)
    n = 300
    means = rng.uniform(-2.0, 2.0, (n, 2))
    labels = rng.choice([-1.0, 1.0], n, p=[0.7, 0.3])
    samples = SampleSet(
        means=means, covariances=np.zeros((n, 2, 2)), labels=labels,
        scan_ids=np.arange(n), pose_factors=np.zeros((n, 2, 3)),
        sensor_ids=np.zeros(n, dtype=np.int16),
    )
    radius = 0.2
    distance = np.linalg.norm(means[:, None] - means[labels > 0][None], axis=2).min(axis=1)
    expected = np.flatnonzero((labels > 0) | (distance >= radius))
    assert 0 < len(expected) < n
    kept = beams.clear_free_near_hits(samples, radius)
    np.testing.assert_array_equal(kept.scan_ids, expected)
    assert beams.clear_free_near_hits(samples, 0.0) is samples


def test_free_clearance_keeps_grazing_beams_off_the_wall():
    """A beam grazing a wall 3 cm away leaves free samples next to the wall's hits; with
    ``free_clearance_m`` 0.05 exactly those within 5 cm of a hit go."""
    # Wall x = 2; scan 0 looks straight at it, scan 1 runs along it 3 cm in front.
    batch = _batch([[2.0], [3.9]], [0.0], [[0.0, 0.0, 0.0], [1.97, -2.0, math.pi / 2]])
    sensor = replace(NOISELESS, mount=MountConfig())
    plain = build_samples([batch], _config(sensor, free_spacing_m=0.1, hit_gap_m=0.1))
    cleared = build_samples([batch], _config(sensor, free_spacing_m=0.1, hit_gap_m=0.1,
                                             free_clearance_m=0.05))
    near = (plain.labels < 0) & (np.linalg.norm(plain.means - [2.0, 0.0], axis=1) < 0.05)
    assert near.sum() == 1  # the grazing beam's sample at (1.97, 0.0)
    assert len(cleared) == len(plain) - 1
    assert not ((cleared.labels < 0)
                & (np.linalg.norm(cleared.means - [2.0, 0.0], axis=1) < 0.05)).any()


def test_label_votes_count_every_chunk_against_brute_force():
    """Shares from counts added chunk by chunk (merged on the way) equal a direct count,
    for cells on both sides of zero and cells seen with one label only."""
    rng = np.random.default_rng(8)
    n, cell = 3000, 0.5
    means = rng.uniform(-4.0, 4.0, (n, 2))
    labels = np.where(rng.random(n) < 0.3 + 0.1 * (means[:, 0] > 0), 1.0, -1.0)
    samples = SampleSet(means=means, covariances=np.zeros((n, 2, 2)), labels=labels,
                        scan_ids=np.arange(n), pose_factors=np.zeros((n, 2, 3)),
                        sensor_ids=np.zeros(n, dtype=np.int16))
    votes = beams.LabelVotes(cell)
    for lo in range(0, n, 170):
        votes.add(samples.subset(np.arange(lo, min(n, lo + 170))))
        if lo == 1020:
            votes._merge()  # a merged table plus pending chunks
    counts: dict[tuple[int, int], list[int]] = {}
    for mean, label in zip(means, labels, strict=True):
        counts.setdefault(tuple(np.floor(mean / cell).astype(int)), [0, 0])[int(label > 0)] += 1
    probe = np.vstack([means[:50], [[40.2, -40.7]]])  # the last cell was never counted
    probe_labels = np.concatenate([labels[:50], [1.0]])
    expected = [counts[tuple(np.floor(m / cell).astype(int))][int(lab > 0)]
                / sum(counts[tuple(np.floor(m / cell).astype(int))])
                for m, lab in zip(probe[:50], probe_labels[:50], strict=True)]
    got = votes.share(SampleSet(means=probe, covariances=np.zeros((51, 2, 2)),
                                labels=probe_labels, scan_ids=np.arange(51),
                                pose_factors=np.zeros((51, 2, 3)),
                                sensor_ids=np.zeros(51, dtype=np.int16)))
    np.testing.assert_array_equal(got[:50], expected)
    assert np.isnan(got[50])  # no count at all: 0 / 0, dropped by any share threshold
    far = samples.subset(np.arange(3))
    far = SampleSet(far.means + 1e9, far.covariances, far.labels, far.scan_ids,
                    far.pose_factors, far.sensor_ids)
    with pytest.raises(GpoccError, match="thin_cell_m"):
        votes.add(far)


def test_label_votes_take_empty_chunks():
    votes = beams.LabelVotes(0.5)
    votes.add_counts(np.zeros(0, np.int64), np.zeros(0, np.int64))
    empty = SampleSet(means=np.zeros((0, 2)), covariances=np.zeros((0, 2, 2)),
                      labels=np.zeros(0), scan_ids=np.zeros(0, np.int64),
                      pose_factors=np.zeros((0, 2, 3)), sensor_ids=np.zeros(0, np.int16))
    votes.add(empty)
    one = SampleSet(means=np.array([[0.1, 0.2]]), covariances=np.zeros((1, 2, 2)),
                    labels=np.array([1.0]), scan_ids=np.zeros(1, np.int64),
                    pose_factors=np.zeros((1, 2, 3)), sensor_ids=np.zeros(1, np.int16))
    votes.add(one)
    np.testing.assert_array_equal(votes.share(one), [1.0])
    assert votes.share(empty).shape == (0,)
