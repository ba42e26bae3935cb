"""The unscented transform of beam samples, compiled (numba).

:func:`gpocc.samples.unscented.unscented_transform` is generic: it builds the (N, 11, 5)
sigma points, pushes them through :func:`gpocc.samples.beam.beam_endpoint` and reduces
them with batched matrix products. For the beam endpoint that costs about 3 us a sample,
and a log gives millions of samples before thinning (Intel: 2 million, the largest stage
of ``gpocc train``). Here the same transform runs as one loop per sample with the
structure of the input covariance used directly: its square root is block diagonal
(range, bearing, then the scan's 3 x 3 pose root), so each sigma point moves one input.
The results equal the generic transform's up to round-off (tests/test_beam_unscented.py
checks it against that transform and against Monte Carlo).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from gpocc.samples.unscented import ut_weights

# Inputs of a beam sample, in this order: range, bearing, base x, base y, base yaw.
_N_INPUTS = 5


@numba.njit(cache=True, error_model="numpy", nogil=True)
def _transform(dist, bearing, range_sd, bearing_sd, scan, poses, pose_root, pose_map, mount,
               wm, wc, gamma, means, covariances, factors):  # pragma: no cover - compiled
    mx, my, myaw = mount[0], mount[1], mount[2]
    sigma = 2 * _N_INPUTS + 1
    points = np.empty((sigma, _N_INPUTS))
    ys = np.empty((sigma, 2))
    # Each sigma point's step from the centre: +-gamma times a column of the
    # block-diagonal root (range, bearing, then the pose root's columns). The bearing and
    # pose steps are the same for every sample of a scan, so they are set once per scan,
    # and so are the cosines and sines of the yaw and beam-angle steps: the points' angles
    # follow from the centre's by the angle-addition formulas, and a sample needs the
    # sines and cosines of its centre only (4 calls instead of up to 16; equal to
    # round-off).
    steps = np.zeros((sigma, _N_INPUTS))
    step_cos = np.empty((sigma, 2))  # columns: yaw, beam angle
    step_sin = np.empty((sigma, 2))
    last_scan = 0
    for i in range(dist.shape[0]):
        s = scan[i]
        if i == 0 or s != last_scan:
            last_scan = s
            steps[2, 1] = gamma * bearing_sd
            steps[2 + _N_INPUTS, 1] = -gamma * bearing_sd
            for j in range(3):
                for d in range(3):
                    step = gamma * pose_root[s, d, j]
                    steps[3 + j, 2 + d] = step
                    steps[3 + j + _N_INPUTS, 2 + d] = -step
            for k in range(sigma):
                yaw, angle = steps[k, 4], steps[k, 4] + steps[k, 1]
                step_cos[k, 0], step_sin[k, 0] = math.cos(yaw), math.sin(yaw)
                step_cos[k, 1], step_sin[k, 1] = math.cos(angle), math.sin(angle)
        steps[1, 0] = gamma * range_sd[i]
        steps[1 + _N_INPUTS, 0] = -gamma * range_sd[i]
        centre = (dist[i], bearing[i], poses[s, 0], poses[s, 1], poses[s, 2])
        for k in range(sigma):
            for d in range(_N_INPUTS):
                points[k, d] = centre[d] + steps[k, d]
        mean_x = 0.0
        mean_y = 0.0
        th0 = centre[4]
        phi0 = th0 + myaw + centre[1]
        c0, s0 = math.cos(th0), math.sin(th0)
        cp0, sp0 = math.cos(phi0), math.sin(phi0)
        for k in range(sigma):
            r, x, y = points[k, 0], points[k, 2], points[k, 3]
            c = c0 * step_cos[k, 0] - s0 * step_sin[k, 0]
            sn = s0 * step_cos[k, 0] + c0 * step_sin[k, 0]
            cp = cp0 * step_cos[k, 1] - sp0 * step_sin[k, 1]
            sp = sp0 * step_cos[k, 1] + cp0 * step_sin[k, 1]
            ys[k, 0] = x + c * mx - sn * my + r * cp
            ys[k, 1] = y + sn * mx + c * my + r * sp
            mean_x += wm[k] * ys[k, 0]
            mean_y += wm[k] * ys[k, 1]
        cxx = 0.0
        cxy = 0.0
        cyy = 0.0
        for k in range(sigma):
            dx = ys[k, 0] - mean_x
            dy = ys[k, 1] - mean_y
            cxx += wc[k] * dx * dx
            cxy += wc[k] * dx * dy
            cyy += wc[k] * dy * dy
        means[i, 0] = mean_x
        means[i, 1] = mean_y
        covariances[i, 0, 0] = cxx
        covariances[i, 0, 1] = cxy
        covariances[i, 1, 0] = cxy
        covariances[i, 1, 1] = cyy
        # Cross-covariance of the pose inputs and the position: only the pose sigma points
        # move the pose, by +-gamma L[:, j], with the (equal) weight wc[1].
        for a in range(2):
            for m in range(3):
                factors[i, a, m] = 0.0
        for j in range(3):
            dpx = (ys[3 + j, 0] - ys[3 + j + _N_INPUTS, 0]) * gamma * wc[1]
            dpy = (ys[3 + j, 1] - ys[3 + j + _N_INPUTS, 1]) * gamma * wc[1]
            for d in range(3):
                # cross[d, :] += L[d, j] * (dpx, dpy); factors = cross^T @ pose_map
                for m in range(3):
                    weight = pose_root[s, d, j] * pose_map[s, d, m]
                    factors[i, 0, m] += weight * dpx
                    factors[i, 1, m] += weight * dpy


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
    through :func:`gpocc.samples.beam.beam_endpoint` with ``mount``.

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
    n = len(distances)
    wm, wc = ut_weights(_N_INPUTS, alpha, beta, kappa)
    gamma = math.sqrt(alpha**2 * (_N_INPUTS + kappa))
    means = np.empty((n, 2))
    covariances = np.empty((n, 2, 2))
    factors = np.empty((n, 2, 3))

    def f64(a: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(a, dtype=np.float64)

    _transform(
        f64(distances), f64(bearings), np.sqrt(f64(range_variances)),
        float(math.sqrt(bearing_variance)), np.ascontiguousarray(scans, dtype=np.int64),
        f64(poses), f64(pose_roots), f64(pose_maps), f64(mount), wm, wc, gamma,
        means, covariances, factors,
    )
    return means, covariances, factors
