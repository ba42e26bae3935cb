"""The ``gpocc`` console script's entry point, light enough to be in place at once.

:func:`gpocc.cli.main` turns a Ctrl-C into one line and status 130 once it runs, but
importing :mod:`gpocc.cli` itself (typer, rich, pydantic: 0.2-0.3 s) came first, and a
Ctrl-C then printed a KeyboardInterrupt traceback. This module imports nothing but
:mod:`sys` and :mod:`gpocc.constants` (literals) before it catches that. :mod:`gpocc.cli`
does not import it: the line both print is :data:`gpocc.constants.INTERRUPTED`.
"""

from __future__ import annotations

import sys

from gpocc.constants import INTERRUPTED


def main() -> None:
    """Import the CLI, then run it; a Ctrl-C during the import is one line, status 130.
    With glibc, freed memory is kept for the command's later arrays unless the
    environment sets ``GPOCC_KEEP_FREED_MEMORY=0`` (:mod:`gpocc.allocator`)."""
    try:
        from gpocc.allocator import keep_freed_memory

        keep_freed_memory()
        from gpocc.cli import main as run
    except KeyboardInterrupt:
        print(INTERRUPTED, file=sys.stderr)
        raise SystemExit(130) from None
    run()
