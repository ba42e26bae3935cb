"""Refining hyperparameters by Fisher scoring: the patches' Fisher information against the
covariance of the likelihood's own gradient under the model (Monte Carlo), and the
scoring search against analytic optima, bounds and invalid steps."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from samplesets import samples_from

from gpocc.config import TrainingConfig
from gpocc.constants import JITTER
from gpocc.gp.expected import expected_kernel_matrix
from gpocc.gp.kernels import NeuralNetworkKernel, SquaredExponentialKernel
from gpocc.gp.local import negative_log_likelihood as patch_likelihood
from gpocc.gp.refine import TOLERANCE, fisher_scoring
from gpocc.gp.train import (
    START_SEPARATION,
    TrainingResult,
    distinct_starts,
    learn_hyperparameters,
    likelihood_with_fisher,
    make_patches,
    negative_log_likelihood_with_scale,
)
from gpocc.samples.sampleset import SampleSet


def _samples(n: int, rng: np.random.Generator, scans: int = 3) -> SampleSet:
    means = rng.uniform(-1, 1, (n, 2))
    factors = rng.normal(0, 0.05, (n, 2, 3))
    covs = (np.einsum("n,ij->nij", rng.uniform(0.002, 0.02, n), np.eye(2))
            + np.einsum("nik,njk->nij", factors, factors))
    return SampleSet(means, covs, np.where(rng.random(n) < 0.3, 1.0, -1.0),
                     rng.integers(0, scans, n), factors, np.zeros(n, dtype=np.int16))


@pytest.mark.parametrize("kernel, scale_gradient", [
    (NeuralNetworkKernel(1.5, 20.0, (30.0, 50.0)), True),
    (SquaredExponentialKernel(1.0, (0.4, 0.6)), False),
], ids=["nn-with-g", "se"])
def test_fisher_information_is_the_covariance_of_the_gradient(kernel, scale_gradient):
    # Under labels drawn from the model itself, the -LML's gradient (the implementation's
    # own, at those labels) has mean zero and covariance F: the oracle is its sample
    # covariance, compared within five of its standard errors.
    rng = np.random.default_rng(4)
    s = _samples(10, rng)
    noise, scale, level = 0.05, 1.7, 2
    got = patch_likelihood(kernel, noise, s, level, with_gradient=True, input_scale=scale,
                           scale_gradient=scale_gradient, with_fisher=True)
    cov = expected_kernel_matrix(kernel, s.means, s.covariances, level, scan_ids=s.scan_ids,
                                 pose_factors=s.pose_factors, input_scale=scale)
    cov[np.diag_indices_from(cov)] += noise + JITTER
    draws = rng.multivariate_normal(np.zeros(len(s)), cov, size=3000)
    scores = np.array([patch_likelihood(kernel, noise, dataclasses.replace(s, labels=y),
                                        level, with_gradient=True, input_scale=scale,
                                        scale_gradient=scale_gradient).gradient
                       for y in draws])
    assert got.fisher.shape == (scores.shape[1],) * 2
    np.testing.assert_allclose(got.fisher, got.fisher.T)
    products = np.einsum("np,nq->npq", scores, scores)
    oracle = products.mean(axis=0)
    error = products.std(axis=0) / math.sqrt(len(draws))
    assert np.all(np.abs(got.fisher - oracle) <= 5 * error + 1e-9)
    # Positive definite: a scoring step goes downhill.
    assert np.linalg.eigvalsh(got.fisher).min() > 0


def test_fisher_information_sums_over_patches_beside_the_likelihood():
    rng = np.random.default_rng(5)
    kernel = NeuralNetworkKernel(1.5, 20.0, (30.0, 50.0))
    patches = make_patches(_samples(150, rng), TrainingConfig(patches=3, patch_size=40), 0)
    params = np.append(kernel.theta, [math.log(0.05), math.log(1.3)])
    value, grad, fisher = likelihood_with_fisher(params, kernel, patches, 2, with_scale=True)
    ref_value, ref_grad = negative_log_likelihood_with_scale(params, kernel, patches, 2)
    assert value == pytest.approx(ref_value, rel=1e-12)
    np.testing.assert_allclose(grad, ref_grad, rtol=1e-10, atol=1e-12)
    each = [patch_likelihood(kernel.with_theta(params[:-2]), 0.05, p.samples, 2,
                             with_gradient=True, input_scale=1.3, scale_gradient=True,
                             with_fisher=True).fisher for p in patches]
    np.testing.assert_allclose(fisher, np.sum(each, axis=0), rtol=1e-12)


def _variance_fit(sums: np.ndarray, n: int):
    """-log likelihood of n zero-mean Gaussian draws per coordinate with mean square
    ``sums`` / n, in log variances x: optimum x = log(sums / n), Fisher n / 2 each."""
    mean_square = sums / n

    def evaluate(x: np.ndarray):
        value = 0.5 * n * float(np.sum(x + mean_square * np.exp(-x)))
        grad = 0.5 * n * (1.0 - mean_square * np.exp(-x))
        return value, grad, np.diag(np.full(x.shape, 0.5 * n))
    return evaluate, np.log(mean_square)


def test_scoring_reaches_an_analytic_optimum_and_stops_on_a_bound():
    evaluate, optimum = _variance_fit(np.array([0.2, 30.0, 4.0]) * 50, 50)
    lower, upper = np.full(3, -4.0), np.array([4.0, 2.0, 4.0])  # log 30 lies above 2
    result = fisher_scoring(evaluate, np.zeros(3), lower, upper, max_evaluations=40)
    assert result.converged and result.evaluations < 15
    expected = np.clip(optimum, lower, upper)
    np.testing.assert_allclose(result.x, expected, atol=0.03)
    assert result.x[1] == upper[1]
    assert result.value == pytest.approx(evaluate(expected)[0], abs=0.01)


_OPTIMUM = np.array([0.3, -0.4])


@pytest.mark.parametrize("overstated", [(1.0, 1.0), (2.0, 2.0), (3.0, 3.0), (5.0, 5.0),
                                        (1.0, 5.0), (5.0, 1.0)], ids=str)
@pytest.mark.parametrize("start", [(1.0, 1.0), (2.0, 2.0), (3.0, 3.0), (4.0, 4.0),
                                   tuple(_OPTIMUM + (0.04, -0.2))], ids=str)
def test_scoring_stops_within_its_tolerance_of_the_optimum_when_the_fisher_overstates(
        overstated, start):
    """A quadratic whose Fisher information is ``overstated`` times its curvature per
    axis (as along a ridge of the likelihood, where the Fisher information is not the
    Hessian): each step falls short, the decreases shrink at a near-constant rate, and the
    search must still stop within :data:`TOLERANCE` nats of the analytic minimum, not
    where the next step alone is predicted to gain less than that; also from a start a
    few tolerances above it."""
    curvature, floor = np.array([50.0, 2.0]), 7.0

    def evaluate(x: np.ndarray):
        d = x - _OPTIMUM
        return (0.5 * float(d @ (curvature * d)) + floor, curvature * d,
                np.diag(np.array(overstated) * curvature))
    result = fisher_scoring(evaluate, np.array(start), np.full(2, -10.0),
                            np.full(2, 10.0), max_evaluations=200)
    assert result.converged
    assert 0.0 <= result.value - floor < TOLERANCE


def test_a_step_into_invalid_values_is_rejected_and_the_search_goes_on():
    evaluate, optimum = _variance_fit(np.array([0.5, 3.0]) * 40, 40)
    far = []

    def guarded(x: np.ndarray):
        # The undamped first step from -3 overshoots past 2: not a valid covariance there.
        if np.any(x > 2.0):
            far.append(x)
            return None
        return evaluate(x)
    result = fisher_scoring(guarded, np.full(2, -3.0), np.full(2, -6.0), np.full(2, 6.0),
                            max_evaluations=60)
    assert far  # the guard was hit
    assert result.converged
    np.testing.assert_allclose(result.x, optimum, atol=0.03)


def test_the_budget_stops_the_search_unconverged():
    evaluate, _ = _variance_fit(np.array([0.5, 3.0]) * 40, 40)
    result = fisher_scoring(evaluate, np.full(2, -3.0), np.full(2, -6.0), np.full(2, 6.0),
                            max_evaluations=2)
    assert not result.converged and result.evaluations == 2
    assert result.value < evaluate(np.full(2, -3.0))[0]


def test_a_warm_start_at_the_optimum_stays_there():
    rng = np.random.default_rng(6)
    samples = _samples(200, rng)
    kernel = NeuralNetworkKernel(1.0, 10.0, (10.0, 10.0))
    config = TrainingConfig(patches=3, patch_size=40, anneal_maxfun=10, lbfgs_maxiter=200)
    learned = learn_hyperparameters(kernel, 0.1, samples, 2, config, seed=0, workers=1)
    again = learn_hyperparameters(
        kernel, 0.1, samples, 2, config, seed=0, workers=1,
        warm_start=TrainingResult(learned.kernel, learned.noise_variance, math.nan,
                                  math.nan, 0, (0, 0), learned.input_noise_scale))
    assert again.warm_started
    # The initial values, the start and at most a step or two that gain under 0.01 nats.
    assert again.evaluations <= 3
    assert again.log_marginal_likelihood == pytest.approx(learned.log_marginal_likelihood,
                                                          abs=0.01)


def _se_patches_problem():
    """300 samples labelled by a draw of an SE GP, exact inputs: learning's oracle."""
    rng = np.random.default_rng(9)
    means = rng.uniform(0, 8, (300, 2))
    truth = SquaredExponentialKernel(1.5, (0.7, 0.7))
    labels = np.linalg.cholesky(truth(means, means) + 0.05 * np.eye(300)) @ (
        rng.standard_normal(300))
    return samples_from(means, labels)


