"""The one exception type the CLI turns into a single error line."""


class GpoccError(Exception):
    """A user-facing error: bad input, bad config, refused overwrite.

    The message must name the file (or key) at fault and say how to fix it; the CLI
    prints it as one line and exits non-zero, without a traceback.
    """
