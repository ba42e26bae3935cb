"""Bag-message validation at the I/O boundary: quaternions, covariances, duplicate stamps,
LaserScan fields; and property tests: any decoded message gives a clean error or a valid
batch."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from fuzzing import fuzz_settings
from hypothesis import given
from hypothesis import strategies as st
from rosbag_scenes import T0, BagWriter, cov6, quat
from typer.testing import CliRunner

from gpocc.config import Config, SensorConfig
from gpocc.errors import GpoccError
from gpocc.io.bags import _add_scan
from gpocc.io.inputs import read_inputs
from gpocc.io.laserpose import ScanTopic, assemble
from gpocc.io.poses import PoseCollector

ANGLES = np.linspace(-1.0, 1.0, 5)
SENSOR = SensorConfig(name="r", scan_topic="/scan", pose_topic="/pose")


def pose_bag(path: Path, poses: list[tuple[float, tuple, tuple, np.ndarray]],
             scans: list[float] | None = None, **scan_fields: float) -> Path:
    """A ROS2 bag: PoseWithCovarianceStamped on /pose, LaserScan on /scan (no TF)."""
    bag = BagWriter("ros2-mcap")
    for t, xyz, q, c in poses:
        bag.pose_cov("/pose", T0 + t, "map", xyz, q, c)
    for t in scans if scans is not None else [0.05, 0.15]:
        bag.scan("/scan", "laser", T0 + t, ANGLES, np.full(5, 2.0), 10.0, **scan_fields)
    return bag.write(path)


def steady(n: int = 3, q: tuple = quat(yaw=0.5), c: np.ndarray | None = None) -> list:
    c = cov6(0.01, 0.02, 0.003) if c is None else c
    return [(0.1 * k, (float(k), 2.0, 0.0), q, c) for k in range(n)]


def test_non_unit_quaternions_are_normalised_and_counted(tmp_path: Path) -> None:
    [unit] = read_inputs([pose_bag(tmp_path / "unit", steady())], Config(sensors=(SENSOR,)))
    scaled = tuple(3.0 * v for v in quat(yaw=0.5))
    [big] = read_inputs([pose_bag(tmp_path / "x3", steady(q=scaled))], Config(sensors=(SENSOR,)))
    np.testing.assert_allclose(big.poses, unit.poses, atol=1e-12)
    np.testing.assert_allclose(big.poses[:, 2], 0.5, atol=1e-12)
    assert "3 non-unit quaternions on /pose normalised" in big.provenance.notes


@pytest.mark.parametrize("q", [(0.0, 0.0, 0.0, 0.0), (math.nan, 0.0, 0.0, 1.0)])
def test_zero_or_nan_quaternion_is_an_error(tmp_path: Path, q: tuple) -> None:
    poses = steady()
    poses[1] = (poses[1][0], poses[1][1], q, poses[1][3])
    path = pose_bag(tmp_path / "zero", poses)
    with pytest.raises(GpoccError, match=r"zero: topic /pose at t=1700000000\.100000 s, field "
                                         r"pose\.orientation: .* (all zero|not finite)"):
        read_inputs([path], Config(sensors=(SENSOR,)))


@pytest.mark.parametrize("x", [math.inf, 3e8])
def test_position_not_finite_or_too_far_is_an_error(tmp_path: Path, x: float) -> None:
    poses = steady()
    poses[1] = (poses[1][0], (x, 2.0, 0.0), poses[1][2], poses[1][3])
    path = pose_bag(tmp_path / "far", poses)
    with pytest.raises(GpoccError, match=r"far: topic /pose at t=1700000000\.100000 s: field "
                                         r"pose\.position is .* not finite or beyond 1e\+08 m"):
        read_inputs([path], Config(sensors=(SENSOR,)))


def test_negative_and_non_psd_covariances(tmp_path: Path) -> None:
    negative = cov6(0.01, -0.02, 0.003)
    not_psd = cov6(0.01, 0.01, 0.003, xy=0.05)  # |xy| > sqrt(0.01 * 0.01)
    for name, c, what in (("neg", negative, "negative variance"),
                          ("npsd", not_psd, "not positive semi-definite")):
        poses = steady()
        poses[2] = (poses[2][0], poses[2][1], poses[2][2], c)
        path = pose_bag(tmp_path / name, poses)
        with pytest.raises(GpoccError, match=rf"{name}: topic /pose at t=1700000000\.200000 s: "
                                             rf"field pose\.covariance .*{what}.*"
                                             r"repair_pose_covariance"):
            read_inputs([path], Config(sensors=(SENSOR,)))
        fix = SensorConfig(name="r", scan_topic="/scan", pose_topic="/pose",
                           repair_pose_covariance=True)
        [batch] = read_inputs([path], Config(sensors=(fix,)))
        assert any("1 non-PSD covariances on /pose repaired" in n for n in batch.provenance.notes)
        # The scan at 0.15 s is interpolated half way to the repaired matrix, which is the
        # nearest PSD matrix: its eigenvalues are the clipped ones (Higham 1988).
        block = c[np.ix_([0, 1, 5], [0, 1, 5])]
        w = np.linalg.eigvalsh(block)
        repaired = batch.pose_covariances[1] * 2 - steady()[0][3][np.ix_([0, 1, 5], [0, 1, 5])]
        # (stamps near 1.7e9 s hold about 0.2 us: the weight is 0.5 to 1e-6)
        np.testing.assert_allclose(np.linalg.eigvalsh(repaired), np.sort(np.maximum(w, 0)),
                                   atol=1e-6)
        assert np.linalg.eigvalsh(batch.pose_covariances).min() >= -1e-12


@pytest.mark.parametrize("block", [
    # an off-diagonal entry past the sentinel (possible only in a non-PSD block)
    cov6(0.0, 0.0, 0.0, xy=-4001.0),
    # every entry below the sentinel, but clipping the negative eigenvalue of
    # [[990, 990], [990, -990]] lifts the x variance to about 1195
    cov6(990.0, -990.0, 0.0, xy=990.0),
])
def test_sentinel_applies_to_magnitudes_and_to_repairs(tmp_path: Path, block) -> None:
    poses = steady()
    poses[2] = (poses[2][0], poses[2][1], poses[2][2], block)
    fix = SensorConfig(name="r", scan_topic="/scan", pose_topic="/pose",
                       repair_pose_covariance=True)
    [batch] = read_inputs([pose_bag(tmp_path / "big", poses)], Config(sensors=(fix,)))
    assert np.abs(batch.pose_covariances).max() < fix.covariance_sentinel
    assert any("1 of 3 covariances unknown (1 with entries >= sensors[].covariance_sentinel"
               in n for n in batch.provenance.notes), batch.provenance.notes
    assert not any("repaired" in n for n in batch.provenance.notes)  # counted once


def test_duplicate_stamps(tmp_path: Path) -> None:
    poses = steady()
    same = pose_bag(tmp_path / "same", poses + [poses[1]])
    [batch] = read_inputs([same], Config(sensors=(SENSOR,)))
    assert batch.n_scans == 2
    moved = (poses[1][0], (6.0, 2.0, 0.0), poses[1][2], poses[1][3])
    path = pose_bag(tmp_path / "dup", poses + [moved])
    with pytest.raises(GpoccError, match=r"dup: topic /pose has two messages at "
                                         r"t=1700000000\.100000 s with different poses"):
        read_inputs([path], Config(sensors=(SENSOR,)))


@pytest.mark.parametrize("field,value,words", [
    ("angle_min", math.inf, "field angle_min is inf"),
    ("angle_increment", math.nan, "field angle_increment is nan"),
    ("angle_increment", 0.0, "field angle_increment=0.0 with 5 ranges"),
    ("angle_max", 3.0, "field angle_max=3.000000 disagrees"),
])
def test_bad_laserscan_fields_are_one_line_errors(tmp_path: Path, field: str, value: float,
                                                  words: str) -> None:
    path = pose_bag(tmp_path / "scan", steady(), **{field: value})
    with pytest.raises(GpoccError, match=r"scan: topic /scan at t=1700000000\.050000 s: "
                       + words.replace(".", r"\.").replace("(", r"\(")):
        read_inputs([path], Config(sensors=(SENSOR,)))
    from gpocc.cli import app

    result = CliRunner().invoke(app, ["info", str(path)])
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert len(result.stderr.strip().splitlines()) == 1 and words in result.stderr


# --------------------------------------------------------------------------- properties

def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE).types


T = _typestore()
_any = st.floats(allow_nan=True, allow_infinity=True, width=32)
_small = st.floats(-10.0, 10.0)


def _header(t: float) -> object:
    sec = int(t)
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=int((t - sec) * 1e9)),
        frame_id="laser")


@st.composite
def scan_messages(draw):
    n = draw(st.integers(0, 6))
    fields = {k: draw(st.one_of(_any, _small)) for k in
              ("angle_min", "angle_max", "angle_increment", "range_min", "range_max")}
    ranges = np.asarray(draw(st.lists(_any, min_size=n, max_size=n)), np.float32)
    return T["sensor_msgs/msg/LaserScan"](
        header=_header(100.0), time_increment=0.0, scan_time=0.0, ranges=ranges,
        intensities=np.zeros(0, np.float32), **fields)


@st.composite
def pose_messages(draw):
    q = [draw(st.one_of(_any, _small)) for _ in range(4)]
    xy = [draw(st.one_of(_any, st.floats(-1e3, 1e3))) for _ in range(2)]
    cov = np.asarray(draw(st.lists(st.one_of(_any, st.floats(-1.0, 1.0)), min_size=36,
                                   max_size=36)), float)
    if draw(st.booleans()):
        with np.errstate(all="ignore"):  # often PSD, maybe huge or NaN
            cov = (cov.reshape(6, 6) @ cov.reshape(6, 6).T).ravel()
    pose = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=xy[0], y=xy[1], z=0.0),
        orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
    stamp = draw(st.sampled_from([99.9, 100.0, 100.1]))
    return T["geometry_msgs/msg/PoseWithCovarianceStamped"](
        header=_header(stamp),
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov))


@fuzz_settings(80)
@given(scan=scan_messages(), poses=st.lists(pose_messages(), min_size=1, max_size=3),
       repair=st.booleans())
def test_decoding_gives_a_clean_error_or_a_valid_batch(scan, poses, repair: bool) -> None:
    path = Path("fuzz.mcap")
    sensor = SensorConfig(name="r", scan_topic="/scan", pose_topic="/pose",
                          repair_pose_covariance=repair)
    try:
        acc = ScanTopic()
        _add_scan(path, "/scan", acc, scan, 0)
        collector = PoseCollector(path, "/pose", "geometry_msgs/msg/PoseWithCovarianceStamped")
        for msg in poses:
            collector.add(msg, 0)
        batch = assemble(path, sensor, acc, None, collector.build())
    except GpoccError as exc:
        text = str(exc)
        assert "\n" not in text and text.startswith("fuzz.mcap")
        return
    assert np.isfinite(batch.angles).all() and np.isfinite(batch.poses).all()
    assert np.all(np.abs(batch.poses[:, 2]) <= math.pi + 1e-12)
    assert 0 <= batch.range_min < batch.range_max and math.isfinite(batch.range_max)
    cov = batch.pose_covariances
    assert np.isfinite(cov).all()
    np.testing.assert_allclose(cov, np.swapaxes(cov, 1, 2), atol=1e-12)
    scale = np.maximum(np.abs(cov).max(axis=(1, 2)), 1e-300)
    assert (np.linalg.eigvalsh(cov).min(axis=1) >= -1e-9 * scale).all()
    assert np.all(np.diagonal(cov, axis1=1, axis2=2) < sensor.covariance_sentinel)
