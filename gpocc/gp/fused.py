"""Compiled (numba) loops for the expected neural-network kernel: quadrature and arcsin fused.

The numpy path of :mod:`gpocc.gp.expected` builds node-pair matrices of arcsin values (and,
for gradients, four of them), then reduces them with the quadrature weights; same-scan
pairs need a batched 4 x 4 Cholesky factor of each joint covariance. Here:

* arcsin is :func:`_asin`, fdlibm's rational approximation written without branches
  (<= 2 ulp from ``numpy.arcsin``), so that LLVM vectorises every loop that calls it:
  libm's scalar ``asin`` is ten times slower than numpy's SIMD one, which it now matches;
* each expected entry is reduced from one row of node values at a time, so nothing of
  size (nodes x nodes) exists and gradients cost one pass instead of five temporaries;
* the 4 x 4 roots of same-scan pairs are Cholesky factors computed in registers, and the
  pairs themselves are listed without (N, N) masks.

Inputs are *scaled* nodes ``u`` in coordinate-major layout (3, M), as built by
``NeuralNetworkKernel._scaled`` (``z = u_a . u_b`` is the kernel's arcsin argument),
per-node quadrature ``weights`` (M,) and ``starts`` (N + 1,), the node offsets of each point.
``scale`` is ``signal_variance * 2 / pi``. Where every point has the same rule of L nodes
(``*_uniform``), the columns are node-major instead (node k of point i in column k N + i)
and ``weights`` is the rule's (L,). Results agree with the numpy path to rounding
(~1e-15; tests/test_expected.py compares them).

Compiled functions are cached on disk (``cache=True``): the first run on a machine compiles
them (seconds, once); later processes load the machine code in milliseconds.
"""

from __future__ import annotations

import math

import numba
import numpy as np

# ``error_model="numpy"``: no ZeroDivisionError checks, which would stop vectorisation.
# ``nogil``: callers may run them on threads. ``fastmath={"contract"}``: a * b + c may
# become one fused multiply-add (one rounding instead of two); nothing else of fast-math
# (no reassociation, no approximate division or square root). It makes the arcsin 35%
# faster (5.4 -> 3.5 ns a value, still <= 2 ulp from numpy's). A fused a * b - c * d no
# longer cancels exactly when the two products are equal; every such difference here is
# guarded against tiny negative results (_clip, the pivot threshold of _cholesky4, the
# zeroed small eigenvalue of gaussian_nodes_2d).
_FAST = {"contract"}
_jit = numba.njit(cache=True, error_model="numpy", nogil=True, fastmath=_FAST)
_inline = numba.njit(cache=True, error_model="numpy", inline="always", fastmath=_FAST)

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
def gaussian_nodes_2d(means: np.ndarray, covariances: np.ndarray, unit: np.ndarray
                      ) -> np.ndarray:
    """(2, N L) nodes ``mean_i + R_i unit_k`` of N 2-D Gaussians, point-major (node k of
    point i in column i L + k), coordinate-major rows.

    R_i is ``gpocc.gp.expected._sqrt_psd2``'s closed-form root, the same formulas in
    the same order: the node sets equal the numpy path's to round-off. A map anchor's
    128 points took 0.55 ms through numpy's small-array calls; here 0.07 ms.
    """
    n = means.shape[0]
    size = unit.shape[0]
    out = np.empty((2, n * size))
    for i in range(n):
        a, c = covariances[i, 0, 0], covariances[i, 1, 1]
        b = 0.5 * (covariances[i, 0, 1] + covariances[i, 1, 0])
        half = 0.5 * (a - c)
        radius = math.hypot(half, b)
        high = max(0.5 * (a + c) + radius, 0.0)
        low = (a * c - b * b) / high if high > 0.0 else 0.0
        if low < 1e-13 * high:
            low = 0.0
        angle = 0.5 * math.atan2(b, half)
        cos, sin = math.cos(angle), math.sin(angle)
        root_low, root_high = math.sqrt(low), math.sqrt(high)
        r00, r01 = -sin * root_low, cos * root_high
        r10, r11 = cos * root_low, sin * root_high
        mx, my = means[i, 0], means[i, 1]
        for k in range(size):
            out[0, i * size + k] = mx + (r00 * unit[k, 0] + r01 * unit[k, 1])
            out[1, i * size + k] = my + (r10 * unit[k, 0] + r11 * unit[k, 1])
    return out


