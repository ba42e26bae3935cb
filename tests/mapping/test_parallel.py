"""gpocc.parallel: thread_map (fn over items on helper threads, results in order) and
worker_pool (processes)."""

from __future__ import annotations

import multiprocessing
import multiprocessing.pool
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time

import pytest

from gpocc import parallel
from gpocc.errors import GpoccError
from gpocc.parallel import thread_map, wait_for, watched, worker_pool


def _threads() -> set[str]:
    return {t.name for t in threading.enumerate()}


def _no_helper_left() -> bool:
    return not any(name.startswith("gpocc-thread") for name in _threads())


def test_results_in_order_from_concurrent_calls_at_most_workers_ahead() -> None:
    drawn: list[int] = []
    # Two calls must be under way at once, or neither passes the barrier.
    barrier = threading.Barrier(2, timeout=10.0)

    def items():
        for k in range(9):
            drawn.append(k)
            yield k

    def square(k: int) -> int:
        if k < 2:
            barrier.wait()
        return k * k

    seen = []
    with thread_map(square, items(), workers=2) as results:
        for result in results:
            seen.append(result)
            # the items drawn never run more than `workers` ahead of the result held
            assert len(drawn) - len(seen) <= 2
    assert seen == [k * k for k in range(9)]
    assert _no_helper_left()


def test_an_error_is_raised_in_place_and_the_threads_end() -> None:
    def fn(k: int) -> int:
        if k == 3:
            raise ValueError("scan 7 is bad")
        return k

    seen = []
    with pytest.raises(ValueError, match="scan 7 is bad"):
        with thread_map(fn, range(10), workers=2) as results:
            for result in results:
                seen.append(result)
    assert seen == [0, 1, 2]
    assert _no_helper_left()


def test_consumer_stopping_early_ends_the_threads_and_draws_no_more() -> None:
    drawn: list[int] = []

    def items():
        for k in range(100):
            drawn.append(k)
            yield k

    with thread_map(lambda k: k, items(), workers=2) as results:
        for result in results:
            if result == 3:
                break
    assert _no_helper_left()
    assert len(drawn) <= 6


def test_one_worker_and_no_items() -> None:
    with thread_map(lambda k: -k, range(4), workers=1) as results:
        assert list(results) == [0, -1, -2, -3]
    with thread_map(lambda k: k, [], workers=2) as results:
        assert list(results) == []
    assert _no_helper_left()


def _square(k: int) -> int:
    return k * k


def _init_nothing() -> None:
    pass


def test_worker_pool_maintenance_thread_does_not_wake_on_every_result(monkeypatch) -> None:
    """The pool's maintenance thread waits for worker exits and state changes only; the
    stock Pool also woke (and polled every worker) for each result in the pipe."""
    wakes = []
    stock = multiprocessing.pool.Pool._wait_for_updates

    def counted(sentinels, change_notifier, timeout=None):
        wakes.append(len(sentinels))
        return stock(sentinels, change_notifier, timeout)

    # The maintenance thread calls it on the base class (``Pool._handle_workers``).
    monkeypatch.setattr(multiprocessing.pool.Pool, "_wait_for_updates", staticmethod(counted))
    with worker_pool(2, _init_nothing, ()) as pool:
        assert pool.map(_square, range(300), chunksize=1) == [k * k for k in range(300)]
        assert list(pool.imap(_square, range(200))) == [k * k for k in range(200)]
    # One wait to start with, and one per state change (each map's end, close): never
    # one per result (500 results).
    assert 1 <= len(wakes) <= 10


@pytest.mark.skipif(sys.platform != "linux", reason="the start method is chosen on Linux only")
def test_a_worker_pool_works_when_the_default_start_method_is_forkserver() -> None:
    """Python 3.14's default on Linux: the pool still forks its workers (a forkserver's
    workers are not the children of the process that checks on them, and were ended and
    replaced forever: the map never came back)."""
    probe = textwrap.dedent("""
        import multiprocessing, os
        from gpocc.parallel import worker_pool
        multiprocessing.set_start_method("forkserver")
        with worker_pool(2, os.getpid, ()) as pool:
            print(sum(pool.apply(os.getpid) != os.getpid() for _ in range(8)))
    """)
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                          timeout=60, check=True)
    assert done.stdout.split() == ["8"]


@pytest.mark.skipif(sys.platform != "linux", reason="pipe capacity is set on Linux only")
def test_the_result_pipe_takes_half_a_megabyte_that_nobody_reads() -> None:
    """A worker's results fit in the pool's result pipe while the parent is busy: with
    the default 64 KiB pipe a non-blocking write stops at 64 KiB."""
    import fcntl

    reader, writer = multiprocessing.Pipe(duplex=False)
    with reader, writer:
        parallel.widen_pipe(writer)
        os.set_blocking(writer.fileno(), False)
        size = parallel.RESULT_PIPE_BYTES // 2
        assert os.write(writer.fileno(), b"\0" * size) == size
    with worker_pool(1, _init_nothing, ()) as pool:
        capacity = fcntl.fcntl(pool._outqueue._writer.fileno(), fcntl.F_GETPIPE_SZ)
    assert capacity >= parallel.RESULT_PIPE_BYTES


def _die_on(k: int) -> int:
    if k == 5:  # killed outright, as by the kernel's out-of-memory killer
        os.kill(os.getpid(), signal.SIGKILL)
    return k


def test_a_worker_killed_outright_is_an_error_not_a_hang(monkeypatch) -> None:
    """The stock Pool replaces the dead worker but never returns the task it held, so
    ``imap`` and ``map`` waited forever; watched() and wait_for() raise instead."""
    monkeypatch.setattr(parallel, "WORKER_CHECK_S", 0.2)
    for consume in ("imap", "map_async"):
        started = time.monotonic()
        with pytest.raises(GpoccError, match=r"killed by signal 9 \(SIGKILL: perhaps out"):
            with worker_pool(2, _init_nothing, ()) as pool:
                if consume == "imap":
                    list(watched(pool, pool.imap(_die_on, range(20))))
                else:
                    wait_for(pool, pool.map_async(_die_on, range(20), chunksize=1))
        assert time.monotonic() - started < 30.0


def test_watched_and_wait_for_give_every_result_when_workers_live() -> None:
    with worker_pool(2, _init_nothing, ()) as pool:
        assert list(watched(pool, pool.imap(_square, range(50)))) == [
            k * k for k in range(50)]
        assert wait_for(pool, pool.map_async(_square, range(50))) == [k * k for k in range(50)]



def test_a_worker_killed_while_idle_does_not_hang_the_pool_s_end_or_the_exit() -> None:
    """A worker killed while it waits for a task (holding the task queue's lock) after
    every result is in: leaving worker_pool, and then the interpreter (whose exit runs the
    pool's finaliser), must not wait for that lock forever. In a fresh interpreter."""
    script = (
        "import os, signal, time\n"
        "from gpocc.parallel import worker_pool\n"
        "def square(k):\n"
        "    return k * k\n"
        "def init():\n"
        "    pass\n"
        "if __name__ == '__main__':\n"
        "    with worker_pool(2, init, ()) as pool:\n"
        "        assert pool.map(square, range(10)) == [k * k for k in range(10)]\n"
        "        os.kill(pool.workers[0].pid, signal.SIGKILL)\n"
        "        while pool.workers[0].exitcode is None:\n"
        "            time.sleep(0.05)\n"
        "    print('left')\n"
    )
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "left"
