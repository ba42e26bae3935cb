"""Calibration of occupancy probabilities against labelled points.

A map is calibrated when, of the points it gives p(occupied) = 0.8, about 80% are
occupied. AUC ignores this (any monotone transform of the scores has the same AUC); the
scores here do not:

* Brier score: mean squared difference between p and the 0/1 label (0 is perfect, a
  constant 0.5 scores 0.25).
* Log-loss: mean negative log-likelihood of the labels, in nats, with p clipped to
  ``[LOG_LOSS_CLIP, 1 - LOG_LOSS_CLIP]`` so that one confident mistake costs at most
  ``-ln(1e-6) = 13.8`` nats instead of infinity.
* Expected calibration error (ECE): the p range [0, 1] is cut into ``CALIBRATION_BINS``
  equal-width bins, bin k holding ``k / K < p <= (k + 1) / K`` (bin 0 also holds p = 0),
  scikit-learn's convention; ECE is the point-weighted mean over non-empty
  bins of ``|mean label - mean p|``.

The reliability diagram plots, per non-empty bin, the mean p (x) against the fraction
of occupied points (y); scikit-learn's ``calibration_curve(strategy="uniform")`` gives
the same points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Probabilities are clipped to [clip, 1 - clip] for the log-loss.
LOG_LOSS_CLIP = 1e-6
#: Equal-width probability bins of the ECE and the reliability diagram.
CALIBRATION_BINS = 10


@dataclass(frozen=True)
class Calibration:
    """Calibration scores of one map's probabilities at the truth points.

    Attributes:
        brier: mean squared error of p against the 0/1 labels.
        log_loss: mean negative log-likelihood (nats), p clipped by :data:`LOG_LOSS_CLIP`.
        ece: expected calibration error over :data:`CALIBRATION_BINS` equal-width bins.
        bin_mean_p: (K,) mean p of each non-empty bin (reliability-diagram x).
        bin_fraction_occupied: (K,) fraction of occupied points per non-empty bin (y).
        bin_counts: (K,) points per non-empty bin.
    """

    brier: float
    log_loss: float
    ece: float
    bin_mean_p: np.ndarray
    bin_fraction_occupied: np.ndarray
    bin_counts: np.ndarray


def _check(labels: np.ndarray, probabilities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    y = np.asarray(labels).ravel()
    p = np.asarray(probabilities, dtype=float).ravel()
    if y.shape != p.shape:
        raise ValueError(f"labels {y.shape} and probabilities {p.shape} differ in length")
    if y.size == 0:
        raise ValueError("no points to score")
    if not np.all((y == 0) | (y == 1)):
        raise ValueError("labels must be 0 (free) or 1 (occupied)")
    if not np.all(np.isfinite(p)) or p.min() < 0.0 or p.max() > 1.0:
        raise ValueError("probabilities must be finite and in [0, 1]")
    return y.astype(float), p


def brier_score(labels: np.ndarray, probabilities: np.ndarray) -> float:
    """Mean of ``(p - y)^2`` over (N,) labels (0/1) and probabilities."""
    y, p = _check(labels, probabilities)
    return float(np.mean((p - y) ** 2))


def log_loss(labels: np.ndarray, probabilities: np.ndarray,
             clip: float = LOG_LOSS_CLIP) -> float:
    """Mean of ``-(y ln p + (1 - y) ln(1 - p))``, nats, with p clipped to [clip, 1 - clip]."""
    y, p = _check(labels, probabilities)
    q = np.clip(p, clip, 1.0 - clip)
    return float(-np.mean(y * np.log(q) + (1.0 - y) * np.log1p(-q)))


def reliability(labels: np.ndarray, probabilities: np.ndarray,
                bins: int = CALIBRATION_BINS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per non-empty equal-width bin: mean p, fraction occupied and point count.

    Bin ``k`` holds ``k / bins < p <= (k + 1) / bins``; p = 0 falls in the first bin.
    """
    y, p = _check(labels, probabilities)
    edges = np.linspace(0.0, 1.0, bins + 1)
    index = np.searchsorted(edges[1:-1], p, side="left")
    counts = np.bincount(index, minlength=bins)
    sum_p = np.bincount(index, weights=p, minlength=bins)
    sum_y = np.bincount(index, weights=y, minlength=bins)
    used = counts > 0
    return sum_p[used] / counts[used], sum_y[used] / counts[used], counts[used]


def expected_calibration_error(labels: np.ndarray, probabilities: np.ndarray,
                               bins: int = CALIBRATION_BINS) -> float:
    """Point-weighted mean of ``|fraction occupied - mean p|`` over equal-width bins."""
    mean_p, frac, counts = reliability(labels, probabilities, bins)
    return float(np.sum(counts * np.abs(frac - mean_p)) / counts.sum())


def calibration(labels: np.ndarray, probabilities: np.ndarray) -> Calibration:
    """All calibration scores of (N,) 0/1 labels and probabilities in [0, 1]."""
    mean_p, frac, counts = reliability(labels, probabilities)
    return Calibration(
        brier=brier_score(labels, probabilities),
        log_loss=log_loss(labels, probabilities),
        ece=float(np.sum(counts * np.abs(frac - mean_p)) / counts.sum()),
        bin_mean_p=mean_p,
        bin_fraction_occupied=frac,
        bin_counts=counts,
    )
