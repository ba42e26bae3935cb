"""What every command runs inside: SIGTERM as Ctrl-C, OS errors as one line, claims freed.

``timeout``, Slurm and systemd stop a job with SIGTERM; Python's default would kill the
process without unwinding, leaving temporary outputs and worker processes behind. Here
SIGTERM raises :class:`KeyboardInterrupt` like Ctrl-C, so the same clean-up runs (the
temporaries of :mod:`gpocc.io.atomic` are removed, map workers are terminated in
:mod:`gpocc.mapping.executors`). SIGKILL cannot be caught: workers die with their parent
(``PR_SET_PDEATHSIG``) and the next run on the same output removes the stale temporaries.
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import sys
import threading
from collections.abc import Iterator

from gpocc.errors import GpoccError, first_line
from gpocc.io.atomic import release_all_claims


class Terminated(KeyboardInterrupt):
    """Raised in the main thread when the process receives SIGTERM."""


def _on_sigterm(signum: int, frame: object) -> None:
    raise Terminated()


def describe_os_error(exc: OSError) -> str:
    """One line naming the path (when known) and the cause of ``exc``."""
    cause = exc.strerror or first_line(exc)
    names = [str(n) for n in (exc.filename, exc.filename2) if n is not None]
    where = " -> ".join(names)
    return f"{where}: {cause}" if where else cause


@contextlib.contextmanager
def command_scope() -> Iterator[None]:
    """Run one command: SIGTERM raises KeyboardInterrupt; an OSError becomes a GpoccError.

    Output claims still held at the end (a command that failed before writing) are
    released.
    """
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        yield
    except BrokenPipeError as exc:
        if exc.filename is not None:
            raise GpoccError(f"{describe_os_error(exc)}; check the path") from None
        # Whoever read our stdout went away (`gpocc ... | head`): the files are written;
        # end quietly with the status of a process killed by SIGPIPE, as Unix tools do.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        raise SystemExit(128 + signal.SIGPIPE) from None
    except OSError as exc:
        if exc.errno == errno.ENOSPC:
            where = exc.filename if exc.filename is not None else "writing"
            raise GpoccError(f"{where}: no space left on device; free some space there, or "
                             "write elsewhere") from None
        raise GpoccError(
            f"{describe_os_error(exc)}; check the path, its permissions and free space"
        ) from None
    finally:
        release_all_claims()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
