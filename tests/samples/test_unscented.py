"""Unscented transform: exact for linear maps, Monte Carlo agreement for beam endpoints."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from gpocc.config import Config, MountConfig, SamplesConfig, SensorConfig, UnscentedConfig
from gpocc.io.scans import ScanBatch
from gpocc.samples.beam_rules import beam_endpoint
from gpocc.samples.beams import build_samples
from gpocc.samples.unscented import (
    matrix_sqrt,
    sigma_points,
    unscented_transform,
    ut_weights,
)

D2R = math.pi / 180.0
MOUNT = np.array([0.3, -0.1, 20.0 * D2R])
# alpha^2 (n + kappa) = 3 puts each axis's sigma points where a Gaussian's fourth moment
# is matched (Julier's n + kappa = 3 rule); beta = 0.5 keeps the centre covariance weight
# positive. The strongly nonlinear cases below are run with these.
ACCURATE_UT = (math.sqrt(3.0 / 5.0), 0.5, 0.0)


def _random_spd(rng: np.random.Generator, n: int, rank: int) -> np.ndarray:
    a = rng.normal(size=(n, rank))
    return a @ a.T


def _se2(x: float, y: float, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


# --------------------------------------------------------------------------- algebra


def test_matrix_sqrt_definite_singular_and_slightly_indefinite():
    rng = np.random.default_rng(1)
    pd = np.stack([_random_spd(rng, 5, 5) for _ in range(4)])
    singular = np.stack([_random_spd(rng, 5, 2) for _ in range(3)])
    singular[0] = np.diag([0.0, 2.0, 0.5, 0.5, 1e-3])  # a zero variance, as for free samples
    w, v = np.linalg.eigh(_random_spd(rng, 5, 5))
    w[0] = -1e-13
    indefinite = (v * w) @ v.T
    stack = np.concatenate([pd, singular, indefinite[None]])

    root = matrix_sqrt(stack)

    np.testing.assert_allclose(root[:7] @ np.swapaxes(root[:7], -1, -2), stack[:7], atol=1e-10)
    # positive definite ones are the Cholesky factor
    np.testing.assert_allclose(root[:4], np.linalg.cholesky(pd), atol=1e-10)
    clipped = (v * np.clip(w, 0.0, None)) @ v.T
    np.testing.assert_allclose(root[7] @ root[7].T, clipped, atol=1e-10)
    assert np.isfinite(root).all()
    # single matrix in, single matrix out
    np.testing.assert_allclose(matrix_sqrt(pd[0]), root[0])


@pytest.mark.parametrize("alpha,beta,kappa", [(1.0, 2.0, 0.0), (0.3, 2.0, 1.0), (1.5, 0.0, 3.0)])
def test_linear_map_is_exact_even_for_singular_covariances(alpha, beta, kappa):
    rng = np.random.default_rng(2)
    n, m, count = 4, 3, 6
    mean = rng.normal(size=(count, n))
    cov = np.stack([_random_spd(rng, n, r) for r in (4, 3, 2, 1, 4, 0)])
    a = rng.normal(size=(m, n))
    c = rng.normal(size=m)

    y_mean, y_cov, cross = unscented_transform(lambda x: x @ a.T + c, mean, cov, alpha, beta, kappa)

    np.testing.assert_allclose(y_mean, mean @ a.T + c, atol=1e-10)
    np.testing.assert_allclose(y_cov, a @ cov @ a.T, atol=1e-10)
    np.testing.assert_allclose(cross, cov @ a.T, atol=1e-10)


@pytest.mark.parametrize(
    "alpha,beta,kappa", [(1.0, 2.0, 0.0), (0.5, 2.0, 0.0), (1.0, 1.0, 1.0), (0.5, 1.75, 1.0)]
)
def test_square_of_a_gaussian_is_exact_when_alpha2_kappa_plus_beta_is_2(alpha, beta, kappa):
    """y = x^2, x ~ N(mu, s^2): E y = mu^2 + s^2, Var y = 4 mu^2 s^2 + 2 s^4 (analytic).

    The scaled UT gets the mean for any parameters and the variance when
    alpha^2 kappa + beta = 2 (the centre weight's beta term carries the fourth moment).
    """
    mu, s = np.array([[0.7], [-2.0]]), np.array([0.3, 1.5])
    cov = (s**2)[:, None, None]
    y_mean, y_cov, cross = unscented_transform(np.square, mu, cov, alpha, beta, kappa)
    m = mu[:, 0]
    np.testing.assert_allclose(y_mean[:, 0], m**2 + s**2, rtol=1e-12)
    np.testing.assert_allclose(y_cov[:, 0, 0], 4 * m**2 * s**2 + 2 * s**4, rtol=1e-12)
    np.testing.assert_allclose(cross[:, 0, 0], 2 * m * s**2, rtol=1e-12)  # Cov(x, x^2)


def test_sigma_points_reproduce_mean_and_covariance():
    rng = np.random.default_rng(3)
    mean = rng.normal(size=(5, 3))
    cov = np.stack([_random_spd(rng, 3, 3) for _ in range(5)])
    points, wm, wc = sigma_points(mean, cov, 0.5, 2.0, 1.0)
    assert points.shape == (5, 7, 3)
    assert wm.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(np.einsum("k,nki->ni", wm, points), mean, atol=1e-12)
    d = points - mean[:, None]
    # the spread points alone carry the covariance (the centre point has zero offset)
    np.testing.assert_allclose(np.einsum("k,nki,nkj->nij", wc, d, d), cov, atol=1e-10)


def test_ut_weights_reject_degenerate_spread():
    with pytest.raises(ValueError):
        ut_weights(5, 0.0, 2.0, 0.0)


def test_beam_endpoint_matches_se2_composition():
    rng = np.random.default_rng(4)
    inputs = np.column_stack([
        rng.uniform(0.1, 20, 50), rng.uniform(-3, 3, 50), rng.normal(size=50) * 10,
        rng.normal(size=50) * 10, rng.uniform(-7, 7, 50),
    ])
    got = beam_endpoint(inputs.reshape(5, 10, 5), MOUNT).reshape(50, 2)
    for (r, b, x, y, th), p in zip(inputs, got, strict=True):
        laser = _se2(x, y, th) @ _se2(*MOUNT)
        expected = laser @ np.array([r * math.cos(b), r * math.sin(b), 1.0])
        np.testing.assert_allclose(p, expected[:2], atol=1e-12)


# --------------------------------------------------------------------------- Monte Carlo


def _input_cov(var_r: float, bearing_sd_deg: float, heading_sd_deg: float) -> np.ndarray:
    cov = np.zeros((5, 5))
    cov[0, 0] = var_r
    cov[1, 1] = (bearing_sd_deg * D2R) ** 2
    cov[2:4, 2:4] = [[0.04, 0.01], [0.01, 0.03]]
    cov[4, 4] = (heading_sd_deg * D2R) ** 2
    cov[2, 4] = cov[4, 2] = 0.2 * math.sqrt(0.04 * cov[4, 4])
    return cov


@pytest.mark.parametrize(
    "bearing_sd_deg,heading_sd_deg", [(10.0, 1.0), (0.5, 15.0)], ids=["bearing10", "heading15"]
)
@pytest.mark.parametrize("kind,distance,var_r", [("hit", 10.0, 0.01), ("free", 10.0, 0.0)])
def test_ut_matches_monte_carlo_in_nonlinear_cases(
    bearing_sd_deg, heading_sd_deg, kind, distance, var_r
):
    mean = np.array([distance, 0.4, 1.0, 2.0, 0.7])
    cov = _input_cov(var_r, bearing_sd_deg, heading_sd_deg)
    rng = np.random.default_rng(5)
    draws = rng.multivariate_normal(mean, cov, size=100_000)
    ys = beam_endpoint(draws, MOUNT)
    mc_mean, mc_cov = ys.mean(axis=0), np.cov(ys.T)
    spread = math.sqrt(np.linalg.eigvalsh(mc_cov).max())

    y_mean, y_cov, _ = unscented_transform(
        lambda x: beam_endpoint(x, MOUNT), mean[None], cov[None], *ACCURATE_UT
    )

    # the case is nonlinear: first-order propagation misplaces the mean by > 5% of the spread
    assert np.linalg.norm(beam_endpoint(mean, MOUNT) - mc_mean) > 0.05 * spread
    assert np.linalg.norm(y_mean[0] - mc_mean) < 0.05 * spread
    assert np.linalg.norm(y_cov[0] - mc_cov) < 0.05 * np.linalg.norm(mc_cov)


def _one_scan(angles, ranges, pose, pose_cov) -> ScanBatch:
    return ScanBatch(
        sensor="r1",
        source="synthetic",
        stamps=np.zeros(1),
        angles=np.asarray(angles, dtype=float),
        ranges=np.asarray([ranges], dtype=float),
        poses=np.asarray([pose], dtype=float),
        pose_covariances=np.asarray([pose_cov], dtype=float),
        range_min=0.1,
        range_max=30.0,
    )


def _nearest(samples, point, label) -> int:
    candidates = np.flatnonzero(samples.labels == label)
    d = np.linalg.norm(samples.means[candidates] - point, axis=1)
    return int(candidates[np.argmin(d)])


def test_build_samples_hit_and_free_covariances_match_monte_carlo():
    """Through the whole pipeline: hits carry range noise, free samples do not."""
    bearing_sd, heading_sd = 10.0, 1.0
    cov = _input_cov(0.0, bearing_sd, heading_sd)
    pose = np.array([1.0, 2.0, 0.7])
    sensor = SensorConfig(
        name="r1", range_variance_m2=0.3, bearing_variance_deg2=bearing_sd**2,
        mount=MountConfig(x_m=MOUNT[0], y_m=MOUNT[1], yaw_deg=20.0),
    )
    alpha, beta, kappa = ACCURATE_UT
    config = Config(
        sensors=(sensor,),
        samples=SamplesConfig(free_spacing_m=2.5, hit_gap_m=0.25, thin_cell_m=0.0,
                              unscented=UnscentedConfig(alpha, beta, kappa)),
    )
    samples = build_samples([_one_scan([0.4], [10.0], pose, cov[2:, 2:])], config)

    rng = np.random.default_rng(6)
    # a large range variance, so that giving it to free samples too would show
    for label, distance, var_r in ((1.0, 10.0, 0.3), (-1.0, 7.5, 0.0)):
        mean = np.concatenate([[distance, 0.4], pose])
        full = cov.copy()
        full[0, 0] = var_r
        ys = beam_endpoint(rng.multivariate_normal(mean, full, size=100_000), MOUNT)
        mc_mean, mc_cov = ys.mean(axis=0), np.cov(ys.T)
        i = _nearest(samples, mc_mean, label)
        spread = math.sqrt(np.linalg.eigvalsh(mc_cov).max())
        assert np.linalg.norm(samples.means[i] - mc_mean) < 0.05 * spread
        assert np.linalg.norm(samples.covariances[i] - mc_cov) < 0.05 * np.linalg.norm(mc_cov)


def test_same_scan_cross_covariance_from_pose_factors_matches_monte_carlo():
    """Cov(x_i, x_j) = A_i A_j^T for two beams of one scan (shared pose, own beam noise)."""
    pose = np.array([-3.0, 1.5, 2.2])
    pose_cov = np.array([[0.01, 0.004, 0.0005], [0.004, 0.02, -0.0008], [0.0005, -0.0008,
                                                                          (5.0 * D2R) ** 2]])
    bearing_var_deg2 = 0.25
    sensor = SensorConfig(
        name="r1", range_variance_m2=0.0025, bearing_variance_deg2=bearing_var_deg2,
        pose_covariance=tuple(map(tuple, pose_cov)),
        mount=MountConfig(x_m=MOUNT[0], y_m=MOUNT[1], yaw_deg=20.0),
    )
    config = Config(sensors=(sensor,),
                    samples=SamplesConfig(free_spacing_m=3.2, hit_gap_m=0.25, thin_cell_m=0.0))
    angles, ranges = [0.3, -0.8], [6.0, 9.0]
    batch = replace(_one_scan(angles, ranges, pose, np.zeros((3, 3))), has_pose_covariance=False)
    samples = build_samples([batch], config)

    rng = np.random.default_rng(7)
    n = 100_000
    poses = rng.multivariate_normal(pose, pose_cov, size=n)
    sd_b = math.sqrt(bearing_var_deg2) * D2R
    hit_in = np.column_stack([6.0 + 0.05 * rng.normal(size=n), 0.3 + sd_b * rng.normal(size=n),
                              poses])
    free_in = np.column_stack([np.full(n, 6.4), -0.8 + sd_b * rng.normal(size=n), poses])
    hit, free = beam_endpoint(hit_in, MOUNT), beam_endpoint(free_in, MOUNT)
    mc_cross = (hit - hit.mean(0)).T @ (free - free.mean(0)) / (n - 1)

    i = _nearest(samples, hit.mean(0), 1.0)
    j = _nearest(samples, free.mean(0), -1.0)
    assert np.linalg.norm(samples.means[j] - free.mean(0)) < 0.05  # the 6.4 m free sample
    got = samples.pose_factors[i] @ samples.pose_factors[j].T
    norms = np.linalg.norm(samples.covariances[[i, j]], axis=(1, 2))
    scale = math.sqrt(norms[0] * norms[1])
    assert np.linalg.norm(mc_cross) > 0.3 * scale  # the pose error is a real share
    assert np.linalg.norm(got - mc_cross) < 0.10 * scale
    # and the joint covariance of the pair is a valid (PSD) covariance
    joint = np.block([[samples.covariances[i], got], [got.T, samples.covariances[j]]])
    assert np.linalg.eigvalsh(joint).min() > -1e-12
