"""A learned scale on the input covariances (issue 10, "hyperparameters that respect
input noise").

Pose and range covariances reported by a robot are rarely exact. The scale ``g > 0``
replaces every training input's covariance ``S_i`` by ``g S_i`` and its pose factor
``A_i`` by ``sqrt(g) A_i``, so the covariance of two same-scan inputs ``A_i A_j'`` and the
whole joint covariance of a pair scale by ``g`` too: ``g`` says how far the GP trusts
the stated input noise (``g < 1``: less noise than stated, ``g > 1``: more). It is
learned with the kernel hyperparameters by the patch log marginal likelihood
(:mod:`gpocc.gp.train`) and the model's samples are stored already scaled, so
prediction and mapping use it without a switch. ``g = 1`` is the model as published.
"""

from __future__ import annotations

import dataclasses
import math

from gpocc.samples.sampleset import SampleSet

#: Step in log g of the central differences in log g: d(-LML)/d log g where the kernel has
#: no analytic one, and the two-draw diagonal's dK/dlog g (values are smooth in log g:
#: truncation ~1e-7 relative, round-off ~1e-13).
LOG_SCALE_STEP = 1e-3


def scale_input_noise(samples: SampleSet, scale: float) -> SampleSet:
    """``samples`` with covariances (N, 2, 2) m^2 times ``scale`` and pose factors
    (N, 2, 3) m times ``sqrt(scale)``; ``scale == 1`` returns ``samples`` itself."""
    if scale == 1.0:
        return samples
    return dataclasses.replace(samples, covariances=samples.covariances * scale,
                               pose_factors=samples.pose_factors * math.sqrt(scale))
