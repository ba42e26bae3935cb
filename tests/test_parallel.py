"""gpocc.parallel.prefetched: a producer one item ahead on a helper thread."""

from __future__ import annotations

import threading

import pytest

from gpocc.parallel import prefetched


def _threads() -> set[str]:
    return {t.name for t in threading.enumerate()}


def test_same_items_in_order_and_produced_ahead() -> None:
    produced: list[int] = []
    reached = [threading.Event() for _ in range(7)]

    def items():
        for k in range(6):
            produced.append(k)
            reached[k].set()
            yield k

    seen = []
    with prefetched(items()) as stream:
        for item in stream:
            seen.append(item)
            if item < 5:
                # while the caller holds item k, the helper produces k + 1 by itself...
                assert reached[item + 1].wait(timeout=10.0)
            # ...and goes no further
            assert len(produced) - 1 - item <= 1
    assert seen == list(range(6))
    assert not any(name.startswith("gpocc-prefetch") for name in _threads())


def test_producer_error_is_raised_in_place_and_the_thread_ends() -> None:
    def items():
        yield 1
        raise ValueError("scan 7 is bad")

    seen = []
    with pytest.raises(ValueError, match="scan 7 is bad"):
        with prefetched(items()) as stream:
            for item in stream:
                seen.append(item)
    assert seen == [1]
    assert not any(name.startswith("gpocc-prefetch") for name in _threads())


def test_consumer_stopping_early_ends_the_thread() -> None:
    with prefetched(iter(range(100))) as stream:
        for item in stream:
            if item == 3:
                break
    assert not any(name.startswith("gpocc-prefetch") for name in _threads())
