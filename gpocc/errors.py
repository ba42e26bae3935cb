"""The exception types the CLI turns into a single error line."""


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
