"""Running map anchors (local problems) serially, on local processes, or on Dask.

Anchors are independent and each is computed by the same deterministic code, so every
executor gives bit-identical results. Workers receive the model once (process
initialiser, or a Dask scatter) and build their own neighbour index; a map opens one
executor for all its tiles (:func:`anchor_executor`), whose local workers load the
compiled kernels as they start.

Local workers never outlive a run (:func:`gpocc.parallel.worker_pool`).
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Iterator
from contextlib import nullcontext

import numpy as np

from gpocc.blas import single_threaded_blas
from gpocc.gp.local import NeighbourIndex, predict_local
from gpocc.gp.model import GPModel
from gpocc.mapping.blocks import (
    Anchor,
    AnchorLattice,
    AnchorResult,
    anchor_problems,
    predict_anchors,
)
from gpocc.parallel import dask_client, watched, worker_pool

_worker_state: dict[str, object] = {}

#: Anchors per task sent to a worker.
ANCHORS_PER_CHUNK = 8


def _chunks(anchors: list[Anchor], size: int) -> list[list[Anchor]]:
    return [anchors[i:i + size] for i in range(0, len(anchors), size)]


def _index_for(model: GPModel) -> NeighbourIndex:
    # One index per model per process: building it costs as much as a few blocks.
    key = id(model)
    if _worker_state.get("key") != key:
        _worker_state.update(key=key, model=model, index=NeighbourIndex(model.samples))
    return _worker_state["index"]  # type: ignore[return-value]


def compute_chunk(model: GPModel, lattice: AnchorLattice,
                  chunk: list[Anchor]) -> list[AnchorResult]:
    """Predict a list of anchors of ``lattice`` with ``model``."""
    index = _index_for(model)
    # Pool workers are single-threaded for life; threadpoolctl's switch costs 1.5 ms
    # (it walks the loaded libraries), a fifth of an anchor, so they skip it.
    limit = nullcontext() if _worker_state.get("single_threaded") else single_threaded_blas()
    with limit:
        return predict_anchors(model, lattice, chunk,
                               anchor_problems(model, index, lattice, chunk))


def _init_worker(model: GPModel) -> None:
    # gpocc.parallel's initialiser has made BLAS single-threaded for this process.
    _worker_state.update(process_model=model, single_threaded=True)
    # Build the neighbour index and touch every routine an anchor uses now, while the
    # parent lays out the tile. A failure here would make the pool restart the worker
    # forever; the anchors that meet the same problem report it.
    with contextlib.suppress(Exception):
        warm_up(model)


def warm_up(model: GPModel) -> None:
    """Predict one query from the neighbourhood of the first sample: loads every compiled
    kernel and LAPACK routine a map anchor uses, and the neighbour index."""
    if len(model.samples) == 0:
        return
    index = _index_for(model)
    centre = model.samples.means[0]
    problem = index.problem(centre, model.config.model.neighbours)
    predict_local(model.kernel, model.noise_variance, problem, centre[None, :], model.level,
                  model.backend)


def _compute_in_worker(lattice: AnchorLattice, chunk: list[Anchor]
                       ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    # Only the predicted layers go back through the result pipe: the parent holds the
    # anchors and makes each footprint's block and weights itself (cached axes), so a
    # chunk is a quarter smaller and unpickles without a dataclass per anchor.
    return [(r.mean, r.variance, r.prior_variance)
            for r in compute_chunk(_worker_state["process_model"], lattice, chunk)]


def _rebuilt(lattice: AnchorLattice, chunk: list[Anchor],
             layers: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> list[AnchorResult]:
    """The :class:`AnchorResult` of each anchor of ``chunk`` from its worker's layers."""
    results = []
    for anchor, (mean, variance, prior) in zip(chunk, layers, strict=True):
        block, weight = lattice.footprint(anchor)
        results.append(AnchorResult(anchor, block, weight, mean, variance, prior))
    return results


