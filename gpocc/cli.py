"""The ``gpocc`` command line: wiring only; each command lives in ``gpocc.commands``.

Errors a user can fix (:class:`gpocc.errors.GpoccError`) become one line on stderr and
exit status 2; results go to files and stdout, progress and logs to stderr.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import typer

from gpocc.errors import GpoccError
from gpocc.lifecycle import command_scope

app = typer.Typer(
    name="gpocc",
    help="Gaussian-process occupancy maps from robot logs, with sensor and pose uncertainty.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def command(name: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Register ``fn`` as ``gpocc NAME``, turning a GpoccError into one error line."""

    def register(fn: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(fn)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            try:
                with command_scope():  # SIGTERM as Ctrl-C, OSError as one line
                    return fn(*args, **kwargs)
            except GpoccError as exc:
                typer.echo(f"gpocc {name}: error: {exc}", err=True)
                raise typer.Exit(2) from None
            except KeyboardInterrupt:
                typer.echo(f"gpocc {name}: interrupted; no partial output was left", err=True)
                raise typer.Exit(130) from None

        app.command(name)(wrapper)
        return fn

    return register


def main() -> None:
    """Console-script entry point."""
    app(prog_name="gpocc")


# Command modules register themselves on import; they come last to avoid a cycle.
from gpocc.commands import (  # noqa: E402,F401
    evaluate,
    grid,
    info,
    map,
    simulate,
    split,
    train,
)
