"""Compiled (numba) loops for the expected neural-network kernel: quadrature and arcsin fused.

The numpy path of :mod:`gpocc.gp.expected` builds node-pair matrices of arcsin values (and,
for gradients, four of them), then reduces them with the quadrature weights; same-scan
pairs need one LAPACK eigendecomposition per 4 x 4 joint covariance. Here:

* arcsin is :func:`_asin`, fdlibm's rational approximation written without branches
  (<= 2 ulp from ``numpy.arcsin``), so that LLVM vectorises every loop that calls it:
  libm's scalar ``asin`` is ten times slower than numpy's SIMD one, which it now matches;
* each expected entry is reduced from one row of node values at a time, so nothing of
  size (nodes x nodes) exists and gradients cost one pass instead of five temporaries;
* the 4 x 4 square roots of same-scan pairs are Jacobi eigendecompositions in registers.

Inputs are *scaled* nodes ``u`` in coordinate-major layout (3, M), as built by
``NeuralNetworkKernel._scaled`` (``z = u_a . u_b`` is the kernel's arcsin argument),
per-node quadrature ``weights`` (M,) and ``starts`` (N + 1,), the node offsets of each point.
``scale`` is ``signal_variance * 2 / pi``. Results agree with the numpy path to rounding
(~1e-15; tests/test_expected.py compares them).

Compiled functions are cached on disk (``cache=True``): the first run on a machine compiles
them (seconds, once); later processes load the machine code in milliseconds.
"""

from __future__ import annotations

import math

import numba
import numpy as np

# ``error_model="numpy"``: no ZeroDivisionError checks, which would stop vectorisation.
_jit = numba.njit(cache=True, error_model="numpy")
_inline = numba.njit(cache=True, error_model="numpy", inline="always")

# fdlibm e_asin.c coefficients: asin(x) = x + x R(x^2) on [0, 0.5], R = P/Q.
_PS0 = 1.66666666666666657415e-01
_PS1 = -3.25565818622400915405e-01
_PS2 = 2.01212532134862925881e-01
_PS3 = -4.00555345006794114027e-02
_PS4 = 7.91534994289814532176e-04
_PS5 = 3.47933107596021167570e-05
_QS1 = -2.40339491173441421878e00
_QS2 = 2.02094576023350569471e00
_QS3 = -6.88283971605453293030e-01
_QS4 = 7.70381505559019352791e-02
_PIO2_HI = 1.57079632679489655800e00
_PIO2_LO = 6.12323399573676603587e-17


@_inline
def _asin(x: float) -> float:
    """arcsin(x) for |x| <= 1, branch-free: both of fdlibm's ranges, then a select.

    |x| >= 0.5 uses asin(x) = pi/2 - 2 asin(sqrt((1 - x) / 2)).
    """
    ax = abs(x)
    big = ax >= 0.5
    t = 0.5 * (1.0 - ax) if big else ax * ax
    p = t * (_PS0 + t * (_PS1 + t * (_PS2 + t * (_PS3 + t * (_PS4 + t * _PS5)))))
    q = 1.0 + t * (_QS1 + t * (_QS2 + t * (_QS3 + t * _QS4)))
    r = p / q
    s = math.sqrt(t)
    v = _PIO2_HI - (2.0 * (s + s * r) - _PIO2_LO) if big else ax + ax * r
    return v if x >= 0.0 else -v


@_inline
def _clip(z: float) -> float:
    # Rounding only: |z| < 1 exactly (Cauchy-Schwarz on normalised rows).
    return min(1.0, max(-1.0, z))


@_jit
def asin_array(x: np.ndarray) -> np.ndarray:
    """:func:`_asin` elementwise (for tests)."""
    out = np.empty_like(x)
    for m in range(x.shape[0]):
        out[m] = _asin(x[m])
    return out


@_jit
def nn_matrix(u: np.ndarray, weights: np.ndarray, starts: np.ndarray, scale: float,
              out: np.ndarray) -> None:
    """out[i, j] = out[j, i] = E k(x_i, x_j) for i < j (product rule); diagonal untouched."""
    n = starts.shape[0] - 1
    total = starts[n]
    row = np.empty(total)
    for i in range(n):
        for j in range(i + 1, n):
            out[i, j] = 0.0
        b0 = starts[i + 1]
        # 1-D views of the later nodes: the loop below vectorises only on those (2x).
        u0, u1, u2, wb = u[0, b0:], u[1, b0:], u[2, b0:], weights[b0:]
        for a in range(starts[i], b0):
            x0, x1, x2 = u[0, a], u[1, a], u[2, a]
            for b in range(total - b0):  # one node against every later node
                row[b] = wb[b] * _asin(_clip(x0 * u0[b] + x1 * u1[b] + x2 * u2[b]))
            wa = weights[a] * scale
            for j in range(i + 1, n):
                acc = 0.0
                for b in range(starts[j] - b0, starts[j + 1] - b0):
                    acc += row[b]
                out[i, j] += wa * acc
        for j in range(i + 1, n):
            out[j, i] = out[i, j]