@_jit
def nn_matrix(u: np.ndarray, weights: np.ndarray, starts: np.ndarray, scale: float,
              out: np.ndarray) -> None:
    """out[i, j] = out[j, i] = E k(x_i, x_j) for i < j (product rule); diagonal untouched.

    Point i's nodes are summed into one row against every later node first, and that row
    is reduced per point j once: reducing after every node (four small sums per pair and
    node) took a quarter of the time.
    """
    n = starts.shape[0] - 1
    total = starts[n]
    acc = np.empty(total)
    for i in range(n):
        b0 = starts[i + 1]
        later = total - b0
        # 1-D views of the later nodes: the loop below vectorises only on those (2x).
        u0, u1, u2, wb = u[0, b0:], u[1, b0:], u[2, b0:], weights[b0:]
        for b in range(later):
            acc[b] = 0.0
        for a in range(starts[i], b0):
            x0, x1, x2 = u[0, a], u[1, a], u[2, a]
            wa = weights[a] * scale
            for b in range(later):  # one node against every later node
                acc[b] += wa * _asin(_clip(x0 * u0[b] + x1 * u1[b] + x2 * u2[b]))
        for j in range(i + 1, n):
            value = 0.0
            for b in range(starts[j] - b0, starts[j + 1] - b0):
                value += acc[b] * wb[b]
            out[i, j] = value
            out[j, i] = value


@_jit
def nn_matrix_uniform(u: np.ndarray, weights: np.ndarray, scale: float, out: np.ndarray
                      ) -> None:
    """:func:`nn_matrix` for N points that share one rule of L nodes: ``u`` (3, L N)
    node-major (node k of point i in column k N + i), ``weights`` (L,). Writes both
    triangles and leaves the diagonal untouched. Same sums in the same order, so the same
    values to the last bit.

    Each row of point i is reduced over the later points' node k in one contiguous pass,
    and the rows of the L node slots are combined point by point without a strided
    reduction; at level 2 point i's four nodes are held in registers through each pass
    (a map anchor's 128 points: 0.86 -> 0.71 ms).
    """
    size = weights.shape[0]
    n = u.shape[1] // size
    acc = np.empty((size, n))
    for i in range(n):
        if size == 4:
            p0, p1, p2 = u[0, i], u[1, i], u[2, i]
            q0, q1, q2 = u[0, n + i], u[1, n + i], u[2, n + i]
            r0, r1, r2 = u[0, 2 * n + i], u[1, 2 * n + i], u[2, 2 * n + i]
            s0, s1, s2 = u[0, 3 * n + i], u[1, 3 * n + i], u[2, 3 * n + i]
            wp, wq = weights[0] * scale, weights[1] * scale
            wr, ws = weights[2] * scale, weights[3] * scale
            for slot in range(4):
                lo, hi = slot * n + i + 1, (slot + 1) * n
                v0, v1, v2, row = u[0, lo:hi], u[1, lo:hi], u[2, lo:hi], acc[slot, i + 1:]
                for j in range(n - i - 1):
                    y0, y1, y2 = v0[j], v1[j], v2[j]
                    t = 0.0
                    t += wp * _asin(_clip(p0 * y0 + p1 * y1 + p2 * y2))
                    t += wq * _asin(_clip(q0 * y0 + q1 * y1 + q2 * y2))
                    t += wr * _asin(_clip(r0 * y0 + r1 * y1 + r2 * y2))
                    t += ws * _asin(_clip(s0 * y0 + s1 * y1 + s2 * y2))
                    row[j] = t
        else:
            for slot in range(size):
                for j in range(i + 1, n):
                    acc[slot, j] = 0.0
            for k in range(size):
                x0, x1, x2 = u[0, k * n + i], u[1, k * n + i], u[2, k * n + i]
                wa = weights[k] * scale
                for slot in range(size):
                    lo, hi = slot * n + i + 1, (slot + 1) * n
                    v0, v1, v2, row = u[0, lo:hi], u[1, lo:hi], u[2, lo:hi], acc[slot, i + 1:]
                    for j in range(n - i - 1):
                        row[j] += wa * _asin(_clip(x0 * v0[j] + x1 * v1[j] + x2 * v2[j]))
        for j in range(i + 1, n):
            value = 0.0
            for slot in range(size):
                value += acc[slot, j] * weights[slot]
            out[i, j] = value
    for i in range(n):  # the lower triangle once, row by row
        for j in range(i):
            out[i, j] = out[j, i]


