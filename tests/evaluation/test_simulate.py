"""The world ray caster, the two-robot simulator and `gpocc simulate`."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.config import load_config
from gpocc.errors import GpoccError
from gpocc.evaluation.simulate import (
    PLATFORM_I,
    PLATFORM_II,
    PoseNoise,
    route_poses,
    simulate,
    truth_raster,
)
from gpocc.evaluation.world import WORLD_NAMES, World, cast_rays, make_world


def _box(x0, y0, x1, y1):
    return np.array([[[x0, y0], [x1, y0]], [[x1, y0], [x1, y1]], [[x1, y1], [x0, y1]],
                     [[x0, y1], [x0, y0]]], dtype=float)


def _route_length(route: np.ndarray) -> float:
    return float(sum(math.hypot(*(b - a)) for a, b in zip(route[:-1], route[1:], strict=True)))


# --------------------------------------------------------------------------- ray casting


def test_rays_inside_a_box_hit_the_walls_at_the_analytic_distance():
    rng = np.random.default_rng(0)
    x0, y0, x1, y1 = -2.0, -1.5, 3.0, 2.5
    origins = rng.uniform([x0 + 0.1, y0 + 0.1], [x1 - 0.1, y1 - 0.1], (500, 2))
    angles = rng.uniform(-np.pi, np.pi, 500)
    got = cast_rays(_box(x0, y0, x1, y1), np.zeros((0, 3)), origins, angles)
    c, s = np.cos(angles), np.sin(angles)
    tx = np.where(c > 0, (x1 - origins[:, 0]) / c, (x0 - origins[:, 0]) / c)
    ty = np.where(s > 0, (y1 - origins[:, 1]) / s, (y0 - origins[:, 1]) / s)
    np.testing.assert_allclose(got, np.minimum(tx, ty), rtol=1e-12, atol=1e-12)
    # Beyond max_range: no return.
    capped = cast_rays(_box(x0, y0, x1, y1), np.zeros((0, 3)), origins, angles, max_range=2.0)
    expected = np.minimum(tx, ty)
    np.testing.assert_array_equal(np.isinf(capped), expected > 2.0)


def test_box_seen_from_outside_and_missed():
    box = _box(1.0, -0.5, 2.0, 0.5)
    angles = np.array([0.0, 0.3, -0.4, 0.6, np.pi])
    got = cast_rays(box, np.zeros((0, 3)), np.zeros((5, 2)), angles)
    # Front face x = 1 for |tan| <= 0.5; missed above atan(0.5) = 0.4636 rad; behind.
    np.testing.assert_allclose(got[:3], 1.0 / np.cos(angles[:3]), rtol=1e-12)
    assert np.isinf(got[3]) and np.isinf(got[4])


def test_rays_hit_a_circle_at_the_analytic_distance():
    cx, cy, radius = 4.0, 1.0, 0.8
    origin = np.array([0.5, -0.2])
    d = math.hypot(cx - origin[0], cy - origin[1])
    towards = math.atan2(cy - origin[1], cx - origin[0])
    offsets = np.linspace(-0.3, 0.3, 41)  # some beyond the tangent angle asin(R/D) = 0.23
    got = cast_rays(np.zeros((0, 2, 2)), np.array([[cx, cy, radius]]),
                    np.tile(origin, (41, 1)), towards + offsets)
    disc = radius**2 - (d * np.sin(offsets)) ** 2
    with np.errstate(invalid="ignore"):
        expected = np.where(disc >= 0, d * np.cos(offsets) - np.sqrt(disc), np.inf)
    np.testing.assert_allclose(got, expected, rtol=1e-10)
    assert np.isinf(got).sum() > 0 and np.isfinite(got).sum() > 0
    # From the centre every ray travels one radius.
    centre = cast_rays(np.zeros((0, 2, 2)), np.array([[cx, cy, radius]]),
                       np.tile([cx, cy], (8, 1)), np.linspace(0, 6, 8))
    np.testing.assert_allclose(centre, radius, rtol=1e-12)


def test_world_cast_takes_the_nearest_obstacle():
    world = World(name="t", segments=_box(-5, -5, 5, 5), circles=np.array([[2.0, 0.0, 0.5]]),
                  routes=())
    got = world.cast(np.zeros((2, 2)), np.array([0.0, np.pi]))
    np.testing.assert_allclose(got, [1.5, 5.0])


# --------------------------------------------------------------------------- worlds, routes


def _assert_routes_clear(world) -> None:
    """Every route stays 0.4 m from obstacles and inside the world's bounds."""
    x0, y0, x1, y1 = world.bounds
    for route in world.routes:
        legs = [a + np.linspace(0, 1, 200)[:, None] * (b - a)
                for a, b in zip(route[:-1], route[1:], strict=True)]
        pts = np.concatenate(legs)
        assert world.clearance(pts).min() >= 0.4
        assert np.all((pts > [x0, y0]) & (pts < [x1, y1]))


