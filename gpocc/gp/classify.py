"""Probabilistic least-squares classification (Platt scaling of the GP regression).

``p(occupied | x) = Phi((a * mu + b) / sqrt(1 + a^2 * var))`` squashes the latent GP
mean ``mu`` and variance ``var`` into a probability. ``a`` and ``b`` maximise the
predictive log probability of training labels that the predicting GP did not see
(Rasmussen and Williams, section 6.5), in one of two ways (``model.training.
classifier_holdout``):

* ``sample`` (default): the method as published, closed-form leave-one-sample-out of
  the training labels (predictive variance including the label noise).
* ``scan``: leave one *scan* out. Each sample of a local problem is predicted, as a map
  cell would be (an exact point at its mean, latent mean and variance), from the
  problem's samples of all *other* scans, so that samples of one scan (which share its
  pose error) cannot vouch for each other. It gives a much flatter classifier (a of
  1.3-1.6 instead of 260-530), which measured *worse* calibrated on held-out scans and
  simulated truth (docs/results.md): free space came out grey (p 0.2-0.3). A likely
  reason, not yet verified: held-out training samples are not distributed like map
  queries (thinning keeps boundary cells over-represented, and map cells lie between
  samples), so a classifier fitted on them is too timid for open space.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_solve
from scipy.optimize import minimize
from scipy.special import log_ndtr, ndtr

from gpocc.gp.expected import expected_kernel_cross
from gpocc.gp.kernels import Kernel
from gpocc.gp.local import LocalProblem, factor_training_covariance, leave_one_out

#: Ways to hold labels out when fitting the classifier (see the module docstring).
HOLDOUTS = ("scan", "sample")

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


def leave_one_scan_out(kernel: Kernel, noise_variance: float, patch: LocalProblem,
                       level: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Latent predictions at each sample of ``patch`` from the patch's other scans.

    Sample ``i`` of scan ``s`` is treated as a query at its mean (exact, like a map
    cell) and predicted by the GP on the patch's samples of every scan but ``s``:
    ``mu_i = k_i,R K_RR^-1 y_R`` and ``var_i = k(x_i, x_i) - k_i,R K_RR^-1 k_R,i``. One
    factorisation serves all scans: ``K_RR^-1`` is the Schur complement of the held-out
    block ``G`` in ``K^-1``, ``(K^-1)_RR - (K^-1)_RG ((K^-1)_GG)^-1 (K^-1)_GR``.

    Returns:
        ``(mean, variance, mask)``, each (M,): predictions, and True where the sample could
        be predicted (its scan is not the patch's only scan).
    """
    s = patch.samples
    m = len(s)
    chol = factor_training_covariance(kernel, noise_variance, s, level)
    inverse = cho_solve((chol, True), np.eye(m))
    alpha = inverse @ s.labels
    cross = expected_kernel_cross(kernel, s.means, s.means, s.covariances, level)
    prior = kernel.diag(s.means)
    mean, variance = np.zeros(m), np.zeros(m)
    mask = np.zeros(m, dtype=bool)
    for scan in np.unique(s.scan_ids):
        held = np.flatnonzero(s.scan_ids == scan)
        rest = np.flatnonzero(s.scan_ids != scan)
        if rest.size == 0:
            continue
        # K_RR^-1 y_R = alpha_R - (K^-1)_RG (K^-1)_GG^-1 alpha_G (block inverse identity).
        g_inv = inverse[np.ix_(held, held)]
        rg = inverse[np.ix_(rest, held)]
        weights_y = alpha[rest] - rg @ np.linalg.solve(g_inv, alpha[held])
        k_gr = cross[np.ix_(held, rest)]
        mean[held] = k_gr @ weights_y
        rr_inv_k = inverse[np.ix_(rest, rest)] @ k_gr.T - rg @ np.linalg.solve(g_inv, rg.T @ k_gr.T)
        variance[held] = np.maximum(prior[held] - np.einsum("gr,rg->g", k_gr, rr_inv_k), 0.0)
        mask[held] = True
    return mean, variance, mask


def holdout_predictions(kernel: Kernel, noise_variance: float, patches: list[LocalProblem],
                        level: int, holdout: str = "sample",
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Held-out latent means, variances and labels (concatenated over ``patches``)."""
    if holdout not in HOLDOUTS:
        raise ValueError(f"holdout must be one of {HOLDOUTS}, got {holdout!r}")
    means, variances, labels = [], [], []
    for patch in patches:
        if holdout == "scan":
            mu, var, mask = leave_one_scan_out(kernel, noise_variance, patch, level)
            mu, var, y = mu[mask], var[mask], patch.samples.labels[mask]
        else:
            chol = factor_training_covariance(kernel, noise_variance, patch.samples, level)
            mu, var = leave_one_out(chol, patch.samples.labels)
            y = patch.samples.labels
        means.append(mu)
        variances.append(var)
        labels.append(y)
    return np.concatenate(means), np.concatenate(variances), np.concatenate(labels)


def fit_platt(mean: np.ndarray, variance: np.ndarray, labels: np.ndarray) -> PlattClassifier:
    """a > 0 and b maximising :func:`loo_log_probability` of held-out predictions (N,)."""
    if mean.size == 0 or np.all(labels > 0) or np.all(labels < 0):
        # Nothing to calibrate against: keep the identity squashing.
        return PlattClassifier()

    def objective(p: np.ndarray) -> float:
        return -loo_log_probability(p[0], p[1], mean, variance, labels)

    result = minimize(objective, np.array([1.0, 0.0]), method="L-BFGS-B",
                      bounds=[(1e-3, 1e3), (-1e2, 1e2)])
    return PlattClassifier(a=float(result.x[0]), b=float(result.x[1]))


def fit_classifier(kernel: Kernel, noise_variance: float, patches: list[LocalProblem],
                   level: int, holdout: str = "sample") -> PlattClassifier:
    """Fit a and b on held-out predictions over ``patches`` (``holdout``: scan or sample)."""
    mu, var, y = holdout_predictions(kernel, noise_variance, patches, level, holdout)
    return fit_platt(mu, var, y)


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