@_inline
def _dz(ua: float, ub: float, hz: float) -> float:
    """dz/dtheta_c = u_c v_c - z (u_c^2 + v_c^2) / 2 (theta_c the log of S_c)."""
    return ua * ub - hz * (ua * ua + ub * ub)


@_inline
def _dz_scale(a0: float, a1: float, a2: float, b0: float, b1: float, b2: float, z: float,
              da1: float, da2: float, db1: float, db2: float) -> float:
    """dz/dlog g: both nodes move away from their means as sqrt(g) (dx/dlog g = (x - m)/2).

    With scaled rows ``a = p / n`` (p = (1, x, y) sqrt(2 S), n = sqrt(1 + |p|^2)) and
    ``da = root (x - m) / n`` (the node's scaled offset from its mean), dz/dp_a =
    (b - z a) / n, so dz/dlog g = ((b - z a) . da + (a - z b) . db) / 2 over x, y.
    """
    return 0.5 * ((b1 - z * a1) * da1 + (b2 - z * a2) * da2
                  + (a1 - z * b1) * db1 + (a2 - z * b2) * db2)


@_jit
def nn_matrix_gradient(u: np.ndarray, weights: np.ndarray, starts: np.ndarray, scale: float,
                       out: np.ndarray, offsets: np.ndarray, with_scale: bool) -> None:
    """out[:, i, j] = out[:, j, i] = E dk(x_i, x_j)/dtheta, theta = log(s, bias, wx, wy),
    for i < j; out[0] is the expected kernel itself. Diagonal untouched.

    ``with_scale``: out[4] is also the derivative in log g of the input-noise scale (every
    node at ``mean + sqrt(g) offset``), from ``offsets`` (2, M), each node's scaled offset
    from its point's mean (see :func:`_dz_scale`); otherwise ``offsets`` is not read.
    Rows are accumulated over point i's nodes and reduced once, as in :func:`nn_matrix`.
    """
    n = starts.shape[0] - 1
    total = starts[n]
    count = 5 if with_scale else 4
    acc = np.empty((count, total))
    for i in range(n):
        b0 = starts[i + 1]
        later = total - b0
        u0, u1, u2 = u[0, b0:], u[1, b0:], u[2, b0:]
        a0, a1, a2, a3 = acc[0], acc[1], acc[2], acc[3]
        for p in range(count):
            for b in range(later):
                acc[p, b] = 0.0
        for a in range(starts[i], b0):
            x0, x1, x2 = u[0, a], u[1, a], u[2, a]
            wa = weights[a] * scale
            for b in range(later):
                y0, y1, y2 = u0[b], u1[b], u2[b]
                z = _clip(x0 * y0 + x1 * y1 + x2 * y2)
                # dk/dz = 1/sqrt(1 - z^2)
                wg = wa / math.sqrt(1.0 - z * z)
                hz = 0.5 * z
                a0[b] += wa * _asin(z)
                a1[b] += wg * _dz(x0, y0, hz)
                a2[b] += wg * _dz(x1, y1, hz)
                a3[b] += wg * _dz(x2, y2, hz)
            if with_scale:  # a loop of its own keeps the one above free of branches
                da1, da2 = offsets[0, a], offsets[1, a]
                o1, o2 = offsets[0, b0:], offsets[1, b0:]
                a4 = acc[4]
                for b in range(later):
                    y0, y1, y2 = u0[b], u1[b], u2[b]
                    z = _clip(x0 * y0 + x1 * y1 + x2 * y2)
                    a4[b] += wa / math.sqrt(1.0 - z * z) * _dz_scale(
                        x0, x1, x2, y0, y1, y2, z, da1, da2, o1[b], o2[b])
        for j in range(i + 1, n):
            for p in range(count):
                value = 0.0
                for b in range(starts[j] - b0, starts[j + 1] - b0):
                    value += acc[p, b] * weights[b0 + b]
                out[p, i, j] = value
                out[p, j, i] = value


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


