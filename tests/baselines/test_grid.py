"""The log-odds grid baseline and `gpocc grid`, against brute-force and analytic oracles."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from gpocc.baselines import grid as grid_mod
from gpocc.baselines.grid import (
    default_grid_spec,
    occupancy_grid,
    ray_cells,
    spread_weights,
)
from gpocc.cli import app
from gpocc.config import Config, GridConfig, MountConfig, SensorConfig
from gpocc.gridspec import GridSpec
from gpocc.io.scans import ScanBatch

# A rectangular room whose walls are not on grid lines.
ROOM = (-4.03, -3.96, 4.07, 4.11)  # x_min, y_min, x_max, y_max metres


# --------------------------------------------------------------------------- helpers


def room_ranges(laser: np.ndarray, angles: np.ndarray, room=ROOM) -> np.ndarray:
    """Analytic distance from laser poses (S, 3) along bearings (B,) to the room walls."""
    x0, y0, x1, y1 = room
    phi = laser[:, 2:3] + angles[None, :]
    c, s = np.cos(phi), np.sin(phi)
    lx, ly = laser[:, 0:1], laser[:, 1:2]
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (x1 - lx) / c, np.where(c < 0, (x0 - lx) / c, np.inf))
        ty = np.where(s > 0, (y1 - ly) / s, np.where(s < 0, (y0 - ly) / s, np.inf))
    return np.minimum(tx, ty)


def laser_from_base(poses: np.ndarray, mount: MountConfig) -> np.ndarray:
    x, y, th = poses.T
    c, s = np.cos(th), np.sin(th)
    return np.column_stack((x + c * mount.x_m - s * mount.y_m, y + s * mount.x_m + c * mount.y_m,
                            th + math.radians(mount.yaw_deg)))


def room_batch(rng, name: str, n_scans: int, n_beams: int, mount: MountConfig, t0: float,
               range_min=0.05, range_max=6.0, corrupt=True) -> ScanBatch:
    """Scans of the room from random poses, with every REP 117 reading kind mixed in."""
    poses = np.column_stack((rng.uniform(-2.4, 2.4, (n_scans, 2)),
                             rng.uniform(-np.pi, np.pi, n_scans)))
    angles = -np.pi + np.arange(n_beams) * 2 * np.pi / n_beams
    ranges = room_ranges(laser_from_base(poses, mount), angles)
    if corrupt:
        kinds = rng.integers(0, 12, ranges.shape)
        ranges[kinds == 0] = np.nan
        ranges[kinds == 1] = -np.inf
        ranges[kinds == 2] = range_min / 2  # too close
        ranges[kinds == 3] = np.inf  # no return
    return ScanBatch(
        sensor=name, source=f"{name}.test", stamps=t0 + np.arange(n_scans) * 1.0,
        angles=angles, ranges=ranges, poses=poses,
        pose_covariances=np.zeros((n_scans, 3, 3)), range_min=range_min, range_max=range_max,
        has_pose_covariance=False,
    )


def midpoint_cells(spec: GridSpec, p0: np.ndarray, p1: np.ndarray) -> set[tuple[int, int]]:
    """Cells (row, col) a segment crosses: the cell of the midpoint of each piece between
    consecutive grid-line crossings (a slow, obviously correct per-beam walk)."""
    u0 = np.array([(p0[0] - spec.x0) / spec.resolution, (p0[1] - spec.y0) / spec.resolution])
    u1 = np.array([(p1[0] - spec.x0) / spec.resolution, (p1[1] - spec.y0) / spec.resolution])
    d = u1 - u0
    length = float(np.hypot(*d))
    ts = [0.0, 1.0]
    for axis in (0, 1):
        if d[axis] == 0:
            continue
        lo, hi = sorted((u0[axis], u1[axis]))
        for k in range(math.ceil(lo), math.floor(hi) + 1):
            t = (k - u0[axis]) / d[axis]
            if 0.0 < t < 1.0:
                ts.append(t)
    ts.sort()
    cells = set()
    for ta, tb in zip(ts[:-1], ts[1:], strict=True):
        if (tb - ta) * length <= 1e-9:
            continue
        m = u0 + 0.5 * (ta + tb) * d
        col, v = math.floor(m[0]), math.floor(m[1])
        row = spec.height - 1 - v
        if 0 <= col < spec.width and 0 <= row < spec.height:
            cells.add((row, col))
    return cells


def reference_grid(batches: list[ScanBatch], config: Config, spec: GridSpec):
    """Per-beam Python loop: counts and per-scan clamped log-odds, scans in time order."""
    g = config.grid
    sensors = {s.name: s for s in config.sensors}
    log_odds = np.zeros(spec.shape)
    hits = np.zeros(spec.shape, dtype=int)
    passes = np.zeros(spec.shape, dtype=int)
    observed = np.zeros(spec.shape, dtype=bool)
    scans = sorted(((float(b.stamps[s]), i, s) for i, b in enumerate(batches)
                    for s in range(b.n_scans)))
    for _, i, s in scans:
        batch = batches[i]
        sensor = sensors.get(batch.sensor, SensorConfig(name=batch.sensor))
        laser = laser_from_base(batch.poses[s:s + 1], sensor.mount)[0]
        delta: dict[tuple[int, int], float] = {}
        for b, r in enumerate(batch.ranges[s]):
            if np.isnan(r) or r < batch.range_min:
                continue
            hit = bool(np.isfinite(r) and r < batch.range_max)
            length = r if hit else min(sensor.no_return_free_m, batch.range_max)
            if length <= 0:
                continue
            phi = laser[2] + batch.angles[b]
            end = laser[:2] + length * np.array([math.cos(phi), math.sin(phi)])
            row, col, inside = spec.index_of(end[None])
            end_cell = (int(row[0]), int(col[0]))
            for cell in midpoint_cells(spec, laser[:2], end):
                if hit and cell == end_cell:
                    continue
                delta[cell] = delta.get(cell, 0.0) + g.log_odds_free
                passes[cell] += 1
            if hit and inside[0]:
                delta[end_cell] = delta.get(end_cell, 0.0) + g.log_odds_occupied
                hits[end_cell] += 1
        for cell, dl in delta.items():
            log_odds[cell] = min(max(log_odds[cell] + dl, g.clamp_min), g.clamp_max)
            observed[cell] = True
    return log_odds, hits, passes, observed


def slab_cells(spec: GridSpec, p0: np.ndarray, p1: np.ndarray) -> set[tuple[int, int]]:
    """Cells whose closed box the segment overlaps over a positive length (Liang-Barsky)."""
    u0 = np.array([(p0[0] - spec.x0), (p0[1] - spec.y0)]) / spec.resolution
    u1 = np.array([(p1[0] - spec.x0), (p1[1] - spec.y0)]) / spec.resolution
    d = u1 - u0
    cu, cv = np.meshgrid(np.arange(spec.width), np.arange(spec.height))
    t_lo = np.zeros(cu.shape)
    t_hi = np.ones(cu.shape)
    for axis, lo in ((0, cu), (1, cv)):
        if d[axis] == 0:
            inside = (u0[axis] >= lo) & (u0[axis] <= lo + 1)
            t_hi = np.where(inside, t_hi, -1.0)
            continue
        ta = (lo - u0[axis]) / d[axis]
        tb = (lo + 1 - u0[axis]) / d[axis]
        t_lo = np.maximum(t_lo, np.minimum(ta, tb))
        t_hi = np.minimum(t_hi, np.maximum(ta, tb))
    crossed = (t_hi - t_lo) * np.hypot(*d) > 1e-7
    v, u = np.nonzero(crossed)
    return {(spec.height - 1 - int(vv), int(uu)) for vv, uu in zip(v, u, strict=True)}


# --------------------------------------------------------------------------- traversal


def test_ray_cells_equal_slab_clipping_brute_force():
    rng = np.random.default_rng(1)
    spec = GridSpec(x0=-1.37, y0=0.42, resolution=0.1, width=40, height=30)
    n = 300
    starts = rng.uniform([-1.8, 0.0], [3.0, 3.8], (n, 2))  # some start outside the grid
    lengths = np.where(rng.random(n) < 0.2, rng.uniform(0.001, 0.08, n), rng.uniform(0.1, 4, n))
    angles = rng.uniform(-np.pi, np.pi, n)
    angles[:20] = np.pi / 4 * rng.integers(-4, 4, 20) + 1e-7  # nearly diagonal / axis-parallel
    ends = starts + lengths[:, None] * np.column_stack((np.cos(angles), np.sin(angles)))
    cells = ray_cells(spec, starts, ends)
    assert np.all(np.diff(cells.ray) >= 0), "entries must be grouped by ray in ray order"
    for i in range(n):
        mine = list(zip(cells.row[cells.ray == i].tolist(), cells.col[cells.ray == i].tolist(),
                        strict=True))
        assert len(mine) == len(set(mine)), f"ray {i} repeats a cell"
        assert set(mine) == slab_cells(spec, starts[i], ends[i]), f"ray {i}"
        r, c, inside = spec.index_of(ends[i:i + 1])
        flagged = cells.is_end[cells.ray == i]
        expected = [inside[0] and (rr, cc) == (r[0], c[0]) for rr, cc in mine]
        assert flagged.tolist() == expected


def test_segments_far_longer_than_the_grid_cross_the_brute_force_cells():
    # Segments of 50-5000 m through a 4 x 3 m grid (at 0.1 m: a --bounds around part of
    # the data) are cut to the grid before the traversal; the cells inside must be the
    # slab oracle's, and those that miss the grid must give none.
    rng = np.random.default_rng(7)
    spec = GridSpec(x0=-1.37, y0=0.42, resolution=0.1, width=40, height=30)
    n = 200
    centre = np.array([0.63, 1.92])
    lengths = rng.uniform(50, 5000, n)
    angles = rng.uniform(-np.pi, np.pi, n)
    through = centre + rng.uniform(-3, 3, (n, 2))  # some lines miss the grid
    t = rng.uniform(0.0, 1.0, n)  # where on the segment that point lies
    direction = np.column_stack((np.cos(angles), np.sin(angles)))
    starts = through - (t * lengths)[:, None] * direction
    ends = starts + lengths[:, None] * direction
    ends[:20] = through[:20]  # some end inside or near the grid
    # Axis-parallel ones (on a row of cells, outside the grid's rows, along its border),
    # one starting inside the grid and one pointing away from it.
    special = np.array([
        [[-500.0, 1.0], [500.0, 1.0]], [[0.0, -400.0], [0.0, 400.0]],
        [[-500.0, 9.0], [500.0, 9.0]], [[-500.0, 0.42], [500.0, 0.42]],
        [[0.5, 1.5], [800.0, 700.0]], [[5.0, 5.0], [900.0, 900.0]],
    ])
    starts[20:26], ends[20:26] = special[:, 0], special[:, 1]
    cells = ray_cells(spec, starts, ends)
    missed = 0
    for i in range(n):
        mine = set(zip(cells.row[cells.ray == i].tolist(), cells.col[cells.ray == i].tolist(),
                       strict=True))
        expected = slab_cells(spec, starts[i], ends[i])
        assert mine == expected, f"segment {i}"
        missed += not expected
        r, c, inside = spec.index_of(ends[i:i + 1])
        flagged = {(rr, cc) for rr, cc, e in zip(cells.row[cells.ray == i].tolist(),
                                                 cells.col[cells.ray == i].tolist(),
                                                 cells.is_end[cells.ray == i].tolist(),
                                                 strict=True) if e}
        assert flagged == ({(int(r[0]), int(c[0]))} if inside[0] and expected else set())
    assert 0 < missed < n


def test_zero_length_ray_is_its_own_cell():
    spec = GridSpec(x0=0.0, y0=0.0, resolution=0.5, width=4, height=4)
    p = np.array([[1.2, 0.3]])
    cells = ray_cells(spec, p, p)
    assert cells.row.tolist() == [3] and cells.col.tolist() == [2]
    assert cells.is_end.tolist() == [True]


# --------------------------------------------------------------------------- the grid


def _room_config(**grid) -> Config:
    mount = MountConfig(x_m=0.2, y_m=-0.05, yaw_deg=5.0)
    sensors = (SensorConfig(name="front", mount=mount, no_return_free_m=1.0),
               SensorConfig(name="rear", mount=MountConfig(x_m=-0.1, yaw_deg=180.0),
                            no_return_free_m=1.0))
    return Config(sensors=sensors, grid=dataclasses.replace(GridConfig(), **grid))


def test_grid_matches_per_beam_reference_and_room_geometry():
    rng = np.random.default_rng(7)
    cfg = _room_config()
    batches = [room_batch(rng, "front", 6, 120, cfg.sensors[0].mount, t0=0.0),
               room_batch(rng, "rear", 5, 90, cfg.sensors[1].mount, t0=0.5)]
    spec = GridSpec.from_bounds(-5.02, -5.13, 5.11, 5.07, 0.1)
    g = occupancy_grid(batches, cfg, spec)
    ref_lo, ref_hits, ref_passes, ref_observed = reference_grid(batches, cfg, spec)
    np.testing.assert_array_equal(g.hit_counts, ref_hits)
    np.testing.assert_array_equal(g.pass_counts, ref_passes)
    np.testing.assert_array_equal(g.observed, ref_observed)
    np.testing.assert_allclose(g.log_odds, ref_lo, atol=1e-12)

    # Geometry: interior cells free, wall cells occupied, outside never observed.
    xc, yc = spec.cell_centres()
    x0, y0, x1, y1 = ROOM
    h = spec.resolution
    inner = (xc > x0 + 3 * h) & (xc < x1 - 3 * h) & (yc > y0 + 3 * h) & (yc < y1 - 3 * h)
    outside = (xc < x0 - h) | (xc > x1 + h) | (yc < y0 - h) | (yc > y1 + h)
    on_wall = (((np.abs(xc - x0) < h / 2) | (np.abs(xc - x1) < h / 2)) & (yc > y0) & (yc < y1)) | (
        ((np.abs(yc - y0) < h / 2) | (np.abs(yc - y1) < h / 2)) & (xc > x0) & (xc < x1))
    p = g.probability
    assert np.all(np.isnan(p[outside]))
    seen_inner = inner & g.observed
    assert seen_inner.sum() > 0.5 * inner.sum()
    assert np.all(g.log_odds[seen_inner] < 0)
    seen_wall = on_wall & g.observed
    assert seen_wall.sum() > 0.5 * on_wall.sum()
    assert np.mean(g.log_odds[seen_wall] > 0) > 0.9
    np.testing.assert_allclose(p[g.observed], 1 - 1 / (1 + np.exp(g.log_odds[g.observed])))
    np.testing.assert_allclose(g.variance, p * (1 - p), equal_nan=True)
    assert np.all(g.log_odds >= cfg.grid.clamp_min) and np.all(g.log_odds <= cfg.grid.clamp_max)


def _beam_batch(ranges: list[float], name="s") -> ScanBatch:
    n = len(ranges)
    return ScanBatch(
        sensor=name, source="beam.test", stamps=np.arange(n, dtype=float),
        angles=np.array([0.0]), ranges=np.array(ranges, dtype=float)[:, None],
        poses=np.tile([0.03, 0.05, 0.0], (n, 1)), pose_covariances=np.zeros((n, 3, 3)),
        range_min=0.01, range_max=10.0, has_pose_covariance=False,
    )


def test_clamping_happens_after_each_scan():
    # One beam along +x from (0.03, 0.05): 20 scans pass through the cell 1.0-1.1 m, then
    # 3 scans hit in it, then 10 more. Per-scan clamping: -4 after the passes, then
    # -4 + 3 * 0.85; clamping only at the end would give max(-8 + 2.55, -4) = -4.
    cfg = Config()
    spec = GridSpec(x0=0.0, y0=0.0, resolution=0.1, width=30, height=3)
    cell = spec.index_of(np.array([[1.05, 0.05]]))[:2]
    near = spec.index_of(np.array([[0.55, 0.05]]))[:2]
    g = occupancy_grid([_beam_batch([2.05] * 20 + [1.02] * 3)], cfg, spec)
    g_cfg = cfg.grid
    assert g.log_odds[cell][0] == pytest.approx(g_cfg.clamp_min + 3 * g_cfg.log_odds_occupied)
    assert g.log_odds[near][0] == pytest.approx(g_cfg.clamp_min)
    assert g.hit_counts[cell][0] == 3 and g.pass_counts[cell][0] == 20
    g = occupancy_grid([_beam_batch([2.05] * 20 + [1.02] * 13)], cfg, spec)
    assert g.log_odds[cell][0] == pytest.approx(g_cfg.clamp_max)


def test_default_extent_covers_hits_and_origins_plus_margin():
    rng = np.random.default_rng(3)
    cfg = _room_config()
    batch = room_batch(rng, "front", 4, 60, cfg.sensors[0].mount, t0=0.0, corrupt=False)
    spec = default_grid_spec([batch], cfg, 0.1)
    ranges = batch.ranges
    laser = laser_from_base(batch.poses, cfg.sensors[0].mount)
    phi = laser[:, 2:3] + batch.angles
    ok = ranges < batch.range_max
    limit = np.where(ok, ranges, cfg.sensors[0].no_return_free_m)
    ends = np.column_stack(((laser[:, 0:1] + limit * np.cos(phi)).ravel(),
                            (laser[:, 1:2] + limit * np.sin(phi)).ravel()))
    pts = np.concatenate([laser[:, :2], ends])
    m = cfg.map.margin_m
    assert spec.x0 == pytest.approx(pts[:, 0].min() - m)
    assert spec.y0 == pytest.approx(pts[:, 1].min() - m)
    assert spec.x1 >= pts[:, 0].max() + m - 1e-9 and spec.x1 < pts[:, 0].max() + m + 0.1
    assert spec.y1 >= pts[:, 1].max() + m - 1e-9 and spec.y1 < pts[:, 1].max() + m + 0.1


# --------------------------------------------------------------------------- spread hits


def _rot_cov(angle: float, s_major: float, s_minor: float) -> np.ndarray:
    r = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    return r @ np.diag([s_major**2, s_minor**2]) @ r.T


@pytest.mark.parametrize("cov", [
    _rot_cov(0.3, 0.2, 0.2), _rot_cov(0.52, 0.5, 0.03), _rot_cov(0.8, 0.05, 0.01),
    _rot_cov(1.2, 0.6, 0.08),
])
def test_spread_weights_are_cell_masses(monkeypatch, cov):
    monkeypatch.setattr(grid_mod, "SPREAD_MIN_WEIGHT", 0.0)
    spec = GridSpec(-3.0, -3.0, 0.1, 60, 60)
    mean = np.array([0.0123, 0.0871])
    _, flat, w = spread_weights(spec, mean[None], cov[None])
    mine = np.bincount(flat, weights=w, minlength=spec.width * spec.height)
    n = 1_000_000
    draws = np.random.default_rng(5).multivariate_normal(mean, cov, size=n)
    row, col, inside = spec.index_of(draws)
    mc = np.bincount((row * spec.width + col)[inside], minlength=spec.width * spec.height) / n
    se = np.sqrt(mc.max() / n)
    assert np.abs(mine - mc).max() < 5 * se + 5e-4
    assert w.sum() == pytest.approx(1.0)


def test_spread_of_a_tiny_covariance_is_the_hit_cell():
    spec = GridSpec(0.0, 0.0, 0.1, 10, 10)
    means = np.array([[0.0999, 0.53], [0.47, 0.7001]])  # near, not on, cell edges
    hit, flat, w = spread_weights(spec, means, np.zeros((2, 2, 2)))
    row, col, _ = spec.index_of(means)
    assert hit.tolist() == [0, 1]
    assert flat.tolist() == (row * spec.width + col).tolist() and w.tolist() == [1.0, 1.0]


def test_spread_grid_follows_the_noisy_endpoint_distribution():
    # log_odds_free = 0 isolates the hit: its spread must match the Monte-Carlo
    # distribution of the endpoint under range, bearing and pose noise.
    sensor = SensorConfig(name="s", range_variance_m2=0.04, bearing_variance_deg2=0.25,
                          pose_covariance=((1e-4, 0, 0), (0, 2e-4, 0), (0, 0, 1e-5)))
    cfg = Config(sensors=(sensor,), grid=GridConfig(log_odds_free=0.0, clamp_min=-50,
                                                    clamp_max=50, spread_hits=True))
    batch = dataclasses.replace(_beam_batch([3.0]), angles=np.array([0.4]))
    spec = GridSpec(1.0, -1.0, 0.1, 40, 40)
    g = occupancy_grid([batch], cfg, spec)
    share = g.log_odds / cfg.grid.log_odds_occupied
    rng = np.random.default_rng(11)
    n = 1_000_000
    r = 3.0 + rng.normal(0, 0.2, n)
    b = 0.4 + rng.normal(0, math.radians(0.5), n)
    pose = rng.multivariate_normal([0.03, 0.05, 0.0], np.array(sensor.pose_covariance), n)
    phi = pose[:, 2] + b
    pts = np.column_stack((pose[:, 0] + r * np.cos(phi), pose[:, 1] + r * np.sin(phi)))
    row, col, inside = spec.index_of(pts)
    mc = np.zeros(spec.shape)
    np.add.at(mc, (row[inside], col[inside]), 1.0 / n)
    assert np.abs(share - mc).max() < 5e-3
    assert g.hit_counts.sum() == 1
    assert g.observed[share >= grid_mod.SPREAD_MIN_WEIGHT].all()


# --------------------------------------------------------------------------- CLI


def test_grid_command_writes_map_folder_and_refuses_overwrite(tmp_path: Path):
    rasterio = pytest.importorskip("rasterio")
    from gpocc.gp.classify import classify
    from gpocc.io.bags import write_bag
    from gpocc.io.inputs import read_inputs

    rng = np.random.default_rng(2)
    batch = room_batch(rng, "scan", 5, 90, MountConfig(), t0=10.0, corrupt=False)
    bag = tmp_path / "room.mcap"
    write_bag(bag, [batch], [("/scan", "/pose")], "mcap")
    out = tmp_path / "grid"
    runner = CliRunner()
    result = runner.invoke(app, ["grid", str(bag), "--resolution", "0.1", "--out", str(out)])
    assert result.exit_code == 0, result.output
    for name in ("probability.tif", "variance.tif", "class.tif", "map.yaml", "map.pgm",
                 "preview.png", "metadata.json"):
        assert (out / name).is_file(), name

    cfg = Config()
    batches = read_inputs([bag], cfg)
    expected = occupancy_grid(batches, cfg, default_grid_spec(batches, cfg, 0.1))
    with rasterio.open(out / "probability.tif") as ds:
        prob = ds.read(1)
        assert ds.res == pytest.approx((0.1, 0.1))
        assert ds.bounds.left == pytest.approx(expected.spec.x0)
        assert ds.bounds.top == pytest.approx(expected.spec.y1)
    np.testing.assert_allclose(prob, expected.probability.astype(np.float32), equal_nan=True)
    with rasterio.open(out / "variance.tif") as ds:
        np.testing.assert_allclose(ds.read(1), (prob * (1 - prob)), rtol=1e-6, equal_nan=True)
    with rasterio.open(out / "class.tif") as ds:
        assert ds.nodata == 255
        np.testing.assert_array_equal(
            ds.read(1), classify(prob, cfg.classify.occupied, cfg.classify.free))
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["method"] == "grid" and meta["resolution_m"] == 0.1
    assert meta["bounds_m"] == pytest.approx(list(expected.spec.bounds))

    again = runner.invoke(app, ["grid", str(bag), "--resolution", "0.1", "--out", str(out)])
    assert again.exit_code == 2
    assert "--force" in again.stderr and "Traceback" not in again.output
    bounded = runner.invoke(app, ["grid", str(bag), "--resolution", "0.2", "--out", str(out),
                                  "--bounds", "-5", "-5", "5", "5", "--force"])
    assert bounded.exit_code == 0, bounded.output
    with rasterio.open(out / "probability.tif") as ds:
        assert tuple(ds.bounds) == pytest.approx((-5, -5, 5, 5))
        assert ds.shape == (50, 50)


def test_grid_command_bad_input_is_one_line(tmp_path: Path):
    bad = tmp_path / "broken.mcap"
    bad.write_bytes(b"\x00not a bag" * 10)
    result = CliRunner().invoke(app, ["grid", str(bad), "--out", str(tmp_path / "g")])
    assert result.exit_code == 2
    lines = [ln for ln in result.stderr.splitlines() if ln.startswith("gpocc grid: error")]
    assert len(lines) == 1 and "broken.mcap" in lines[0]
    assert "Traceback" not in result.output and not (tmp_path / "g").exists()


# --------------------------------------------------------------------------- real data

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "carmen"


@pytest.mark.slow
def test_intel_grid_counts_every_hit():
    # Its speed is measured in bench/ (docs/benchmarks.md), not asserted here.
    from gpocc.io.inputs import read_inputs

    path = DATA / "intel.gfs.log"
    if not path.is_file():
        pytest.skip(f"real data absent: {path}")
    cfg = Config()
    (batch,) = read_inputs([path], cfg)
    spec = default_grid_spec([batch], cfg, 0.1)
    g = occupancy_grid([batch], cfg, spec)
    r = batch.ranges
    with np.errstate(invalid="ignore"):
        n_hits = int((np.isfinite(r) & (r >= batch.range_min) & (r < batch.range_max)).sum())
    assert g.hit_counts.sum() == n_hits  # the default extent holds every endpoint
    hit_cells = g.hit_counts > 0
    # A SLAM-corrected log: most cells that were hit are occupied in the end.
    assert np.mean(g.log_odds[hit_cells] > 0) > 0.5
    assert np.all(np.isnan(g.probability[~g.observed]))
