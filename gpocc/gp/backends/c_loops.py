"""The compiled backend: the C loops of ``gpocc/_kernels.c`` (through :mod:`gpocc.compiled`).

For the neural-network kernel the quadrature sums run with the arcsin, the reduction and
the 4 x 4 roots of same-scan pairs fused, and no node-pair temporaries; gradients of the
cross-covariance, which no caller needs fast, are left to the numpy quadrature. For every
kernel the 2-D node sets and the same-scan pair list are built in C too. Importing this
module loads the library (ImportError where it is not built).
"""

from __future__ import annotations

import numpy as np

from gpocc import compiled
from gpocc.gp.backends import PRECISIONS
from gpocc.gp.backends.quadrature import QUADRATURE, Quadrature
from gpocc.gp.expected import (
    POSE_SHARE_MIN,
    ZERO_VARIANCE_M2,
    _check_inputs,
    _check_queries,
    _check_scan_inputs,
    _Expansion,
    _nparams,
    _reduce_last,
    gauss_hermite,
)
from gpocc.gp.kernels import Kernel, NeuralNetworkKernel


def _scaled_offsets(kernel: NeuralNetworkKernel, u: np.ndarray, ex: _Expansion,
                    means: np.ndarray) -> np.ndarray:
    """(2, M) each node's offset from its point's mean in scaled coordinates,
    ``root_c (x_c - m_c) / n``, from its scaled row u (3, M) (``u_0 = root_0 / n``)."""
    root = kernel.root_two_s
    centres = np.repeat(means, np.diff(ex.starts), axis=0)  # (M, 2)
    inv = u[0] / root[0]
    return np.ascontiguousarray(u[1:] - root[1:, None] * centres.T * inv)


def _diag_scale_gradient(kernel: NeuralNetworkKernel, u: np.ndarray, offsets: np.ndarray,
                         ex: _Expansion) -> np.ndarray:
    """(N,) dE[k(x_i, x_i)]/dlog g: the pair derivative with both nodes the same point,
    ``k'(z) (1 - z) a . da`` with z = |a|^2."""
    z = np.einsum("ij,ij->j", u, u)
    slope = kernel.arcsin_scale / np.sqrt(1.0 - np.minimum(z, 1.0) ** 2)
    per_node = slope * (1.0 - z) * np.einsum("ij,ij->j", u[1:], offsets)
    return _reduce_last(per_node, ex)


def _node_major(u: np.ndarray, size: int) -> np.ndarray:
    """(3, N L) point-major scaled rows (node k of point i in column i L + k) reordered
    node-major (column k N + i), the layout of the compiled uniform loops."""
    return np.ascontiguousarray(u.reshape(3, -1, size).transpose(0, 2, 1).reshape(3, -1))