@_jit
def nn_cross_uniform(q: np.ndarray, u: np.ndarray, weights: np.ndarray, scale: float,
                     out: np.ndarray) -> None:
    """out[r, i] = E k(query_r, x_i), as :func:`nn_cross`, when all N points share one rule
    of L nodes: ``u`` (3, L N) node-major (node k of point i in column k N + i),
    ``weights`` (L,).

    Each node's loop runs over the points with nothing to reduce after it: the point-major
    loop summed each point's L values one by one, which took as long as their arcsin
    values (a map anchor's 341 queries and 128 points at level 2: 1.39 -> 0.60 ms).
    """
    size = weights.shape[0]
    n = u.shape[1] // size
    if size == 4:  # level 2, the default: the four nodes summed in registers
        w0, w1, w2, w3 = weights[0], weights[1], weights[2], weights[3]
        a0, a1, a2 = u[0, :n], u[1, :n], u[2, :n]
        b0, b1, b2 = u[0, n:2 * n], u[1, n:2 * n], u[2, n:2 * n]
        c0, c1, c2 = u[0, 2 * n:3 * n], u[1, 2 * n:3 * n], u[2, 2 * n:3 * n]
        d0, d1, d2 = u[0, 3 * n:], u[1, 3 * n:], u[2, 3 * n:]
        for r in range(q.shape[1]):
            x0, x1, x2 = q[0, r], q[1, r], q[2, r]
            row = out[r]
            for i in range(n):
                row[i] = scale * (w0 * _asin(_clip(x0 * a0[i] + x1 * a1[i] + x2 * a2[i]))
                                  + w1 * _asin(_clip(x0 * b0[i] + x1 * b1[i] + x2 * b2[i]))
                                  + w2 * _asin(_clip(x0 * c0[i] + x1 * c1[i] + x2 * c2[i]))
                                  + w3 * _asin(_clip(x0 * d0[i] + x1 * d1[i] + x2 * d2[i])))
        return
    for r in range(q.shape[1]):
        x0, x1, x2 = q[0, r], q[1, r], q[2, r]
        row = out[r]
        for i in range(n):
            row[i] = 0.0
        for k in range(size):
            wk = weights[k]
            v0, v1, v2 = u[0, k * n:(k + 1) * n], u[1, k * n:(k + 1) * n], u[2, k * n:(k + 1) * n]
            for i in range(n):
                row[i] += wk * _asin(_clip(x0 * v0[i] + x1 * v1[i] + x2 * v2[i]))
        for i in range(n):
            row[i] *= scale


# --------------------------------------------------------------------------- same-scan pairs


