"""Expected kernels over Gaussian inputs, by Gauss-Hermite quadrature.

Training inputs are uncertain, x_i ~ N(u_i, S_i) (metres, m^2); queries are exact. The GP
uses

* ``K[i, j] = E[k(x_i, x_j)]`` over the joint law of (x_i, x_j): a product of two 2-D
  rules when the inputs are independent, one 4-D rule over ``[[S_i, C], [C', S_j]]`` when
  they share a scan's pose error (``C = A_i A_j'``, ``A = pose_factors``);
* ``K[i, i] = E[k(x_i, x_i)]`` over ONE random point (not two independent copies), or
  with ``model.diagonal: two-draw`` (:func:`two_draw_diag`) ``E[k(x_i, x_i')]`` over two
  draws that share the scan's pose error and have independent sensor noise;
* ``Kx[q, i] = E[k(x*_q, x_i)]`` for exact queries.

Nodes never depend on the hyperparameters, so gradients are the same quadrature applied to
``kernel.gradient``. Points whose covariance is zero get one node.

This module builds the node sets and assembles the matrices; the sums run in a backend
(:mod:`gpocc.gp.backends`, chosen by ``model.backend`` and passed as ``backend=``): the
numpy quadrature for any kernel (the reference), or compiled loops for the kernels they
serve (the NN kernel). Node sets are cached for repeated calls on the same inputs
(training).

:func:`expected_se_closed_form` is Girard's closed form for the squared exponential, used as
an independent check of the quadrature.
"""

from __future__ import annotations

import functools
import hashlib
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from numpy.polynomial.hermite_e import hermegauss

from gpocc.gp import backends
from gpocc.gp.inputscale import LOG_SCALE_STEP
from gpocc.gp.kernels import Kernel, SquaredExponentialKernel

#: Smallest share of a point's covariance trace due to the shared pose error for its
#: same-scan pairs to get the correlated 4-D rule.
POSE_SHARE_MIN = 0.01

#: A covariance whose entries are all below this (m^2; std 1e-12 m) is treated as exactly
#: zero: its point gets one node at the mean.
ZERO_VARIANCE_M2 = 1e-24

# Row-group size of the node matrix, in nodes (128-256 were fastest for N = 200-300 at
# level 3, single-threaded), and the node-pair chunk (float64 per temporary).
_BLOCK_NODES = 192
_PAIR_CHUNK = 1 << 19


# --------------------------------------------------------------------------- quadrature rules


