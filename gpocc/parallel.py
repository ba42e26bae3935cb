"""Cores and worker processes: map anchors and training patches both run here.

Worker processes never outlive a run: an exception in the parent (Ctrl-C, SIGTERM via
:mod:`gpocc.lifecycle`, an error) terminates them, and they die with the parent when it is
killed outright (``PR_SET_PDEATHSIG`` on Linux, and a thread polling the parent pid).
"""

from __future__ import annotations

import collections
import contextlib
import ctypes
import multiprocessing
import multiprocessing.pool
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from gpocc.allocator import keep_freed_memory, keeps_freed_memory
from gpocc.blas import single_threaded_blas
from gpocc.errors import GpoccError, SchedulerUnreachable

_PR_SET_PDEATHSIG = 1


def default_workers() -> int:
    """All cores this process may use (its CPU affinity, not the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


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


def _init_worker(parent: int, keep_memory: bool, initializer: Callable[..., None],
                 initargs: tuple) -> None:
    if keep_memory:  # as the parent: a worker not forked from it has glibc's defaults
        keep_freed_memory()
    # Ctrl-C reaches the whole process group: the parent handles it and ends the workers,
    # so they must not print their own KeyboardInterrupt tracebacks.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # not the parent's (gpocc.lifecycle)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
    _die_with_parent(parent)
    single_threaded_blas()  # many small matrices: see gpocc.blas
    initializer(*initargs)


#: The result pipe's capacity asked for (Linux's default cap for any user, as
#: /proc/sys/fs/pipe-max-size): 1 MiB.
RESULT_PIPE_BYTES = 1 << 20


def widen_pipe(connection: Any, size: int = RESULT_PIPE_BYTES) -> None:
    """Ask the kernel for a pipe buffer of ``size`` bytes behind ``connection`` (Linux;
    elsewhere, or if refused, the pipe keeps its size).

    A worker whose result does not fit in the pipe waits until the parent has read it.
    Pool results are read by a thread of the parent that needs the GIL, which the
    parent's own work (loading the map's writers, blending results) holds for up to
    the switch interval at a time: with the default 64 KiB pipe, Intel map workers spent
    0.6-0.9 s each of their 2-3 s waiting to send chunks of about 100 kB."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        return
    setter = getattr(fcntl, "F_SETPIPE_SZ", None)
    if setter is None:  # pragma: no cover - not Linux
        return
    with contextlib.suppress(OSError, ValueError):
        fcntl.fcntl(connection.fileno(), setter, size)