@_inline
def _dz(ua: float, ub: float, hz: float) -> float:
    """dz/dtheta_c = u_c v_c - z (u_c^2 + v_c^2) / 2 (theta_c the log of S_c)."""
    return ua * ub - hz * (ua * ua + ub * ub)


@_jit
def nn_matrix_gradient(u: np.ndarray, weights: np.ndarray, starts: np.ndarray, scale: float,
                       out: np.ndarray) -> None:
    """out[:, i, j] = out[:, j, i] = E dk(x_i, x_j)/dtheta, theta = log(s, bias, wx, wy),
    for i < j; out[0] is the expected kernel itself. Diagonal untouched."""
    n = starts.shape[0] - 1
    total = starts[n]
    rows = np.empty((4, total))
    for i in range(n):
        for p in range(4):
            for j in range(i + 1, n):
                out[p, i, j] = 0.0
        b0 = starts[i + 1]
        u0, u1, u2, wb = u[0, b0:], u[1, b0:], u[2, b0:], weights[b0:]
        for a in range(starts[i], b0):
            x0, x1, x2 = u[0, a], u[1, a], u[2, a]
            for b in range(total - b0):
                y0, y1, y2 = u0[b], u1[b], u2[b]
                z = _clip(x0 * y0 + x1 * y1 + x2 * y2)
                w = wb[b]
                # dk/dz = 1/sqrt(1 - z^2)
                wg = w / math.sqrt(1.0 - z * z)
                hz = 0.5 * z
                rows[0, b] = w * _asin(z)
                rows[1, b] = wg * _dz(x0, y0, hz)
                rows[2, b] = wg * _dz(x1, y1, hz)
                rows[3, b] = wg * _dz(x2, y2, hz)
            wa = weights[a] * scale
            for j in range(i + 1, n):
                for p in range(4):
                    acc = 0.0
                    for b in range(starts[j] - b0, starts[j + 1] - b0):
                        acc += rows[p, b]
                    out[p, i, j] += wa * acc
        for p in range(4):
            for j in range(i + 1, n):
                out[p, j, i] = out[p, i, j]


@_jit
def nn_cross(q: np.ndarray, u: np.ndarray, weights: np.ndarray, starts: np.ndarray,
             scale: float, out: np.ndarray) -> None:
    """out[r, i] = E k(query_r, x_i) for exact queries with scaled rows q (3, Q)."""
    n = starts.shape[0] - 1
    total = starts[n]
    row = np.empty(total)
    u0, u1, u2 = u[0], u[1], u[2]
    for r in range(q.shape[1]):
        x0, x1, x2 = q[0, r], q[1, r], q[2, r]
        for b in range(total):
            row[b] = weights[b] * _asin(_clip(x0 * u0[b] + x1 * u1[b] + x2 * u2[b]))
        for i in range(n):
            acc = 0.0
            for b in range(starts[i], starts[i + 1]):
                acc += row[b]
            out[r, i] = scale * acc


# --------------------------------------------------------------------------- same-scan pairs


@_jit
def sqrt_psd4(s: np.ndarray) -> np.ndarray:
    """R (4, 4, P) with R R' = s for P symmetric 4 x 4 matrices s (4, 4, P), pair-minor.

    As ``expected.sqrt_psd``: cyclic Jacobi rotations (to rounding) give the eigenpairs,
    eigenvalues below 1e-13 of the largest are zeroed and R = V sqrt(L). Every rotation is
    applied to all P matrices in one loop over the last axis, which vectorises. Eigenvector
    signs and order may differ from LAPACK's, which leaves the tensor Gauss-Hermite rule
    unchanged: its unit nodes are symmetric under every coordinate reflection and
    permutation, with equal weights (for distinct eigenvalues; with a repeated one, any
    rule in its eigenspace is as valid). ``s`` is overwritten.
    """
    size = s.shape[2]
    vec = np.zeros((4, 4, size))
    for r in range(4):
        vec[r, r, :] = 1.0
    tiny = np.empty(size)
    for _sweep in range(30):  # converges in 4-6 sweeps
        # Off-diagonal entries below 1e-18 of the largest diagonal one move no eigenvalue by
        # more than that (eigenvalues under 1e-13 of it are zeroed anyway): treated as 0.
        busy = False
        for m in range(size):
            top = max(max(abs(s[0, 0, m]), abs(s[1, 1, m])),
                      max(abs(s[2, 2, m]), abs(s[3, 3, m])))
            tiny[m] = 1e-18 * top
            for p in range(3):
                for q in range(p + 1, 4):
                    if abs(s[p, q, m]) > tiny[m]:
                        busy = True
        if not busy:
            break
        for p in range(3):
            for q in range(p + 1, 4):
                for m in range(size):
                    apq = s[p, q, m]
                    rotate = abs(apq) > tiny[m]
                    theta = (s[q, q, m] - s[p, p, m]) / (2.0 * apq if rotate else 1.0)
                    t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                    t = -t if theta < 0.0 else t
                    t = t if rotate else 0.0
                    c = 1.0 / math.sqrt(t * t + 1.0)
                    sn = t * c
                    for k in range(4):
                        skp, skq = s[k, p, m], s[k, q, m]
                        s[k, p, m] = c * skp - sn * skq
                        s[k, q, m] = sn * skp + c * skq
                    for k in range(4):
                        spk, sqk = s[p, k, m], s[q, k, m]
                        s[p, k, m] = c * spk - sn * sqk
                        s[q, k, m] = sn * spk + c * sqk
                    for k in range(4):
                        vkp, vkq = vec[k, p, m], vec[k, q, m]
                        vec[k, p, m] = c * vkp - sn * vkq
                        vec[k, q, m] = sn * vkp + c * vkq
    out = np.empty((4, 4, size))
    for m in range(size):
        top = max(max(s[0, 0, m], s[1, 1, m]), max(s[2, 2, m], s[3, 3, m]))
        for c in range(4):
            lam = s[c, c, m]
            root = 0.0 if lam < 1e-13 * top else math.sqrt(lam)
            for r in range(4):
                out[r, c, m] = vec[r, c, m] * root
    return out