@functools.lru_cache(maxsize=64)
def _rule(level: int, dim: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = hermegauss(level)
    w = w / w.sum()  # the probabilists' weights sum to sqrt(2 pi)
    grids = np.meshgrid(*([x] * dim), indexing="ij")
    nodes = np.stack([g.reshape(-1) for g in grids], axis=1)
    weights = functools.reduce(np.multiply.outer, [w] * dim).reshape(-1)
    nodes.setflags(write=False)
    weights.setflags(write=False)
    return nodes, weights


def gauss_hermite(level: int, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Tensor-product Gauss-Hermite rule for the standard normal N(0, I_dim).

    Exact for polynomials of degree up to ``2 level - 1`` in each coordinate.

    Returns:
        unit_nodes: (level**dim, dim), read-only.
        weights: (level**dim,) positive, summing to 1, read-only.
    """
    if int(level) != level or level < 1:
        raise ValueError(f"quadrature level must be a positive integer, got {level!r}")
    if int(dim) != dim or dim < 1:
        raise ValueError(f"dimension must be a positive integer, got {dim!r}")
    return _rule(int(level), int(dim))


def sqrt_psd(covariances: np.ndarray) -> np.ndarray:
    """Factors R with R R' = S for a stack of symmetric matrices, robust to singular ones.

    Symmetrises, takes eigenvalues and zeroes those below 1e-13 of the largest (rounding
    noise, whose square root would otherwise move nodes off a singular covariance's
    support by ~1e-8 m); a zero matrix gives a zero factor.

    Args:
        covariances: (..., d, d).

    Returns:
        (..., d, d).
    """
    s = np.asarray(covariances, dtype=np.float64)
    if s.shape[-2:] == (2, 2):
        return _sqrt_psd2(s)
    s = 0.5 * (s + np.swapaxes(s, -1, -2))
    lam, vec = np.linalg.eigh(s)
    lam[lam < 1e-13 * lam[..., -1:]] = 0.0  # eigh sorts ascending
    return vec * np.sqrt(lam)[..., None, :]


def _sqrt_psd2(s: np.ndarray) -> np.ndarray:
    """:func:`sqrt_psd` of 2 x 2 matrices in closed form (the eigenvalues of
    ``[[a, b], [b, c]]`` are ``(a + c) / 2 +- hypot((a - c) / 2, b)``, the larger one's
    eigenvector at angle ``atan2(b, (a - c) / 2) / 2``): a third of the time of a batched
    LAPACK call for the 128 points of a map anchor. The columns may differ from
    ``eigh``'s in sign and order, which leaves a Gauss-Hermite node set unchanged (the
    rule is the same along both axes and symmetric)."""
    a, c = s[..., 0, 0], s[..., 1, 1]
    b = 0.5 * (s[..., 0, 1] + s[..., 1, 0])
    half = 0.5 * (a - c)
    radius = np.hypot(half, b)
    # A negative largest eigenvalue (rounding of a zero matrix) is zeroed as eigh's path
    # zeroes it; the smaller one as det / larger, free of the cancellation in mean - radius.
    high = np.maximum(0.5 * (a + c) + radius, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        low = np.where(high > 0.0, (a * c - b * b) / high, 0.0)
    low = np.where(low < 1e-13 * high, 0.0, low)
    angle = 0.5 * np.arctan2(b, half)
    cos, sin = np.cos(angle), np.sin(angle)
    root_low, root_high = np.sqrt(low), np.sqrt(high)
    out = np.empty(s.shape)
    out[..., 0, 0] = -sin * root_low
    out[..., 1, 0] = cos * root_low
    out[..., 0, 1] = cos * root_high
    out[..., 1, 1] = sin * root_high
    return out


def cholesky_psd(covariances: np.ndarray) -> np.ndarray:
    """Lower-triangular R with R R' = S for a stack of symmetric positive semi-definite
    matrices: the roots of the correlated 4-D rules.

    Any root gives a valid Gauss-Hermite rule (exact for polynomials of total degree up to
    2 level - 1); Cholesky's costs a few dozen flops where an eigendecomposition costs
    hundreds, and on the same-scan pairs of the Intel model its rule was as close to a
    level-7 reference as the eigenvector root's (mean error 1.1e-4 against 1.1e-4 at
    level 2). A pivot below 1e-10 of the largest diagonal entry (a standard deviation 1e-5
    of the largest) is rounding noise of a singular matrix: its column is zero.

    Args:
        covariances: (..., d, d).

    Returns:
        (..., d, d), zero above the diagonal.
    """
    s = np.asarray(covariances, dtype=np.float64)
    s = 0.5 * (s + np.swapaxes(s, -1, -2))
    d = s.shape[-1]
    root = np.zeros_like(s)
    tiny = 1e-10 * np.max(np.diagonal(s, axis1=-2, axis2=-1), axis=-1)
    for k in range(d):
        pivot = s[..., k, k] - np.sum(root[..., k, :k] ** 2, axis=-1)
        live = pivot > tiny
        diag = np.sqrt(np.where(live, pivot, 1.0))
        root[..., k, k] = np.where(live, diag, 0.0)
        below = s[..., k + 1:, k] - np.einsum("...ij,...j->...i", root[..., k + 1:, :k],
                                               root[..., k, :k])
        root[..., k + 1:, k] = np.where(live[..., None], below / diag[..., None], 0.0)
    return root


def gaussian_nodes(
    means: np.ndarray, covariances: np.ndarray, level: int
) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Hermite nodes of N(means[i], covariances[i]) for every i.

    Args:
        means: (N, d), e.g. metres.
        covariances: (N, d, d).
        level: nodes per dimension.

    Returns:
        nodes: (N, level**d, d); all at the mean where the covariance is zero.
        weights: (level**d,) summing to 1, shared by every point.
    """
    means = np.asarray(means, dtype=np.float64)
    covariances = np.asarray(covariances, dtype=np.float64)
    n, d = means.shape
    if covariances.shape != (n, d, d):
        raise ValueError(f"covariances must have shape {(n, d, d)}, got {covariances.shape}")
    unit, weights = gauss_hermite(level, d)
    nodes = np.tensordot(sqrt_psd(covariances), unit, axes=([2], [1]))  # (N, d, L^d)
    nodes += means[:, :, None]
    return np.swapaxes(nodes, 1, 2), weights


# --------------------------------------------------------------------------- node sets


