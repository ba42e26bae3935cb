"""The exception types the CLI turns into a single error line."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path


class GpoccError(Exception):
    """A user-facing error: bad input, bad config, refused overwrite.

    The message must name the file (or key) at fault and say how to fix it; the CLI
    prints it as one line and exits non-zero, without a traceback.
    """


class SchedulerUnreachable(GpoccError):
    """No Dask scheduler answers at ``address``; ``cause`` is Dask's reason, one line."""

    def __init__(self, address: str, cause: str) -> None:
        super().__init__(f"cannot reach the Dask scheduler at {address} ({cause}); check "
                         "the address and that the scheduler is running")
        self.address = address
        self.cause = cause


class CompiledLoopsUnavailable(GpoccError, ImportError):
    """gpocc's compiled loops (``gpocc/_kernels.c``) are not built, or older than their
    source: an install problem, said in one line like any other (an ImportError too, for
    code that imports gpocc and checks for it)."""


def first_line(exc: BaseException) -> str:
    """The first line of ``exc``'s message, or its type's name when it has none: the cause
    a one-line error quotes from a library's (often multi-line) message."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def check_regular_file(path: str | os.PathLike[str], what: str, fix: str,
                       missing_fix: str | None = None) -> None:
    """Refuse ``path`` unless it is a regular file (a symlink to one counts).

    Missing paths and folders are refused with ``fix``; pipes, sockets and devices too,
    since gpocc reads its files more than once (format detection, then the read) and a
    pipe would block or give its bytes only once.

    Args:
        path: the file.
        what: what the file should be, e.g. ``"config file"``.
        fix: what to do instead, e.g. ``"check the path"``.
        missing_fix: the fix for a missing path, if not ``fix``.
    """
    path = Path(path)
    if path.is_file():
        return
    if not path.exists():
        raise GpoccError(f"{path}: {what} not found; {missing_fix or fix}")
    if path.is_dir():
        raise GpoccError(f"{path}: is a folder, not a {what}; {fix}")
    raise GpoccError(f"{path}: not a regular file (a pipe, socket or device); save the "
                     f"{what} to a file and pass that file")


def check_distinct(paths: Sequence[str | Path],
                   consequence: str = "or its scans count twice") -> None:
    """Refuse a path given twice (``run.log ./run.log``, a shell glob that also matches a
    named input): its scans would count twice, and the config's ``inputs`` entries, keyed
    by path, cannot tell the two apart. Another name of the same log (a link, a copy) is
    allowed: an ``inputs`` entry each can place it twice (training warns,
    :func:`gpocc.io.records.warn_repeated_content`).

    Raises:
        GpoccError: naming both spellings.
    """
    seen: dict[str, int] = {}
    for i, p in enumerate(paths):
        first = seen.setdefault(os.path.abspath(p), i)
        if first != i:
            also = "" if str(p) == str(paths[first]) else f" (also as {paths[first]})"
            raise GpoccError(f"{p}: given twice{also}; pass each input once, {consequence}")
