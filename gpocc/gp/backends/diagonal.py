"""A backend with another training diagonal (``model.diagonal``): the wrapped backend's
loops, with every training covariance's diagonal taken from
:func:`gpocc.gp.expected.two_draw_diag`.

:func:`gpocc.gp.expected.expected_kernel_matrix` (training likelihood, the classifier's
leave-one-out) reads the diagonal from the backend it is given; the one-pass local
systems of a map are the wrapped backend's, with their diagonal replaced here. The
off-diagonal entries, cross-covariances and node sets are the wrapped backend's.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from gpocc.gp.backends import Backend, Choice, KernelLoops
from gpocc.gp.expected import two_draw_diag
from gpocc.gp.kernels import Kernel
from gpocc.samples.sampleset import SampleSet

if TYPE_CHECKING:
    from gpocc.gp.local import PatchLikelihood

System = tuple[np.ndarray, np.ndarray, np.ndarray]


class DiagonalLoops:
    """``base``'s loops with the local systems' diagonal replaced."""

    def __init__(self, base: KernelLoops, backend: DiagonalBackend) -> None:
        self._base = base
        self._backend = backend

    def __getattr__(self, name: str) -> Any:
        return getattr(self._base, name)

    def _corrected(self, kernel: Kernel, system: System | None, means: np.ndarray,
                   covariances: np.ndarray, level: int, diagonal: float,
                   scan_ids: np.ndarray | None, pose_factors: np.ndarray | None
                   ) -> System | None:
        if system is None:
            return None
        k = system[0]
        np.einsum("ii->i", k)[:] = two_draw_diag(  # the diagonal, as a writable view
            kernel, means, covariances, level, scan_ids=scan_ids, pose_factors=pose_factors,
            backend=self._backend) + diagonal
        return system

    def local_system(self, kernel: Kernel, means: np.ndarray, covariances: np.ndarray,
                     queries: np.ndarray, level: int, diagonal: float,
                     scan_ids: np.ndarray | None, pose_factors: np.ndarray | None
                     ) -> System | None:
        system = self._base.local_system(kernel, means, covariances, queries, level,
                                         diagonal, scan_ids, pose_factors)
        return self._corrected(kernel, system, means, covariances, level, diagonal,
                               scan_ids, pose_factors)

    def local_systems(self, kernel: Kernel, batch: Sequence[tuple[SampleSet, np.ndarray]],
                      level: int, diagonal: float) -> list[System | None]:
        systems = self._base.local_systems(kernel, batch, level, diagonal)
        return [self._corrected(kernel, system, s.means, s.covariances, level, diagonal,
                                s.scan_ids, s.pose_factors)
                for system, (s, _) in zip(systems, batch, strict=True)]

    def patch_likelihoods(self, kernel: Kernel, noise: float, patches: Sequence[SampleSet],
                          level: int, *, with_gradient: bool, input_scale: float,
                          scale_gradient: bool, backend: Backend, with_fisher: bool = False
                          ) -> Iterable[PatchLikelihood | None]:
        # The base's likelihoods build K through expected_kernel_matrix with this backend.
        return self._base.patch_likelihoods(
            kernel, noise, patches, level, with_gradient=with_gradient,
            input_scale=input_scale, scale_gradient=scale_gradient, backend=self._backend,
            with_fisher=with_fisher)


class DiagonalBackend:
    """``base`` with the diagonal of ``choice``; named as ``base`` (same node sets)."""

    def __init__(self, choice: Choice, base: Backend) -> None:
        self.choice = choice
        self.diagonal = choice.diagonal
        self.base = base
        self.name = base.name

    def __reduce__(self) -> tuple[Any, tuple[Choice]]:
        from gpocc.gp import backends

        return backends.get, (self.choice,)

    def loops(self, kernel: Kernel) -> DiagonalLoops:
        return DiagonalLoops(self.base.loops(kernel), self)

    def nodes_2d(self, means: np.ndarray, covariances: np.ndarray, level: int
                 ) -> tuple[np.ndarray, np.ndarray] | None:
        return self.base.nodes_2d(means, covariances, level)

    def same_scan_pairs(self, covariances: np.ndarray, scan_ids: np.ndarray,
                        pose_factors: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        return self.base.same_scan_pairs(covariances, scan_ids, pose_factors)

    def in_precision(self, precision: str) -> Backend:
        from gpocc.gp import backends

        return backends.get(Choice(self.choice.backend, self.diagonal, precision))