@dataclass(frozen=True)
class _Expansion:
    """Every point's nodes, flattened; zero-covariance points carry one node of weight 1.

    nodes (M, 2), weights (M,), starts (N + 1,) node offsets of each point (the last is M),
    uniform: nodes per point when all points have the same count, else 0.
    """

    nodes: np.ndarray
    weights: np.ndarray
    starts: np.ndarray
    uniform: int

    def rows(self, lo: int, hi: int) -> _Expansion:
        """The expansion of points lo..hi-1."""
        a, b = self.starts[lo], self.starts[hi]
        return _Expansion(
            self.nodes[a:b], self.weights[a:b], self.starts[lo : hi + 1] - a, self.uniform
        )

    @property
    def size(self) -> int:
        return self.starts.shape[0] - 1


def _expand(means: np.ndarray, covariances: np.ndarray, level: int,
            backend: str | backends.Backend = "auto") -> _Expansion:
    n = means.shape[0]
    zero = np.abs(covariances).reshape(n, 4).max(axis=1) <= ZERO_VARIANCE_M2
    unit, w = gauss_hermite(level, 2)
    if zero.all() or unit.shape[0] == 1:
        return _Expansion(means.copy(), np.ones(n), np.arange(n + 1, dtype=np.intp), 1)
    if not zero.any():
        starts = np.arange(n + 1, dtype=np.intp) * w.shape[0]
        built = backends.get(backend).nodes_2d(means, covariances, level)
        if built is not None:
            flat, w = built
        else:
            nodes, w = gaussian_nodes(means, covariances, level)
            flat = np.transpose(nodes, (2, 0, 1)).reshape(2, -1).T
        return _Expansion(flat, np.tile(w, n), starts, w.shape[0])
    counts = np.where(zero, 1, w.shape[0])
    starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.intp)
    nodes = np.empty((starts[-1], 2))
    weights = np.empty(starts[-1])
    first = starts[:-1]
    nodes[first[zero]] = means[zero]
    weights[first[zero]] = 1.0
    moving = np.flatnonzero(~zero)
    idx = (first[moving][:, None] + np.arange(w.shape[0])).reshape(-1)
    sub, _ = gaussian_nodes(means[moving], covariances[moving], level)
    nodes[idx] = sub.reshape(-1, 2)
    weights[idx] = np.tile(w, moving.shape[0])
    return _Expansion(nodes, weights, starts, 0)


def _spread(nodes: np.ndarray, centres: np.ndarray, scale: float) -> np.ndarray:
    """``nodes`` moved away from their points' ``centres`` (same shape) by sqrt(scale):
    the nodes of covariances times ``scale``, since the root of g S is sqrt(g) times the
    root of S. The result keeps ``nodes``' memory layout."""
    out = np.empty_like(nodes)
    np.multiply(nodes - centres, math.sqrt(scale), out=out)
    out += centres
    return out


def _scaled_expansion(ex: _Expansion, means: np.ndarray, scale: float) -> _Expansion:
    """The expansion of the same points with covariances times ``scale`` (:func:`_spread`),
    so the cached nodes of S serve every g."""
    if scale == 1.0:
        return ex
    centres = np.repeat(means, np.diff(ex.starts), axis=0)
    return _Expansion(_spread(ex.nodes, centres, scale), ex.weights, ex.starts, ex.uniform)


def _reduce_last(values: np.ndarray, ex: _Expansion) -> np.ndarray:
    """Weighted sum over each point's nodes along the last axis: (..., M) -> (..., N)."""
    if ex.uniform == 1:
        return values
    if ex.uniform:
        return values.reshape(*values.shape[:-1], ex.size, ex.uniform) @ ex.weights[: ex.uniform]
    values = values * ex.weights
    return np.add.reduceat(values, ex.starts[:-1], axis=-1)


def _reduce_block(values: np.ndarray, rows: _Expansion, cols: _Expansion) -> np.ndarray:
    """(..., Mr, Mc) node values -> (..., Nr, Nc) expectations."""
    t = _reduce_last(values, cols)
    return np.swapaxes(_reduce_last(np.swapaxes(t, -1, -2), rows), -1, -2)


def _groups(ex: _Expansion) -> list[tuple[int, int]]:
    """Contiguous point ranges of about _BLOCK_NODES nodes each."""
    cuts = np.searchsorted(ex.starts, np.arange(0, ex.starts[-1], _BLOCK_NODES), side="right")
    bounds = np.unique(np.concatenate([[0], cuts - 1, [ex.size]]))
    return list(zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True))