@_inline
def _cholesky4(a00: float, a10: float, a11: float, a20: float, a21: float, a22: float,
               a30: float, a31: float, a32: float, a33: float
               ) -> tuple[float, float, float, float, float, float, float, float, float, float]:
    """The lower Cholesky factor (l00, l10, l11, l20, l21, l22, l30, l31, l32, l33) of one
    symmetric positive semi-definite 4 x 4 matrix given by its lower triangle.

    A pivot below 1e-10 of the largest diagonal entry is rounding noise of a singular
    matrix: its column is zero (for a PSD matrix the entries below it vanish with it).
    """
    tiny = 1e-10 * max(max(a00, a11), max(a22, a33))
    l00 = l10 = l20 = l30 = l11 = l21 = l31 = l22 = l32 = l33 = 0.0
    if a00 > tiny:
        l00 = math.sqrt(a00)
        l10, l20, l30 = a10 / l00, a20 / l00, a30 / l00
    d = a11 - l10 * l10
    if d > tiny:
        l11 = math.sqrt(d)
        l21 = (a21 - l20 * l10) / l11
        l31 = (a31 - l30 * l10) / l11
    d = a22 - l20 * l20 - l21 * l21
    if d > tiny:
        l22 = math.sqrt(d)
        l32 = (a32 - l30 * l20 - l31 * l21) / l22
    d = a33 - l30 * l30 - l31 * l31 - l32 * l32
    if d > tiny:
        l33 = math.sqrt(d)
    return l00, l10, l11, l20, l21, l22, l30, l31, l32, l33


@_jit
def cholesky_psd4(s: np.ndarray) -> np.ndarray:
    """Lower-triangular R (4, 4, P) with R R' = s for P symmetric positive semi-definite
    4 x 4 matrices s (4, 4, P), pair-minor: ``expected.cholesky_psd`` in registers
    (:func:`_cholesky4`, the off-diagonal entries symmetrised). :func:`correlated_nodes`
    calls :func:`_cholesky4` itself; this array form is how the tests check it."""
    size = s.shape[2]
    out = np.zeros((4, 4, size))
    for m in range(size):
        l00, l10, l11, l20, l21, l22, l30, l31, l32, l33 = _cholesky4(
            s[0, 0, m], 0.5 * (s[1, 0, m] + s[0, 1, m]), s[1, 1, m],
            0.5 * (s[2, 0, m] + s[0, 2, m]), 0.5 * (s[2, 1, m] + s[1, 2, m]), s[2, 2, m],
            0.5 * (s[3, 0, m] + s[0, 3, m]), 0.5 * (s[3, 1, m] + s[1, 3, m]),
            0.5 * (s[3, 2, m] + s[2, 3, m]), s[3, 3, m])
        out[0, 0, m] = l00
        out[1, 0, m], out[1, 1, m] = l10, l11
        out[2, 0, m], out[2, 1, m], out[2, 2, m] = l20, l21, l22
        out[3, 0, m], out[3, 1, m], out[3, 2, m], out[3, 3, m] = l30, l31, l32, l33
    return out


@_inline
def _pose_cross(pose_factors: np.ndarray, a: int, b: int, r: int, c: int) -> float:
    """Cov(x_a[r], x_b[c]) = (A_a A_b')[r, c] of two points of one scan."""
    return (pose_factors[a, r, 0] * pose_factors[b, c, 0]
            + pose_factors[a, r, 1] * pose_factors[b, c, 1]
            + pose_factors[a, r, 2] * pose_factors[b, c, 2])


