"""Calibration scores against scikit-learn, and their place in `gpocc evaluate` outputs."""

from __future__ import annotations

import numpy as np
import pytest

from gpocc.evaluation.calibration import (
    CALIBRATION_BINS,
    LOG_LOSS_CLIP,
    brier_score,
    calibration,
    expected_calibration_error,
    log_loss,
    reliability,
)
from gpocc.evaluation.roc import evaluate_scores

sklearn_metrics = pytest.importorskip("sklearn.metrics")
sklearn_calibration = pytest.importorskip("sklearn.calibration")


def random_case(seed: int, n: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    p = rng.beta(0.7, 0.9, n)
    # Labels drawn from a distorted version of p: mis-calibrated on purpose.
    y = (rng.random(n) < p**1.5).astype(int)
    p[:5] = [0.0, 1.0, 0.1, 0.5, 1.0]  # bin edges and exact 0/1
    return y, p


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_brier_and_log_loss_match_sklearn(seed):
    y, p = random_case(seed)
    assert brier_score(y, p) == pytest.approx(sklearn_metrics.brier_score_loss(y, p), rel=1e-12)
    clipped = np.clip(p, LOG_LOSS_CLIP, 1 - LOG_LOSS_CLIP)
    assert log_loss(y, p) == pytest.approx(sklearn_metrics.log_loss(y, clipped), rel=1e-10)


@pytest.mark.parametrize("seed", [0, 3])
def test_reliability_bins_match_sklearn_calibration_curve(seed):
    y, p = random_case(seed)
    frac, mean_p = sklearn_calibration.calibration_curve(y, p, n_bins=CALIBRATION_BINS,
                                                         strategy="uniform")
    got_mean, got_frac, counts = reliability(y, p)
    np.testing.assert_allclose(got_mean, mean_p, rtol=1e-12)
    np.testing.assert_allclose(got_frac, frac, rtol=1e-12)
    assert counts.sum() == y.size


def test_ece_by_brute_force():
    y, p = random_case(4, 500)
    total = 0.0
    for k in range(CALIBRATION_BINS):
        edges = np.linspace(0.0, 1.0, CALIBRATION_BINS + 1)
        lo, hi = edges[k], edges[k + 1]
        inside = ((p > lo) | (k == 0)) & (p <= hi)
        if inside.any():
            total += inside.sum() * abs(y[inside].mean() - p[inside].mean())
    assert expected_calibration_error(y, p) == pytest.approx(total / y.size, rel=1e-12)


def test_perfectly_calibrated_scores_have_small_ece_and_mismatched_large():
    rng = np.random.default_rng(7)
    p = rng.random(200_000)
    y = (rng.random(p.size) < p).astype(int)
    assert expected_calibration_error(y, p) < 0.01
    assert expected_calibration_error(y, p**3) > 0.1


def test_uncovered_points_count_as_one_half():
    y = np.array([1, 0, 1, 0])
    scores = np.array([0.9, np.nan, 0.2, 0.1])
    inside = np.array([True, True, False, True])
    result = evaluate_scores("m", y, scores, inside)
    filled = np.array([0.9, 0.5, 0.5, 0.1])
    assert result.calibration.brier == pytest.approx(np.mean((filled - y) ** 2))
    expected = calibration(y, filled)
    assert result.calibration.log_loss == pytest.approx(expected.log_loss)
    assert result.calibration.ece == pytest.approx(expected.ece)


def test_bad_probabilities_raise():
    with pytest.raises(ValueError, match="in \\[0, 1\\]"):
        brier_score(np.array([0, 1]), np.array([0.5, 1.2]))
    with pytest.raises(ValueError, match="0 \\(free\\) or 1"):
        log_loss(np.array([0, 2]), np.array([0.5, 0.5]))