def _nparams(kernel: Kernel) -> int:
    return int(np.asarray(kernel.theta).shape[0])


# --------------------------------------------------------------------------- expected kernels


# Node sets never depend on the hyperparameters, and training evaluates the same patches a
# hundred times: the last few expansions are kept, keyed by a digest of their inputs (a hash
# of a few kB, microseconds). A map's anchor expands its samples for the training matrix and
# again for the cross-covariance; mapping never repeats a problem otherwise.
# The lock makes the cache safe for callers on threads (held for look-ups, not builds).
_NODE_CACHE: OrderedDict[bytes, _Expansion] = OrderedDict()
_NODE_CACHE_ENTRIES = 48
_NODE_CACHE_LOCK = threading.Lock()


def _cached_expansion(means: np.ndarray, covariances: np.ndarray, level: int,
                      backend: backends.Backend) -> _Expansion:
    """:func:`_expand` through the node-set cache."""
    digest = hashlib.blake2b(digest_size=20)
    # Backends build the nodes apart (equal to round-off): a comparison of two backends
    # must not be served the other one's nodes.
    digest.update(backend.name.encode())
    for a in (means, covariances, np.array([level])):
        a = np.ascontiguousarray(a)
        digest.update(str((a.dtype.str, a.shape)).encode())
        digest.update(a.data)
    key = digest.digest()
    with _NODE_CACHE_LOCK:
        hit = _NODE_CACHE.get(key)
        if hit is not None:
            _NODE_CACHE.move_to_end(key)
            return hit
    value = _expand(means, covariances, level, backend)
    for a in vars(value).values():
        if isinstance(a, np.ndarray):
            a.setflags(write=False)  # shared between calls: nobody may change it
    with _NODE_CACHE_LOCK:
        _NODE_CACHE[key] = value
        while len(_NODE_CACHE) > _NODE_CACHE_ENTRIES:
            _NODE_CACHE.popitem(last=False)
    return value