@_jit
def correlated_nodes(means: np.ndarray, covariances: np.ndarray, pose_factors: np.ndarray,
                     i: np.ndarray, j: np.ndarray, unit: np.ndarray,
                     input_scale: float = 1.0) -> np.ndarray:
    """(4, P L) nodes of the joint 4-D rule of each pair (x_i then x_j), pair-major.

    The joint covariance is ``[[S_i, A_i A_j'], [A_j A_i', S_j]]`` (S symmetrised) times
    ``input_scale``, its root :func:`_cholesky4` (times the scale's square root); nodes
    are ``mean + R unit_k``. Each pair's covariance and root stay in registers: building
    them as (4, 4, P) arrays first took 40% of the same-scan pairs' time.
    """
    size = unit.shape[0]
    pairs = i.shape[0]
    root_scale = math.sqrt(input_scale)
    nodes = np.empty((4, pairs * size))
    n0, n1, n2, n3 = nodes[0], nodes[1], nodes[2], nodes[3]
    columns = np.ascontiguousarray(unit.T)
    u0, u1, u2, u3 = columns[0], columns[1], columns[2], columns[3]
    for p in range(pairs):
        a, b = i[p], j[p]
        l00, l10, l11, l20, l21, l22, l30, l31, l32, l33 = _cholesky4(
            covariances[a, 0, 0], 0.5 * (covariances[a, 1, 0] + covariances[a, 0, 1]),
            covariances[a, 1, 1],
            _pose_cross(pose_factors, a, b, 0, 0), _pose_cross(pose_factors, a, b, 1, 0),
            covariances[b, 0, 0],
            _pose_cross(pose_factors, a, b, 0, 1), _pose_cross(pose_factors, a, b, 1, 1),
            0.5 * (covariances[b, 1, 0] + covariances[b, 0, 1]), covariances[b, 1, 1])
        l00, l10, l11 = l00 * root_scale, l10 * root_scale, l11 * root_scale
        l20, l21, l22 = l20 * root_scale, l21 * root_scale, l22 * root_scale
        l30, l31 = l30 * root_scale, l31 * root_scale
        l32, l33 = l32 * root_scale, l33 * root_scale
        ma0, ma1, mb0, mb1 = means[a, 0], means[a, 1], means[b, 0], means[b, 1]
        base = p * size
        for m in range(size):
            n0[base + m] = ma0 + l00 * u0[m]
            n1[base + m] = ma1 + (l10 * u0[m] + l11 * u1[m])
            n2[base + m] = mb0 + (l20 * u0[m] + l21 * u1[m] + l22 * u2[m])
            n3[base + m] = mb1 + (l30 * u0[m] + l31 * u1[m] + l32 * u2[m] + l33 * u3[m])
    return nodes


@_inline
def _scaled_row(x: float, y: float, root: np.ndarray) -> tuple[float, float, float, float]:
    """u = (1, x, y) sqrt(2 S) / sqrt(1 + 2 (1, x, y)' S (1, x, y)), as ``_scaled``, and
    the normaliser 1 / sqrt(...)."""
    u1 = x * root[1]
    u2 = y * root[2]
    inv = 1.0 / math.sqrt(u1 * u1 + u2 * u2 + (1.0 + root[0] * root[0]))
    return inv * root[0], u1 * inv, u2 * inv, inv


