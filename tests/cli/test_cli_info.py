"""``gpocc info`` on the sample data, and its one-line errors on bad inputs."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.config import load_config
from gpocc.io.bags import write_bag
from gpocc.io.scans import ScanBatch

SAMPLE = Path(__file__).resolve().parents[2] / "data" / "sample"


def _run(*args: str):
    result = CliRunner().invoke(app, ["info", *args])
    assert "Traceback" not in result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)
    return result


def test_info_on_sample() -> None:
    mcap, config = SAMPLE / "intel_sample.mcap", SAMPLE / "sample.yaml"
    result = _run(str(mcap), "--config", str(config))
    assert result.exit_code == 0, result.output
    out = result.stdout
    assert "format: MCAP file" in out
    assert re.search(r"/scan\s+sensor_msgs/msg/LaserScan\s+50\b", out)
    assert re.search(r"/pose\s+geometry_msgs/msg/PoseWithCovarianceStamped\s+50\b", out)
    assert "time span: 240.000 .. 289.000 s" in out
    assert "intel: 50 scans used, 0 skipped, 180 beams per scan" in out
    assert "pose covariance from input" in out

    # The sample summary against the sample builder run directly on the same scans.
    from gpocc.io.inputs import read_inputs
    from gpocc.samples.beams import build_samples

    cfg = load_config(config)
    samples = build_samples(read_inputs([mcap], cfg), cfg)
    occupied = int(np.sum(samples.labels > 0))
    spread = np.mean(np.sqrt(samples.covariances[:, 0, 0] + samples.covariances[:, 1, 1]))
    assert f"occupied: {occupied}\n" in out
    assert f"free: {len(samples) - occupied}\n" in out
    printed = float(re.search(r"mean sqrt\(trace\(covariance\)\): ([0-9.]+) m", out).group(1))
    assert printed == pytest.approx(spread, abs=6e-5)
    # Every sample inherits the pose's x and y variance (3 cm standard deviation each), so
    # its sqrt(trace) is at least sqrt(2) * 0.03 m; the laser adds centimetres, not metres.
    assert 0.03 * np.sqrt(2) < printed < 0.5


def _batch() -> ScanBatch:
    return ScanBatch(
        sensor="r", source="memory", stamps=np.arange(3.0), angles=np.linspace(-1, 1, 5),
        ranges=np.full((3, 5), 2.0), poses=np.zeros((3, 3)),
        pose_covariances=np.zeros((3, 3, 3)) + np.eye(3) * 1e-3, range_min=0.1, range_max=5.0,
    )


def _bad_inputs(tmp_path: Path) -> dict[str, tuple[list[str], str]]:
    """name -> (CLI arguments, expected words), each input wrong in one way."""
    good = tmp_path / "good.mcap"
    write_bag(good, [_batch()], [("/scan", "/pose")], "mcap")
    # Two pose topics for one laser and no TF to settle it: the user must choose.
    two = tmp_path / "two.mcap"
    write_bag(two, [_batch(), _batch()], [("/scan", "/pose"), ("/b_scan", "/amcl_pose")], "mcap")
    (tmp_path / "empty.mcap").write_bytes(b"")
    (tmp_path / "noise.bag").write_bytes(os.urandom(2000))
    (tmp_path / "half.mcap").write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    (tmp_path / "bad.log").write_text("FLASER 3 1 2 0 0 0 0 0 0 1.0 pippo 1.0\n")
    (tmp_path / "missing.yaml").write_text(
        "sensors:\n  - name: r\n    scan_topic: /front\n    pose_topic: /pose\n")
    return {
        "empty": ([str(tmp_path / "empty.mcap")], "empty.mcap: the file is empty"),
        "noise": ([str(tmp_path / "noise.bag")], "noise.bag: cannot read the bag"),
        "half": ([str(tmp_path / "half.mcap")], "half.mcap: cannot read the bag"),
        "carmen": ([str(tmp_path / "bad.log")], "bad.log: line 1:"),
        "ambiguous": ([str(two)], "two.mcap: cannot choose the pose topic for /b_scan among "
                      "/amcl_pose, /pose (no TF to settle it); set sensors[].pose_topic in a "
                      "config for all its lasers: "
                      "sensors: [{name: b_scan, scan_topic: /b_scan, pose_topic: /amcl_pose}, "
                      "{name: scan, scan_topic: /scan, pose_topic: /amcl_pose}]"),
        "missing": ([str(good), "--config", str(tmp_path / "missing.yaml")],
                    "good.mcap: topic /front"),
    }


@pytest.mark.parametrize("case", ["empty", "noise", "half", "carmen", "ambiguous", "missing"])
def test_info_errors_are_one_line(tmp_path: Path, case: str) -> None:
    args, words = _bad_inputs(tmp_path)[case]
    result = _run(*args)
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("gpocc info: error: ")
    assert words in lines[0]


def test_a_path_with_a_semicolon_keeps_the_whole_problem(tmp_path: Path) -> None:
    """The problem part of the message is kept whole: it used to be cut at the first
    '; ', here inside the folder's name."""
    folder = tmp_path / "lab; day 2"
    folder.mkdir()
    two = folder / "two.mcap"
    write_bag(two, [_batch(), _batch()], [("/scan", "/pose"), ("/b_scan", "/amcl_pose")], "mcap")
    result = _run(str(two))
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert (f"{two}: cannot choose the pose topic for /b_scan among /amcl_pose, /pose (no TF "
            f"to settle it); set sensors[].pose_topic in a config for all its lasers: "
            "sensors: [") in lines[0]
