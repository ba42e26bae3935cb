"""gpocc's benchmark suite: run the registered benchmarks and write docs/benchmarks.md.

    .venv/bin/python -m bench.run_bench                 # everything (make bench)
    .venv/bin/python -m bench.run_bench --list          # the benchmarks' names
    .venv/bin/python -m bench.run_bench --only intel --only samples --out -
    .venv/bin/python -m bench.run_bench --quick         # smaller sizes, long ones left out

Run it from the repository's root. The page is stamped with the date, the git commit and
the machine, and says which benchmarks ran and whether the run was quick. The real logs
are read from ``../shared/data/carmen`` (or ``GPOCC_CARMEN_DIR``); benchmarks whose data is
missing are listed as skipped. The benchmarks live in ``bench/pipeline.py`` (whole
commands), ``bench/stages.py``, ``bench/kernels.py``, ``bench/knobs.py`` and
``bench/fingerprints.py``; a new one is a function registered with
``bench.registry.benchmark``.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

from . import fingerprints, kernels, knobs, pipeline, stages  # noqa: F401 (they register)
from .paths import CARMEN, ROOT
from .registry import REGISTRY, Context, Result, Skipped

PAGE = ROOT / "docs" / "benchmarks.md"
#: The page's order; a benchmark not named here comes last.
ORDER = ("intel", "intel-repeats", "campus", "scaling-data", "scaling-size", "samples",
         "sample-memory", "anchor-cost", "expected-kernels", "quadrature", "blas-threads",
         "anneal-budget", "knobs", "fingerprints")


def ordered() -> list[str]:
    """Every registered benchmark's name, in the page's order."""
    return sorted(REGISTRY, key=lambda n: ORDER.index(n) if n in ORDER else len(ORDER))


def _git(*args: str) -> str:
    try:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return ""


def commit() -> str:
    """The short commit hash, with ``+ uncommitted changes`` when tracked files other than
    markdown pages (which change no measurement) differ from it."""
    head = _git("rev-parse", "--short", "HEAD") or "unknown"
    changed = [line for line in _git("status", "--porcelain", "--untracked-files=no")
               .splitlines() if not line.endswith(".md")]
    return f"{head} + uncommitted changes" if changed else head


def machine() -> str:
    """CPU model, cores, memory, OS, Python and numpy with its BLAS, in one line."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next(line.split(":", 1)[1].strip() for line in fh
                       if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    memory = ""
    try:
        with open("/proc/meminfo") as fh:
            kib = next(int(line.split()[1]) for line in fh if line.startswith("MemTotal"))
        memory = f", {kib / 2**20:.0f} GiB memory"
    except (OSError, StopIteration):
        pass
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    cores = f"{os.cpu_count()} cores" + (f" ({usable} usable)" if usable != os.cpu_count()
                                         else "")
    import numpy as np
    from threadpoolctl import threadpool_info

    blas = next((f"{i.get('internal_api')} {i.get('version')}" for i in threadpool_info()
                 if i.get("user_api") == "blas"), "unknown BLAS")
    return (f"{cpu} ({platform.machine()}), {cores}{memory}; {platform.system()} "
            f"{platform.release()}, Python {platform.python_version()}, numpy "
            f"{np.__version__} with {blas}")


def run_all(names: list[str], ctx: Context) -> list[tuple[str, Result | str, float]]:
    """(name, its Result or why it has none, wall seconds) of each benchmark, in order."""
    done = []
    for name in names:
        print(f"bench: {name} ...", file=sys.stderr, flush=True)
        started = time.perf_counter()
        try:
            outcome: Result | str = REGISTRY[name].run(ctx)
        except Skipped as why:
            outcome = f"skipped: {why}"
        except Exception as error:  # the page says which failed; the run goes on
            traceback.print_exc()
            outcome = f"FAILED: {str(error).splitlines()[0] if str(error) else repr(error)}"
        seconds = time.perf_counter() - started
        print(f"bench: {name} {seconds:.1f} s", file=sys.stderr, flush=True)
        done.append((name, outcome, seconds))
    return done


