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
# ``nogil``: callers may run them on threads.
_jit = numba.njit(cache=True, error_model="numpy", nogil=True)
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


@_inline
def _rot(app, aqq, apq, x1p, x1q, x2p, x2q, v0p, v0q, v1p, v1q, v2p, v2q, v3p, v3q):
    """One Jacobi rotation zeroing a_pq (Numerical Recipes' update): x1, x2 are the other
    two rows of columns p, q, v the eigenvector columns p, q."""
    theta = (aqq - app) / (2.0 * apq)
    t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
    t = -t if theta < 0.0 else t
    c = 1.0 / math.sqrt(t * t + 1.0)
    s = t * c
    tau = s / (1.0 + c)
    return (app - t * apq, aqq + t * apq,
            x1p - s * (x1q + tau * x1p), x1q + s * (x1p - tau * x1q),
            x2p - s * (x2q + tau * x2p), x2q + s * (x2p - tau * x2q),
            v0p - s * (v0q + tau * v0p), v0q + s * (v0p - tau * v0q),
            v1p - s * (v1q + tau * v1p), v1q + s * (v1p - tau * v1q),
            v2p - s * (v2q + tau * v2p), v2q + s * (v2p - tau * v2q),
            v3p - s * (v3q + tau * v3p), v3q + s * (v3p - tau * v3q))


@_jit
def sqrt_psd4(s: np.ndarray) -> np.ndarray:
    """R (4, 4, P) with R R' = s for P symmetric 4 x 4 matrices s (4, 4, P), pair-minor.

    As ``expected.sqrt_psd``: cyclic Jacobi rotations (to rounding) give the eigenpairs,
    eigenvalues below 1e-13 of the largest are zeroed and R = V sqrt(L). Each matrix is
    diagonalised in registers (its 10 entries and 16 eigenvector entries are scalars).
    Eigenvector signs and order may differ from LAPACK's, which leaves the tensor
    Gauss-Hermite rule unchanged: its unit nodes are symmetric under every coordinate
    reflection and permutation, with equal weights (for distinct eigenvalues; with a
    repeated one, any rule in its eigenspace is as valid).
    """
    size = s.shape[2]
    out = np.empty((4, 4, size))
    for m in range(size):
        a00, a11, a22, a33 = s[0, 0, m], s[1, 1, m], s[2, 2, m], s[3, 3, m]
        a01, a02, a03 = s[0, 1, m], s[0, 2, m], s[0, 3, m]
        a12, a13, a23 = s[1, 2, m], s[1, 3, m], s[2, 3, m]
        v00, v01, v02, v03 = 1.0, 0.0, 0.0, 0.0
        v10, v11, v12, v13 = 0.0, 1.0, 0.0, 0.0
        v20, v21, v22, v23 = 0.0, 0.0, 1.0, 0.0
        v30, v31, v32, v33 = 0.0, 0.0, 0.0, 1.0
        for _sweep in range(30):  # converges in 4-6 sweeps
            # Off-diagonal entries below 1e-18 of the largest diagonal one move no
            # eigenvalue by more than that (those under 1e-13 of it are zeroed anyway).
            tiny = 1e-18 * max(max(abs(a00), abs(a11)), max(abs(a22), abs(a33)))
            if max(max(max(abs(a01), abs(a02)), max(abs(a03), abs(a12))),
                   max(abs(a13), abs(a23))) <= tiny:
                break
            if abs(a01) > tiny:
                (a00, a11, a02, a12, a03, a13, v00, v01, v10, v11, v20, v21, v30,
                 v31) = _rot(a00, a11, a01, a02, a12, a03, a13, v00, v01, v10, v11, v20,
                             v21, v30, v31)
                a01 = 0.0
            if abs(a02) > tiny:
                (a00, a22, a01, a12, a03, a23, v00, v02, v10, v12, v20, v22, v30,
                 v32) = _rot(a00, a22, a02, a01, a12, a03, a23, v00, v02, v10, v12, v20,
                             v22, v30, v32)
                a02 = 0.0
            if abs(a03) > tiny:
                (a00, a33, a01, a13, a02, a23, v00, v03, v10, v13, v20, v23, v30,
                 v33) = _rot(a00, a33, a03, a01, a13, a02, a23, v00, v03, v10, v13, v20,
                             v23, v30, v33)
                a03 = 0.0
            if abs(a12) > tiny:
                (a11, a22, a01, a02, a13, a23, v01, v02, v11, v12, v21, v22, v31,
                 v32) = _rot(a11, a22, a12, a01, a02, a13, a23, v01, v02, v11, v12, v21,
                             v22, v31, v32)
                a12 = 0.0
            if abs(a13) > tiny:
                (a11, a33, a01, a03, a12, a23, v01, v03, v11, v13, v21, v23, v31,
                 v33) = _rot(a11, a33, a13, a01, a03, a12, a23, v01, v03, v11, v13, v21,
                             v23, v31, v33)
                a13 = 0.0
            if abs(a23) > tiny:
                (a22, a33, a02, a03, a12, a13, v02, v03, v12, v13, v22, v23, v32,
                 v33) = _rot(a22, a33, a23, a02, a03, a12, a13, v02, v03, v12, v13, v22,
                             v23, v32, v33)
                a23 = 0.0
        top = max(max(a00, a11), max(a22, a33))
        r0 = 0.0 if a00 < 1e-13 * top else math.sqrt(a00)
        r1 = 0.0 if a11 < 1e-13 * top else math.sqrt(a11)
        r2 = 0.0 if a22 < 1e-13 * top else math.sqrt(a22)
        r3 = 0.0 if a33 < 1e-13 * top else math.sqrt(a33)
        for r, (c0, c1, c2, c3) in enumerate(((v00, v01, v02, v03), (v10, v11, v12, v13),
                                               (v20, v21, v22, v23), (v30, v31, v32, v33))):
            out[r, 0, m] = c0 * r0
            out[r, 1, m] = c1 * r1
            out[r, 2, m] = c2 * r2
            out[r, 3, m] = c3 * r3
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
