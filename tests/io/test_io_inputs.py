"""Input dispatch and sensor choice; the shipped configs and sample data."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from gpocc.config import Config, SensorConfig, load_config
from gpocc.errors import GpoccError
from gpocc.io.bags import write_bag
from gpocc.io.carmen import read_carmen
from gpocc.io.inputs import (
    default_sensor,
    describe_input,
    detect_format,
    read_inputs,
    sensors_for_input,
)
from gpocc.io.scans import ScanBatch
from gpocc.samples.beam_rules import sensor_config

REPO = Path(__file__).resolve().parents[2]
DATA = REPO.parent / "shared" / "data" / "carmen"
SAMPLE = REPO / "data" / "sample"


def _batch(sensor: str, n_scans: int = 5, t0: float = 1.0, x0: float = 0.0) -> ScanBatch:
    return ScanBatch(
        sensor=sensor,
        source="memory",
        stamps=t0 + 0.1 * np.arange(n_scans),
        angles=np.linspace(-1.0, 1.0, 7),
        ranges=np.full((n_scans, 7), 2.0),
        poses=np.column_stack([x0 + np.arange(n_scans), np.zeros(n_scans), np.zeros(n_scans)]),
        pose_covariances=np.broadcast_to(np.diag([0.01, 0.01, 0.001]), (n_scans, 3, 3)).copy(),
        range_min=0.1,
        range_max=10.0,
    )


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """robot1_a.mcap, robot2_a.mcap (one robot each), both.bag (two), ros2/ (a folder)."""
    base = tmp_path_factory.mktemp("inputs")
    r1, r2 = _batch("a", 5), _batch("b", 4, x0=10.0)
    t1, t2 = ("/robot1/scan", "/robot1/pose"), ("/robot2/scan", "/robot2/pose")
    paths = {
        "robot1": base / "robot1_a.mcap",
        "robot2": base / "robot2_a.mcap",
        "both": base / "both.bag",
        "ros2": base / "ros2",
        "plain": base / "plain.mcap",
    }
    write_bag(paths["robot1"], [r1], [t1], "mcap")
    write_bag(paths["robot2"], [r2], [t2], "mcap")
    write_bag(paths["both"], [r1, r2], [t1, t2], "ros1")
    write_bag(paths["ros2"], [r1], [t1], "ros2-sqlite3")
    write_bag(paths["plain"], [r1], [("/scan", "/amcl_pose")], "mcap")
    return paths


def test_detect_format(tmp_path: Path, bags: dict[str, Path]) -> None:
    assert detect_format(bags["both"]) == "ros1"
    assert detect_format(bags["ros2"]) == "ros2-sqlite3"
    assert detect_format(bags["robot1"]) == "mcap"
    flaser = "FLASER 3 1 1 1 0 0 0 0 0 0 1.0 host 1.0\n"
    (tmp_path / "run.clf").write_text(flaser)
    (tmp_path / "noext").write_text("# a log\n" + flaser)
    assert detect_format(tmp_path / "run.clf") == "carmen"
    assert detect_format(tmp_path / "noext") == "carmen"

    (tmp_path / "notes.txt").write_text("hello world\n")
    (tmp_path / "folder").mkdir()
    shutil.copy(bags["robot1"], tmp_path / "renamed.dat")
    (tmp_path / "empty.bag").write_bytes(b"")
    for name, why in [
        ("notes.txt", "unknown input format"),
        ("folder", "without metadata.yaml"),
        ("renamed.dat", r"rename it to \*\.mcap"),
        ("empty.bag", "empty"),
        ("missing.mcap", "no such file"),
    ]:
        with pytest.raises(GpoccError, match=rf"{name}.*{why}"):
            read_inputs([tmp_path / name], Config())


def test_default_sensor_for_plain_bag_and_carmen(tmp_path: Path, bags: dict[str, Path]) -> None:
    [batch] = read_inputs([bags["plain"]], Config())
    assert batch.sensor == "scan" and batch.n_scans == 5
    sensor = default_sensor(describe_input(bags["plain"]))
    assert (sensor.scan_topic, sensor.pose_topic) == ("/scan", "/amcl_pose")
    # The reader attaches the entry it resolved; a batch made elsewhere gets the defaults.
    assert batch.sensor_config == sensor
    assert sensor_config(_batch("scan"), Config()) == SensorConfig(name="scan")

    log = tmp_path / "lab.gfs.log"
    log.write_text("FLASER 3 1 1 1 0 0 0 0 0 0 1.0 host 1.0\n")
    [carmen] = read_inputs([log], Config())
    assert carmen.sensor == "lab.gfs"


def test_namespaced_robots_pair_without_config(bags: dict[str, Path]) -> None:
    batches = read_inputs([bags["both"]], Config())
    assert [(b.sensor, b.n_scans) for b in batches] == [("robot1/scan", 5), ("robot2/scan", 4)]
    np.testing.assert_allclose(batches[1].poses[:, 0], 10.0 + np.arange(4))


def test_missing_topic_names_topic_file_and_topics(bags: dict[str, Path]) -> None:
    config = Config(sensors=(SensorConfig(name="r", scan_topic="/front/scan",
                                          pose_topic="/robot1/pose"),))
    with pytest.raises(GpoccError, match=r"robot1_a\.mcap: topic /front/scan .*topics present: "
                                         r".*/robot1/pose.*/robot1/scan"):
        read_inputs([bags["robot1"]], config)
    wrong_type = Config(sensors=(SensorConfig(name="r", scan_topic="/robot1/pose",
                                              pose_topic="/robot1/pose"),))
    with pytest.raises(GpoccError, match=r"/robot1/pose is geometry_msgs"):
        read_inputs([bags["robot1"]], wrong_type)


def test_two_robots_in_separate_and_shared_inputs(bags: dict[str, Path]) -> None:
    sensors = (
        SensorConfig(name="one", scan_topic="/robot1/scan", pose_topic="/robot1/pose"),
        SensorConfig(name="two", scan_topic="/robot2/scan", pose_topic="/robot2/pose"),
    )
    batches = read_inputs([bags["robot1"], bags["robot2"], bags["both"]], Config(sensors=sensors))
    got = [(Path(b.source).name, b.sensor, b.n_scans) for b in batches]
    assert got == [("robot1_a.mcap", "one", 5), ("robot2_a.mcap", "two", 4),
                   ("both.bag", "one", 5), ("both.bag", "two", 4)]
    np.testing.assert_allclose(batches[1].poses[:, 0], 10.0 + np.arange(4))


def test_inputs_globs_tie_entries_to_files(bags: dict[str, Path], tmp_path: Path) -> None:
    # Topics left out: each entry takes the only LaserScan/pose topic of its own files.
    config = Config(sensors=(
        SensorConfig(name="first", inputs=("robot1_*",)),
        SensorConfig(name="second", inputs=("*/robot2_*.mcap",)),
    ))
    batches = read_inputs([bags["robot2"], bags["robot1"]], config)
    assert [(b.sensor, b.n_scans) for b in batches] == [("second", 4), ("first", 5)]
    summary = describe_input(bags["robot1"])
    [chosen] = sensors_for_input(summary, config)
    assert (chosen.scan_topic, chosen.pose_topic) == ("/robot1/scan", "/robot1/pose")
    with pytest.raises(GpoccError, match=r"plain\.mcap: no `sensors` entry .*applies"):
        read_inputs([bags["plain"]], config)
    # An entry with inputs must find its topics there.
    strict = Config(sensors=(SensorConfig(name="x", inputs=("robot1_*",),
                                          scan_topic="/robot2/scan"),))
    with pytest.raises(GpoccError, match=r"robot1_a\.mcap: topic /robot2/scan"):
        read_inputs([bags["robot1"]], strict)


def test_ros2_folder_reads(bags: dict[str, Path]) -> None:
    [batch] = read_inputs([bags["ros2"]], Config())
    assert (batch.sensor, batch.n_scans, batch.n_beams) == ("robot1/scan", 5, 7)


def test_all_configs_load() -> None:
    files = sorted((REPO / "configs").glob("*.yaml")) + [SAMPLE / "sample.yaml"]
    names = {p.name for p in files}
    assert {"one_robot.yaml", "two_robots.yaml", "carmen_intel.yaml", "sample.yaml"} <= names
    for path in files:
        config = load_config(path)
        assert config.sensors, path
    two = load_config(REPO / "configs" / "two_robots.yaml")
    assert [s.range_max_m for s in two.sensors] == [20.0, 8.0]
    assert two.sensors[1].range_variance_m2 == 0.8
    assert two.sensors[1].bearing_variance_deg2 == 0.5


def test_sample_mcap_matches_the_intel_log() -> None:
    config = load_config(SAMPLE / "sample.yaml")
    [batch] = read_inputs([SAMPLE / "intel_sample.mcap"], config)
    got = (batch.sensor, batch.n_scans, batch.n_beams, batch.skipped_scans)
    assert got == ("intel", 50, 180, 0)
    assert batch.has_pose_covariance
    std = np.sqrt(np.diagonal(batch.pose_covariances, axis1=1, axis2=2))
    np.testing.assert_allclose(std, np.broadcast_to([0.03, 0.03, math.radians(0.5)], (50, 3)),
                               rtol=1e-4)
    log = DATA / "intel.gfs.log"
    if not log.is_file():
        pytest.skip(f"real data absent: {log}")
    full = read_carmen(log, SensorConfig())
    np.testing.assert_array_equal(batch.ranges,
                                  full.ranges[240:290].astype(np.float32).astype(float))
    np.testing.assert_allclose(batch.poses[:, :2], full.poses[240:290, :2], atol=1e-12)
    dyaw = np.angle(np.exp(1j * (batch.poses[:, 2] - full.poses[240:290, 2])))
    np.testing.assert_allclose(dyaw, 0.0, atol=1e-12)
    np.testing.assert_allclose(batch.angles, full.angles, atol=1e-6)
