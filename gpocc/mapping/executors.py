"""Running map anchors (local problems) serially, on local processes, or on Dask.

Anchors are independent and each is computed by the same deterministic code, so every
executor gives bit-identical results. Workers receive the model once (process
initialiser, or a Dask scatter) and build their own neighbour index.

Local workers never outlive a run: any exception in the parent (Ctrl-C, SIGTERM via
:mod:`gpocc.lifecycle`, an error) terminates them, and they die with the parent when it
is killed outright (``PR_SET_PDEATHSIG`` on Linux, and a thread polling the parent pid).
"""

from __future__ import annotations

import ctypes
import functools
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator

from gpocc.blas import single_threaded_blas
from gpocc.errors import GpoccError
from gpocc.gp.local import NeighbourIndex
from gpocc.gp.model import GPModel
from gpocc.mapping.blocks import Anchor, AnchorLattice, AnchorResult, predict_anchor

_worker_state: dict[str, object] = {}
_PR_SET_PDEATHSIG = 1


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
    with single_threaded_blas():
        return [predict_anchor(model, index, lattice, anchor) for anchor in chunk]


def _die_with_parent(parent: int) -> None:
    """End this worker when ``parent`` dies, even by SIGKILL (which it cannot catch)."""
    try:  # Linux: the kernel sends SIGKILL when the parent exits.
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        pass
    if os.getppid() != parent:  # the parent died before prctl took effect
        os._exit(1)

    def watch() -> None:  # elsewhere (and as a backstop): poll the parent
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="gpocc-parent-watch").start()


def _init_worker(model: GPModel, parent: int) -> None:
    # Ctrl-C reaches the whole process group: the parent handles it and ends the workers,
    # so they must not print their own KeyboardInterrupt tracebacks.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # not the parent's (gpocc.lifecycle)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
    _die_with_parent(parent)
    _worker_state["process_model"] = model


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
    pool = None
    try:
        # Workers start with SIGTERM blocked, so none can run the parent's handler (see
        # gpocc.lifecycle) before its initialiser restores the default.
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
        try:
            pool = multiprocessing.Pool(workers, initializer=_init_worker,
                                        initargs=(model, os.getpid()))
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        results_per_chunk = pool.imap(functools.partial(_compute_in_worker, lattice), chunks)
        for chunk, results in zip(chunks, results_per_chunk, strict=True):
            yield from results
            if on_done:
                on_done(len(chunk))
    except BaseException:
        # Ctrl-C, SIGTERM, an error, or the consumer stopping: no worker may outlive it.
        if pool is not None:
            pool.terminate()
            pool.join()
        raise
    pool.close()
    pool.join()


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
