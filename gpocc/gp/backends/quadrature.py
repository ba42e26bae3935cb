"""The numpy backend: Gauss-Hermite quadrature of any kernel, and the reference of every
other backend.

The node matrix is evaluated by row groups over its upper triangle only (the expected
matrix is symmetric): a handful of vectorised kernel calls instead of one, for a little
over half of the kernel evaluations and blocks that stay in cache. Gradients are the same
quadrature applied to ``kernel.gradient`` (nodes never depend on the hyperparameters).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING

import numpy as np

from gpocc.gp.expected import (
    _PAIR_CHUNK,
    _Expansion,
    _groups,
    _nparams,
    _reduce_block,
    _reduce_last,
    cholesky_psd,
    gauss_hermite,
)
from gpocc.gp.kernels import Kernel
from gpocc.gp.local import PatchLikelihood, negative_log_likelihood
from gpocc.samples.sampleset import SampleSet

if TYPE_CHECKING:
    from gpocc.gp.backends import Backend


class Quadrature:
    """:class:`gpocc.gp.backends.KernelLoops` for any kernel, in numpy."""

    scale_gradient = False
    symmetric = False

    def matrix(self, kernel: Kernel, ex: _Expansion, means: np.ndarray, k: np.ndarray,
               dk: np.ndarray | None, with_scale_gradient: bool) -> np.ndarray | None:
        n = ex.size
        groups = _groups(ex)
        # Upper triangle only. Values: one call per row group against every later point
        # (fewest calls); gradients hold P values per entry, so square blocks that stay
        # in cache.
        for gi, (r0, r1) in enumerate(groups):
            rows = ex.rows(r0, r1)
            for c0, c1 in groups[gi:] if dk is not None else [(r0, n)]:
                cols = ex.rows(c0, c1)
                if dk is None:
                    block = _reduce_block(kernel(rows.nodes, cols.nodes), rows, cols)
                else:
                    # theta[0] is log(signal_variance), so the first derivative is k.
                    gblock = _reduce_block(kernel.gradient(rows.nodes, cols.nodes), rows,
                                           cols)
                    dk[:, r0:r1, c0:c1] = gblock
                    dk[:, c0:c1, r0:r1] = np.swapaxes(gblock, 1, 2)
                    block = gblock[0]
                k[r0:r1, c0:c1] = block
                k[c0:c1, r0:r1] = block.T
        return None

    def same_scan(self, kernel: Kernel, means: np.ndarray, covariances: np.ndarray,
                  pose_factors: np.ndarray, i: np.ndarray, j: np.ndarray, level: int,
                  with_gradient: bool, input_scale: float, with_scale_gradient: bool
                  ) -> tuple[np.ndarray, np.ndarray | None]:
        unit, w = gauss_hermite(level, 4)
        values = np.empty(i.shape[0])
        grads = np.empty((_nparams(kernel), i.shape[0])) if with_gradient else None
        step = max(1, _PAIR_CHUNK // w.shape[0])
        for lo in range(0, i.shape[0], step):
            ii, jj = i[lo : lo + step], j[lo : lo + step]
            cross = np.einsum("pik,pjk->pij", pose_factors[ii], pose_factors[jj])
            joint = np.empty((ii.shape[0], 4, 4))
            joint[:, :2, :2] = covariances[ii]
            joint[:, 2:, 2:] = covariances[jj]
            joint[:, :2, 2:] = cross
            joint[:, 2:, :2] = np.swapaxes(cross, 1, 2)
            # One GEMM for all pairs, coordinate-major so each coordinate is contiguous.
            nodes = np.tensordot(cholesky_psd(joint), unit, axes=([2], [1]))  # (p, 4, L^4)
            nodes[:, :2] += means[ii, :, None]
            nodes[:, 2:] += means[jj, :, None]
            flat = np.swapaxes(nodes, 0, 1).reshape(4, -1)
            a, b = flat[:2].T, flat[2:].T
            if grads is None:
                values[lo : lo + step] = kernel.pairwise(a, b).reshape(-1, w.shape[0]) @ w
            else:
                g = kernel.pairwise_gradient(a, b)
                grads[:, lo : lo + step] = g.reshape(g.shape[0], -1, w.shape[0]) @ w
                values[lo : lo + step] = grads[0, lo : lo + step]  # d/dlog(signal) = k
        return values, grads

    def cross(self, kernel: Kernel, queries: np.ndarray, ex: _Expansion,
              with_gradient: bool) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        q = queries.shape[0]
        out = np.empty((q, ex.size))
        dout = np.empty((_nparams(kernel), q, ex.size)) if with_gradient else None
        step = max(1, _PAIR_CHUNK // max(1, ex.nodes.shape[0]))
        for lo in range(0, q, step):
            chunk = queries[lo : lo + step]
            out[lo : lo + step] = _reduce_last(kernel(chunk, ex.nodes), ex)
            if dout is not None:
                dout[:, lo : lo + step] = _reduce_last(kernel.gradient(chunk, ex.nodes), ex)
        return out if dout is None else (out, dout)

    def local_system(self, kernel: Kernel, means: np.ndarray, covariances: np.ndarray,
                     queries: np.ndarray, level: int, diagonal: float,
                     scan_ids: np.ndarray | None, pose_factors: np.ndarray | None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        return None

    # Batches: one problem after another here; a backend that gains from doing many at
    # once (a GPU) overrides these.

    def local_systems(self, kernel: Kernel, batch: Sequence[tuple[SampleSet, np.ndarray]],
                      level: int, diagonal: float
                      ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray] | None]:
        return [self.local_system(kernel, s.means, s.covariances, queries, level, diagonal,
                                  s.scan_ids, s.pose_factors) for s, queries in batch]

    def patch_likelihoods(self, kernel: Kernel, noise: float, patches: Sequence[SampleSet],
                          level: int, *, with_gradient: bool, input_scale: float,
                          scale_gradient: bool, backend: Backend, with_fisher: bool = False
                          ) -> Iterator[PatchLikelihood | None]:
        # Lazily: the learner stops at the first patch whose K is not a covariance.
        return (negative_log_likelihood(kernel, noise, s, level, with_gradient=with_gradient,
                                        input_scale=input_scale,
                                        scale_gradient=scale_gradient, backend=backend,
                                        with_fisher=with_fisher)
                for s in patches)


QUADRATURE = Quadrature()


class NumpyBackend:
    """Every expectation by :class:`Quadrature`; node sets and pairs in numpy."""

    name = "numpy"

    def loops(self, kernel: Kernel) -> Quadrature:
        return QUADRATURE

    def nodes_2d(self, means: np.ndarray, covariances: np.ndarray, level: int) -> None:
        return None

    def same_scan_pairs(self, covariances: np.ndarray, scan_ids: np.ndarray,
                        pose_factors: np.ndarray) -> None:
        return None

    def in_precision(self, precision: str) -> NumpyBackend:
        return self  # the reference: double only


BACKEND = NumpyBackend()
