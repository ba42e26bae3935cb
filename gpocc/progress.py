"""Progress bars and log lines on stderr (stdout is kept for results).

How much goes to stderr is one process-wide setting, :func:`set_verbosity`: ``QUIET``
prints nothing (errors are the CLI's business), ``NORMAL`` prints :func:`log` lines and
progress bars, ``VERBOSE`` adds :func:`debug` lines.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

QUIET, NORMAL, VERBOSE = 0, 1, 2

_console = Console(stderr=True)
_verbosity = NORMAL


def set_verbosity(level: int) -> None:
    """``QUIET``, ``NORMAL`` or ``VERBOSE`` for every later log line and progress bar."""
    global _verbosity
    _verbosity = level


def log(message: str) -> None:
    """One progress/log line on stderr (not when quiet)."""
    # soft_wrap: one line stays one line (rich would break it at the console's width, 80
    # columns off a terminal), so that logs can be searched line by line.
    if _verbosity >= NORMAL:
        _console.print(message, highlight=False, markup=False, soft_wrap=True)


def debug(message: str) -> None:
    """One detail line on stderr, only when verbose."""
    if _verbosity >= VERBOSE:
        _console.print(message, highlight=False, markup=False, soft_wrap=True)


@contextlib.contextmanager
def progress_bar(total: int, description: str) -> Iterator[Callable[[int], None]]:
    """A progress bar on stderr (none when quiet); yields ``advance(n)`` to call as work
    completes."""
    if _verbosity < NORMAL:
        yield lambda n: None
        return
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
               TimeElapsedColumn())
    with Progress(*columns, console=_console, transient=False) as progress:
        task = progress.add_task(description, total=total)
        yield lambda n: progress.advance(task, n)
