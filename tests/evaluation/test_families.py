"""The second world generator (offices, halls, cluttered warehouses) and its platforms."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.errors import GpoccError
from gpocc.evaluation.families import FAMILIES, family_seed
from gpocc.evaluation.simulate import (
    PLATFORM_I,
    PLATFORM_II,
    platforms_for,
    region_truth,
    simulate,
    truth_raster,
)
from gpocc.evaluation.world import is_world_name, make_world

runner = CliRunner()


def _route_points(route: np.ndarray, step_m: float = 0.05) -> np.ndarray:
    legs = [a + np.linspace(0.0, 1.0, max(2, int(np.linalg.norm(b - a) / step_m) + 1))[:, None]
            * (b - a) for a, b in zip(route[:-1], route[1:], strict=True)]
    return np.concatenate(legs)


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("seed", [0, 7])
def test_family_worlds_have_clear_routes_and_are_deterministic(family, seed):
    name = f"{family}-{seed}"
    assert is_world_name(name) and family_seed(name) == (family, seed)
    world = make_world(name)
    x0, y0, x1, y1 = world.bounds
    assert len(world.routes) == 2
    for route in world.routes:
        pts = _route_points(route)
        # Exact distances to every obstacle, every 5 cm: the planner's raster is not trusted.
        assert world.clearance(pts).min() >= 0.45
        assert np.all((pts > [x0, y0]) & (pts < [x1, y1]))
    # The traverser reaches farther east than the explorer ever goes.
    assert world.routes[1][:, 0].max() > world.routes[0][:, 0].max() + 2.0
    again = make_world(name)
    np.testing.assert_array_equal(world.segments, again.segments)
    np.testing.assert_array_equal(world.circles, again.circles)
    for a, b in zip(world.routes, again.routes, strict=True):
        np.testing.assert_array_equal(a, b)


def test_families_differ_from_each_other_and_across_seeds():
    worlds = [make_world(f"{f}-{s}") for f in FAMILIES for s in (1, 2)]
    shapes = {(w.segments.shape, w.circles.shape, w.bounds) for w in worlds}
    assert len(shapes) == len(worlds)


def test_platforms_are_table_one_except_on_family_worlds():
    assert platforms_for(make_world("default")) == (PLATFORM_I, PLATFORM_II)
    assert platforms_for(make_world("grown-3")) == (PLATFORM_I, PLATFORM_II)
    draws = [platforms_for(make_world(f"hall-{s}")) for s in range(4)]
    assert len({p[1].range_variance_m2 for p in draws}) == 4
    for first, second in draws:
        for mine, table in ((first, PLATFORM_I), (second, PLATFORM_II)):
            for key in ("range_variance_m2", "bearing_variance_deg2"):
                ratio = getattr(mine, key) / getattr(table, key)
                assert 0.25 <= ratio <= 2.0
        assert 6.0 <= second.max_range_m <= 10.0 and 3.0 <= second.speed_m_s <= 5.0
    assert platforms_for(make_world("hall-2")) == draws[2]


def test_a_family_simulation_has_a_region_only_the_noisy_robot_saw():
    sim = simulate("clutter-1", seed=3)
    assert sim.runs[1].platform == platforms_for(sim.world)[1]
    labels, spec = truth_raster(sim.world, sim.runs)
    only_2 = region_truth(labels, spec, sim.runs[:1])
    assert (only_2 == 1).any() and (only_2 == 0).any()


def test_simulate_command_writes_the_drawn_platform_noise(tmp_path):
    out = tmp_path / "sim"
    result = runner.invoke(app, ["simulate", "--quiet", "--world", "offices-2", "--out",
                                 str(out)])
    assert result.exit_code == 0, result.output
    config = yaml.safe_load((out / "sim.yaml").read_text())
    drawn = platforms_for(make_world("offices-2"))
    for sensor, platform in zip(config["sensors"], drawn, strict=True):
        assert math.isclose(sensor["range_variance_m2"], platform.range_variance_m2)
        assert math.isclose(sensor["bearing_variance_deg2"], platform.bearing_variance_deg2)


@pytest.mark.parametrize("name", ["hall-x", "hall-", "attic-3"])
def test_bad_family_names_are_clear_errors(name):
    assert not is_world_name(name)
    with pytest.raises(GpoccError, match="hall-<seed>"):
        make_world(name)
