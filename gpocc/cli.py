"""The ``gpocc`` command line: wiring only; each command lives in ``gpocc.commands``.

Commands are plain functions registered here from :data:`COMMANDS` (command modules never
import this module, so there is no import cycle). The console script imports only the
module of the command it runs: importing all of them (numba then, scipy.optimize, rosbags, ...)
took about a second more per run than one command needs. Registration adds what every command
shares: ``--quiet`` / ``--verbose`` and the error policy: errors a user can fix
(:class:`gpocc.errors.GpoccError`) become one line on stderr and exit status 2; results
go to files and stdout, progress and logs to stderr.
"""

from __future__ import annotations

import atexit
import functools
import importlib
import inspect
import os
import sys
import threading
import typing
from collections.abc import Callable
from typing import Annotated, Any

import typer

import gpocc
from gpocc import progress
from gpocc.constants import INTERRUPTED
from gpocc.errors import GpoccError
from gpocc.lifecycle import command_scope

#: (name, "module:function") of every ``gpocc`` subcommand, in help order.
COMMANDS: tuple[tuple[str, str], ...] = (
    ("info", "gpocc.commands.info:info"),
    ("train", "gpocc.commands.train:train"),
    ("update", "gpocc.commands.update:update"),
    ("map", "gpocc.commands.map:map_command"),
    ("build", "gpocc.commands.build:build"),
    ("grid", "gpocc.commands.grid:grid_command"),
    ("bhm", "gpocc.commands.bhm:bhm_command"),
    ("evaluate", "gpocc.commands.evaluate:evaluate"),
    ("split", "gpocc.commands.split:split"),
    ("simulate", "gpocc.commands.simulate:simulate_command"),
    ("config", "gpocc.commands.config:config_command"),
)

Quiet = Annotated[bool, typer.Option(
    "--quiet", "-q", help="No progress or log lines on stderr (errors still show).")]
Verbose = Annotated[bool, typer.Option(
    "--verbose", "-v", help="More log lines on stderr.")]


def _version(value: bool) -> None:
    if value:
        typer.echo(f"gpocc {gpocc.__version__}")
        raise typer.Exit()


def _root(
    version: Annotated[bool, typer.Option(
        "--version", callback=_version, is_eager=True, help="Print the version and exit.")
    ] = False,
) -> None:
    """Gaussian-process occupancy maps from robot logs, with sensor and pose uncertainty."""


def build_app(names: tuple[str, ...] | None = None) -> typer.Typer:
    """The ``gpocc`` app with the commands ``names`` (default: all), importing only their
    modules."""
    app = typer.Typer(
        name="gpocc",
        help="Gaussian-process occupancy maps from robot logs, with sensor and pose "
             "uncertainty.",
        no_args_is_help=True,
        add_completion=True,
        pretty_exceptions_enable=False,
        context_settings={"help_option_names": ["-h", "--help"]},
    )
    app.callback()(_root)
    for name, target in COMMANDS:
        if names is None or name in names:
            module, attribute = target.split(":")
            register(app, name, getattr(importlib.import_module(module), attribute))
    return app


def register(app: typer.Typer, name: str, fn: Callable[..., Any]) -> None:
    """Add ``fn`` to ``app`` as ``gpocc NAME`` with ``--quiet/--verbose`` and one-line
    errors."""

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


def __getattr__(name: str) -> Any:
    # ``gpocc.cli.app``: every command (tests, documentation tools), built on first use.
    if name == "app":
        globals()["app"] = build_app()
        return globals()["app"]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def main() -> None:
    """Console-script entry point: registers only the command named on the command line
    (all of them for the top-level help, an unknown name, or shell completion)."""
    words = [w for w in sys.argv[1:] if not w.startswith("-")]
    known = {name for name, _ in COMMANDS}
    completing = any(key.endswith("_COMPLETE") for key in os.environ)
    chosen = (words[0],) if words and words[0] in known and not completing else None
    try:
        code = build_app(chosen)(prog_name="gpocc", standalone_mode=False)
    except SystemExit as exc:
        _exit_without_teardown(exc.code)
    except KeyboardInterrupt:
        # Ctrl-C while the command's modules load (scipy, typer: about a second), before
        # the command's own handler: nothing was written yet.
        print(INTERRUPTED, file=sys.stderr)
        _exit_without_teardown(130)
    except GpoccError as exc:
        # A command's modules failed to load for a reason it states (gpocc.compiled: the
        # compiled loops are not built or are stale): one line, as a command's errors.
        print(f"gpocc: error: {exc}", file=sys.stderr)
        _exit_without_teardown(2)
    except typer.Abort:
        # An EOFError (or typer.Abort) in a command: typer's standalone mode printed this
        # line; without it the Abort would end in a traceback.
        print("Aborted.", file=sys.stderr)
        _exit_without_teardown(1)
    except _usage_errors() as exc:
        line = usage_error_line(exc)
        if line:  # none for a bare ``gpocc``: typer has printed the help
            print(line, file=sys.stderr)
        _exit_without_teardown(exc.exit_code)
    _exit_without_teardown(code if isinstance(code, int) else 0)


def _usage_errors() -> tuple[type[Exception], ...]:
    """Click's ``ClickException`` as typer raises it (its own copy of click in recent
    typer, click itself before): the base of every usage error."""
    return tuple(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")


def usage_error_line(exc: Exception) -> str:
    """A usage error (unknown option, missing argument, a value of the wrong type) as one
    line, like every other error: ``gpocc map: error: ... (see 'gpocc map --help')``;
    empty when the error carries no message. Typer drew a usage line, a hint and a box
    of several lines instead."""
    ctx = getattr(exc, "ctx", None)
    where = ctx.command_path if ctx is not None else "gpocc"
    message = " ".join(exc.format_message().split())
    return f"{where}: error: {message} (see '{where} --help')" if message else ""


def _exit_without_teardown(code: int | str | None) -> None:
    """End the process once the command is done, skipping the interpreter's teardown.

    Finalising numba's (then a dependency) and matplotlib's module graphs took 0.5-1 s
    after every command (Intel: ``gpocc map`` ended 1 s sooner). Every output is already
    written and closed (atomically), so only the exit handlers matter: they run (logging
    flush, multiprocessing clean-up), then stdout and stderr are flushed. With any other thread
    alive, or under a profiler or tracer, the normal exit runs.
    """
    if threading.active_count() > 1 or sys.getprofile() or sys.gettrace():
        sys.exit(code)  # a profiler or coverage tool writes its report at teardown
    if code is None:
        code = 0
    elif not isinstance(code, int):  # sys.exit("message"): printed, status 1
        print(code, file=sys.stderr)
        code = 1
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more to say
            pass
    os._exit(code)
