"""Running map anchors (local problems) serially, on local processes, or on Dask.

Anchors are independent and each is computed by the same deterministic code, so every
executor gives bit-identical results. Workers receive the model once (process
initialiser, or a Dask scatter) and build their own neighbour index.

Local workers never outlive a run (:func:`gpocc.parallel.worker_pool`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from contextlib import nullcontext

from gpocc.blas import single_threaded_blas
from gpocc.errors import GpoccError
from gpocc.gp.local import NeighbourIndex
from gpocc.gp.model import GPModel
from gpocc.mapping.blocks import Anchor, AnchorLattice, AnchorResult, predict_anchor
from gpocc.parallel import worker_pool

_worker_state: dict[str, object] = {}


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
        return [predict_anchor(model, index, lattice, anchor) for anchor in chunk]


def _init_worker(model: GPModel) -> None:
    # gpocc.parallel's initialiser has made BLAS single-threaded for this process.
    _worker_state.update(process_model=model, single_threaded=True)


def _compute_in_worker(lattice: AnchorLattice, chunk: list[Anchor]) -> list[AnchorResult]:
    return compute_chunk(_worker_state["process_model"], lattice, chunk)


def run_anchors(
    model: GPModel,
    lattice: AnchorLattice,
    anchors: list[Anchor],
    workers: int = 1,
    scheduler: str | None = None,
    chunk_size: int = 8,
    on_done: Callable[[int], None] | None = None,
) -> Iterator[AnchorResult]:
    """Yield the result of every anchor (in ``anchors`` order).

    ``scheduler`` (``tcp://HOST:PORT``) sends chunks to a Dask distributed cluster;
    otherwise ``workers`` > 1 uses local processes and 1 runs in this process.
    ``on_done(n)`` is called after each chunk with the number of anchors it held.
    """
    chunks = _chunks(anchors, chunk_size)
    if scheduler:
        yield from _run_dask(model, lattice, chunks, scheduler, on_done)
        return
    workers = min(workers, len(chunks))  # --workers 10000 must not start 10000 processes
    if workers <= 1:
        for chunk in chunks:
            yield from compute_chunk(model, lattice, chunk)
            if on_done:
                on_done(len(chunk))
        return
    with worker_pool(workers, _init_worker, (model,)) as pool:
        results_per_chunk = pool.imap(functools.partial(_compute_in_worker, lattice), chunks)
        for chunk, results in zip(chunks, results_per_chunk, strict=True):
            yield from results
            if on_done:
                on_done(len(chunk))


def _run_dask(model: GPModel, lattice: AnchorLattice, chunks: list[list[Anchor]],
              scheduler: str,
              on_done: Callable[[int], None] | None) -> Iterator[AnchorResult]:
    from distributed import Client

    try:
        client = Client(scheduler, timeout="10s")
    except (OSError, TimeoutError) as exc:
        raise GpoccError(
            f"cannot reach the Dask scheduler at {scheduler} ({exc}); check the address"
        ) from None
    try:
        model_future = client.scatter(model, broadcast=True)
        futures = [client.submit(compute_chunk, model_future, lattice, chunk, pure=False)
                   for chunk in chunks]
        for chunk, future in zip(chunks, futures, strict=True):
            yield from future.result()
            if on_done:
                on_done(len(chunk))
    finally:
        client.close()