class AnchorExecutor:
    """Runs anchors of one model: serially, on a pool of local processes, or on Dask
    (:func:`anchor_executor`). The workers (and the model's copy on a cluster) last for
    every call of :meth:`run`, so a map of many tiles starts them once."""

    def __init__(self, model: GPModel, pool=None, client=None, model_future=None) -> None:
        self.model = model
        #: Whether anchors run on local worker processes (which load their compiled
        #: kernels as they start, so the caller has time to spare at first).
        self.local_workers = pool is not None
        self._pool = pool
        self._client = client
        self._model_future = model_future

    def run(self, lattice: AnchorLattice, anchors: list[Anchor],
            on_done: Callable[[int], None] | None = None) -> Iterator[AnchorResult]:
        """The result of every anchor (in ``anchors`` order); ``on_done(n)`` after each
        chunk (:data:`ANCHORS_PER_CHUNK`) with the number of anchors it held.

        Every chunk is queued for the workers or the cluster before this returns, so
        the caller may do other work before it collects the results; in this process,
        each chunk is computed as it is collected."""
        chunks = _chunks(anchors, ANCHORS_PER_CHUNK)
        if self._client is not None:
            futures = [self._client.submit(compute_chunk, self._model_future, lattice, chunk,
                                           pure=False) for chunk in chunks]
            results: Iterator[list[AnchorResult]] = (f.result() for f in futures)
        elif self._pool is not None:
            results = (_rebuilt(lattice, chunk, layers) for chunk, layers in zip(
                chunks, watched(self._pool, self._pool.imap(
                    functools.partial(_compute_in_worker, lattice), chunks)), strict=True))
        else:
            results = (compute_chunk(self.model, lattice, chunk) for chunk in chunks)
        return _in_order(chunks, results, on_done)


def _in_order(chunks: list[list[Anchor]], results: Iterator[list[AnchorResult]],
              on_done: Callable[[int], None] | None) -> Iterator[AnchorResult]:
    """Each anchor's result, chunk by chunk in ``chunks`` order (``results`` gives one
    list per chunk); ``on_done(n)`` after each chunk of n anchors."""
    for chunk, done in zip(chunks, results, strict=True):
        yield from done
        if on_done:
            on_done(len(chunk))


@contextlib.contextmanager
def anchor_executor(model: GPModel, workers: int = 1, scheduler: str | None = None,
                    anchors: int | None = None) -> Iterator[AnchorExecutor]:
    """An :class:`AnchorExecutor` for ``model``: ``scheduler`` (``tcp://HOST:PORT``) sends
    chunks to a Dask distributed cluster; otherwise ``workers`` > 1 starts that many local
    processes (at once: they load the compiled kernels while the caller prepares its
    anchors) and 1 runs in this process. With ``anchors`` (at most that many to run), no
    more processes than their chunks of :data:`ANCHORS_PER_CHUNK`: ``--workers 10000``
    must not start 10000 processes."""
    if anchors is not None:
        workers = min(workers, -(-anchors // ANCHORS_PER_CHUNK))
    if scheduler:
        with dask_client(scheduler) as client:
            yield AnchorExecutor(model, client=client,
                                 model_future=client.scatter(model, broadcast=True))
        return
    if workers <= 1:
        yield AnchorExecutor(model)
        return
    with worker_pool(workers, _init_worker, (model,)) as pool:
        yield AnchorExecutor(model, pool=pool)


def run_anchors(
    model: GPModel,
    lattice: AnchorLattice,
    anchors: list[Anchor],
    workers: int = 1,
    scheduler: str | None = None,
    on_done: Callable[[int], None] | None = None,
) -> Iterator[AnchorResult]:
    """Yield the result of every anchor (in ``anchors`` order) on a new
    :func:`anchor_executor` (at most one local process per chunk)."""
    with anchor_executor(model, workers, scheduler, len(anchors)) as executor:
        yield from executor.run(lattice, anchors, on_done)
