"""gpocc.parallel: thread_map (fn over items on helper threads, results in order) and
worker_pool (processes)."""

from __future__ import annotations

import multiprocessing.pool
import threading

import pytest

from gpocc.parallel import thread_map, worker_pool


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

