"""ROC curve, AUC and FPR-at-TPR against scikit-learn and brute force."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.metrics import roc_auc_score
from sklearn.metrics import roc_curve as sk_roc_curve

from gpocc.evaluation.roc import (
    UNKNOWN_SCORE,
    auc,
    evaluate_scores,
    fpr_at_tpr,
    roc_curve,
)


def _random_case(seed: int, n: int = 400, levels: int | None = None):
    rng = np.random.default_rng(seed)
    labels = rng.integers(0, 2, n)
    scores = rng.normal(size=n) + 0.8 * labels
    if levels is not None:
        # Quantise to force many ties, as a probability map does.
        scores = np.round(scores * levels) / levels
    return labels, scores


def _brute_fpr_at_tpr(fpr, tpr, target, per_segment=20001):
    """Smallest FPR on the densely sampled polyline whose TPR reaches the target."""
    t = np.linspace(0.0, 1.0, per_segment)
    xs = fpr[:-1, None] + t * (fpr[1:] - fpr[:-1])[:, None]
    ys = tpr[:-1, None] + t * (tpr[1:] - tpr[:-1])[:, None]
    ok = ys >= target - 1e-12
    return float(xs[ok].min())


@pytest.mark.parametrize("seed, levels", [(0, None), (1, 4), (2, 1), (3, 20)])
def test_curve_matches_sklearn_with_ties(seed, levels):
    labels, scores = _random_case(seed, levels=levels)
    fpr, tpr, thr = roc_curve(labels, scores)
    sk_fpr, sk_tpr, sk_thr = sk_roc_curve(labels, scores, drop_intermediate=False)
    np.testing.assert_allclose(fpr, sk_fpr, rtol=0, atol=1e-12)
    np.testing.assert_allclose(tpr, sk_tpr, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(thr[1:], sk_thr[1:])
    assert np.isinf(thr[0])
    # One point per distinct score, plus the origin.
    assert fpr.size == np.unique(scores).size + 1
    assert auc(fpr, tpr) == pytest.approx(roc_auc_score(labels, scores), abs=1e-12)


def test_input_order_does_not_matter():
    labels, scores = _random_case(5, levels=3)
    perm = np.random.default_rng(9).permutation(labels.size)
    a = roc_curve(labels, scores)
    b = roc_curve(labels[perm], scores[perm])
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)


def test_all_tied_scores_give_the_diagonal():
    labels = np.array([0, 1, 1, 0, 1])
    fpr, tpr, _ = roc_curve(labels, np.full(5, 0.5))
    np.testing.assert_array_equal(fpr, [0.0, 1.0])
    np.testing.assert_array_equal(tpr, [0.0, 1.0])
    assert auc(fpr, tpr) == 0.5
    assert fpr_at_tpr(fpr, tpr, 0.97) == pytest.approx(0.97)


def test_perfect_and_inverted_classifiers():
    labels = np.array([0] * 50 + [1] * 30)
    scores = np.linspace(0.0, 1.0, labels.size)  # every positive above every negative
    fpr, tpr, _ = roc_curve(labels, scores)
    assert auc(fpr, tpr) == pytest.approx(roc_auc_score(labels, scores)) == pytest.approx(1.0)
    assert fpr_at_tpr(fpr, tpr, 0.97) == 0.0
    fpr, tpr, _ = roc_curve(labels, -scores)
    assert auc(fpr, tpr) == pytest.approx(roc_auc_score(labels, -scores)) == pytest.approx(0.0)
    assert fpr_at_tpr(fpr, tpr, 0.97) == 1.0


@pytest.mark.parametrize("seed, levels", [(0, None), (1, 3), (4, 10)])
@pytest.mark.parametrize("target", [0.5, 0.9, 0.97, 1.0])
def test_fpr_at_tpr_matches_dense_polyline(seed, levels, target):
    labels, scores = _random_case(seed, n=150, levels=levels)
    sk_fpr, sk_tpr, _ = sk_roc_curve(labels, scores, drop_intermediate=False)
    fpr, tpr, _ = roc_curve(labels, scores)
    expected = _brute_fpr_at_tpr(sk_fpr, sk_tpr, target)
    # The dense sampling is within one step (1/20000 of a segment) of the exact answer.
    assert fpr_at_tpr(fpr, tpr, target) == pytest.approx(expected, abs=1e-4)


def test_fpr_at_tpr_analytic_segment():
    # Negatives at 0.2 (x4) and 0.6 (x4); positives at 0.6 (x4) and 0.9 (x4). Curve:
    # (0, 0) -> (0, 0.5) -> (0.5, 1) -> (1, 1). TPR 0.97 lies on the middle segment at
    # FPR (0.97 - 0.5) / 0.5 * 0.5 = 0.47.
    labels = np.array([0] * 8 + [1] * 8)
    scores = np.array([0.2] * 4 + [0.6] * 4 + [0.6] * 4 + [0.9] * 4)
    fpr, tpr, _ = roc_curve(labels, scores)
    np.testing.assert_allclose(fpr, [0, 0, 0.5, 1])
    np.testing.assert_allclose(tpr, [0, 0.5, 1, 1])
    assert fpr_at_tpr(fpr, tpr, 0.97) == pytest.approx(0.47)
    assert fpr_at_tpr(fpr, tpr, 0.5) == 0.0


def test_one_class_is_rejected():
    with pytest.raises(ValueError, match="both occupied and free"):
        roc_curve(np.ones(4), np.arange(4.0))
    with pytest.raises(ValueError, match="0 \\(free\\) or 1"):
        roc_curve(np.array([0, 2]), np.arange(2.0))


def test_evaluate_scores_fills_uncovered_points():
    labels, scores = _random_case(7, n=300)
    p = 1.0 / (1.0 + np.exp(-scores))
    rng = np.random.default_rng(1)
    inside = rng.random(300) < 0.7
    p_nan = p.copy()
    p_nan[rng.random(300) < 0.1] = np.nan  # no-data cells inside the map
    result = evaluate_scores("m", labels, p_nan, inside)
    covered = inside & np.isfinite(p_nan)
    filled = np.where(covered, p_nan, UNKNOWN_SCORE)
    assert result.auc == pytest.approx(roc_auc_score(labels, filled), abs=1e-12)
    assert result.coverage == pytest.approx(covered.mean())
    assert result.n_points == 300
    assert result.name == "m"
    sk_fpr, sk_tpr, _ = sk_roc_curve(labels, filled, drop_intermediate=False)
    assert result.fpr_at_tpr97 == pytest.approx(_brute_fpr_at_tpr(sk_fpr, sk_tpr, 0.97), abs=1e-4)