def test_scoring_as_learning_local_search_reaches_the_optimum_of_lbfgs():
    # L-BFGS-B run to convergence from the annealing's best point is the oracle.
    samples = _se_patches_problem()
    start = SquaredExponentialKernel(0.5, (2.0, 2.0))
    base = TrainingConfig(patches=4, patch_size=60, anneal_maxfun=30, lbfgs_maxiter=200,
                          min_noise_variance=0.01)
    lbfgs = learn_hyperparameters(start, 0.5, samples, 1, base, seed=0, workers=1)
    scoring = learn_hyperparameters(start, 0.5, samples, 1,
                                    dataclasses.replace(base, local_search="scoring"),
                                    seed=0, workers=1)
    assert scoring.log_marginal_likelihood == pytest.approx(lbfgs.log_marginal_likelihood,
                                                            abs=0.01)
    np.testing.assert_allclose(scoring.kernel.theta, lbfgs.kernel.theta, atol=0.02)
    assert scoring.evaluations < lbfgs.evaluations


@pytest.mark.parametrize("search", ["lbfgs", "scoring"])
def test_more_local_starts_never_end_worse(search):
    samples = _se_patches_problem()
    start = SquaredExponentialKernel(0.5, (2.0, 2.0))
    base = TrainingConfig(patches=4, patch_size=60, anneal_maxfun=30, lbfgs_maxiter=200,
                          min_noise_variance=0.01, local_search=search)
    one = learn_hyperparameters(start, 0.5, samples, 1, base, seed=0, workers=1)
    three = learn_hyperparameters(start, 0.5, samples, 1,
                                  dataclasses.replace(base, local_starts=3), seed=0,
                                  workers=1)
    assert three.log_marginal_likelihood >= one.log_marginal_likelihood - 1e-9
    assert three.evaluations > one.evaluations


