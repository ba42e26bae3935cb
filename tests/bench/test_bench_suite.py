"""The benchmark suite stays runnable: its registry, its page and its skips (no timings
are asserted; speed is what the suite itself reports)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def run_bench(*args: str, env: dict[str, str] | None = None) -> str:
    result = subprocess.run([sys.executable, "-m", "bench.run_bench", *args], cwd=ROOT,
                            capture_output=True, text=True, timeout=300,
                            env={**os.environ, **(env or {})})
    assert result.returncode == 0, result.stderr
    return result.stdout


def test_list_names_each_benchmark_once() -> None:
    listed = [line.split()[0] for line in run_bench("--list").splitlines()]
    assert len(listed) == len(set(listed))
    assert {"intel", "intel-repeats", "freiburg-repeats", "campus", "quadrature",
            "fingerprints"} <= set(listed)


def test_page_is_stamped_and_quadrature_error_falls_with_the_level() -> None:
    page = run_bench("--quick", "--only", "quadrature", "--out", "-")
    assert page.startswith("# Benchmarks\n")
    assert "a **quick** run" in page
    assert re.search(r"Generated on \d{4}-\d\d-\d\d \d\d:\d\d UTC at commit `\w+", page)
    assert "- Machine: " in page and " cores" in page
    assert "## Expected-kernel quadrature" in page
    rows = [line.split("|")[1:-1] for line in page.splitlines()
            if re.match(r"\| [123] \|", line)]
    assert [r[0].strip() for r in rows] == ["1", "2", "3"]
    # Against Girard's closed form (SE, same-scan pairs): each level is more exact.
    se_same = [float(r[-1]) for r in rows]
    assert se_same[0] > se_same[1] > se_same[2]


def test_a_benchmark_without_its_data_is_listed_as_skipped(tmp_path: Path) -> None:
    page = run_bench("--only", "samples", "--only", "freiburg-repeats", "--out", "-",
                     env={"GPOCC_CARMEN_DIR": str(tmp_path)})
    assert f"skipped: {tmp_path / 'intel.gfs.log'} not found" in page
    assert f"skipped: {tmp_path / 'freiburg-079-corrected.log'} not found" in page
