"""How flat is the Platt classifier's objective? Refit a and b of a trained model with the
compiled and the numpy expected kernels, and evaluate the objective at both fits.

    .venv/bin/python bench/platt_ridge.py MODEL.npz

The held-out predictions of the two kernel paths agree to ~1e-14; when the printed fits
differ while the objective values agree to ~0.01, the optimum lies on the a -> infinity
ridge (p -> Phi((mu + b/a) / sqrt(var))) and the fitted a is set by where L-BFGS-B stops.
"""

from __future__ import annotations

import sys

import numpy as np

from gpocc.blas import single_threaded_blas
from gpocc.gp import expected
from gpocc.gp.classify import fit_platt, holdout_predictions, loo_log_probability
from gpocc.gp.model import load_model
from gpocc.gp.train import make_patches


def main() -> None:
    model = load_model(sys.argv[1])
    cfg = model.config
    patches = make_patches(model.samples, cfg.model.training, cfg.seed + 1)
    fits, predictions = {}, {}
    with single_threaded_blas():
        for fused in (False, True):
            expected.USE_FUSED = fused
            predictions[fused] = holdout_predictions(
                model.kernel, model.noise_variance, patches, cfg.model.quadrature_level,
                cfg.model.training.classifier_holdout)
            fits[fused] = fit_platt(*predictions[fused])
    mu, var, y = predictions[True]
    print(f"max |mean difference| {np.abs(predictions[False][0] - mu).max():.2e}, "
          f"max |variance difference| {np.abs(predictions[False][1] - var).max():.2e}")
    for fused, fit in fits.items():
        value = loo_log_probability(fit.a, fit.b, mu, var, y)
        print(f"{'compiled' if fused else 'numpy   '} kernels: a = {fit.a:9.3f}, "
              f"b = {fit.b:8.3f}, log probability {value:.4f}")


if __name__ == "__main__":
    main()