def test_local_starts_are_the_best_points_apart_from_each_other():
    # Brute force over every subset in order: the first `count` points (by value) that are
    # each at least the separation from all kept before them.
    rng = np.random.default_rng(10)
    visited = [(float(v), rng.uniform(-2, 2, 3)) for v in rng.uniform(0, 10, 40)]
    best = np.zeros(3)
    starts = distinct_starts(best, visited, 4)
    assert starts[0] is best and len(starts) == 4
    kept = [best]
    for _, point in sorted(visited, key=lambda v: v[0]):
        if len(kept) == 4:
            break
        if min(np.abs(point - k).max() for k in kept) >= START_SEPARATION:
            kept.append(point)
    for got, want in zip(starts, kept, strict=True):
        np.testing.assert_array_equal(got, want)
    assert distinct_starts(best, visited, 1) == [best]


def test_scoring_says_once_when_the_kept_search_stops_at_its_budget(monkeypatch):
    """Three local starts, one step each: every search stops short, and the line that
    says so comes once, for the kept result; with a budget to converge in, never."""
    from gpocc.gp import train as train_module

    lines: list[str] = []
    monkeypatch.setattr(train_module, "log", lines.append)
    samples = _se_patches_problem()
    start = SquaredExponentialKernel(0.5, (2.0, 2.0))
    base = TrainingConfig(patches=4, patch_size=60, anneal_maxfun=30, lbfgs_maxiter=1,
                          min_noise_variance=0.01, local_search="scoring", local_starts=3)
    learn_hyperparameters(start, 0.5, samples, 1, base, seed=0, workers=1)
    stopped = [line for line in lines if line.startswith("Fisher scoring stopped")]
    assert stopped == ["Fisher scoring stopped after 1 steps, its budget, with more than "
                       f"{TOLERANCE} nats still to gain; model.training.lbfgs_maxiter "
                       "raises it"]
    lines.clear()
    learn_hyperparameters(start, 0.5, samples, 1,
                          dataclasses.replace(base, lbfgs_maxiter=200), seed=0, workers=1)
    assert not [line for line in lines if line.startswith("Fisher scoring stopped")]
