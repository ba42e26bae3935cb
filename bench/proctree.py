"""The process tree of a running command, for the bench scripts (Linux ``/proc``)."""

from __future__ import annotations


def process_tree(pid: int) -> list[int]:
    """``pid`` and all its descendants, parents first. A process that ends meanwhile is
    still listed (its children, if any were left, are not); callers skip what has gone."""
    found, stack = [], [pid]
    while stack:
        p = stack.pop()
        found.append(p)
        try:
            with open(f"/proc/{p}/task/{p}/children") as fh:
                stack.extend(int(c) for c in fh.read().split())
        except OSError:  # it has ended
            pass
    return found