@pytest.mark.parametrize("name", WORLD_NAMES)
def test_routes_stay_in_free_space(name):
    world = make_world(name)
    _assert_routes_clear(world)


def test_route_poses_are_evenly_spaced_along_the_route():
    route = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 4.0]])
    stamps, poses = route_poses(route, speed=2.0, rate=4.0, t0=10.0)
    # Length 7 m at 2 m/s: 3.5 s, 4 scans/s -> 14 intervals, 15 scans.
    assert len(stamps) == 15
    np.testing.assert_allclose(np.diff(stamps), 0.25)
    travelled = 0.5 * np.arange(15)
    expected_xy = np.where(travelled[:, None] <= 3.0,
                           np.column_stack((travelled, 0 * travelled)),
                           np.column_stack((3.0 + 0 * travelled, travelled - 3.0)))
    np.testing.assert_allclose(poses[:, :2], expected_xy, atol=1e-12)
    np.testing.assert_allclose(poses[travelled < 3.0, 2], 0.0)
    np.testing.assert_allclose(poses[travelled >= 3.0, 2], np.pi / 2)


def test_unknown_world_is_a_clear_error():
    with pytest.raises(GpoccError, match="default"):
        make_world("moon")


# --------------------------------------------------------------------------- simulation


@pytest.fixture(scope="module")
def default_sim():
    return simulate("default", seed=4)


def test_platforms_follow_table_one(default_sim):
    r1, r2 = default_sim.runs
    assert (r1.platform, r2.platform) == (PLATFORM_I, PLATFORM_II)
    world = make_world("default")
    for run, route, speed, rate in ((r1, world.routes[0], 0.5, 0.5),
                                    (r2, world.routes[1], 4.0, 4.0)):
        assert run.n_scans == math.floor(_route_length(route) / speed * rate) + 1
        np.testing.assert_allclose(np.diff(run.stamps), 1.0 / rate)
        # Scans are speed / rate metres apart along straight legs.
        step = np.hypot(*np.diff(run.true_poses[:, :2], axis=0).T)
        assert np.median(step) == pytest.approx(speed / rate)
    assert np.nanmax(r2.ranges[np.isfinite(r2.ranges)]) < 8.0
    assert np.nanmax(r1.ranges[np.isfinite(r1.ranges)]) < 20.0


def test_simulation_is_seeded():
    a = simulate("office", seed=1)
    b = simulate("office", seed=1)
    c = simulate("office", seed=2)
    np.testing.assert_array_equal(a.runs[1].ranges, b.runs[1].ranges)
    assert not np.array_equal(a.runs[1].ranges, c.runs[1].ranges)


def test_truth_raster_labels_the_observed_area(default_sim):
    world = default_sim.world
    labels, spec = truth_raster(world, default_sim.runs)
    assert (labels == 1).sum() > 1000 and (labels == 0).sum() > 10000
    assert set(np.unique(labels)) == {0, 1, 255}
    xc, yc = spec.cell_centres()
    centres = np.column_stack((xc.ravel(), yc.ravel()))
    flat = labels.ravel()
    # Occupied cells hold an obstacle surface: their centre is within half a diagonal.
    occ = centres[flat == 1]
    assert world.clearance(occ).max() <= spec.resolution / math.sqrt(2) + 1e-9
    # Nothing inside a round obstacle is labelled.
    for cx, cy, r in world.circles:
        inside = np.hypot(centres[:, 0] - cx, centres[:, 1] - cy) < r - spec.resolution
        assert np.all(flat[inside] == 255)
    # Where the robots stand is free.
    for run in default_sim.runs:
        row, col, _ = spec.index_of(run.true_poses[:, :2])
        assert np.all(labels[row, col] == 0)