@_jit
def nn_node_pairs(nodes: np.ndarray, weights: np.ndarray, root: np.ndarray, scale: float,
                  out: np.ndarray, with_gradient: bool, centres: np.ndarray,
                  with_scale: bool) -> None:
    """out[:, p] = sum_k w_k (k, dk/dtheta)(a_pk, b_pk) over each pair's L nodes.

    ``nodes`` as from :func:`correlated_nodes`; out (4, P) with gradients (row 0 the
    value), else (1, P); with ``with_scale`` (gradients only) out (5, P), row 4 the
    derivative in log g (:func:`_dz_scale`), ``centres`` (4, P) the two means of each pair.
    Each case has a loop of its own without branches, so that all of them vectorise.
    """
    size = weights.shape[0]
    total = nodes.shape[1]
    count = (5 if with_scale else 4) if with_gradient else 1
    rows = np.empty((count, total))
    n0, n1, n2, n3 = nodes[0], nodes[1], nodes[2], nodes[3]
    if not with_gradient:
        values = rows[0]
        for m in range(total):  # vectorised over every node of every pair
            a0, a1, a2, _ = _scaled_row(n0[m], n1[m], root)
            b0, b1, b2, _ = _scaled_row(n2[m], n3[m], root)
            values[m] = _asin(_clip(a0 * b0 + a1 * b1 + a2 * b2))
    else:
        r0, r1, r2, r3 = rows[0], rows[1], rows[2], rows[3]
        for m in range(total):
            a0, a1, a2, _ = _scaled_row(n0[m], n1[m], root)
            b0, b1, b2, _ = _scaled_row(n2[m], n3[m], root)
            z = _clip(a0 * b0 + a1 * b1 + a2 * b2)
            slope = 1.0 / math.sqrt(1.0 - z * z)  # dk/dz
            hz = 0.5 * z
            r0[m] = _asin(z)
            r1[m] = slope * _dz(a0, b0, hz)
            r2[m] = slope * _dz(a1, b1, hz)
            r3[m] = slope * _dz(a2, b2, hz)
        if with_scale:
            # Each node's offset from its pair's means, so that the loop below is flat.
            offsets = np.empty((4, total))
            for p in range(total // size):
                for m in range(p * size, (p + 1) * size):
                    offsets[0, m] = n0[m] - centres[0, p]
                    offsets[1, m] = n1[m] - centres[1, p]
                    offsets[2, m] = n2[m] - centres[2, p]
                    offsets[3, m] = n3[m] - centres[3, p]
            r4, d0, d1, d2, d3 = rows[4], offsets[0], offsets[1], offsets[2], offsets[3]
            for m in range(total):
                a0, a1, a2, ia = _scaled_row(n0[m], n1[m], root)
                b0, b1, b2, ib = _scaled_row(n2[m], n3[m], root)
                z = _clip(a0 * b0 + a1 * b1 + a2 * b2)
                r4[m] = _dz_scale(a0, a1, a2, b0, b1, b2, z,
                                  root[1] * d0[m] * ia, root[2] * d1[m] * ia,
                                  root[1] * d2[m] * ib, root[2] * d3[m] * ib
                                  ) / math.sqrt(1.0 - z * z)
    for p in range(out.shape[1]):
        for r in range(count):
            acc = 0.0
            for k in range(size):
                acc += weights[k] * rows[r, p * size + k]
            out[r, p] = scale * acc


# Pairs per batch of :func:`nn_same_scan_pairs`: their nodes (4 x 16 float64 per pair at
# level 2) stay in cache.
_PAIR_BATCH = 256


@_jit
def nn_same_scan_pairs(means: np.ndarray, covariances: np.ndarray, pose_factors: np.ndarray,
                       i: np.ndarray, j: np.ndarray, unit: np.ndarray, weights: np.ndarray,
                       root: np.ndarray, scale: float, input_scale: float, out: np.ndarray,
                       with_gradient: bool, with_scale: bool) -> None:
    """out[:, p]: the expected kernel (and gradients, and with ``with_scale`` the
    derivative in log g) of same-scan pair (i[p], j[p]) under its joint 4-D rule:
    :func:`correlated_nodes` and :func:`nn_node_pairs` in batches.

    The nodes are rebuilt on every call rather than kept: a batch's Cholesky roots and nodes
    cost less than a third of its arcsin values, and a map's local problems never repeat.
    """
    pairs = i.shape[0]
    centres = np.empty((4, _PAIR_BATCH))
    for lo in range(0, pairs, _PAIR_BATCH):
        hi = min(pairs, lo + _PAIR_BATCH)
        nodes = correlated_nodes(means, covariances, pose_factors, i[lo:hi], j[lo:hi], unit,
                                 input_scale)
        if with_scale:
            for p in range(hi - lo):
                centres[0, p], centres[1, p] = means[i[lo + p], 0], means[i[lo + p], 1]
                centres[2, p], centres[3, p] = means[j[lo + p], 0], means[j[lo + p], 1]
        nn_node_pairs(nodes, weights, root, scale, out[:, lo:hi], with_gradient, centres,
                      with_scale)


@_jit
def correlated_pairs(covariances: np.ndarray, scan_ids: np.ndarray, pose_factors: np.ndarray,
                     pose_share_min: float, zero_variance: float) -> tuple[np.ndarray, np.ndarray]:
    """The same-scan pairs of ``gpocc.gp.expected.same_scan_pairs`` (its rule, its
    row-major order), without the (N, N) masks: about 10 us instead of 0.4 ms for the
    128 points of a map anchor.

    Args:
        covariances: (N, 2, 2); scan_ids: (N,) integers; pose_factors: (N, 2, 3).

    Returns:
        (i, j), (P,) each, i < j.
    """
    n = covariances.shape[0]
    live = np.empty(n, dtype=np.bool_)
    for a in range(n):
        pose_part = 0.0
        for r in range(2):
            for c in range(3):
                pose_part += pose_factors[a, r, c] * pose_factors[a, r, c]
        trace = covariances[a, 0, 0] + covariances[a, 1, 1]
        biggest = max(max(abs(covariances[a, 0, 0]), abs(covariances[a, 0, 1])),
                      max(abs(covariances[a, 1, 0]), abs(covariances[a, 1, 1])))
        live[a] = pose_part > pose_share_min * trace and biggest > zero_variance
    count = 0
    for a in range(n):
        if live[a]:
            for b in range(a + 1, n):
                if live[b] and scan_ids[b] == scan_ids[a]:
                    count += 1
    first = np.empty(count, dtype=np.intp)
    second = np.empty(count, dtype=np.intp)
    k = 0
    for a in range(n):
        if live[a]:
            for b in range(a + 1, n):
                if live[b] and scan_ids[b] == scan_ids[a]:
                    first[k] = a
                    second[k] = b
                    k += 1
    return first, second


@_jit
def nn_local_system(means: np.ndarray, covariances: np.ndarray, scan_ids: np.ndarray,
                    pose_factors: np.ndarray, queries: np.ndarray, unit: np.ndarray,
                    weights: np.ndarray, unit4: np.ndarray, weights4: np.ndarray,
                    root: np.ndarray, scale: float, diagonal: float, correlated: bool,
                    pose_share_min: float, zero_variance: float, k_out: np.ndarray,
                    cross_out: np.ndarray, prior_out: np.ndarray) -> None:
    """Every covariance one local GP problem needs, in one call: what
    ``gpocc.gp.expected.expected_kernel_matrix``, ``expected_kernel_cross`` and the
    kernel's ``diag`` give, for N points that all share one 2-D rule (``unit`` (L, 2),
    ``weights`` (L,); one node at the mean for zero covariances or level 1).

    k_out (N, N): the expected training matrix (product rule, same-scan pairs by the 4-D
    rule ``unit4``/``weights4`` when ``correlated`` and L > 1, one-point diagonal) plus
    ``diagonal`` on the diagonal; cross_out (Q, N): expected cross-covariances of the exact
    (Q, 2) ``queries``; prior_out (Q,): k(q, q). A map anchor made a dozen calls for
    these, whose glue (checks, node cache, scaling, the diagonal, symmetrising) cost
    about a sixth of the anchor.
    """
    n = means.shape[0]
    size = unit.shape[0]
    total = n * size
    nodes = gaussian_nodes_2d(means, covariances, unit)
    # Node-major scaled rows (node k of point i in column k N + i) for the uniform loops.
    u = np.empty((3, total))
    for i in range(n):
        for k in range(size):
            m = i * size + k
            u[0, k * n + i], u[1, k * n + i], u[2, k * n + i], _ = _scaled_row(
                nodes[0, m], nodes[1, m], root)
    nn_matrix_uniform(u, weights, scale, k_out)
    for i in range(n):
        acc = 0.0
        for k in range(size):
            m = k * n + i
            acc += weights[k] * _asin(_clip(u[0, m] * u[0, m] + u[1, m] * u[1, m]
                                            + u[2, m] * u[2, m]))
        k_out[i, i] = scale * acc + diagonal
    if correlated and size > 1:
        first, second = correlated_pairs(covariances, scan_ids, pose_factors, pose_share_min,
                                         zero_variance)
        if first.shape[0]:
            values = np.empty((1, first.shape[0]))
            nn_same_scan_pairs(means, covariances, pose_factors, first, second, unit4,
                               weights4, root, scale, 1.0, values, False, False)
            for p in range(first.shape[0]):
                k_out[first[p], second[p]] = values[0, p]
                k_out[second[p], first[p]] = values[0, p]
    rows = queries.shape[0]
    q = np.empty((3, rows))
    for r in range(rows):
        q0, q1, q2, _ = _scaled_row(queries[r, 0], queries[r, 1], root)
        q[0, r], q[1, r], q[2, r] = q0, q1, q2
        prior_out[r] = scale * _asin(_clip(q0 * q0 + q1 * q1 + q2 * q2))
    nn_cross_uniform(q, u, weights, scale, cross_out)
