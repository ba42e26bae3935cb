"""Backends: where the expected kernels of :mod:`gpocc.gp.expected` are computed.

A backend is one module of this package with a ``BACKEND`` object satisfying
:class:`Backend`. It supplies the kernel-independent geometry of the quadrature (the
node sets of 2-D rules, the list of same-scan pairs) where it has a faster form than
numpy, and :class:`KernelLoops` for the kernels it serves; every other kernel gets the
numpy Gauss-Hermite quadrature (:mod:`gpocc.gp.backends.quadrature`), which works for
any :class:`~gpocc.gp.kernels.Kernel`.

``model.backend`` chooses: ``numpy`` (quadrature only: the reference), ``compiled`` (the
C loops of ``gpocc/_kernels.c`` for the kernels they serve) or ``auto`` (compiled where
built). Adding a backend is a module here with a ``BACKEND`` and one entry in
:data:`MODULES`.

``model.diagonal`` (:data:`DIAGONALS`) and ``model.covariance_precision``
(:data:`PRECISIONS`) travel with the backend: :func:`choose` gives the backend's name for
``one-point`` in double precision and otherwise a :class:`Choice`, which :func:`get` turns
into the backend in that precision (``Backend.in_precision``), wrapped by
:mod:`gpocc.gp.backends.diagonal` for another diagonal; every function that takes
``backend=`` then builds its training covariances with that diagonal, and a map's local
systems in that precision.
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from gpocc.gp.expected import _Expansion
    from gpocc.gp.kernels import Kernel
    from gpocc.gp.local import PatchLikelihood
    from gpocc.samples.sampleset import SampleSet

#: backend name -> its module (``auto`` is not a module: the first of ``compiled``,
#: ``numpy`` that loads).
MODULES: dict[str, str] = {
    "numpy": "gpocc.gp.backends.quadrature",
    "compiled": "gpocc.gp.backends.c_loops",
}

#: The values of ``model.backend``.
NAMES: tuple[str, ...] = ("auto", *MODULES)
_AUTO_ORDER = ("compiled", "numpy")

#: The values of ``model.diagonal`` (the first is the default).
DIAGONALS: tuple[str, ...] = ("one-point", "two-draw")
#: The values of ``model.covariance_precision`` (the first is the default): the
#: arithmetic of a map's local systems (``KernelLoops.local_system``); training's
#: likelihoods and gradients are always double.
PRECISIONS: tuple[str, ...] = ("single", "double")


@dataclass(frozen=True)
class Choice:
    """A backend's name with a diagonal other than ``one-point`` or a precision other than
    ``double`` (plain data: it crosses process pools and Dask as the name alone does)."""

    backend: str
    diagonal: str = DIAGONALS[0]
    precision: str = "double"


def choose(backend: str, diagonal: str = DIAGONALS[0], precision: str = "double"
           ) -> str | Choice:
    """What to pass as ``backend=`` for ``model.backend``, ``model.diagonal`` and
    ``model.covariance_precision``: the name itself for ``one-point`` in ``double``, else
    a :class:`Choice`."""
    if diagonal not in DIAGONALS:
        raise ValueError(f"diagonal must be one of {', '.join(DIAGONALS)}, got {diagonal!r}")
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got "
                         f"{precision!r}")
    if diagonal == DIAGONALS[0] and precision == "double":
        return backend
    return Choice(backend, diagonal, precision)


def diagonal_of(backend: str | Choice | Backend) -> str:
    """The training diagonal a ``backend=`` argument asks for."""
    return getattr(backend, "diagonal", DIAGONALS[0])


class KernelLoops(Protocol):
    """The expected kernels of local problems for the kernels a backend serves, one at a
    time and in batches (a map's chunk of anchors, a learner's patches).

    Inputs are the problem's expansion (:class:`gpocc.gp.expected._Expansion`: every
    point's quadrature nodes and weights), its means (N, 2) metres, and preallocated
    outputs. The numpy quadrature implements all of it for any kernel; a backend's
    loops may leave a case to it by inheriting from it.
    """

    #: Whether the loops take ``input_scale`` g themselves and give dK/dlog g; if not,
    #: the caller scales the inputs' covariances and pose factors first.
    scale_gradient: bool
    #: Whether ``matrix`` leaves K (and dK) symmetric as they stand.
    symmetric: bool

    def matrix(self, kernel: Kernel, ex: _Expansion, means: np.ndarray, k: np.ndarray,
               dk: np.ndarray | None, with_scale_gradient: bool) -> np.ndarray | None:
        """Fill the off-diagonal entries of K (N, N) (and dK (P, N, N)); with
        ``with_scale_gradient``, return the diagonal's dK/dlog g (N,)."""
        ...

    def same_scan(self, kernel: Kernel, means: np.ndarray, covariances: np.ndarray,
                  pose_factors: np.ndarray, i: np.ndarray, j: np.ndarray, level: int,
                  with_gradient: bool, input_scale: float, with_scale_gradient: bool
                  ) -> tuple[np.ndarray, np.ndarray | None]:
        """E[k(x_i, x_j)] of correlated same-scan pairs under their joint 4-D rule:
        values (Pp,) and, with ``with_gradient``, gradients (P, Pp)."""
        ...

    def cross(self, kernel: Kernel, queries: np.ndarray, ex: _Expansion,
              with_gradient: bool) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Kx (Q, N) for exact (Q, 2) queries, or (Kx, dKx (P, Q, N))."""
        ...

    def local_system(self, kernel: Kernel, means: np.ndarray, covariances: np.ndarray,
                     queries: np.ndarray, level: int, diagonal: float,
                     scan_ids: np.ndarray | None, pose_factors: np.ndarray | None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """K + diagonal I, Kx and k(q, q) of one prediction in one pass, or None where
        the loops have no such pass (the caller makes the separate calls)."""
        ...

    def local_systems(self, kernel: Kernel, batch: Sequence[tuple[SampleSet, np.ndarray]],
                      level: int, diagonal: float
                      ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray] | None]:
        """:meth:`local_system` of a batch of local problems (samples with means centred,
        and their centred (Q, 2) queries): a map's chunk of anchors."""
        ...

    def patch_likelihoods(self, kernel: Kernel, noise: float, patches: Sequence[SampleSet],
                          level: int, *, with_gradient: bool, input_scale: float,
                          scale_gradient: bool, backend: Backend, with_fisher: bool = False
                          ) -> Iterable[PatchLikelihood | None]:
        """Each training patch's -LML and its gradient in ``[kernel.theta..., log noise
        (, log g)]`` (:func:`gpocc.gp.local.negative_log_likelihood`; with
        ``with_fisher`` also its Fisher information), or None where K is not a
        covariance; in patch order, and a consumer may stop at the first None."""
        ...


