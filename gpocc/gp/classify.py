"""Probabilistic least-squares classification (Platt scaling of the GP regression).

``p(occupied | x) = Phi((a * mu + b) / sqrt(1 + a^2 * var))`` squashes the latent GP
mean ``mu`` and variance ``var`` into a probability. ``a`` and ``b`` maximise the
leave-one-out predictive log probability of the training labels (Rasmussen and Williams,
section 6.5), computed in closed form from the same local problems used for training.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize
from scipy.special import log_ndtr, ndtr

from gpocc.gp.kernels import Kernel
from gpocc.gp.local import LocalProblem, factor_training_covariance, leave_one_out

OCCUPIED, FREE, UNSURE, NO_DATA = 1, 0, 2, 255


@dataclass(frozen=True)
class PlattClassifier:
    """The squashing p = Phi((a mu + b) / sqrt(1 + a^2 var)) with its fitted a > 0, b."""

    a: float = 1.0
    b: float = 0.0

    def probability(self, mean: np.ndarray, variance: np.ndarray) -> np.ndarray:
        """p(occupied) for latent means and variances of any (matching) shape."""
        return ndtr((self.a * mean + self.b) / np.sqrt(1.0 + self.a**2 * variance))


def loo_log_probability(a: float, b: float, mean: np.ndarray, variance: np.ndarray,
                        labels: np.ndarray) -> float:
    """Sum of log Phi(y_i (a mu_i + b) / sqrt(1 + a^2 var_i)) over LOO predictions."""
    z = labels * (a * mean + b) / np.sqrt(1.0 + a**2 * variance)
    return float(log_ndtr(z).sum())


def fit_classifier(kernel: Kernel, noise_variance: float, patches: list[LocalProblem],
                   level: int) -> PlattClassifier:
    """Fit a and b by maximising the LOO predictive log probability over ``patches``."""
    means, variances, labels = [], [], []
    for patch in patches:
        chol = factor_training_covariance(kernel, noise_variance, patch.samples, level)
        mu, var = leave_one_out(chol, patch.samples.labels)
        means.append(mu)
        variances.append(var)
        labels.append(patch.samples.labels)
    mu, var, y = np.concatenate(means), np.concatenate(variances), np.concatenate(labels)

    def objective(p: np.ndarray) -> float:
        return -loo_log_probability(p[0], p[1], mu, var, y)

    result = minimize(objective, np.array([1.0, 0.0]), method="L-BFGS-B",
                      bounds=[(1e-3, 1e3), (-1e2, 1e2)])
    return PlattClassifier(a=float(result.x[0]), b=float(result.x[1]))


def class_counts(classes: np.ndarray) -> dict[str, int]:
    """Cells per class of a ``classify`` result (no-data cells are not counted)."""
    return {"free": int(np.count_nonzero(classes == FREE)),
            "occupied": int(np.count_nonzero(classes == OCCUPIED)),
            "unsure": int(np.count_nonzero(classes == UNSURE))}


def classify(probability: np.ndarray, occupied: float, free: float,
             unsure: np.ndarray | None = None) -> np.ndarray:
    """uint8 classes: 1 occupied (p > occupied), 0 free (p < free), 2 unsure, 255 no data.

    ``unsure`` (bool, same shape) forces cells to unsure, e.g. where the predictive
    variance is too close to the prior variance for a decision.
    """
    classes = np.full(probability.shape, UNSURE, dtype=np.uint8)
    classes[probability > occupied] = OCCUPIED
    classes[probability < free] = FREE
    if unsure is not None:
        classes[unsure] = UNSURE
    classes[~np.isfinite(probability)] = NO_DATA
    return classes
