"""How flat is the Platt classifier's objective? Refit the classifier of a trained model
with the compiled and the numpy expected kernels, in the published (a, b) parametrisation
(as gpocc fitted it before 2026-11-22) and in today's (c = b/a, s = 1/a^2), and evaluate
the objective at every fit.

    .venv/bin/python bench/platt_ridge.py MODEL.npz

The held-out predictions of the two kernel paths agree to ~1e-14. In (a, b) the optimum
lies on the a -> infinity ridge (p -> Phi((mu + b/a) / sqrt(var))), so the fitted a is
set by where L-BFGS-B stops; in (c, s) the ridge is the bound s = 1e-6 and both paths
should give the same fit.
"""

from __future__ import annotations

import sys

import numpy as np
from scipy.optimize import minimize
from scipy.special import log_ndtr

from gpocc.blas import single_threaded_blas
from gpocc.gp.classify import (
    PlattClassifier,
    fit_platt,
    held_out_log_probability,
    holdout_predictions,
)
from gpocc.gp.model import load_model
from gpocc.gp.train import make_patches


def fit_ab(mean: np.ndarray, variance: np.ndarray, labels: np.ndarray) -> PlattClassifier:
    """The fit of gpocc before 2026-11-22: L-BFGS-B in (a, b), numeric gradient."""

    def objective(p: np.ndarray) -> float:
        z = labels * (p[0] * mean + p[1]) / np.sqrt(1.0 + p[0] ** 2 * variance)
        return -float(log_ndtr(z).sum())

    result = minimize(objective, np.array([1.0, 0.0]), method="L-BFGS-B",
                      bounds=[(1e-3, 1e3), (-1e2, 1e2)])
    return PlattClassifier.from_ab(float(result.x[0]), float(result.x[1]))


def main() -> None:
    model = load_model(sys.argv[1])
    cfg = model.config
    patches = make_patches(model.samples, cfg.model.training, cfg.seed + 1)
    fits, predictions = {}, {}
    with single_threaded_blas():
        for fused in (False, True):
            predictions[fused] = holdout_predictions(
                model.kernel, model.noise_variance, patches, cfg.model.quadrature_level,
                cfg.model.training.classifier_holdout, "compiled" if fused else "numpy")
            fits[("(a, b)", fused)] = fit_ab(*predictions[fused])
            fits[("(c, s)", fused)] = fit_platt(*predictions[fused])
    mu, var, y = predictions[True]
    print(f"max |mean difference| {np.abs(predictions[False][0] - mu).max():.2e}, "
          f"max |variance difference| {np.abs(predictions[False][1] - var).max():.2e}")
    for (form, fused), fit in fits.items():
        value = held_out_log_probability(fit.offset, fit.extra_variance, mu, var, y)
        print(f"fit in {form}, {'compiled' if fused else 'numpy   '} kernels: "
              f"a = {fit.a:9.3f}, b = {fit.b:8.3f}, c = {fit.offset:+.6f}, "
              f"s = {fit.extra_variance:.3e}, log probability {value:.4f}")


if __name__ == "__main__":
    main()
