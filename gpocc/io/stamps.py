"""Which clock a topic's messages are timed by: their header stamps, or the log time.

A message's header stamp is when its data was taken; the log (receive) time is when the
recorder got it, a few milliseconds later. Header stamps are used when they can be
trusted. A topic whose header stamps are zero (a driver that never sets them), all equal
(a driver that stamps once), or not increasing in log order (a scan topic whose stamps
repeat or go back; a pose topic whose stamps go back: a clock reset or a replayed
segment) is timed by its log time instead, for the whole topic (mixing the two clocks
would reorder messages), with one warning giving the count.

A few bad stamps among good ones (at most :data:`MAX_DROPPED_SHARE` of the topic: a zero
stamp, a repeated one, one out of order) are a glitch, not a broken clock: those messages
are dropped, with one warning, and the rest keep their header stamps. Switching the
whole topic to log time for them would shift every message by the recorder's latency
against TF, which stays on header stamps (a ghost of every wall at 0.4 s of latency).
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np

HEADER = "header stamps"
LOG_TIME = "log (receive) time"
#: Most messages of a topic whose bad header stamps are dropped (a glitch); more, and the
#: topic is timed by its log time.
MAX_DROPPED_SHARE = 0.05


@dataclass(frozen=True)
class Stamps:
    """A topic's message times: (N,) seconds in log order, and where they came from.

    Attributes:
        times: (N,) seconds.
        source: :data:`HEADER` or :data:`LOG_TIME`.
        reason: why the header stamps were not used ("" when they were), or, with
            ``keep``, why some messages are dropped.
        keep: (N,) bool, the messages to use (None: all).
    """

    times: np.ndarray
    source: str
    reason: str = ""
    keep: np.ndarray | None = None

    def describe(self, topic: str) -> str:
        """``/scan: log (receive) time (120 of 120 header stamps are zero)``."""
        return f"{topic}: {self.source}" + (f" ({self.reason})" if self.reason else "")

    def warning(self, topic: str) -> str:
        """The one warning for a topic timed by its log time, or with messages dropped
        ("" when neither)."""
        if not self.reason:
            return ""
        if self.keep is not None:
            return (f"topic {topic}: {self.reason}; those messages are dropped, the others "
                    "keep their header stamps")
        return (f"topic {topic}: {self.reason}; its messages are timed by their log "
                "(receive) time instead (fix the driver's header stamps to use the time "
                "the data was taken)")


def choose_stamps(header: np.ndarray, log_time: np.ndarray, repeats_allowed: bool) -> Stamps:
    """The times of one topic's messages (see the module docs for the rules).

    Args:
        header: (N,) header stamps, seconds, in log order; 0 where the stamp is zero.
        log_time: (N,) log times, seconds.
        repeats_allowed: whether two consecutive messages may share a stamp (pose topics
            repeat a message; a laser never takes two scans at once).
    """
    header = np.asarray(header, dtype=float)
    log_time = np.asarray(log_time, dtype=float)
    n = header.size
    reason = ""
    # A zero stamp is unset, unless the recorder logged the message at time 0 too (a log
    # converted from line order, as gpocc split writes CARMEN logs: scan 0 at 0 s).
    unset = (header == 0.0) & (log_time != 0.0)
    zero = int(np.count_nonzero(unset))
    step = np.diff(header)
    back = int(np.count_nonzero(step < 0 if repeats_allowed else step <= 0))
    if zero:
        reason = f"{zero} of {n} header stamps are zero"
    elif n > 1 and np.all(header == header[0]):
        reason = f"all {n} header stamps are equal ({header[0]:.6f} s)"
    elif back:
        what = "go back" if repeats_allowed else "repeat or go back"
        reason = f"{back} of {n - 1} header stamps {what} in log order"
    if not reason:
        return Stamps(header, HEADER)
    keep = _ordered(header, unset, repeats_allowed)
    dropped = n - int(np.count_nonzero(keep))
    if dropped <= MAX_DROPPED_SHARE * n:  # all equal or all zero: never (n > 20)
        what = "are zero or go back" if repeats_allowed else "are zero, repeat or go back"
        return Stamps(header, HEADER, f"{dropped} of {n} header stamps {what}", keep)
    return Stamps(log_time, LOG_TIME, reason)


def _ordered(header: np.ndarray, unset: np.ndarray, repeats_allowed: bool) -> np.ndarray:
    """(N,) bool: the most messages of ``header`` (N,) s, leaving out ``unset`` (N,), whose
    stamps increase in log order. With ``repeats_allowed`` a message may repeat the
    stamp of the one just before it (a pose topic's repeat), not an earlier one (a stale
    stamp): runs of equal consecutive stamps are kept or dropped whole."""
    stamped = np.flatnonzero(~unset)
    values = header[stamped]
    if repeats_allowed and values.size:
        first = np.r_[True, values[1:] != values[:-1]]
        runs = np.cumsum(first) - 1
        kept = _increasing(values[first])[runs]
    else:
        kept = _increasing(values)
    keep = np.zeros(header.size, bool)
    keep[stamped[kept]] = True
    return keep


def _increasing(values: np.ndarray) -> np.ndarray:
    """(N,) bool: a longest strictly increasing subsequence of ``values`` (N,) in their
    order (patience sorting, O(N log N)); of equal values the first is kept, as tf2
    keeps the first transform of a repeated stamp."""
    tails: list[float] = []  # tails[k]: the smallest end of an increasing run of k + 1
    tail_at: list[int] = []
    parent = np.full(values.size, -1)
    for i, v in enumerate(values.tolist()):
        k = bisect.bisect_left(tails, v)
        if k < len(tails) and tails[k] == v:
            continue
        if k == len(tails):
            tails.append(v)
            tail_at.append(i)
        else:
            tails[k], tail_at[k] = v, i
        parent[i] = tail_at[k - 1] if k else -1
    keep = np.zeros(values.size, bool)
    i = tail_at[-1] if tail_at else -1
    while i >= 0:
        keep[i] = True
        i = parent[i]
    return keep
