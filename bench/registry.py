"""The benchmark registry: named benchmarks, what they return, and what they share.

A benchmark is a function ``(Context) -> Result`` registered with :func:`benchmark`; its
docstring's first paragraph is its description on the generated page. ``quick`` runs
use smaller sizes (each benchmark reads ``ctx.quick``); benchmarks registered with
``in_quick=False`` are left out of a quick run unless named with ``--only``.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from .harness import gpocc
from .paths import INTEL, INTEL_CONFIG, missing


class Skipped(Exception):  # noqa: N818 (a benchmark's outcome, not an error)
    """Raised by a benchmark that cannot run here (missing data or extra); the message
    says why and goes on the page."""


def require(*paths: Path) -> None:
    """Skip the calling benchmark unless every path exists."""
    why = missing(*paths)
    if why:
        raise Skipped(why)


@dataclass(frozen=True)
class Table:
    """A markdown table: a header and rows of already formatted cells."""

    header: tuple[str, ...]
    rows: list[list[str]]

    def markdown(self) -> str:
        lines = ["| " + " | ".join(self.header) + " |", "|" + "---|" * len(self.header)]
        lines += ["| " + " | ".join(r) + " |" for r in self.rows]
        return "\n".join(lines)


@dataclass
class Result:
    """What a benchmark reports: tables (each with an optional caption) and notes."""

    tables: list[tuple[str, Table]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def add(self, table: Table, caption: str = "") -> None:
        self.tables.append((caption, table))


@dataclass
class Context:
    """Shared by the benchmarks of one run: a scratch folder, the size switch and the
    Intel model that several benchmarks use (trained once, on first use)."""

    work: Path
    quick: bool
    repeats: int
    _intel_model: Path | None = None

    def intel_model(self) -> Path:
        """A model of the whole Intel log with ``configs/carmen_intel.yaml``
        (``gpocc train``)."""
        if self._intel_model is None:
            path = self.work / "shared-intel.npz"
            gpocc("train", INTEL, "--config", INTEL_CONFIG, "--out", path, "--force")
            self._intel_model = path
        return self._intel_model


@dataclass(frozen=True)
class Benchmark:
    name: str
    title: str
    run: Callable[[Context], Result]
    in_quick: bool

    @property
    def description(self) -> str:
        doc = inspect.getdoc(self.run) or ""
        return doc.split("\n\n")[0].replace("\n", " ")


#: Every registered benchmark by name, in the order of the generated page.
REGISTRY: dict[str, Benchmark] = {}


def benchmark(name: str, title: str, in_quick: bool = True):
    """Register the decorated function as benchmark ``name`` with a section ``title``."""

    def register(fn: Callable[[Context], Result]) -> Callable[[Context], Result]:
        if name in REGISTRY:
            raise ValueError(f"benchmark {name!r} registered twice")
        REGISTRY[name] = Benchmark(name, title, fn, in_quick)
        return fn

    return register