def page(done: list[tuple[str, Result | str, float]], quick: bool, repeats: int,
         stamp: datetime.datetime) -> str:
    """The markdown of docs/benchmarks.md."""
    ran = [name for name, _, _ in done]
    left_out = [name for name in ordered() if name not in ran]
    kind = ("a **quick** run (`--quick`: smaller sizes, some benchmarks left out); "
            "its figures are not comparable with a full run's" if quick else "a full run")
    lines = [
        "# Benchmarks",
        "",
        "<!-- Generated by `make bench` (python -m bench.run_bench); edits are overwritten. -->",
        "",
        f"Generated on {stamp:%Y-%m-%d %H:%M} UTC at commit `{commit()}`, {kind}.",
        "",
        f"- Machine: {machine()}.",
        f"- Data: `{_shown(CARMEN)}` (`GPOCC_CARMEN_DIR`).",
        f"- Benchmarks run: {', '.join(f'`{n}`' for n in ran) or 'none'}"
        + (f"; not run: {', '.join(f'`{n}`' for n in left_out)}." if left_out else "."),
        "",
        "Times are wall-clock seconds unless a column says CPU. On a shared machine they",
        "drift from run to run: compare figures within one page, or repeat "
        "(`intel-repeats`).",
        "",
        "## Reproduce",
        "",
        "```sh",
        "make bench                                    # every benchmark; writes this page",
        ".venv/bin/python -m bench.run_bench --list    # the benchmarks",
        ".venv/bin/python -m bench.run_bench --only NAME --out -   # one, printed",
        ".venv/bin/python -m bench.run_bench --quick   # smaller sizes",
        "```",
        "",
        f"`make bench` installs the `bench` extra (pyoctomap, for the OctoMap rows) first. "
        f"This run: `{_command(ran, quick, repeats)}`.",
        "",
        "| benchmark | section | took s |",
        "|---|---|---|",
    ]
    for name, outcome, seconds in done:
        title = REGISTRY[name].title
        status = "" if isinstance(outcome, Result) else f" ({outcome.split(':')[0]})"
        lines.append(f"| `{name}` | [{title}](#{_anchor(title)}){status} | {seconds:.0f} |")
    for name, outcome, _ in done:
        bench = REGISTRY[name]
        lines += ["", f"## {bench.title}", "", bench.description, "",
                  f"`.venv/bin/python -m bench.run_bench --only {name}`", ""]
        if not isinstance(outcome, Result):
            lines.append(f"**{outcome}**")
            continue
        for caption, table in outcome.tables:
            if caption:
                lines += [caption, ""]
            lines += [table.markdown(), ""]
        lines += [f"- {note}" for note in outcome.notes]
    return "\n".join(lines).rstrip() + "\n"


def _shown(path: Path) -> str:
    try:
        return os.path.relpath(path, ROOT)
    except ValueError:
        return str(path)


def _anchor(title: str) -> str:
    """GitHub's anchor of a heading."""
    kept = "".join(c for c in title.lower() if c.isalnum() or c in " -_")
    return kept.replace(" ", "-")


def _command(ran: list[str], quick: bool, repeats: int) -> str:
    parts = [".venv/bin/python -m bench.run_bench"]
    if quick:
        parts.append("--quick")
    if repeats != 5:
        parts.append(f"--repeats {repeats}")
    default = [n for n in ordered() if REGISTRY[n].in_quick or not quick]
    if ran != default:
        parts += [f"--only {n}" for n in ran]
    return " ".join(parts)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    parser.add_argument("--only", action="append", metavar="NAME", default=[],
                        help="run this benchmark (repeatable); default: all")
    parser.add_argument("--quick", action="store_true",
                        help="smaller sizes; benchmarks marked slow are left out unless named")
    parser.add_argument("--repeats", type=int, default=5,
                        help="back-to-back pairs of `intel-repeats` (default 5)")
    parser.add_argument("--out", default=str(PAGE),
                        help="where to write the page ('-': stdout; default docs/benchmarks.md)")
    args = parser.parse_args()
    if args.list:
        for name in ordered():
            bench = REGISTRY[name]
            slow = "" if bench.in_quick else "  (left out of --quick)"
            print(f"{name:18} {bench.title}{slow}")
        return
    unknown = [n for n in args.only if n not in REGISTRY]
    if unknown:
        parser.error(f"unknown benchmark(s) {', '.join(unknown)}; --list shows them")
    names = args.only or [n for n in ordered() if REGISTRY[n].in_quick or not args.quick]
    stamp = datetime.datetime.now(datetime.UTC)
    with tempfile.TemporaryDirectory(prefix="gpocc-bench-") as tmp:
        done = run_all(names, Context(Path(tmp), args.quick, args.repeats))
    text = page(done, args.quick, args.repeats, stamp)
    if args.out == "-":
        sys.stdout.write(text)
    else:
        out = Path(args.out)
        partial = out.with_name(f".{out.name}.partial")
        partial.write_text(text)
        partial.replace(out)
        print(f"bench: wrote {out}", file=sys.stderr)
    if any(isinstance(o, str) and o.startswith("FAILED") for _, o, _ in done):
        sys.exit(1)


if __name__ == "__main__":
    main()