def _check_inputs(means: np.ndarray, covariances: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    means = np.asarray(means, dtype=np.float64)
    covariances = np.asarray(covariances, dtype=np.float64)
    if means.ndim != 2 or means.shape[1] != 2:
        raise ValueError(f"means must have shape (N, 2), got {means.shape}")
    if covariances.shape != (means.shape[0], 2, 2):
        raise ValueError(
            f"covariances must have shape ({means.shape[0]}, 2, 2), got {covariances.shape}"
        )
    if not (np.isfinite(means).all() and np.isfinite(covariances).all()):
        raise ValueError("means and covariances must be finite (found NaN or inf)")
    return means, covariances


def _check_scan_inputs(n: int, scan_ids: np.ndarray, pose_factors: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """``scan_ids`` (n,) as an array and ``pose_factors`` (n, 2, 3) as float64, or a
    ValueError naming their shapes or non-finite pose factors."""
    scan_ids = np.asarray(scan_ids)
    pose_factors = np.asarray(pose_factors, dtype=np.float64)
    if scan_ids.shape != (n,) or pose_factors.shape != (n, 2, 3):
        raise ValueError(
            f"scan_ids must have shape ({n},) and pose_factors ({n}, 2, 3), got "
            f"{scan_ids.shape} and {pose_factors.shape}"
        )
    if not np.isfinite(pose_factors).all():
        raise ValueError("pose_factors must be finite (found NaN or inf)")
    return scan_ids, pose_factors


def _check_queries(queries: np.ndarray) -> np.ndarray:
    """``queries`` (Q, 2) as finite float64, or a ValueError."""
    queries = np.asarray(queries, dtype=np.float64)
    if queries.ndim != 2 or queries.shape[1] != 2:
        raise ValueError(f"queries must have shape (Q, 2), got {queries.shape}")
    if not np.isfinite(queries).all():
        raise ValueError("queries must be finite (found NaN or inf)")
    return queries


def same_scan_pairs(
    covariances: np.ndarray, scan_ids: np.ndarray | None, pose_factors: np.ndarray | None,
    backend: str | backends.Backend = "auto",
) -> tuple[np.ndarray, np.ndarray]:
    """(i, j) with i < j, same scan and both with nonzero pose factors and covariances."""
    n = covariances.shape[0]
    if scan_ids is None or pose_factors is None:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
    scan_ids, pose_factors = _check_scan_inputs(n, scan_ids, pose_factors)
    # A pair is treated as correlated only when the shared pose error is a noticeable
    # part (POSE_SHARE_MIN) of both points' covariances: below that the cross-covariance
    # is negligible and the product rule is both cheaper and exactly positive definite.
    listed = backends.get(backend).same_scan_pairs(covariances, scan_ids, pose_factors)
    if listed is not None:
        return listed
    pose_part = np.einsum("nij,nij->n", pose_factors, pose_factors)
    trace = covariances[:, 0, 0] + covariances[:, 1, 1]
    live = pose_part > POSE_SHARE_MIN * trace
    live &= np.abs(covariances).reshape(n, 4).max(axis=1) > ZERO_VARIANCE_M2
    mask = scan_ids[:, None] == scan_ids[None, :]
    mask &= live[:, None]
    mask &= live[None, :]
    return np.nonzero(np.triu(mask, 1))


def expected_kernel_diag(
    kernel: Kernel,
    means: np.ndarray,
    covariances: np.ndarray,
    level: int,
    *,
    with_gradient: bool = False,
    backend: str | backends.Backend = "auto",
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """E[k(x_i, x_i)] for ONE random point x_i ~ N(means[i], covariances[i]).

    Returns:
        (N,), or ((N,), (P, N)) with the gradient w.r.t. ``kernel.theta``.
    """
    means, covariances = _check_inputs(means, covariances)
    return _diag(kernel, _expand(means, covariances, level, backend), with_gradient)


def _diag(
    kernel: Kernel, ex: _Expansion, with_gradient: bool
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    values = _reduce_last(kernel.diag(ex.nodes), ex)
    if not with_gradient:
        return values
    return values, _reduce_last(kernel.pairwise_gradient(ex.nodes, ex.nodes), ex)


def two_draw_diag(
    kernel: Kernel,
    means: np.ndarray,
    covariances: np.ndarray,
    level: int,
    *,
    scan_ids: np.ndarray | None = None,
    pose_factors: np.ndarray | None = None,
    with_gradient: bool = False,
    backend: str | backends.Backend = "auto",
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """``E[k(x_i, x_i')]`` for two draws x_i, x_i' of sample i's input N(u_i, S_i) that
    share its scan's pose error and have independent sensor noise: joint covariance
    ``[[S_i, A_i A_i'], [A_i A_i', S_i]]`` (``A = pose_factors``).

    A sample whose pose share :func:`same_scan_pairs` would not treat as correlated (no
    scan ids or pose factors, or a pose part below ``POSE_SHARE_MIN`` of its trace) gets
    independent draws, the product of two 2-D rules ``sum_ab w_a w_b k(n_a, n_b)``; the
    others get the same-scan 4-D rule at (i, i) (where the sensor part is ~0 the joint
    covariance is singular and the two draws coincide: the one-point value). A zero
    covariance gives ``k(u_i, u_i)``.

    Args:
        means: (N, 2) metres; covariances: (N, 2, 2) m^2; scan_ids (N,), pose_factors
            (N, 2, 3) metres, as for :func:`expected_kernel_matrix`.

    Returns:
        (N,), or ((N,), (P, N)) with the gradient w.r.t. ``kernel.theta``.
    """
    means, covariances = _check_inputs(means, covariances)
    n = means.shape[0]
    chosen = backends.get(backend)
    values = np.empty(n)
    grads = np.empty((_nparams(kernel), n)) if with_gradient else None
    zero = np.abs(covariances).reshape(n, 4).max(axis=1) <= ZERO_VARIANCE_M2
    correlated = np.zeros(n, dtype=bool)
    if scan_ids is not None and pose_factors is not None and level > 1:
        _, pose_factors = _check_scan_inputs(n, scan_ids, pose_factors)
        pose_part = np.einsum("nij,nij->n", pose_factors, pose_factors)
        correlated = (pose_part > POSE_SHARE_MIN * (covariances[:, 0, 0] + covariances[:, 1, 1])
                      ) & ~zero
    if zero.any():
        at = means[zero]
        if grads is None:
            values[zero] = kernel.diag(at)
        else:
            grads[:, zero] = kernel.pairwise_gradient(at, at)
            values[zero] = grads[0, zero]  # d/dlog(signal) = k
    free = np.flatnonzero(~zero & ~correlated)
    if free.shape[0]:
        nodes, w = gaussian_nodes(means[free], covariances[free], level)  # (F, L, 2)
        size = w.shape[0]
        weights = np.multiply.outer(w, w).reshape(-1)
        step = max(1, _PAIR_CHUNK // (size * size))
        for lo in range(0, free.shape[0], step):
            part = nodes[lo : lo + step]
            a = np.repeat(part, size, axis=1).reshape(-1, 2)
            b = np.tile(part, (1, size, 1)).reshape(-1, 2)
            idx = free[lo : lo + step]
            if grads is None:
                values[idx] = kernel.pairwise(a, b).reshape(-1, size * size) @ weights
            else:
                g = kernel.pairwise_gradient(a, b)
                grads[:, idx] = g.reshape(g.shape[0], -1, size * size) @ weights
                values[idx] = grads[0, idx]
    both = np.flatnonzero(correlated)
    if both.shape[0]:
        pair_values, pair_grads = chosen.loops(kernel).same_scan(
            kernel, means, covariances, pose_factors, both, both, level, with_gradient,
            1.0, False)
        values[both] = pair_values
        if grads is not None:
            grads[:, both] = pair_grads[: grads.shape[0]]
    return values if grads is None else (values, grads)


def _two_draw_scale_gradient(
    kernel: Kernel, means: np.ndarray, covariances: np.ndarray, level: int,
    scan_ids: np.ndarray | None, pose_factors: np.ndarray | None, input_scale: float,
    backend: backends.Backend,
) -> np.ndarray:
    """(N,) d/dlog g of :func:`two_draw_diag` at covariances ``g S`` and pose factors
    ``sqrt(g) A``, by a central difference in log g (the diagonal alone: N values)."""
    out = []
    for sign in (1.0, -1.0):
        g = input_scale * math.exp(sign * LOG_SCALE_STEP)
        out.append(two_draw_diag(
            kernel, means, covariances * g, level, scan_ids=scan_ids,
            pose_factors=None if pose_factors is None else pose_factors * math.sqrt(g),
            backend=backend))
    return (out[0] - out[1]) / (2.0 * LOG_SCALE_STEP)


def supports_scale_gradient(kernel: Kernel, backend: str | backends.Backend = "auto") -> bool:
    """Whether :func:`expected_kernel_matrix` gives dK/dlog g for ``kernel``."""
    return backends.get(backend).loops(kernel).scale_gradient


def expected_kernel_matrix(
    kernel: Kernel,
    means: np.ndarray,
    covariances: np.ndarray,
    level: int,
    *,
    scan_ids: np.ndarray | None = None,
    pose_factors: np.ndarray | None = None,
    with_gradient: bool = False,
    input_scale: float = 1.0,
    with_scale_gradient: bool = False,
    backend: str | backends.Backend = "auto",
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Expected training covariance ``K[i, j] = E[k(x_i, x_j)]``, x_i ~ N(u_i, S_i).

    Pairs from one scan (equal ``scan_ids``) with nonzero ``pose_factors`` are correlated,
    ``Cov(x_i, x_j) = A_i A_j'``, and use a 4-D rule (level**4 nodes); other pairs are
    independent and use the product of the two 2-D rules; the diagonal is the one-point
    expectation, or :func:`two_draw_diag` where ``backend`` carries ``model.diagonal:
    two-draw`` (:func:`gpocc.gp.backends.choose`). Without ``scan_ids``/``pose_factors``
    all pairs are independent.

    Args:
        kernel: a :class:`~gpocc.gp.kernels.Kernel`.
        means: (N, 2) metres.
        covariances: (N, 2, 2) m^2.
        level: Gauss-Hermite nodes per dimension (1 evaluates at the means).
        scan_ids: (N,) integers.
        pose_factors: (N, 2, 3) metres.
        with_gradient: also return dK/dtheta.
        input_scale: g > 0: the inputs' covariances are ``g S_i`` and their pose factors
            ``sqrt(g) A_i`` (:mod:`gpocc.gp.inputscale`); node sets are built once for
            ``g = 1`` and scaled, so learning g reuses them.
        with_scale_gradient: with ``with_gradient``, dK gains a last entry, dK/dlog g
            (every node moves away from its mean as sqrt(g)); compiled NN path only, see
            :func:`supports_scale_gradient`.
        backend: ``model.backend``'s name or a backend (:mod:`gpocc.gp.backends`).

    Returns:
        K (N, N) symmetric, or (K, dK) with dK (P, N, N), P = len(kernel.theta) (+ 1).
    """
    means, covariances = _check_inputs(means, covariances)
    backend = backends.get(backend)
    loops = backend.loops(kernel)
    if with_scale_gradient and (not loops.scale_gradient or not with_gradient):
        raise ValueError("dK/dlog g needs with_gradient and the compiled NN kernel")
    if input_scale != 1.0 and not loops.scale_gradient:  # scaled inputs instead
        covariances = covariances * input_scale
        if pose_factors is not None:
            pose_factors = np.asarray(pose_factors, dtype=np.float64) * math.sqrt(input_scale)
        input_scale = 1.0
    ex = _cached_expansion(means, covariances, level, backend)
    ex = _scaled_expansion(ex, means, input_scale)
    n = ex.size
    nparams = _nparams(kernel) + (1 if with_scale_gradient else 0)
    k = np.empty((n, n))
    dk = np.empty((nparams, n, n)) if with_gradient else None
    diag_scale_gradient = loops.matrix(kernel, ex, means, k, dk, with_scale_gradient)

    i, j = same_scan_pairs(covariances, scan_ids, pose_factors, backend)
    if i.shape[0] and level > 1:  # a 1-node rule puts both points at their means anyway
        values, grads = loops.same_scan(
            kernel, means, covariances, np.asarray(pose_factors, dtype=np.float64),
            i, j, level, with_gradient, input_scale, with_scale_gradient,
        )
        k[i, j] = values
        k[j, i] = values
        if dk is not None:
            dk[:, i, j] = grads
            dk[:, j, i] = grads

    diag = np.arange(n)
    # Loops that write both triangles with one value (as the pair scatter does) leave
    # the matrices symmetric as they stand; the numpy path's diagonal blocks come from
    # products that need not be (averaging the transposed gradients took a tenth of a
    # training evaluation).
    symmetrise = not loops.symmetric
    two_draw = backends.diagonal_of(backend) == "two-draw"
    if two_draw:
        # At g S and sqrt(g) A, whichever of the loops or this function scaled them.
        scaled_covariances = covariances * input_scale
        scaled_factors = (None if pose_factors is None else
                          np.asarray(pose_factors, dtype=np.float64) * math.sqrt(input_scale))
    if dk is None:
        if two_draw:
            k[diag, diag] = two_draw_diag(kernel, means, scaled_covariances, level,
                                          scan_ids=scan_ids, pose_factors=scaled_factors,
                                          backend=backend)
        else:
            k[diag, diag] = _diag(kernel, ex, False)
        if symmetrise:
            k += k.T
            k *= 0.5
        return k
    if two_draw:
        dvalues, dgrads = two_draw_diag(kernel, means, scaled_covariances, level,
                                        scan_ids=scan_ids, pose_factors=scaled_factors,
                                        with_gradient=True, backend=backend)
        if with_scale_gradient:
            diag_scale_gradient = _two_draw_scale_gradient(
                kernel, means, covariances, level, scan_ids, pose_factors, input_scale,
                backend)
    else:
        dvalues, dgrads = _diag(kernel, ex, True)
    if with_scale_gradient:
        dgrads = np.vstack([dgrads, diag_scale_gradient])
    k[diag, diag] = dvalues
    dk[:, diag, diag] = dgrads
    if symmetrise:
        k += k.T
        k *= 0.5
        dk += np.swapaxes(dk, 1, 2)
        dk *= 0.5
    return k, dk


def expected_kernel_cross(
    kernel: Kernel,
    queries: np.ndarray,
    means: np.ndarray,
    covariances: np.ndarray,
    level: int,
    *,
    with_gradient: bool = False,
    backend: str | backends.Backend = "auto",
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """``Kx[q, i] = E[k(x*_q, x_i)]`` for exact queries and x_i ~ N(u_i, S_i).

    Args:
        queries: (Q, 2) metres.
        means: (N, 2) metres.
        covariances: (N, 2, 2) m^2.

    Returns:
        (Q, N), or ((Q, N), (P, Q, N)) with the gradient w.r.t. ``kernel.theta``.
    """
    means, covariances = _check_inputs(means, covariances)
    queries = _check_queries(queries)
    # The training matrix of the same problem has just expanded these points.
    backend = backends.get(backend)
    ex = _cached_expansion(means, covariances, level, backend)
    return backend.loops(kernel).cross(kernel, queries, ex, with_gradient)


def expected_local_system(
    kernel: Kernel,
    means: np.ndarray,
    covariances: np.ndarray,
    queries: np.ndarray,
    level: int,
    diagonal: float,
    *,
    scan_ids: np.ndarray | None = None,
    pose_factors: np.ndarray | None = None,
    backend: str | backends.Backend = "auto",
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The three covariances of one local prediction in one compiled call, or None where
    that call does not apply (a kernel without such a pass in ``backend``, or some
    covariances zero and others not): then use :func:`expected_kernel_matrix`,
    :func:`expected_kernel_cross` and ``kernel.diag``, which give the same values to
    round-off.

    Args:
        means: (N, 2) metres; covariances: (N, 2, 2) m^2; queries: (Q, 2) metres.
        level: Gauss-Hermite nodes per dimension.
        diagonal: added to K's diagonal (label noise and jitter).
        scan_ids, pose_factors: as for :func:`expected_kernel_matrix`.

    Returns:
        K + diagonal I (N, N), Kx (Q, N), k(q, q) (Q,).
    """
    return backends.get(backend).loops(kernel).local_system(
        kernel, means, covariances, queries, level, diagonal, scan_ids, pose_factors)


# --------------------------------------------------------------------------- closed form (SE)


def _girard(
    kernel: SquaredExponentialKernel,
    d0: np.ndarray,
    d1: np.ndarray,
    s00: np.ndarray,
    s01: np.ndarray,
    s11: np.ndarray,
) -> np.ndarray:
    """s |I + W^-1 S|^-1/2 exp(-d'(W + S)^-1 d / 2) for the 2x2 case, elementwise."""
    w0, w1 = kernel.lengthscale[0] ** 2, kernel.lengthscale[1] ** 2
    m00, m11 = w0 + s00, w1 + s11
    det = m00 * m11 - s01 * s01
    quad = (m11 * d0 * d0 - 2.0 * s01 * d0 * d1 + m00 * d1 * d1) / det
    return kernel.signal_variance * np.sqrt(w0 * w1 / det) * np.exp(-0.5 * quad)


def expected_se_closed_form(
    kernel: SquaredExponentialKernel,
    means_a: np.ndarray,
    covs_a: np.ndarray,
    means_b: np.ndarray,
    covs_b: np.ndarray,
) -> np.ndarray:
    """Girard's closed form of E[k(x_a, x_b)] for independent Gaussian inputs.

    ``s |I + W^-1 (S_a + S_b)|^-1/2 exp(-1/2 d' (W + S_a + S_b)^-1 d)``, W = diag(l^2),
    d = u_a - u_b. Only valid for two distinct (independent) random points.

    Args:
        means_a: (Na, 2) metres; covs_a: (Na, 2, 2) m^2; likewise for b.

    Returns:
        (Na, Nb).
    """
    ua, sa = _check_inputs(means_a, covs_a)
    ub, sb = _check_inputs(means_b, covs_b)
    return _girard(
        kernel,
        np.subtract.outer(ua[:, 0], ub[:, 0]),
        np.subtract.outer(ua[:, 1], ub[:, 1]),
        np.add.outer(sa[:, 0, 0], sb[:, 0, 0]),
        np.add.outer(0.5 * (sa[:, 0, 1] + sa[:, 1, 0]), 0.5 * (sb[:, 0, 1] + sb[:, 1, 0])),
        np.add.outer(sa[:, 1, 1], sb[:, 1, 1]),
    )


def expected_se_closed_form_pairs(
    kernel: SquaredExponentialKernel,
    means_a: np.ndarray,
    covs_a: np.ndarray,
    means_b: np.ndarray,
    covs_b: np.ndarray,
    cross: np.ndarray | None = None,
) -> np.ndarray:
    """Girard's closed form for elementwise pairs, optionally correlated.

    With cross-covariance ``C = Cov(x_a, x_b)`` the difference is
    ``x_a - x_b ~ N(u_a - u_b, S_a + S_b - C - C')``; ``cross = covs_a`` with equal
    points gives the one-point value ``signal_variance``.

    Args:
        means_a, means_b: (P, 2) metres; covs_a, covs_b: (P, 2, 2) m^2;
        cross: (P, 2, 2) m^2 or None (independent).

    Returns:
        (P,).
    """
    ua, sa = _check_inputs(means_a, covs_a)
    ub, sb = _check_inputs(means_b, covs_b)
    if ua.shape != ub.shape:
        raise ValueError(f"pairs need equal shapes, got {ua.shape} and {ub.shape}")
    s = sa + sb
    if cross is not None:
        c = np.asarray(cross, dtype=np.float64)
        s = s - c - np.swapaxes(c, 1, 2)
    d = ua - ub
    return _girard(
        kernel, d[:, 0], d[:, 1], s[:, 0, 0], 0.5 * (s[:, 0, 1] + s[:, 1, 0]), s[:, 1, 1]
    )
