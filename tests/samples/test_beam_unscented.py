"""The compiled beam transform against the generic unscented transform and Monte Carlo."""

from __future__ import annotations

import numpy as np
import pytest

from gpocc.samples import beam_rules
from gpocc.samples.beam_unscented import beam_unscented
from gpocc.samples.unscented import matrix_sqrt, unscented_transform


def _case(seed: int, n: int = 40, scans: int = 3):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(scans, 3, 3)) * np.array([0.05, 0.05, 0.02])[:, None]
    pose_cov = a @ np.swapaxes(a, 1, 2)
    pose_cov[0] = np.diag([0.0, 0.0009, 0.0])  # singular: the pinv route
    return dict(
        distances=rng.uniform(0.2, 8.0, n),
        bearings=rng.uniform(-2.0, 2.0, n),
        range_variances=np.where(rng.random(n) < 0.5, rng.uniform(0, 0.01, n), 0.0),
        bearing_variance=float(rng.uniform(1e-6, 1e-3)),
        scans=rng.integers(0, scans, n),
        poses=rng.normal(size=(scans, 3)) * np.array([5.0, 5.0, 2.0]),
        pose_cov=pose_cov,
        mount=np.array([0.2, -0.1, 0.3]),
    )


def _pose_maps(pose_cov):
    root = matrix_sqrt(pose_cov)
    return root, np.linalg.pinv(pose_cov, hermitian=True) @ root


@pytest.mark.parametrize("alpha, beta, kappa", [(0.7745966692414834, 0.5, 0.0),
                                                (1.0, 2.0, 0.0), (0.5, 2.0, 3.0)])
@pytest.mark.parametrize("seed", [0, 1])
def test_compiled_transform_equals_the_generic_one(seed, alpha, beta, kappa):
    c = _case(seed)
    root, pose_map = _pose_maps(c["pose_cov"])
    means, covs, factors = beam_unscented(
        c["distances"], c["bearings"], c["range_variances"], c["bearing_variance"],
        c["scans"], c["poses"], root, pose_map, c["mount"], alpha, beta, kappa,
    )
    n = len(c["distances"])
    mean = np.column_stack([c["distances"], c["bearings"], c["poses"][c["scans"]]])
    cov = np.zeros((n, 5, 5))
    cov[:, 0, 0] = c["range_variances"]
    cov[:, 1, 1] = c["bearing_variance"]
    cov[:, 2:, 2:] = c["pose_cov"][c["scans"]]
    sqrt_cov = np.zeros((n, 5, 5))
    sqrt_cov[:, 0, 0] = np.sqrt(c["range_variances"])
    sqrt_cov[:, 1, 1] = np.sqrt(c["bearing_variance"])
    sqrt_cov[:, 2:, 2:] = root[c["scans"]]
    ref_mean, ref_cov, cross = unscented_transform(
        lambda x: beam_rules.beam_endpoint(x, c["mount"]), mean, cov, alpha, beta, kappa,
        sqrt_cov=sqrt_cov,
    )
    ref_factors = np.swapaxes(cross[:, 2:, :], -1, -2) @ pose_map[c["scans"]]
    np.testing.assert_allclose(means, ref_mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(covs, ref_cov, rtol=0, atol=1e-14)
    np.testing.assert_allclose(factors, ref_factors, rtol=0, atol=1e-13)


def test_compiled_transform_matches_monte_carlo():
    """Mean and covariance of the beam endpoint, and the pose factor's shared part."""
    rng = np.random.default_rng(5)
    pose = np.array([1.0, -2.0, 0.4])
    pose_cov = np.diag([0.01, 0.004, 0.003])
    root, pose_map = _pose_maps(pose_cov[None])
    distance, bearing, var_r, var_b = 4.0, 0.3, 0.0025, 1e-4
    mount = np.array([0.2, -0.1, 0.3])
    means, covs, factors = beam_unscented(
        np.array([distance]), np.array([bearing]), np.array([var_r]), var_b,
        np.array([0]), pose[None], root, pose_map, mount, 0.7745966692414834, 0.5, 0.0,
    )
    draws = 400_000
    x = np.column_stack([
        distance + np.sqrt(var_r) * rng.standard_normal(draws),
        bearing + np.sqrt(var_b) * rng.standard_normal(draws),
        pose + rng.standard_normal((draws, 3)) @ np.sqrt(pose_cov),
    ])
    y = beam_rules.beam_endpoint(x, mount)
    np.testing.assert_allclose(means[0], y.mean(axis=0), atol=3e-3)
    np.testing.assert_allclose(covs[0], np.cov(y.T), rtol=0.05, atol=2e-4)
    # A A^T is the covariance explained by the pose: Cov(y, pose) P^-1 Cov(pose, y).
    shared = factors[0] @ factors[0].T
    c_yp = np.cov(np.column_stack([y, x[:, 2:]]).T)[:2, 2:]
    np.testing.assert_allclose(shared, c_yp @ np.linalg.inv(pose_cov) @ c_yp.T,
                               rtol=0.05, atol=2e-4)
