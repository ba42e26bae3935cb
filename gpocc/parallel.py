"""How many cores gpocc may use: map processes and training threads both ask here."""

from __future__ import annotations

import os


def default_workers() -> int:
    """All cores this process may use (its CPU affinity, not the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)