class _Pool(multiprocessing.pool.Pool):
    """``multiprocessing.pool.Pool`` whose worker-maintenance thread wakes only when a
    worker exits or the pool's state changes (close, terminate, the last task done).

    CPython's also waits on the result pipe, so every result makes it loop, polling each
    worker and building a selector, until the result thread has read that result: 0.18 s
    of the parent's CPU in an Intel map (155 chunks) and 0.11 s in its training (430
    patch results), taken from the two cores the workers use. A worker that exits is
    still seen at once through its sentinel, which the thread keeps waiting on.

    ``workers`` are the processes started with the pool: none of them may end before it
    does (the pool replaces a dead one, but the task it held is lost).
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.workers = tuple(self._pool)

    def _setup_queues(self) -> None:
        super()._setup_queues()
        widen_pipe(self._outqueue._writer)

    def _get_sentinels(self):
        return [self._change_notifier._reader]

    def dead_worker_exitcode(self) -> int | None:
        """The exit code of the first of :attr:`workers` that has ended, or None."""
        return next((p.exitcode for p in self.workers if p.exitcode is not None), None)


def _worker_context() -> Any:
    """Linux: fork, whatever the default start method. A forkserver's workers are the
    children of the server, not of this process, so the check that their parent lives
    (:func:`_die_with_parent`) would end each one at its start and the pool would
    replace them forever (Python 3.14 made forkserver Linux's default). Elsewhere, the
    default."""
    if sys.platform.startswith("linux"):
        return multiprocessing.get_context("fork")
    return None


@contextlib.contextmanager
def worker_pool(workers: int, initializer: Callable[..., None],
                initargs: tuple[Any, ...]) -> Iterator[_Pool]:
    """A ``multiprocessing.Pool`` of ``workers`` processes, each set up by
    ``initializer(*initargs)``, that ends (terminated on any exception) with the block."""
    # Workers start with SIGTERM blocked, so none can run the parent's handler (see
    # gpocc.lifecycle) before its initialiser restores the default.
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    try:
        pool = _Pool(workers, initializer=_init_worker,
                     initargs=(os.getpid(), keeps_freed_memory(), initializer, initargs),
                     context=_worker_context())
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
    try:
        yield pool
    except BaseException:
        # Ctrl-C, SIGTERM, an error, or the consumer stopping: no worker may outlive it.
        if pool.dead_worker_exitcode() is not None:
            _kill_workers(pool)
        else:
            pool.terminate()
            pool.join()
        raise
    if pool.dead_worker_exitcode() is not None:
        _kill_workers(pool)  # every result is in, but the pool's own shutdown could hang
        return
    pool.close()
    pool.join()


def _kill_workers(pool: _Pool) -> None:
    """End every worker of ``pool`` at once, without the pool's own shutdown.

    A worker that died while it waited for a task (or sent a result) held a queue's lock,
    and the pool's ``close``/``join``, ``terminate`` and exit-time finaliser all wait for
    that lock forever (gpocc hung so after a worker was killed with ``kill -9`` at the end
    of a map). So: the maintenance thread is told to stop replacing workers, the
    finaliser is cancelled, and the workers are killed; the pool's helper threads are
    daemons and are left behind.
    """
    pool._worker_handler._state = multiprocessing.pool.TERMINATE
    pool._change_notifier.put(None)
    pool._terminate.cancel()
    processes = {*pool.workers, *pool._pool}  # replacements too
    for process in processes:
        if process.exitcode is None:
            process.kill()
    for process in processes:
        process.join(timeout=5.0)


#: Seconds between checks that a pool's workers are alive while waiting for results.
WORKER_CHECK_S = 1.0


def check_workers(pool: _Pool) -> None:
    """Raise :class:`GpoccError` if a worker of ``pool`` (a :func:`worker_pool`) has died.

    ``multiprocessing.Pool`` replaces a worker that dies, but the task it held is lost and
    its result never comes: without this check a worker killed outright (the kernel's
    out-of-memory killer, ``kill -9``) left the map or the training waiting forever.
    """
    code = pool.dead_worker_exitcode()
    if code is None:
        return
    if code == -signal.SIGKILL:
        how = "was killed by signal 9 (SIGKILL: perhaps out of memory; try fewer --workers)"
    elif code < 0:
        how = f"was killed by signal {-code}"
    else:
        how = f"ended with exit status {code}"
    raise GpoccError(f"a worker process {how} during the run; nothing was written")


def watched(pool: _Pool, results: Any) -> Iterator[Any]:
    """The items of ``results`` (``pool.imap``'s iterator), checking every
    :data:`WORKER_CHECK_S` seconds of waiting that no worker has died."""
    while True:
        try:
            yield results.next(timeout=WORKER_CHECK_S)
        except StopIteration:
            return
        except multiprocessing.TimeoutError:
            check_workers(pool)


def wait_for(pool: _Pool, result: multiprocessing.pool.AsyncResult) -> Any:
    """``result.get()`` (of ``pool.map_async`` or ``apply_async``), checking every
    :data:`WORKER_CHECK_S` seconds of waiting that no worker has died."""
    while True:
        try:
            return result.get(timeout=WORKER_CHECK_S)
        except multiprocessing.TimeoutError:
            check_workers(pool)


@contextlib.contextmanager
def thread_map(fn: Callable[[Any], Any], items: Iterable[Any],
               workers: int) -> Iterator[Iterator[Any]]:
    """``fn(item)`` of every item, in order, computed on ``workers`` helper threads while
    the caller works on earlier results: parallel when ``fn`` mostly runs without the GIL
    (compiled ``nogil`` loops, numpy's sorts and large operations). Items are drawn on
    the caller's thread, at most ``workers`` ahead of the result it holds, which bounds
    memory. An exception of ``fn`` is raised where its result would have been. The
    threads have ended when the block exits, so that no fork (worker pools) happens
    beside them.
    """
    from concurrent.futures import Future, ThreadPoolExecutor

    workers = max(1, workers)
    with ThreadPoolExecutor(workers, thread_name_prefix="gpocc-thread") as pool:
        pending: collections.deque[Future] = collections.deque()

        def generate() -> Iterator[Any]:
            try:
                for item in items:
                    pending.append(pool.submit(fn, item))
                    if len(pending) > workers:
                        yield pending.popleft().result()
                while pending:
                    yield pending.popleft().result()
            finally:
                for future in pending:
                    future.cancel()

        stream = generate()
        try:
            yield stream
        finally:
            stream.close()


def _single_threaded_worker() -> None:
    # A plain call (no context) limits BLAS for the worker's whole life; returns nothing,
    # so that nothing has to travel back to the client.
    single_threaded_blas()


#: The clients :func:`dask_client` has open in this process, by scheduler address.
_OPEN_CLIENTS: dict[str, Any] = {}


@contextlib.contextmanager
def dask_client(scheduler: str) -> Iterator[Any]:
    """A ``distributed.Client`` of the Dask cluster at ``scheduler`` (``tcp://HOST:PORT``),
    closed on exit. Its workers run BLAS on one thread, as gpocc's local workers do, so
    that a cluster computes every local problem bit for bit as this process would.

    Nested blocks share one client: inside an open ``dask_client(scheduler)``, another for
    the same address yields the same client and leaves it open, so that a command made of
    stages that each ask for a client (``gpocc build``: training, then the map) connects
    once when it wraps them in one block. The outermost block closes it.

    Raises:
        SchedulerUnreachable: the scheduler cannot be reached or the address is malformed.
    """
    if scheduler in _OPEN_CLIENTS:
        yield _OPEN_CLIENTS[scheduler]
        return
    from distributed import Client

    try:
        client = Client(scheduler, timeout="10s")
    except (OSError, TimeoutError, ValueError) as exc:  # ValueError: a malformed address
        raise SchedulerUnreachable(scheduler, " ".join(str(exc).split())) from None
    _OPEN_CLIENTS[scheduler] = client
    try:
        client.run(_single_threaded_worker)
        yield client
    finally:
        del _OPEN_CLIENTS[scheduler]
        client.close()


def cluster_map(client: Any) -> Callable[[Callable[[Any], Any], Iterable[Any]], list[Any]]:
    """A ``map(fn, items)`` that runs each item as one task on ``client``'s cluster and
    returns the results in ``items`` order (``fn``: a module-level function or a partial
    of one, so that workers can receive it)."""

    def run(fn: Callable[[Any], Any], items: Iterable[Any]) -> list[Any]:
        return client.gather(client.map(fn, list(items), pure=False))

    return run
