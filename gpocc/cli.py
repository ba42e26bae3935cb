"""The ``gpocc`` command line: wiring only; each command lives in ``gpocc.commands``.

Commands are plain functions registered here from :data:`COMMANDS` (command modules never
import this module, so there is no import cycle). Registration adds what every command
shares: ``--quiet`` / ``--verbose`` and the error policy: errors a user can fix
(:class:`gpocc.errors.GpoccError`) become one line on stderr and exit status 2; results
go to files and stdout, progress and logs to stderr.
"""

from __future__ import annotations

import functools
import inspect
import typing
from collections.abc import Callable
from typing import Annotated, Any

import typer

import gpocc
from gpocc import progress
from gpocc.commands import config as config_cmd
from gpocc.commands import evaluate, grid, info, simulate, split, train
from gpocc.commands import map as map_cmd
from gpocc.errors import GpoccError
from gpocc.lifecycle import command_scope

#: (name, function) of every ``gpocc`` subcommand, in help order.
COMMANDS: tuple[tuple[str, Callable[..., Any]], ...] = (
    ("info", info.info),
    ("train", train.train),
    ("map", map_cmd.map_command),
    ("grid", grid.grid_command),
    ("evaluate", evaluate.evaluate),
    ("split", split.split),
    ("simulate", simulate.simulate_command),
    ("config", config_cmd.config_command),
)

app = typer.Typer(
    name="gpocc",
    help="Gaussian-process occupancy maps from robot logs, with sensor and pose uncertainty.",
    no_args_is_help=True,
    add_completion=True,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)

Quiet = Annotated[bool, typer.Option(
    "--quiet", "-q", help="No progress or log lines on stderr (errors still show).")]
Verbose = Annotated[bool, typer.Option(
    "--verbose", "-v", help="More log lines on stderr.")]


def _version(value: bool) -> None:
    if value:
        typer.echo(f"gpocc {gpocc.__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[bool, typer.Option(
        "--version", callback=_version, is_eager=True, help="Print the version and exit.")
    ] = False,
) -> None:
    """Gaussian-process occupancy maps from robot logs, with sensor and pose uncertainty."""


def register(name: str, fn: Callable[..., Any]) -> None:
    """Add ``fn`` as ``gpocc NAME`` with ``--quiet/--verbose`` and one-line errors."""

    @functools.wraps(fn)
    def wrapper(*args: Any, quiet: bool = False, verbose: bool = False, **kwargs: Any) -> Any:
        if quiet and verbose:
            typer.echo(f"gpocc {name}: error: --quiet and --verbose exclude each other",
                       err=True)
            raise typer.Exit(2)
        progress.set_verbosity(progress.QUIET if quiet else
                               progress.VERBOSE if verbose else progress.NORMAL)
        try:
            with command_scope():  # SIGTERM as Ctrl-C, OSError as one line
                return fn(*args, **kwargs)
        except GpoccError as exc:
            typer.echo(f"gpocc {name}: error: {exc}", err=True)
            raise typer.Exit(2) from None
        except KeyboardInterrupt:
            typer.echo(f"gpocc {name}: interrupted; no partial output was left", err=True)
            raise typer.Exit(130) from None
        finally:
            progress.set_verbosity(progress.NORMAL)

    # Typer reads the options from the signature and type hints: the command's own
    # (resolved, since command modules use postponed annotations) plus the shared two.
    hints = {**typing.get_type_hints(fn, include_extras=True), "quiet": Quiet,
             "verbose": Verbose}
    own = [p.replace(annotation=hints[p.name])
           for p in inspect.signature(fn).parameters.values()]
    shared = [inspect.Parameter(n, inspect.Parameter.KEYWORD_ONLY, default=False,
                                annotation=hints[n]) for n in ("quiet", "verbose")]
    wrapper.__signature__ = inspect.Signature(own + shared)  # type: ignore[attr-defined]
    wrapper.__annotations__ = {k: v for k, v in hints.items() if k != "return"}
    app.command(name)(wrapper)


for _name, _fn in COMMANDS:
    register(_name, _fn)


def main() -> None:
    """Console-script entry point."""
    app(prog_name="gpocc")
