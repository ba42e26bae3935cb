"""Receiver operating characteristic of occupancy maps against labelled points.

Conventions follow scikit-learn's ``roc_curve`` with ``drop_intermediate=False``: a point
is predicted occupied when its score is ``>= threshold``; the curve has one point per
distinct score (tied scores move together, never one by one) plus the origin, whose
threshold is ``+inf``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpocc.evaluation.calibration import Calibration, calibration

#: Score given to truth points the map does not cover: the uninformative prior.
UNKNOWN_SCORE = 0.5


def roc_curve(labels: np.ndarray, scores: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """False- and true-positive rates at every distinct score.

    Args:
        labels: (N,) 1 occupied (positive), 0 free (negative).
        scores: (N,) finite, higher means more likely occupied (e.g. p(occupied)).

    Returns:
        ``(fpr, tpr, thresholds)``, each (T + 1,) for T distinct scores: ``fpr[0] = tpr[0]
        = 0`` at threshold ``+inf``, then thresholds in decreasing order ending at
        ``fpr = tpr = 1``.

    Raises:
        ValueError: if the labels are not all 0/1, a score is not finite, or one class is
            missing (the rates are then undefined).
    """
    y = np.asarray(labels).ravel()
    s = np.asarray(scores, dtype=float).ravel()
    if y.shape != s.shape:
        raise ValueError(f"labels {y.shape} and scores {s.shape} differ in length")
    if not np.all((y == 0) | (y == 1)):
        raise ValueError("labels must be 0 (free) or 1 (occupied)")
    if not np.all(np.isfinite(s)):
        raise ValueError("scores must be finite")
    positives = int(np.count_nonzero(y == 1))
    negatives = y.size - positives
    if positives == 0 or negatives == 0:
        raise ValueError(
            f"ROC needs both occupied and free labels, got {positives} occupied and "
            f"{negatives} free"
        )
    # A stable sort keeps the result independent of the input order within ties, and
    # cumulative counts taken at the last index of each run of equal scores give one
    # point per distinct score.
    order = np.argsort(-s, kind="stable")
    s_sorted = s[order]
    y_sorted = y[order].astype(np.int64)
    run_ends = np.flatnonzero(np.diff(s_sorted) != 0)
    last = np.append(run_ends, s.size - 1)
    tp = np.cumsum(y_sorted)[last]
    fp = (last + 1) - tp
    fpr = np.concatenate(([0.0], fp / negatives))
    tpr = np.concatenate(([0.0], tp / positives))
    thresholds = np.concatenate(([np.inf], s_sorted[last]))
    return fpr, tpr, thresholds


def auc(fpr: np.ndarray, tpr: np.ndarray) -> float:
    """Area under a ROC curve by the trapezoid rule (exact for a piecewise linear curve).

    Args:
        fpr: (T,) non-decreasing false-positive rates.
        tpr: (T,) matching true-positive rates.
    """
    x = np.asarray(fpr, dtype=float)
    y = np.asarray(tpr, dtype=float)
    return float(np.sum(np.diff(x) * (y[1:] + y[:-1]) * 0.5))


def fpr_at_tpr(fpr: np.ndarray, tpr: np.ndarray, target: float = 0.97) -> float:
    """The smallest false-positive rate whose true-positive rate reaches ``target``.

    The ROC points are joined by straight lines (each segment is achievable by randomly
    mixing the two thresholds at its ends), and the answer is the FPR where that
    polyline first reaches ``tpr == target``: with ``i`` the first point whose TPR is
    ``>= target``, the FPR interpolated linearly in TPR between points ``i - 1`` and
    ``i``. A target at or below ``tpr[0]`` gives ``fpr[0]``.

    Args:
        fpr: (T,) non-decreasing false-positive rates, as from :func:`roc_curve`.
        tpr: (T,) matching non-decreasing true-positive rates, ending at 1.
        target: the true-positive rate to reach, in [0, 1].
    """
    if not 0.0 <= target <= 1.0:
        raise ValueError(f"target TPR must be in [0, 1], got {target}")
    x = np.asarray(fpr, dtype=float)
    y = np.asarray(tpr, dtype=float)
    reached = np.flatnonzero(y >= target)
    if reached.size == 0:
        raise ValueError(f"the curve never reaches TPR {target}")
    i = int(reached[0])
    if i == 0:
        return float(x[0])
    # y[i - 1] < target <= y[i], so the segment rises and the division is safe.
    t = (target - y[i - 1]) / (y[i] - y[i - 1])
    return float(x[i - 1] + t * (x[i] - x[i - 1]))


@dataclass(frozen=True)
class RocResult:
    """One map's ROC summary against a ground truth.

    Attributes:
        name: the map's name (its folder or file stem).
        auc: area under the ROC curve, in [0, 1].
        fpr_at_tpr97: false-positive rate at a true-positive rate of 0.97 (see
            :func:`fpr_at_tpr`).
        coverage: fraction of truth points the map has a value for; the others were
            scored :data:`UNKNOWN_SCORE`.
        n_points: number of truth points.
        fpr: (T,) curve false-positive rates.
        tpr: (T,) curve true-positive rates.
        calibration: Brier score, log-loss, ECE and reliability bins of the same scores
            (uncovered points at :data:`UNKNOWN_SCORE`), see
            :mod:`gpocc.evaluation.calibration`.
    """

    name: str
    auc: float
    fpr_at_tpr97: float
    coverage: float
    n_points: int
    fpr: np.ndarray
    tpr: np.ndarray
    calibration: Calibration


def evaluate_scores(
    name: str, labels: np.ndarray, scores: np.ndarray, inside: np.ndarray
) -> RocResult:
    """ROC summary of scores sampled from a map at the truth points.

    A point the map does not cover (``inside`` False, or a NaN score: no data) is scored
    :data:`UNKNOWN_SCORE`, as a map that says nothing about it would be, so a map is not
    rewarded for covering less; ``coverage`` reports how many were covered. The
    calibration scores use the same filled scores.

    Args:
        name: the map's name.
        labels: (N,) 1 occupied, 0 free.
        scores: (N,) p(occupied) at the points; NaN where the map has no data.
        inside: (N,) bool, True where the point lies inside the map.
    """
    s = np.asarray(scores, dtype=float).ravel()
    covered = np.asarray(inside, dtype=bool).ravel() & np.isfinite(s)
    filled = np.where(covered, s, UNKNOWN_SCORE)
    fpr, tpr, _ = roc_curve(labels, filled)
    return RocResult(
        name=name,
        auc=auc(fpr, tpr),
        fpr_at_tpr97=fpr_at_tpr(fpr, tpr, 0.97),
        coverage=float(np.mean(covered)) if covered.size else 0.0,
        n_points=int(s.size),
        fpr=fpr,
        tpr=tpr,
        calibration=calibration(labels, filled),
    )