@_jit
def correlated_nodes(means: np.ndarray, covariances: np.ndarray, pose_factors: np.ndarray,
                     i: np.ndarray, j: np.ndarray, unit: np.ndarray) -> np.ndarray:
    """(4, P L) nodes of the joint 4-D rule of each pair (x_i then x_j), pair-major.

    The joint covariance is ``[[S_i, A_i A_j'], [A_j A_i', S_j]]`` (S symmetrised), its
    root :func:`sqrt_psd4`; nodes are ``mean + R unit_k``.
    """
    size = unit.shape[0]
    pairs = i.shape[0]
    joint = np.empty((4, 4, pairs))
    for p in range(pairs):
        a, b = i[p], j[p]
        for r in range(2):
            for c in range(2):
                joint[r, c, p] = 0.5 * (covariances[a, r, c] + covariances[a, c, r])
                joint[2 + r, 2 + c, p] = 0.5 * (covariances[b, r, c] + covariances[b, c, r])
                cross = 0.0
                for k in range(3):
                    cross += pose_factors[a, r, k] * pose_factors[b, c, k]
                joint[r, 2 + c, p] = cross
                joint[2 + c, r, p] = cross
    factor = sqrt_psd4(joint)
    nodes = np.empty((4, pairs * size))
    for p in range(pairs):
        a, b = i[p], j[p]
        base = p * size
        for r in range(4):
            mu = means[a, r] if r < 2 else means[b, r - 2]
            f0, f1, f2, f3 = factor[r, 0, p], factor[r, 1, p], factor[r, 2, p], factor[r, 3, p]
            for m in range(size):
                nodes[r, base + m] = mu + (f0 * unit[m, 0] + f1 * unit[m, 1]
                                           + f2 * unit[m, 2] + f3 * unit[m, 3])
    return nodes


@_inline
def _scaled_row(x: float, y: float, root: np.ndarray) -> tuple[float, float, float]:
    """u = (1, x, y) sqrt(2 S) / sqrt(1 + 2 (1, x, y)' S (1, x, y)), as ``_scaled``."""
    u1 = x * root[1]
    u2 = y * root[2]
    inv = 1.0 / math.sqrt(u1 * u1 + u2 * u2 + (1.0 + root[0] * root[0]))
    return inv * root[0], u1 * inv, u2 * inv


@_jit
def nn_node_pairs(nodes: np.ndarray, weights: np.ndarray, root: np.ndarray, scale: float,
                  out: np.ndarray, with_gradient: bool) -> None:
    """out[:, p] = sum_k w_k (k, dk/dtheta)(a_pk, b_pk) over each pair's L nodes.

    ``nodes`` as from :func:`correlated_nodes`; out (4, P) with gradients (row 0 the
    value), else (1, P).
    """
    size = weights.shape[0]
    total = nodes.shape[1]
    rows = np.empty((4 if with_gradient else 1, total))
    for m in range(total):  # vectorised over every node of every pair
        a0, a1, a2 = _scaled_row(nodes[0, m], nodes[1, m], root)
        b0, b1, b2 = _scaled_row(nodes[2, m], nodes[3, m], root)
        z = _clip(a0 * b0 + a1 * b1 + a2 * b2)
        w = weights[m % size]
        rows[0, m] = w * _asin(z)
        if with_gradient:
            wg = w / math.sqrt(1.0 - z * z)
            hz = 0.5 * z
            rows[1, m] = wg * _dz(a0, b0, hz)
            rows[2, m] = wg * _dz(a1, b1, hz)
            rows[3, m] = wg * _dz(a2, b2, hz)
    for p in range(out.shape[1]):
        for r in range(rows.shape[0]):
            acc = 0.0
            for m in range(p * size, (p + 1) * size):
                acc += rows[r, m]
            out[r, p] = scale * acc
