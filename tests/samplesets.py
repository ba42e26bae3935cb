"""Small training sample sets for tests: a ``SampleSet`` from plain arrays."""

from __future__ import annotations

import numpy as np

from gpocc.samples.sampleset import SampleSet


def samples_from(means, labels, covariances=None, scan_ids=None, pose_factors=None,
                 noise_factors=None) -> SampleSet:
    """(N, 2) ``means`` with (N,) ``labels``; exact inputs, one scan each and unit
    label-noise factors unless given."""
    n = len(means)
    return SampleSet(
        means=np.asarray(means, float),
        covariances=np.zeros((n, 2, 2)) if covariances is None else covariances,
        labels=np.asarray(labels, float),
        scan_ids=np.arange(n) if scan_ids is None else scan_ids,
        pose_factors=np.zeros((n, 2, 3)) if pose_factors is None else pose_factors,
        sensor_ids=np.zeros(n, dtype=np.int16),
        noise_factors=None if noise_factors is None else np.asarray(noise_factors, float),
    )
