"""The unscented transform of beam samples, compiled (C: gpocc/_kernels.c).

:func:`gpocc.samples.unscented.unscented_transform` is generic: it builds the (N, 11, 5)
sigma points, pushes them through :func:`gpocc.samples.beam_rules.beam_endpoint` and reduces
them with batched matrix products. For the beam endpoint that costs about 3 us a sample,
and a log gives millions of samples before thinning (Intel: 2 million, the largest stage
of ``gpocc train``). Here the same transform runs as one loop per sample with the
structure of the input covariance used directly: its square root is block diagonal
(range, bearing, then the scan's 3 x 3 pose root), so each sigma point moves one input.
The results equal the generic transform's up to round-off (tests/samples/test_beam_unscented.py
checks it against that transform and against Monte Carlo).
"""

from __future__ import annotations

import math

import numpy as np

from gpocc import compiled
from gpocc.samples.unscented import ut_weights

# Inputs of a beam sample, in this order: range, bearing, base x, base y, base yaw.
_N_INPUTS = 5


def beam_unscented(
    distances: np.ndarray,
    bearings: np.ndarray,
    range_variances: np.ndarray,
    bearing_variance: float,
    scans: np.ndarray,
    poses: np.ndarray,
    pose_roots: np.ndarray,
    pose_maps: np.ndarray,
    mount: np.ndarray,
    alpha: float,
    beta: float,
    kappa: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position Gaussians and pose factors of beam samples (the scaled unscented transform).

    Each sample's inputs (range, bearing, base x, y, yaw) are Gaussian with covariance
    ``blockdiag(range_variances[i], bearing_variance, P_s)`` for its scan ``s``, pushed
    through :func:`gpocc.samples.beam_rules.beam_endpoint` with ``mount``.

    Args:
        distances: (N,) metres along the beam.
        bearings: (N,) radians in the laser frame.
        range_variances: (N,) m^2.
        bearing_variance: rad^2, all samples.
        scans: (N,) index of each sample's scan into ``poses``.
        poses: (S, 3) base poses (x m, y m, yaw rad).
        pose_roots: (S, 3, 3) ``L`` with ``L L^T = P_s``.
        pose_maps: (S, 3, 3) ``pinv(P_s) L``: the pose factor is ``C^T pinv(P_s) L`` with
            ``C`` the (3, 2) pose block of the cross-covariance.
        mount: (3,) laser offset (m) and yaw (rad) on the base.
        alpha, beta, kappa: the transform's parameters (see ``ut_weights``).

    Returns:
        means (N, 2) metres, covariances (N, 2, 2) m^2, pose factors (N, 2, 3) metres.
    """
    wm, wc = ut_weights(_N_INPUTS, alpha, beta, kappa)
    gamma = math.sqrt(alpha**2 * (_N_INPUTS + kappa))
    return compiled.beam_unscented(
        distances, bearings, np.sqrt(np.asarray(range_variances, dtype=np.float64)),
        float(math.sqrt(bearing_variance)), scans, poses, pose_roots, pose_maps, mount,
        wm, wc, gamma)
