"""Options shared by several commands, declared once so they read the same everywhere.

Each is an ``Annotated`` type for a command's signature; the checks that go with them
(:func:`check_resolution`, :func:`check_at_least`) are the only place an error message
names a flag.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer

from gpocc.config import MAX_RESOLUTION_M
from gpocc.errors import GpoccError, SchedulerUnreachable


class Switch(StrEnum):
    """An on/off option's value (``--input-noise on``)."""

    on = "on"
    off = "off"


Force = Annotated[bool, typer.Option(
    "--force", help="Replace an existing output (the --out file or folder).")]
ConfigFile = Annotated[Path | None, typer.Option(
    "--config", help="YAML job config (see `gpocc config`); default: built-in defaults.")]
OutFolder = Annotated[Path, typer.Option("--out", help="Folder to write.")]
Bounds = Annotated[tuple[float, float, float, float] | None, typer.Option(
    "--bounds", metavar="XMIN YMIN XMAX YMAX",
    help="Map area in the map frame, metres; default: the data's extent plus "
         "map.margin_m.")]
InputNoise = Annotated[Switch | None, typer.Option(
    "--input-noise", help="on: use sample covariances (default); off: the baseline.")]
Seed = Annotated[int | None, typer.Option("--seed", help="Overrides the config's seed.")]
Resolution = Annotated[float, typer.Option("--resolution", help="Cell size, metres.")]
ConfigResolution = Annotated[float | None, typer.Option(
    "--resolution", help="Cell size, metres (default: the config's map.resolution_m).")]
Workers = Annotated[int | None, typer.Option(
    "--workers", help="Local processes for the map's local problems (default and most: the "
    "cores this process may use).")]


def _scheduler_option(work: str) -> typer.models.OptionInfo:
    """``--scheduler``, whose workers compute ``work``."""
    return typer.Option("--scheduler", help="Dask scheduler address tcp://HOST:PORT: its "
                        f"workers compute {work} (output identical to a local run).")


_TRAINING_WORK = "training's likelihood patches and classifier predictions"
_MAP_WORK = "the map's local problems"
Scheduler = Annotated[str | None, _scheduler_option(f"{_TRAINING_WORK} and {_MAP_WORK}")]
TrainScheduler = Annotated[str | None, _scheduler_option(_TRAINING_WORK)]
MapScheduler = Annotated[str | None, _scheduler_option(_MAP_WORK)]
Inputs = Annotated[list[Path], typer.Argument(
    metavar="INPUT...", help="Bags, bag folders, .mcap files or CARMEN logs.")]


@contextlib.contextmanager
def scheduler_errors() -> Iterator[None]:
    """An unreachable ``--scheduler`` as one error line naming the option and address."""
    try:
        yield
    except SchedulerUnreachable as exc:
        raise GpoccError(
            f"--scheduler {exc.address}: cannot reach a Dask scheduler there "
            f"({exc.cause}); check the address (tcp://HOST:PORT) and that the scheduler "
            "is running, or leave --scheduler out to work on this machine") from None


def check_resolution(resolution: float) -> float:
    """``resolution`` if it is a positive, finite number of metres (--resolution), at most
    :data:`MAX_RESOLUTION_M`."""
    if not (resolution > 0 and math.isfinite(resolution)):
        raise GpoccError(f"--resolution must be a positive number of metres, got {resolution}")
    if resolution > MAX_RESOLUTION_M:
        raise GpoccError(f"--resolution must be at most {MAX_RESOLUTION_M:g} m, got "
                         f"{resolution:.10g}; check its units (metres)")
    return resolution


def check_at_least(flag: str, value: int, minimum: int, why: str = "") -> int:
    """``value`` if it is at least ``minimum``; else an error naming ``flag``."""
    if value < minimum:
        raise GpoccError(f"{flag} must be at least {minimum}{why}, got {value}")
    return value
