"""The update-cost benchmark's account of where a learning command's time goes."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from bench.update_cost import where_time_goes

SAMPLE = Path(__file__).resolve().parents[2] / "data" / "sample"


def test_where_time_goes_reads_the_commands_own_account(tmp_path: Path) -> None:
    model = tmp_path / "m.npz"
    trained = subprocess.run(
        [sys.executable, "-m", "gpocc", "train", str(SAMPLE / "intel_sample.mcap"),
         "--config", str(SAMPLE / "sample.yaml"), "--out", str(model), "--quiet"],
        check=True, capture_output=True, text=True)
    told = where_time_goes(10.0, trained.stdout, model)

    # Against `gpocc info`, which prints the evaluations from the file on its own.
    info = subprocess.run([sys.executable, "-m", "gpocc", "info", str(model)],
                          check=True, capture_output=True, text=True).stdout
    assert told["evaluations"] == int(re.search(r"\((\d+) evaluations[;)]", info).group(1))
    assert told["evaluations"] > 1
    total = float(re.search(r"^time: ([0-9.]+) s$", trained.stdout, re.MULTILINE).group(1))
    assert told["startup_s"] == pytest.approx(10.0 - total)
    assert told["stages"].startswith("read ")
    assert "hyperparameters+classifier" in told["stages"]