class Backend(Protocol):
    """A backend module's ``BACKEND``."""

    #: Its name in ``model.backend`` (and in the node-set cache's keys).
    name: str

    def loops(self, kernel: Kernel) -> KernelLoops:
        """Its loops for ``kernel``, or the numpy quadrature for a kernel it does not
        serve."""
        ...

    def nodes_2d(self, means: np.ndarray, covariances: np.ndarray, level: int
                 ) -> tuple[np.ndarray, np.ndarray] | None:
        """(M, 2) nodes (point-major) and (L,) weights of N points that all have a
        covariance, each under its own 2-D rule; None: the numpy path builds them."""
        ...

    def same_scan_pairs(self, covariances: np.ndarray, scan_ids: np.ndarray,
                        pose_factors: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """The correlated same-scan pairs (:func:`gpocc.gp.expected.same_scan_pairs`'
        rule), or None: the numpy path lists them."""
        ...

    def in_precision(self, precision: str) -> Backend:
        """This backend with its local systems in ``precision`` (:data:`PRECISIONS`), or
        itself where it has one precision only (numpy: double)."""
        ...


@functools.cache
def _load(name: str) -> Backend:
    return importlib.import_module(MODULES[name]).BACKEND


def get(backend: str | Choice | Backend = "auto") -> Backend:
    """The backend named ``backend`` (one of :data:`NAMES`), or ``backend`` itself.

    ``auto`` is the compiled backend where its library loads, else numpy; ``compiled``
    without a built library raises the loader's ImportError (how to build it). A
    :class:`Choice` gives its backend in its precision with its diagonal."""
    if isinstance(backend, Choice):
        return _chosen(backend)
    if not isinstance(backend, str):
        return backend
    if backend == "auto":
        return _auto()
    if backend not in MODULES:
        raise ValueError(f"backend must be one of {', '.join(NAMES)}, got {backend!r}")
    return _load(backend)


@functools.cache
def _auto() -> Backend:
    for name in _AUTO_ORDER[:-1]:
        try:
            return _load(name)
        except ImportError:
            continue
    return _load(_AUTO_ORDER[-1])


@functools.cache
def _chosen(choice: Choice) -> Backend:
    base = get(choice.backend).in_precision(choice.precision)
    if choice.diagonal == DIAGONALS[0]:
        return base
    from gpocc.gp.backends.diagonal import DiagonalBackend  # it imports gp.expected

    return DiagonalBackend(choice, base)
