"""The front of a wall: what the training samples and the GP make of free space just
before a straight wall of known position (issue 35, "sharp walls")."""

from __future__ import annotations

import numpy as np
import pytest

from gpocc.config import Config, ModelConfig, SamplesConfig, SensorConfig
from gpocc.gp.kernels import make_kernel
from gpocc.gp.local import NeighbourIndex, predict_local
from gpocc.io.scans import ScanBatch
from gpocc.samples.beams import build_samples

WALL_X = 3.0  # the wall is the line x = 3 m; everything at x < 3 is free
SENSOR = SensorConfig(name="bot", range_variance_m2=0.0004, bearing_variance_deg2=0.01,
                      pose_covariance=((0.0009, 0, 0), (0, 0.0009, 0), (0, 0, 7.6e-5)))


def wall_scans(n_scans: int = 60, n_beams: int = 31, seed: int = 0) -> ScanBatch:
    """Scans of the wall from random poses in front of it, beams within 30 deg of it."""
    rng = np.random.default_rng(seed)
    poses = np.column_stack((rng.uniform(0.0, 1.5, n_scans), rng.uniform(-1.0, 1.0, n_scans),
                             rng.uniform(-0.2, 0.2, n_scans)))
    angles = np.linspace(-np.pi / 6, np.pi / 6, n_beams)
    phi = poses[:, 2:3] + angles[None, :]
    ranges = (WALL_X - poses[:, 0:1]) / np.cos(phi)  # exact: the wall is a known line
    return ScanBatch(sensor="bot", source="wall.test", stamps=np.arange(n_scans, dtype=float),
                     angles=angles, ranges=ranges, poses=poses,
                     pose_covariances=np.zeros((n_scans, 3, 3)), range_min=0.05,
                     range_max=10.0, has_pose_covariance=False)


def latent_profile(samples_cfg: SamplesConfig, xs: np.ndarray) -> np.ndarray:
    """The GP's latent mean at (x, 0) for each x, with the default initial
    hyperparameters (no learning: the samples alone make the difference)."""
    config = Config(sensors=(SENSOR,), samples=samples_cfg)
    samples = build_samples([wall_scans()], config)
    model = ModelConfig()
    kernel = make_kernel(model.kernel, model.hyperparameters)
    index = NeighbourIndex(samples)
    queries = np.column_stack((xs, np.zeros_like(xs)))
    problem = index.problem(np.array([WALL_X - 0.2, 0.0]), model.neighbours)
    return predict_local(kernel, model.hyperparameters.noise_variance, problem, queries,
                         model.quadrature_level).mean


@pytest.mark.parametrize("gap", [0.05, 0.25])
def test_free_samples_stop_the_hit_gap_short_of_the_wall(gap):
    """Free samples end ``hit_gap_m`` short of each hit (2 cm range noise: 2 sigma is
    below both gaps), so the band in front of the wall holds none nearer than that."""
    cfg = Config(sensors=(SENSOR,), samples=SamplesConfig(hit_gap_m=gap, thin_cell_m=0.0,
                                                          free_clearance_m=0.0))
    batch = wall_scans()
    samples = build_samples([batch], cfg)
    free = samples.means[samples.labels < 0]
    # Along each beam, a free sample at distance d from the sensor has d <= r - gap; in
    # x that is at most (r - gap) cos(phi) from the sensor, i.e. gap * cos(phi) or more
    # short of the wall, and cos(phi) >= cos(30 deg + 0.2 rad) here.
    assert free[:, 0].max() <= WALL_X - gap * np.cos(np.pi / 6 + 0.2) + 1e-9
    assert free[:, 0].max() > WALL_X - gap - 0.4  # spacing 0.4 m: the last one is near


def test_a_short_hit_gap_moves_the_latent_crossing_to_the_wall():
    """The wall is at x = 3 m and everything before it free. With free samples up to
    0.05 m short of the hits the latent mean is negative (free) 0.1 m in front of the
    wall and positive on it; with free samples stopping 0.25 m short, the GP
    interpolates +1 at the hits over the empty band and 0.1 m in front of the wall is
    already occupied: the wall is drawn that much thick (issue 35's blur)."""
    xs = np.array([WALL_X - 0.1, WALL_X])
    short_front, short_wall = latent_profile(SamplesConfig(hit_gap_m=0.05), xs)
    long_front, long_wall = latent_profile(SamplesConfig(hit_gap_m=0.25), xs)
    assert short_front < -0.2 < 0.2 < short_wall
    assert long_front > 0.0
