"""The beam rules (gpocc.samples.beam_rules) and that every consumer applies the same ones."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from gpocc.config import Config, MountConfig, SamplesConfig, SensorConfig
from gpocc.errors import GpoccError
from gpocc.evaluation.split import labelled_points
from gpocc.io.scans import ScanBatch
from gpocc.samples import beam_rules
from gpocc.samples.beams import build_samples

MOUNT = SensorConfig(name="laser", mount=MountConfig(x_m=0.3, y_m=-0.2, yaw_deg=15.0))


def _se2(x: float, y: float, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def _batch(ranges: np.ndarray, poses: np.ndarray, **kw: object) -> ScanBatch:
    s, b = ranges.shape
    return ScanBatch(
        sensor=str(kw.pop("sensor", "laser")), source="memory",
        stamps=np.arange(s, dtype=float), angles=np.linspace(-1.2, 1.2, b), ranges=ranges,
        poses=poses, pose_covariances=np.broadcast_to(np.diag([0.01, 0.02, 0.003]),
                                                      (s, 3, 3)).copy(),
        range_min=0.2, range_max=8.0, **kw,
    )


def test_classes_follow_rep_117_element_by_element() -> None:
    values = [np.nan, -np.inf, np.inf, 0.0, 0.1999, 0.2, 3.0, 7.9999, 8.0, 9.0, -1.0]
    classes = beam_rules.classify_beams(np.array(values), 0.2, 8.0)
    for v, hit, none, bad in zip(values, classes.hit, classes.no_return, classes.invalid,
                                 strict=True):
        # The rule as REP 117 states it, one value at a time.
        want_hit = math.isfinite(v) and 0.2 <= v < 8.0
        want_none = v == math.inf or (math.isfinite(v) and v >= 8.0)
        assert (hit, none, bad) == (want_hit, want_none, not (want_hit or want_none)), v


def test_laser_pose_and_points_are_the_se2_composition() -> None:
    rng = np.random.default_rng(3)
    poses = rng.uniform([-5, -5, -np.pi], [5, 5, np.pi], size=(20, 3))
    mount = beam_rules.mount_vector(MOUNT)
    lasers = beam_rules.laser_poses(poses, mount)
    bearings = rng.uniform(-2, 2, size=20)
    dist = rng.uniform(0, 9, size=20)
    points = beam_rules.beam_points(lasers, bearings, dist)
    for pose, laser, b, d, p in zip(poses, lasers, bearings, dist, points, strict=True):
        t = _se2(*pose) @ _se2(*mount)
        np.testing.assert_allclose(laser[:2], t[:2, 2], atol=1e-12)
        assert math.isclose(math.cos(laser[2]), t[0, 0], abs_tol=1e-12)
        assert math.isclose(math.sin(laser[2]), t[1, 0], abs_tol=1e-12)
        np.testing.assert_allclose(p, (t @ np.array([d * math.cos(b), d * math.sin(b), 1]))[:2],
                                   atol=1e-12)
    inputs = np.column_stack((dist, bearings, poses))
    np.testing.assert_allclose(beam_rules.beam_endpoint(inputs, mount), points, atol=1e-12)


def test_laser_pose_covariance_matches_monte_carlo() -> None:
    pose = np.array([1.0, -2.0, 0.7])
    cov = np.array([[0.004, 0.001, 0.0005], [0.001, 0.003, -0.0004], [0.0005, -0.0004, 0.002]])
    mount = np.array([0.8, 0.4, 0.3])
    rng = np.random.default_rng(0)
    draws = rng.multivariate_normal(pose, cov, size=200_000)
    mc = np.cov(beam_rules.laser_poses(draws, mount).T)
    lin = beam_rules.laser_pose_covariances(pose[None], cov[None], mount)[0]
    # Linearisation error is second order in the yaw spread (sd 0.045 rad): ~0.2% here.
    np.testing.assert_allclose(lin, mc, rtol=0.03, atol=2e-5)
    # The mount matters: without it the position covariance would be the base's.
    assert not np.allclose(lin[:2, :2], cov[:2, :2], rtol=0.03, atol=2e-5)


def test_which_pose_covariance_applies() -> None:
    batch = _batch(np.full((3, 4), 2.0), np.zeros((3, 3)))
    np.testing.assert_array_equal(beam_rules.pose_covariances(batch, MOUNT), batch.pose_covariances)
    override = SensorConfig(name="laser", override_pose_covariance=True,
                            pose_covariance=((0.5, 0.0, 0.0), (0.0, 0.6, 0.0),
                                             (0.0, 0.0, 0.7)))
    np.testing.assert_allclose(beam_rules.pose_covariances(batch, override, np.array([0, 2, 2])),
                               np.broadcast_to(np.diag([0.5, 0.6, 0.7]), (3, 3, 3)))
    absent = _batch(np.full((3, 4), 2.0), np.zeros((3, 3)), has_pose_covariance=False)
    np.testing.assert_allclose(beam_rules.pose_covariances(absent, MOUNT)[1],
                               MOUNT.pose_covariance_matrix)
    bad = _batch(np.full((3, 4), 2.0), np.zeros((3, 3)))
    bad.pose_covariances[1, 0, 0] = np.nan
    with pytest.raises(GpoccError, match="non-finite pose covariances"):
        beam_rules.pose_covariances(bad, MOUNT)


def test_sensor_config_prefers_the_readers_entry_then_the_name() -> None:
    attached = SensorConfig(name="laser", range_variance_m2=0.3)
    named = SensorConfig(name="laser", range_variance_m2=0.7)
    config = Config(sensors=(named,))
    ranges, poses = np.full((1, 2), 1.0), np.zeros((1, 3))
    given = _batch(ranges, poses, sensor_config=attached)
    assert beam_rules.sensor_config(given, config) is attached
    assert beam_rules.sensor_config(_batch(ranges, poses), config) is named
    assert beam_rules.sensor_config(_batch(ranges, poses, sensor="other"), config) == SensorConfig(
        name="other")


def test_samples_and_heldout_truth_put_hits_at_the_same_points() -> None:
    """The GP's occupied samples (noise-free) and split's occupied points coincide."""
    rng = np.random.default_rng(5)
    ranges = rng.uniform(0.5, 7.5, size=(4, 9))
    ranges[0, :3] = (np.nan, np.inf, 0.1)  # invalid, no return, too close: no hit
    poses = rng.uniform([-3, -3, -np.pi], [3, 3, np.pi], size=(4, 3))
    sensor = SensorConfig(name="laser", mount=MOUNT.mount, range_variance_m2=0.0,
                          bearing_variance_deg2=0.0, pose_covariance=((0.0,) * 3,) * 3,
                          override_pose_covariance=True)
    batch = _batch(ranges, poses, sensor_config=sensor)
    config = Config(samples=SamplesConfig(thin_cell_m=0.0))
    samples = build_samples([batch], config)
    hits = samples.means[samples.labels > 0]
    points, labels = labelled_points(batch, sensor, 0, np.random.default_rng(0))
    assert len(hits) == int(np.isfinite(ranges).sum() - 1) == len(points)
    np.testing.assert_allclose(hits, points[labels == 1], atol=1e-9)


def test_scan_ids_are_unique_across_inputs_and_sensors_are_named() -> None:
    """Two inputs of one sensor and a second sensor: no scan id is shared, so no pose
    correlation is assumed between scans of different inputs."""
    rng = np.random.default_rng(2)
    poses = rng.uniform(-1, 1, size=(3, 3))
    a = _batch(np.full((3, 5), 2.0), poses)
    b = dataclasses.replace(a, source="second input")
    c = dataclasses.replace(a, sensor="other")
    samples = build_samples([a, b, c], Config(samples=SamplesConfig(thin_cell_m=0.0)))
    assert samples.sensor_names == ("laser", "other")
    per_batch = len(samples) // 3
    ids = [set(samples.scan_ids[i * per_batch:(i + 1) * per_batch]) for i in range(3)]
    assert all(len(s) == 3 for s in ids)
    assert not (ids[0] & ids[1]) and not (ids[0] & ids[2]) and not (ids[1] & ids[2])
    np.testing.assert_array_equal(samples.sensor_ids[:2 * per_batch], 0)
    np.testing.assert_array_equal(samples.sensor_ids[2 * per_batch:], 1)
