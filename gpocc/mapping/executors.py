"""Running map blocks serially, on local processes, or on a Dask distributed cluster.

Blocks are independent and each is computed by the same deterministic code, so every
executor gives bit-identical results. Workers receive the model once (process
initialiser, or a Dask scatter) and build their own neighbour index.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor

from gpocc.blas import single_threaded_blas
from gpocc.errors import GpoccError
from gpocc.gp.local import NeighbourIndex
from gpocc.gp.model import GPModel
from gpocc.gridspec import GridSpec
from gpocc.mapping.blocks import Block, BlockResult, predict_block

_worker_state: dict[str, object] = {}


def _chunks(blocks: list[Block], size: int) -> list[list[Block]]:
    return [blocks[i:i + size] for i in range(0, len(blocks), size)]


def _index_for(model: GPModel) -> NeighbourIndex:
    # One index per model per process: building it costs as much as a few blocks.
    key = id(model)
    if _worker_state.get("key") != key:
        _worker_state.update(key=key, model=model, index=NeighbourIndex(model.samples))
    return _worker_state["index"]  # type: ignore[return-value]


def compute_chunk(model: GPModel, spec: GridSpec, chunk: list[Block]) -> list[BlockResult]:
    """Predict a list of blocks of ``spec`` with ``model``."""
    index = _index_for(model)
    with single_threaded_blas():
        return [predict_block(model, index, spec, block) for block in chunk]


def _init_worker(model: GPModel) -> None:
    _worker_state["process_model"] = model


def _compute_in_worker(spec: GridSpec, chunk: list[Block]) -> list[BlockResult]:
    return compute_chunk(_worker_state["process_model"], spec, chunk)


def default_workers() -> int:
    """All cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def run_blocks(
    model: GPModel,
    spec: GridSpec,
    blocks: list[Block],
    workers: int = 1,
    scheduler: str | None = None,
    chunk_size: int = 8,
    on_done: Callable[[int], None] | None = None,
) -> Iterator[BlockResult]:
    """Yield the result of every block (in ``blocks`` order).

    ``scheduler`` (``tcp://HOST:PORT``) sends chunks to a Dask distributed cluster;
    otherwise ``workers`` > 1 uses local processes and 1 runs in this process.
    ``on_done(n)`` is called after each chunk with the number of blocks it held.
    """
    chunks = _chunks(blocks, chunk_size)
    if scheduler:
        yield from _run_dask(model, spec, chunks, scheduler, on_done)
        return
    if workers <= 1 or len(chunks) <= 1:
        for chunk in chunks:
            yield from compute_chunk(model, spec, chunk)
            if on_done:
                on_done(len(chunk))
        return
    with ProcessPoolExecutor(max_workers=workers, initializer=_init_worker,
                             initargs=(model,)) as pool:
        results_per_chunk = pool.map(_compute_in_worker, [spec] * len(chunks), chunks)
        for chunk, results in zip(chunks, results_per_chunk, strict=True):
            yield from results
            if on_done:
                on_done(len(chunk))


def _run_dask(model: GPModel, spec: GridSpec, chunks: list[list[Block]], scheduler: str,
              on_done: Callable[[int], None] | None) -> Iterator[BlockResult]:
    from distributed import Client

    try:
        client = Client(scheduler, timeout="10s")
    except (OSError, TimeoutError) as exc:
        raise GpoccError(
            f"cannot reach the Dask scheduler at {scheduler} ({exc}); check the address"
        ) from None
    try:
        model_future = client.scatter(model, broadcast=True)
        futures = [client.submit(compute_chunk, model_future, spec, chunk, pure=False)
                   for chunk in chunks]
        for chunk, future in zip(chunks, futures, strict=True):
            yield from future.result()
            if on_done:
                on_done(len(chunk))
    finally:
        client.close()
