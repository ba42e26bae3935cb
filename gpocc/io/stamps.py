"""Which clock a topic's messages are timed by: their header stamps, or the log time.

A message's header stamp is when its data was taken; the log (receive) time is when the
recorder got it, a few milliseconds later. Header stamps are used when they can be
trusted. A topic whose header stamps are zero (a driver that never sets them), all equal
(a driver that stamps once), or not increasing in log order (a scan topic whose stamps
repeat or go back; a pose topic whose stamps go back: a clock reset or a replayed
segment) is timed by its log time instead, for the whole topic (mixing the two clocks
would reorder messages), with one warning giving the count.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

HEADER = "header stamps"
LOG_TIME = "log (receive) time"


@dataclass(frozen=True)
class Stamps:
    """A topic's message times: (N,) seconds in log order, and where they came from.

    Attributes:
        times: (N,) seconds.
        source: :data:`HEADER` or :data:`LOG_TIME`.
        reason: why the header stamps were not used ("" when they were).
    """

    times: np.ndarray
    source: str
    reason: str = ""

    def describe(self, topic: str) -> str:
        """``/scan: log (receive) time (120 of 120 header stamps are zero)``."""
        return f"{topic}: {self.source}" + (f" ({self.reason})" if self.reason else "")

    def warning(self, topic: str) -> str:
        """The one warning for a topic timed by its log time ("" when it is not)."""
        if not self.reason:
            return ""
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
    zero = int(np.count_nonzero(header == 0.0))
    step = np.diff(header)
    back = int(np.count_nonzero(step < 0 if repeats_allowed else step <= 0))
    if zero:
        reason = f"{zero} of {n} header stamps are zero"
    elif n > 1 and np.all(header == header[0]):
        reason = f"all {n} header stamps are equal ({header[0]:.6f} s)"
    elif back:
        what = "go back" if repeats_allowed else "repeat or go back"
        reason = f"{back} of {n - 1} header stamps {what} in log order"
    if reason:
        return Stamps(log_time, LOG_TIME, reason)
    return Stamps(header, HEADER)