class NeuralNetworkLoops(Quadrature):
    """The NN kernel's expectations in C; the cross-covariance's gradient in numpy.
    ``single``: :meth:`local_system` computes the product-rule part of K and the
    cross-covariances in single precision (``model.covariance_precision``)."""

    scale_gradient = True
    symmetric = True  # the loops and the pair scatter write both triangles with one value

    def __init__(self, single: bool = False) -> None:
        self.single = single

    def matrix(self, kernel: NeuralNetworkKernel, ex: _Expansion, means: np.ndarray,
               k: np.ndarray, dk: np.ndarray | None, with_scale_gradient: bool
               ) -> np.ndarray | None:
        # Off-diagonal entries straight from the scaled nodes, no node-pair temporaries.
        u = kernel.scaled_columns(ex.nodes)
        offsets = _scaled_offsets(kernel, u, ex, means) if with_scale_gradient else u[1:]
        if dk is None and ex.uniform:
            compiled.nn_matrix_uniform(_node_major(u, ex.uniform), ex.weights[: ex.uniform],
                                       kernel.arcsin_scale, k)
        elif dk is None:
            compiled.nn_matrix(u, ex.weights, ex.starts, kernel.arcsin_scale, k)
        else:
            compiled.nn_matrix_gradient(u, ex.weights, ex.starts, kernel.arcsin_scale, dk,
                                        offsets, with_scale_gradient)
            k[...] = dk[0]
        if with_scale_gradient:
            return _diag_scale_gradient(kernel, u, offsets, ex)
        return None

    def same_scan(self, kernel: NeuralNetworkKernel, means: np.ndarray,
                  covariances: np.ndarray, pose_factors: np.ndarray, i: np.ndarray,
                  j: np.ndarray, level: int, with_gradient: bool, input_scale: float,
                  with_scale_gradient: bool) -> tuple[np.ndarray, np.ndarray | None]:
        # Joint covariance, its root, the nodes and the arcsin in one compiled call: no
        # (pairs x nodes) temporaries and no per-matrix LAPACK call for the 4 x 4 roots.
        unit, w = gauss_hermite(level, 4)
        rows = _nparams(kernel) + (1 if with_scale_gradient else 0) if with_gradient else 1
        out = np.empty((rows, i.shape[0]))
        compiled.nn_same_scan_pairs(
            means, covariances, pose_factors, i, j, unit, w, kernel.root_two_s,
            kernel.arcsin_scale, float(input_scale), out, with_gradient, with_scale_gradient)
        return out[0].copy(), (out if with_gradient else None)

    def cross(self, kernel: NeuralNetworkKernel, queries: np.ndarray, ex: _Expansion,
              with_gradient: bool) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        if with_gradient:
            return super().cross(kernel, queries, ex, with_gradient)
        out = np.empty((queries.shape[0], ex.size))
        u = kernel.scaled_columns(ex.nodes)
        if ex.uniform:
            compiled.nn_cross_uniform(kernel.scaled_columns(queries),
                                      _node_major(u, ex.uniform), ex.weights[: ex.uniform],
                                      kernel.arcsin_scale, out)
        else:
            compiled.nn_cross(kernel.scaled_columns(queries), u, ex.weights, ex.starts,
                              kernel.arcsin_scale, out)
        return out

    def local_system(self, kernel: NeuralNetworkKernel, means: np.ndarray,
                     covariances: np.ndarray, queries: np.ndarray, level: int,
                     diagonal: float, scan_ids: np.ndarray | None,
                     pose_factors: np.ndarray | None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        means, covariances = _check_inputs(means, covariances)
        n = means.shape[0]
        zero = np.abs(covariances).reshape(n, 4).max(axis=1) <= ZERO_VARIANCE_M2
        if zero.any() and not zero.all():
            return None
        unit, weights = gauss_hermite(1 if zero.all() else level, 2)
        unit4, weights4 = gauss_hermite(level, 4)
        correlated = scan_ids is not None and pose_factors is not None
        if correlated:
            scan_ids, pose_factors = _check_scan_inputs(n, scan_ids, pose_factors)
        else:
            scan_ids, pose_factors = np.zeros(n, dtype=np.int64), np.zeros((n, 2, 3))
        queries = _check_queries(queries)
        k = np.empty((n, n))
        cross = np.empty((queries.shape[0], n))
        prior = np.empty(queries.shape[0])
        # gpocc.compiled gives the C loop its C-ordered float64 / int64 copies where needed.
        compiled.nn_local_system(
            means, covariances, scan_ids, pose_factors, queries, unit, weights, unit4,
            weights4, kernel.root_two_s, kernel.arcsin_scale, float(diagonal), correlated,
            POSE_SHARE_MIN, ZERO_VARIANCE_M2, self.single, k, cross, prior)
        return k, cross, prior


class CompiledBackend:
    """The C loops for the kernels in :attr:`served`; numpy quadrature for the others.
    ``precision``: that of the local systems (:data:`gpocc.gp.backends.PRECISIONS`)."""

    name = "compiled"

    def __init__(self, precision: str = "double") -> None:
        self.precision = precision
        #: kernel class -> its compiled loops.
        self.served: dict[type, Quadrature] = {
            NeuralNetworkKernel: NeuralNetworkLoops(single=precision == "single")}

    def __reduce__(self) -> tuple:
        return _in_precision, (self.precision,)

    def in_precision(self, precision: str) -> CompiledBackend:
        return _in_precision(precision)

    def loops(self, kernel: Kernel) -> Quadrature:
        return self.served.get(type(kernel), QUADRATURE)

    def nodes_2d(self, means: np.ndarray, covariances: np.ndarray, level: int
                 ) -> tuple[np.ndarray, np.ndarray]:
        unit, w = gauss_hermite(level, 2)
        # (M, 2) with contiguous columns: what the kernels read fastest.
        return compiled.gaussian_nodes_2d(means, covariances, unit).T, w

    def same_scan_pairs(self, covariances: np.ndarray, scan_ids: np.ndarray,
                        pose_factors: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        if scan_ids.dtype.kind not in "iu":
            return None
        # gpocc.compiled converts layout, dtype and byte order for the C loop.
        return compiled.correlated_pairs(covariances, scan_ids, pose_factors,
                                         POSE_SHARE_MIN, ZERO_VARIANCE_M2)


BACKEND = CompiledBackend()
_SINGLE = CompiledBackend("single")


def _in_precision(precision: str) -> CompiledBackend:
    """The module's backend in ``precision`` (one object each: pickles restore them)."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got "
                         f"{precision!r}")
    return _SINGLE if precision == "single" else BACKEND
