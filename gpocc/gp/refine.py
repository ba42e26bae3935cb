"""Refining hyperparameters from a good start: Fisher scoring in a box.

``gpocc update`` starts from a model's learned values, usually tens of nats from the
optimum of the union's patches. L-BFGS-B must first learn the likelihood's curvature
from its own steps (its first, a unit step along the gradient, often leaves the valid
covariances); the patches give that curvature directly. The Fisher information of a
Gaussian likelihood, ``F_pq = 1/2 tr(K^-1 dK_p K^-1 dK_q)``, costs a product per
parameter beside the gradient's, and a scoring step ``-F^-1 g`` damped as
Levenberg-Marquardt's reaches the optimum in fewer evaluations than L-BFGS-B from the
same start (docs/benchmarks.md, "Learning's local search", counts both).

Bounds: a parameter on its bound whose gradient pushes outwards is held there for the
step (an active set), and a step is clipped into the box.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

#: The refinement stops where the decrease still to come (nats) is estimated under this.
#: The patches' optimum moves by far more from one draw of patches to the next.
TOLERANCE = 0.01

#: The largest rate of linear convergence taken from two steps' decreases, and the rate
#: assumed before two are known. Where the Fisher information is not the likelihood's
#: curvature (along a ridge), the steps fall short and each gains a near-constant
#: fraction of the one before, more than the quadratic model predicts: the decrease still
#: to come is then the geometric series of the next step's, estimated as the model's
#: prediction times the last step's gain over its prediction, not the prediction alone.
_MAX_RATE = 0.9

#: The largest gain over its prediction taken from a step (a tiny prediction's ratio says
#: little).
_MAX_GAIN = 10.0

#: Initial damping, relative to the Fisher information's diagonal.
_DAMPING = 1e-2

#: Damping's range: below it the solve is plain scoring; above it a step is negligible.
_MIN_DAMPING, _MAX_DAMPING = 1e-8, 1e8

#: Rejected steps in a row after which the start is taken as the optimum.
_REJECTIONS = 6


@dataclass(frozen=True)
class Refinement:
    """Where a refinement ended.

    Attributes:
        x: (P,) the parameters (same units as the start).
        value: the objective there.
        evaluations: objective evaluations spent here (the start's when it was not
            given).
        converged: stopped before the budget ran out: the decrease still to come was
            estimated under the tolerance, or no step was accepted.
    """

    x: np.ndarray
    value: float
    evaluations: int
    converged: bool


Evaluation = tuple[float, np.ndarray, np.ndarray]


def fisher_scoring(
    evaluate: Callable[[np.ndarray], Evaluation | None], x0: np.ndarray,
    lower: np.ndarray, upper: np.ndarray, max_evaluations: int,
    start: Evaluation | None = None, tolerance: float = TOLERANCE,
) -> Refinement:
    """Minimise an objective from ``x0`` within ``[lower, upper]`` (each (P,)).

    Args:
        evaluate: ``x -> (value, gradient (P,), fisher (P, P))``, or None where the
            objective is not defined (an invalid covariance): the step is rejected.
        x0: (P,) the start, inside the box.
        max_evaluations: the budget (the start's evaluation included when it is not
            given).
        start: ``evaluate(x0)`` when the caller has it already. Where it is None (``x0``
            is not a valid covariance), the result is ``x0`` with an infinite value.
        tolerance: see :data:`TOLERANCE`.
    """
    x = np.clip(np.asarray(x0, dtype=float), lower, upper)
    evaluations = 0
    if start is None:
        start = evaluate(x)
        evaluations += 1
    if start is None:  # not a valid covariance: nowhere to go from
        return Refinement(x, math.inf, evaluations, False)
    value, grad, fisher = start
    damping = _DAMPING
    rejections = 0
    # The rate is the larger of the last two steps' ratios: the first ratio mixes the
    # directions the model got right (done in one step) with those it did not. Until two
    # ratios are known, the slowest rate is assumed.
    ratios = [_MAX_RATE, _MAX_RATE]
    gain = 1.0
    last_decrease = math.inf
    while evaluations < max_evaluations:
        # Converged when the model's own step (undamped), scaled by the last step's gain
        # over its prediction, and the steps after it at the rate of the last two, promise
        # under the tolerance.
        promised = _predicted(grad, fisher, _scoring_step(x, grad, fisher, 0.0, lower, upper))
        if 0.0 <= promised * gain / (1.0 - max(ratios)) < tolerance:
            return Refinement(x, value, evaluations, True)
        step = _scoring_step(x, grad, fisher, damping, lower, upper)
        if _predicted(grad, fisher, step) <= 0.0:
            # Clipped into the box, a step along correlated parameters may climb; more
            # damping turns it towards the (scaled) gradient, which clipping keeps
            # downhill.
            damping *= 10.0
            if damping > _MAX_DAMPING:
                return Refinement(x, value, evaluations, True)
            continue
        trial = evaluate(x + step)
        evaluations += 1
        if trial is None or not trial[0] < value:
            rejections += 1
            if rejections >= _REJECTIONS:
                return Refinement(x, value, evaluations, True)
            damping *= 10.0
            continue
        rejections = 0
        decrease = value - trial[0]
        predicted = _predicted(grad, fisher, step)
        if decrease > 0.5 * predicted:
            damping = max(damping / 3.0, _MIN_DAMPING)
        # A model that under-predicts its steps under-predicts the rest too; one that
        # over-predicts is trusted as before (never stop earlier than its prediction).
        gain = min(max(decrease / predicted, 1.0), _MAX_GAIN)
        x = x + step
        value, grad, fisher = trial
        if math.isfinite(last_decrease):
            ratios = [ratios[1], min(decrease / last_decrease, _MAX_RATE)]
        last_decrease = decrease
        rate = max(ratios)
        if decrease < tolerance and decrease * rate / (1.0 - rate) < tolerance:
            return Refinement(x, value, evaluations, True)
    return Refinement(x, value, evaluations, False)


def _predicted(grad: np.ndarray, fisher: np.ndarray, step: np.ndarray) -> float:
    """The decrease the quadratic model (gradient, Fisher information) predicts."""
    return float(-(grad @ step + 0.5 * step @ fisher @ step))


def _scoring_step(x: np.ndarray, grad: np.ndarray, fisher: np.ndarray, damping: float,
                  lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """The damped scoring step from ``x`` over the parameters not held on a bound,
    clipped into the box."""
    held = ((x <= lower) & (grad > 0)) | ((x >= upper) & (grad < 0))
    free = ~held
    step = np.zeros_like(x)
    if not free.any():
        return step
    block = fisher[np.ix_(free, free)]
    scale = np.maximum(np.diag(block), 1e-12 * max(1.0, float(np.abs(block).max())))
    try:
        step[free] = np.linalg.solve(block + max(damping, _MIN_DAMPING) * np.diag(scale),
                                     -grad[free])
    except np.linalg.LinAlgError:
        step[free] = -grad[free] / ((1.0 + damping) * scale)
    return np.clip(x + step, lower, upper) - x