def test_platform_two_sees_what_platform_one_never_does(default_sim):
    r1, r2 = default_sim.runs
    seen_by_1 = truth_raster(default_sim.world, [r1])[0] != 255
    labels_2, spec = truth_raster(default_sim.world, [r2])
    seen_by_2 = labels_2 != 255
    only_2 = seen_by_2 & ~seen_by_1
    assert only_2.sum() > 0.2 * seen_by_2.sum()
    # The north-east room platform II drives through is out of platform I's sight (away
    # from its door, through which platform I glimpses it from the corridor).
    east = (r2.true_poses[:, 0] > 27.0) & (r2.true_poses[:, 1] > 16.5)
    assert east.sum() >= 10
    row, col, _ = spec.index_of(r2.true_poses[east, :2])
    assert not seen_by_1[row, col].any() and seen_by_2[row, col].all()


def test_pose_noise_is_drawn_from_the_recorded_covariance():
    noise = PoseNoise(0.1, 2.0)
    sim = simulate("default", seed=9, pose_noise=noise)
    err = np.concatenate([run.poses - run.true_poses for run in sim.runs])
    err[:, 2] = np.angle(np.exp(1j * err[:, 2]))
    expected = np.array([0.01, 0.01, math.radians(2.0) ** 2])
    n = len(err)
    # Sample variances: within 4 standard errors (sqrt(2 / n) relative).
    np.testing.assert_allclose(err.var(axis=0), expected, rtol=4 * math.sqrt(2 / n))
    for run in sim.runs:
        np.testing.assert_allclose(run.pose_covariance, np.diag(expected))
    with pytest.raises(GpoccError, match="pose noise"):
        PoseNoise(-1.0, 0.0)


# --------------------------------------------------------------------------- CLI


def test_simulate_command_writes_a_trainable_log(tmp_path: Path):
    rasterio = pytest.importorskip("rasterio")
    from gpocc.io.inputs import read_inputs

    out = tmp_path / "sim"
    runner = CliRunner()
    result = runner.invoke(app, ["simulate", "--out", str(out), "--seed", "3"])
    assert result.exit_code == 0, result.output
    for name in ("sim.mcap", "truth.tif", "sim.yaml", "simulation.json"):
        assert (out / name).is_file(), name

    config = load_config(out / "sim.yaml")
    assert config.seed == 3
    by_name = {s.name: s for s in config.sensors}
    assert by_name["robot2"].range_variance_m2 == 0.8
    assert by_name["robot2"].bearing_variance_deg2 == 0.5
    assert by_name["robot1"].scan_topic == "/robot1/scan"
    batches = {b.sensor: b for b in read_inputs([out / "sim.mcap"], config)}
    assert set(batches) == {"robot1", "robot2"}
    world = make_world("default")
    for name, route, speed, rate, rmax in (("robot1", world.routes[0], 0.5, 0.5, 20.0),
                                           ("robot2", world.routes[1], 4.0, 4.0, 8.0)):
        b = batches[name]
        assert b.n_scans == math.floor(_route_length(route) / speed * rate) + 1
        assert b.n_beams == 180 and b.range_max == pytest.approx(rmax)
        assert b.has_pose_covariance and b.skipped_scans == 0
        np.testing.assert_allclose(b.poses[0, :2], route[0], atol=1e-9)

    # Range noise: measured minus the noiseless range from the recorded (= true) pose.
    b = batches["robot2"]
    origins = np.repeat(b.poses[:, :2], b.n_beams, axis=0)
    phi = (b.poses[:, 2:3] + b.angles).ravel()
    true = world.cast(origins, phi).reshape(b.ranges.shape)
    sd = math.sqrt(0.8)
    usable = np.isfinite(b.ranges) & (true > 0.1 + 3 * sd) & (true < 8.0 - 3 * sd)
    diff = (b.ranges - true)[usable]
    diff = diff[np.abs(diff) < 6 * sd]  # a bearing error can slip a ray past an edge
    assert diff.size > 2000
    assert abs(diff.mean()) < 4 * sd / math.sqrt(diff.size)
    assert diff.var() == pytest.approx(0.8, rel=0.2)
    # Platform I is nearly noiseless.
    b1 = batches["robot1"]
    true1 = world.cast(np.repeat(b1.poses[:, :2], b1.n_beams, axis=0),
                       (b1.poses[:, 2:3] + b1.angles).ravel()).reshape(b1.ranges.shape)
    ok = np.isfinite(b1.ranges) & np.isfinite(true1)
    assert np.median(np.abs(b1.ranges - true1)[ok]) < 0.005

    with rasterio.open(out / "truth.tif") as ds:
        truth = ds.read(1)
        assert ds.nodata == 255
    assert set(np.unique(truth)) == {0, 1, 255}
    meta = json.loads((out / "simulation.json").read_text())
    assert [r["scans"] for r in meta["robots"]] == [batches["robot1"].n_scans,
                                                    batches["robot2"].n_scans]

    again = runner.invoke(app, ["simulate", "--out", str(out)])
    assert again.exit_code == 2 and "--force" in again.stderr
    assert "Traceback" not in again.output


