"""Learned values that ended on (or next to) a bound of their search.

A value on its bound was stopped by the box, not chosen by the data: the likelihood (or
the classifier's held-out fit) still improves beyond it, so the model is misspecified
there or the box is too narrow. Checked are the Platt slope ``a`` and offset ``c``
(:mod:`gpocc.gp.classify`), and, when they were learned (:func:`gpocc.gp.train.
search_bounds`), the kernel hyperparameters, the label-noise variance (whose lower
bound is the floor ``min_noise_variance``) and the input-noise scale ``g``. A positive
value is on a bound when its log is within ``log(1 + REL_TOL)`` of the bound's; the
offset ``c`` when within ``REL_TOL`` times the bound its fit had (``C_BOUND``, or with
``classifier_offset_range: latent`` the largest latent mean among its points, which the
model's training record keeps as ``classifier_offset_bound``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from gpocc.gp.classify import C_BOUND, S_MAX, S_MIN, T_MAX, T_MIN
from gpocc.gp.kernels import make_kernel
from gpocc.gp.model import GPModel
from gpocc.gp.train import search_bounds

#: Relative distance to a bound that counts as on it.
REL_TOL = 0.01

#: Where users read what each value on its bound means and what a wider box did on the
#: results page's worlds and logs.
GUIDE_SECTION = "docs/guide.md, 'Learned values on their bounds'"


@dataclass(frozen=True)
class OnBound:
    """One learned value on a bound.

    Attributes:
        name: what it is (``classifier slope a``, ``kernel bias_variance``, ...).
        value: the learned value.
        bound: the bound it is on.
        side: ``lower`` or ``upper``.
        setting: the config key (or constant) that sets the bound.
    """

    name: str
    value: float
    bound: float
    side: str
    setting: str

    def message(self) -> str:
        """One line for a warning or ``gpocc info``."""
        return (f"{self.name} = {self.value:.4g} is on its {self.side} bound "
                f"{self.bound:.4g} ({self.setting})")


def side_on_bound(value: float, lower: float, upper: float, log: bool = True,
                  rel_tol: float = REL_TOL) -> str | None:
    """``lower``, ``upper`` or None: which bound ``value`` is on (see the module doc);
    ``log``: compare positive values in logs, else absolutely within ``rel_tol`` of the
    box's half-width."""
    if log:
        v, lo, hi, tol = math.log(value), math.log(lower), math.log(upper), math.log1p(rel_tol)
    else:
        v, lo, hi, tol = value, lower, upper, rel_tol * 0.5 * (upper - lower)
    if v - lo <= tol:
        return "lower"
    if hi - v <= tol:
        return "upper"
    return None


def theta_names(kernel: object) -> list[str]:
    """Names of a kernel's ``theta`` entries: its fields in order, tuples expanded
    (``weight_variance[0]``, ...); every kernel's theta is the log of its fields."""
    names = []
    for f in dataclasses.fields(kernel):  # type: ignore[arg-type]
        value = getattr(kernel, f.name)
        if isinstance(value, tuple):
            names += [f"{f.name}[{i}]" for i in range(len(value))]
        else:
            names.append(f.name)
    return names


def learned_scale(model: GPModel) -> bool:
    """Whether training learned g (as :func:`gpocc.gp.train.learn_hyperparameters`
    decides: asked for, and some input has a covariance)."""
    training = model.config.model.training
    return (training.learn and training.learn_input_noise_scale and model.input_noise
            and bool(np.any(model.samples.covariances)))


def _offset_bound(training: object) -> float:
    """The largest |c| the classifier's offset fit allowed, as the model's training
    record states it (files written before it: :data:`C_BOUND`)."""
    bound = training.get("classifier_offset_bound") if isinstance(training, dict) else None
    valid = isinstance(bound, int | float) and math.isfinite(bound) and 0 < bound <= C_BOUND
    return float(bound) if valid else C_BOUND


def values_on_bounds(model: GPModel, rel_tol: float = REL_TOL) -> list[OnBound]:
    """Every learned value of ``model`` on a bound of its search (see the module doc)."""
    found = []
    a_lower, a_upper = 1.0 / math.sqrt(S_MAX), 1.0 / math.sqrt(S_MIN)
    offset_box = _offset_bound(model.training)
    checks: list[tuple[str, float, float, float, bool, str]] = [
        ("classifier slope a", model.classifier.a, a_lower, a_upper, True,
         "gpocc.gp.classify.S_MIN/S_MAX; model.training.classifier_variance: latent "
         "fits it on the latent variance"),
        ("classifier offset c", model.classifier.offset, -offset_box, offset_box, False,
         "gpocc.gp.classify.C_BOUND" if offset_box == C_BOUND else
         "model.training.classifier_offset_range: latent, the largest latent mean among "
         "its points"),
    ]
    if model.config.model.training.classifier_temperature != "none":
        checks.append(("classifier temperature T", model.classifier.temperature, T_MIN, T_MAX,
                       True, "gpocc.gp.classify.T_MIN/T_MAX"))
    cfg = model.config.model
    training = cfg.training
    if training.learn:
        initial = make_kernel(cfg.kernel, cfg.hyperparameters)
        scale = learned_scale(model)
        box = search_bounds(initial.theta, cfg.hyperparameters.noise_variance, training, scale)
        learned = [*model.kernel.theta, math.log(model.noise_variance)]
        names = [f"kernel {n}" for n in theta_names(model.kernel)] + ["label-noise variance"]
        settings = ["model.training.log_bounds_width"] * len(names)
        settings[-1] = ("model.training.min_noise_variance / log_bounds_width")
        if scale:
            learned.append(math.log(model.input_noise_scale))
            names.append("input-noise scale g")
            settings.append("model.training.min/max_input_noise_scale")
        for name, v, (lo, hi), setting in zip(names, learned, box, settings, strict=True):
            checks.append((name, math.exp(v), math.exp(lo), math.exp(hi), True, setting))
    for name, value, lo, hi, log, setting in checks:
        side = side_on_bound(value, lo, hi, log, rel_tol)
        if side is not None:
            found.append(OnBound(name, value, lo if side == "lower" else hi, side, setting))
    return found
