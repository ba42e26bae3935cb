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

With ``part="pose"`` (``model.training.input_noise_scale_part: pose``) g scales only the
pose part ``A_i A_i'`` of each covariance: ``S_i -> S_i + (g - 1) A_i A_i'``, ``A_i ->
sqrt(g) A_i``; the sensor's range and bearing noise stay as stated.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from gpocc.config import INPUT_NOISE_SCALE_PARTS
from gpocc.samples.sampleset import SampleSet

#: Step in log g of the central differences in log g: d(-LML)/d log g where the kernel has
#: no analytic one, and the two-draw diagonal's dK/dlog g (values are smooth in log g:
#: truncation ~1e-7 relative, round-off ~1e-13).
LOG_SCALE_STEP = 1e-3


def scale_input_noise(samples: SampleSet, scale: float, part: str = "all") -> SampleSet:
    """``samples`` with pose factors (N, 2, 3) m times ``sqrt(scale)`` and covariances
    (N, 2, 2) m^2 times ``scale`` (``part="all"``) or with their pose part ``A A'`` times
    ``scale`` (``part="pose"``); ``scale == 1`` returns ``samples`` itself."""
    if part not in INPUT_NOISE_SCALE_PARTS:
        raise ValueError(f"part must be one of {INPUT_NOISE_SCALE_PARTS}, not {part!r}")
    if scale == 1.0:
        return samples
    factors = samples.pose_factors
    if part == "all":
        covariances = samples.covariances * scale
    else:
        pose = np.einsum("nik,njk->nij", factors, factors)
        if scale >= 1.0:
            covariances = samples.covariances + (scale - 1.0) * pose
        else:
            # The sensor part S - A A' is PSD only up to the unscented transform's
            # nonlinearity (A is the pose Jacobian's factor): clipped to PSD before the
            # pose part shrinks.
            values, vectors = np.linalg.eigh(samples.covariances - pose)
            sensor = np.einsum("nij,nj,nkj->nik", vectors, np.maximum(values, 0.0), vectors)
            covariances = sensor + scale * pose
    return dataclasses.replace(samples, covariances=covariances,
                               pose_factors=factors * math.sqrt(scale))