def test_simulate_command_pose_noise_reaches_the_bag(tmp_path: Path):
    from gpocc.io.inputs import read_inputs

    out = tmp_path / "noisy"
    result = CliRunner().invoke(app, ["simulate", "--out", str(out), "--world", "office",
                                      "--pose-noise", "0.05", "1.0", "--seed", "1"])
    assert result.exit_code == 0, result.output
    config = load_config(out / "sim.yaml")
    expected = np.diag([0.05**2, 0.05**2, math.radians(1.0) ** 2])
    for sensor in config.sensors:
        np.testing.assert_allclose(sensor.pose_covariance_matrix, expected)
    for b in read_inputs([out / "sim.mcap"], config):
        np.testing.assert_allclose(b.pose_covariances, np.broadcast_to(expected, (b.n_scans, 3, 3)),
                                   rtol=1e-6, atol=1e-12)
        route = make_world("office").routes[0 if b.sensor == "robot1" else 1]
        # Recorded poses are the route plus errors of the configured size.
        assert 0 < np.hypot(*(b.poses[0, :2] - route[0])) < 5 * 0.05


def test_simulate_command_unknown_world(tmp_path: Path):
    result = CliRunner().invoke(app, ["simulate", "--out", str(tmp_path / "x"),
                                      "--world", "moon"])
    assert result.exit_code == 2 and "default" in result.stderr
    assert not (tmp_path / "x").exists()


# --------------------------------------------------------------------------- grown worlds


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 5, 8])
def test_grown_worlds_keep_routes_in_free_space_and_differ(seed):
    world = make_world(f"grown-{seed}")
    assert world.name == f"grown-{seed}"
    _assert_routes_clear(world)
    again = make_world(f"grown-{seed}")
    np.testing.assert_array_equal(world.segments, again.segments)
    other = make_world(f"grown-{seed + 100}")
    assert world.segments.shape != other.segments.shape or not np.allclose(
        world.segments, other.segments)


def test_grown_world_platform_two_sees_a_region_platform_one_never_does():
    from gpocc.evaluation.simulate import region_truth

    sim = simulate("grown-2", seed=1)
    labels, spec = truth_raster(sim.world, sim.runs)
    only_2 = region_truth(labels, spec, sim.runs[:1])
    seen_by_1 = truth_raster(sim.world, sim.runs[:1])[0] != 255
    kept = only_2 != 255
    # The region is the truth minus everything platform I's rays crossed, labels intact.
    assert kept.sum() > 0.1 * (labels != 255).sum()
    assert not (kept & seen_by_1).any()
    np.testing.assert_array_equal(only_2[kept], labels[kept])
    assert (only_2 == 1).any() and (only_2 == 0).any()


def test_bad_grown_world_name_is_a_clear_error():
    with pytest.raises(GpoccError, match="grown-<seed>"):
        make_world("grown-x")


def test_stretch_pose_noise_is_honest_per_stretch():
    from gpocc.evaluation.simulate import perturb_poses, stretch_covariances

    levels = (PoseNoise(0.02, 0.5), PoseNoise(0.2, 4.0))
    cov = stretch_covariances(40_000, 100, levels)
    assert cov.shape == (40_000, 3, 3)
    np.testing.assert_allclose(cov[:100], np.broadcast_to(levels[0].covariance, (100, 3, 3)))
    np.testing.assert_allclose(cov[100:200], np.broadcast_to(levels[1].covariance, (100, 3, 3)))
    poses = np.zeros((40_000, 3))
    poses[:, 2] = 3.0  # near the wrap: errors must be measured modulo 2 pi
    out = perturb_poses(poses, cov, np.random.default_rng(0))
    err = out - poses
    err[:, 2] = np.angle(np.exp(1j * err[:, 2]))
    assert np.all(np.abs(out[:, 2]) <= np.pi)
    for k, level in enumerate(levels):
        stretch = ((np.arange(40_000) // 100) % 2) == k
        n = stretch.sum()
        np.testing.assert_allclose(err[stretch].var(axis=0), np.diag(level.covariance),
                                   rtol=4 * math.sqrt(2 / n))
