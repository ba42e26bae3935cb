"""ROS bag reading and writing: round trips, pose interpolation, pose sources, bad bags."""

from __future__ import annotations

import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from gpocc.config import Config, SensorConfig
from gpocc.errors import GpoccError
from gpocc.io.bags import describe_bag, interpolate_poses, read_bag, write_bag
from gpocc.io.inputs import read_inputs
from gpocc.io.scans import ScanBatch

FORMATS = {"ros1": "run.bag", "ros2-sqlite3": "run", "ros2-mcap": "run", "mcap": "run.mcap"}


def make_batch(sensor: str, n_scans: int, n_beams: int, t0: float, seed: int) -> ScanBatch:
    """Random scans with every special range value, yaws wrapping through +-pi."""
    rng = np.random.default_rng(seed)
    ranges = rng.uniform(0.2, 12.0, (n_scans, n_beams))
    ranges[0, :3] = [np.nan, np.inf, -np.inf]
    ranges[-1, -1] = np.inf
    a = rng.normal(size=(n_scans, 3, 3)) * 0.05
    cov = a @ a.transpose(0, 2, 1) + np.diag([1e-3, 2e-3, 3e-4])
    poses = np.column_stack([
        rng.uniform(-20, 20, n_scans),
        rng.uniform(-20, 20, n_scans),
        np.linspace(-math.pi + 0.01, math.pi - 0.01, n_scans),
    ])
    return ScanBatch(
        sensor=sensor,
        source="memory",
        stamps=t0 + 0.1 * np.arange(n_scans) + 1e-3 * seed,
        angles=np.linspace(-2.0, 2.0, n_beams),
        ranges=ranges,
        poses=poses,
        pose_covariances=cov,
        range_min=0.1,
        range_max=30.0,
    )


def test_bags_with_message_definitions_do_not_build_the_default_typestore(tmp_path):
    """ROS 1 bags, MCAP files and rosbag2 bags written since Iron carry their message
    definitions: reading them leaves the ROS 2 Humble typestore (0.15 s) unbuilt."""
    from gpocc.io import bags

    written = [make_batch("robot1", 5, 10, 1_700_000_000.0, 1)]
    config = Config(sensors=(SensorConfig(name="robot1", scan_topic="/scan",
                                          pose_topic="/pose"),))
    for fmt in FORMATS:
        path = tmp_path / fmt / FORMATS[fmt]
        path.parent.mkdir()
        write_bag(path, written, [("/scan", "/pose")], fmt)
        bags._typestore.cache_clear()
        [batch] = read_inputs([path], config)
        describe_bag(path)
        assert bags._typestore.cache_info().misses == 0, fmt
        np.testing.assert_array_equal(batch.poses, written[0].poses)


def test_a_rosbag2_without_message_definitions_reads_with_the_humble_types(tmp_path):
    """A rosbag2 sqlite3 bag recorded before Iron stores no message definitions: its
    messages are read with the ROS 2 Humble types."""
    import sqlite3

    from gpocc.io import bags

    written = [make_batch("robot1", 5, 10, 1_700_000_000.0, 1)]
    config = Config(sensors=(SensorConfig(name="robot1", scan_topic="/scan",
                                          pose_topic="/pose"),))
    path = tmp_path / "run"
    write_bag(path, written, [("/scan", "/pose")], "ros2-sqlite3")
    [with_definitions] = read_inputs([path], config)
    [db] = path.glob("*.db3")
    with sqlite3.connect(db) as connection:
        assert connection.execute("delete from message_definitions").rowcount > 0
    bags._typestore.cache_clear()
    [without] = read_inputs([path], config)
    assert bags._typestore.cache_info().misses == 1  # built, for this bag only
    for field in ("stamps", "ranges", "poses", "pose_covariances", "angles"):
        np.testing.assert_array_equal(getattr(without, field),
                                      getattr(with_definitions, field), err_msg=field)


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_round_trip_two_sensors(tmp_path: Path, fmt: str) -> None:
    written = [make_batch("robot1", 12, 25, 1_700_000_000.0, 1),
               make_batch("robot2", 9, 40, 1_700_000_000.05, 2)]
    topics = [("/robot1/scan", "/robot1/pose"), ("/robot2/scan", "/robot2/pose")]
    path = tmp_path / FORMATS[fmt]
    write_bag(path, written, topics, fmt)
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temporaries left

    config = Config(sensors=tuple(
        SensorConfig(name=b.sensor, scan_topic=s, pose_topic=p)
        for b, (s, p) in zip(written, topics, strict=True)
    ))
    read = read_inputs([path], config)
    assert [b.sensor for b in read] == ["robot1", "robot2"]
    for w, r in zip(written, read, strict=True):
        assert r.source == str(path)
        assert r.skipped_scans == 0 and r.has_pose_covariance
        # LaserScan holds float32: the ranges come back exactly as float32, specials kept.
        np.testing.assert_array_equal(r.ranges, w.ranges.astype(np.float32).astype(float))
        np.testing.assert_allclose(r.stamps, w.stamps, rtol=0, atol=2e-6)
        np.testing.assert_allclose(r.poses, w.poses, rtol=0, atol=1e-9)
        np.testing.assert_allclose(r.pose_covariances, w.pose_covariances, rtol=0, atol=1e-15)
        np.testing.assert_allclose(r.angles, w.angles, rtol=0, atol=1e-6)
        assert r.range_min == pytest.approx(0.1, abs=1e-6)
        assert r.range_max == pytest.approx(30.0, abs=1e-6)

    contents = describe_bag(path)
    assert contents.format == fmt
    assert {t.name: t.count for t in contents.topics} == {
        "/robot1/scan": 12, "/robot1/pose": 12, "/robot2/scan": 9, "/robot2/pose": 9}
    assert contents.start_s == pytest.approx(written[0].stamps[0], abs=1e-6)
    assert contents.end_s == pytest.approx(written[0].stamps[-1], abs=1e-6)


def test_write_refuses_overwrite_and_bad_layout(tmp_path: Path) -> None:
    batch = make_batch("r", 3, 5, 10.0, 0)
    path = tmp_path / "a.mcap"
    write_bag(path, [batch], [("/scan", "/pose")], "mcap")
    before = path.read_bytes()
    with pytest.raises(GpoccError, match="already exists"):
        write_bag(path, [batch], [("/scan", "/pose")], "mcap")
    assert path.read_bytes() == before
    write_bag(path, [make_batch("r", 4, 5, 10.0, 1)], [("/scan", "/pose")], "mcap", force=True)
    assert read_bag(path, [SensorConfig(scan_topic="/scan", pose_topic="/pose")])[0].n_scans == 4

    uneven = ScanBatch(**{**batch.__dict__, "angles": np.array([0.0, 0.1, 0.3, 0.4, 0.5])})
    with pytest.raises(GpoccError, match="unevenly spaced"):
        write_bag(tmp_path / "b.mcap", [uneven], [("/scan", "/pose")], "mcap")
    with pytest.raises(GpoccError, match=r"\.bag"):
        write_bag(tmp_path / "c.mcap", [batch], [("/scan", "/pose")], "ros1")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.mcap"]


def test_interpolate_poses_analytic() -> None:
    # Constant velocity and yaw rate, yaw crossing +-pi; covariance linear in time.
    def truth(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        yaw = np.angle(np.exp(1j * (3.0 + 0.8 * t)))
        pose = np.column_stack([1.0 + 0.5 * t, -2.0 + 0.25 * t, yaw])
        cov = np.diag([1e-3, 2e-3, 1e-4])[None] + t[:, None, None] * np.diag([1e-4, 0, 1e-5])
        return pose, cov

    pose_t = np.round(np.arange(0.0, 3.0001, 0.1), 10)
    pose_t = pose_t[(pose_t < 1.5) | (pose_t > 1.95)]  # a gap 1.4 .. 2.0 (0.6 s)
    poses, covs = truth(pose_t)
    # 0.15 lies in the step where the yaw wraps from +pi to -pi.
    scan_t = np.array([-0.05, 0.0, 0.03, 0.15, 0.77, 1.4, 1.45, 1.7, 1.99, 2.0, 2.04, 3.0, 3.05])
    got, got_cov, valid = interpolate_poses(pose_t, poses, covs, scan_t, 0.25)
    expected_valid = [False, True, True, True, True, True, False, False, False, True, True, True,
                      False]
    np.testing.assert_array_equal(valid, expected_valid)
    want, want_cov = truth(scan_t[valid])
    np.testing.assert_allclose(got[valid][:, :2], want[:, :2], atol=1e-12)
    dyaw = np.angle(np.exp(1j * (got[valid][:, 2] - want[:, 2])))
    np.testing.assert_allclose(dyaw, 0.0, atol=1e-12)
    assert np.all(np.abs(got[:, 2]) <= math.pi)
    np.testing.assert_allclose(got_cov[valid], want_cov, atol=1e-15)


# --------------------------------------------------------------------------- custom bags


def _write_raw_bag(path: Path, scans: list[float], poses: list[tuple[float, tuple, np.ndarray]],
                   pose_type: str, scan_topics: tuple[str, ...] = ("/scan",),
                   pose_topics: tuple[str, ...] = ("/odom",),
                   angle_min: list[float] | None = None) -> None:
    """A ROS2 MCAP bag written with rosbags directly (independent of write_bag).
    ``angle_min``: per scan (default -1 rad), each scan spanning 2 rad in 3 beams."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types

    def header(t: float) -> object:
        sec = int(math.floor(t))
        return T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=round((t - sec) * 1e9)),
            frame_id="x")

    def pose_msg(xyz: tuple, quat: tuple) -> object:
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=xyz[0], y=xyz[1], z=0.0),
            orientation=T["geometry_msgs/msg/Quaternion"](x=quat[0], y=quat[1], z=quat[2],
                                                          w=quat[3]))

    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        sc = [writer.add_connection(t, "sensor_msgs/msg/LaserScan", typestore=ts)
              for t in scan_topics]
        pc = [writer.add_connection(t, pose_type, typestore=ts) for t in pose_topics]
        for k, t in enumerate(scans):
            first = -1.0 if angle_min is None else angle_min[k]
            msg = T["sensor_msgs/msg/LaserScan"](
                header=header(t), angle_min=first, angle_max=first + 2.0, angle_increment=1.0,
                time_increment=0.0, scan_time=0.0, range_min=0.05, range_max=10.0,
                ranges=np.array([1.0, 2.0, 3.0], dtype=np.float32),
                intensities=np.zeros(0, dtype=np.float32))
            for c in sc:
                writer.write(c, round(t * 1e9), ts.serialize_cdr(msg, c.msgtype))
        for t, (x, y, quat), cov6 in poses:
            p = pose_msg((x, y), quat)
            if pose_type == "nav_msgs/msg/Odometry":
                zero = np.zeros(36)
                msg = T[pose_type](
                    header=header(t), child_frame_id="base",
                    pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=p, covariance=cov6),
                    twist=T["geometry_msgs/msg/TwistWithCovariance"](
                        twist=T["geometry_msgs/msg/Twist"](
                            linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                            angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                        covariance=zero))
            else:
                msg = T[pose_type](header=header(t), pose=p)
            for c in pc:
                writer.write(c, round(t * 1e9), ts.serialize_cdr(msg, c.msgtype))


def _quat(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """ZYX Euler angles to a quaternion (x, y, z, w)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy)


def test_odometry_at_10hz_interpolated_to_scans(tmp_path: Path) -> None:
    # Odometry at 10 Hz from t=100 s, with a 0.5 s dropout; small roll/pitch must not
    # disturb the yaw. The 6x6 covariance has distinct values everywhere, so picking the
    # wrong rows or columns shows.
    t_pose = [100.0 + 0.1 * k for k in range(31) if not 12 <= k <= 16]
    # (positive definite: a non-PSD covariance in a bag is an error, tested below)
    a = np.arange(36, dtype=float).reshape(6, 6) * 0.01 + np.eye(6)
    cov6 = a @ a.T * 1e-4
    vx, wz = 0.4, 1.5
    poses = [(t, (vx * (t - 100), 0.0, _quat(0.02, -0.03, 3.0 + wz * (t - 100))),
              cov6.reshape(36)) for t in t_pose]
    scans = [99.95, 100.05, 100.5, 101.05, 101.3, 101.42, 101.75, 102.0, 103.0, 103.05]
    path = tmp_path / "odom"
    _write_raw_bag(path, scans, poses, "nav_msgs/msg/Odometry")
    [batch] = read_bag(path, [SensorConfig(name="r", scan_topic="/scan", pose_topic="/odom")])
    # 99.95 is before the first pose, 101.3 and 101.42 in the dropout (101.1 .. 101.7 s),
    # 103.05 after the last pose.
    np.testing.assert_allclose(batch.stamps, [100.05, 100.5, 101.05, 101.75, 102.0, 103.0],
                               atol=1e-6)
    assert batch.skipped_scans == 4
    dt = batch.stamps - 100.0
    np.testing.assert_allclose(batch.poses[:, 0], vx * dt, atol=1e-9)
    np.testing.assert_allclose(batch.poses[:, 1], 0.0, atol=1e-12)
    # The ZYX yaw is unaffected by roll and pitch, and linear in time.
    dyaw = np.angle(np.exp(1j * (batch.poses[:, 2] - (3.0 + wz * dt))))
    np.testing.assert_allclose(dyaw, 0.0, atol=1e-9)
    expected = cov6[np.ix_([0, 1, 5], [0, 1, 5])]
    np.testing.assert_allclose(batch.pose_covariances, np.broadcast_to(expected, (6, 3, 3)))
    assert batch.has_pose_covariance
    np.testing.assert_allclose(batch.angles, [-1.0, 0.0, 1.0])
    assert batch.range_min == pytest.approx(0.05) and batch.range_max == pytest.approx(10.0)

    # Config overrides: range limits, and the covariance when asked to.
    own = ((0.04, 0.0, 0.0), (0.0, 0.04, 0.0), (0.0, 0.0, 0.01))
    sensor = SensorConfig(name="r", scan_topic="/scan", pose_topic="/odom", range_min_m=0.5,
                          range_max_m=4.0, pose_covariance=own, override_pose_covariance=True,
                          max_pose_gap_s=0.65)
    [wide] = read_bag(path, [sensor])
    assert wide.skipped_scans == 2  # the 0.6 s gap is now bridged
    assert (wide.range_min, wide.range_max) == (0.5, 4.0)
    assert not wide.has_pose_covariance
    np.testing.assert_allclose(wide.pose_covariances, np.broadcast_to(own, (8, 3, 3)))


def test_pose_sources_without_covariance(tmp_path: Path) -> None:
    poses = [(10.0 + 0.1 * k, (float(k), 0.0, _quat(0, 0, 0.1 * k)), np.zeros(36))
             for k in range(5)]
    sensor = SensorConfig(name="r", scan_topic="/scan", pose_topic="/odom",
                          pose_covariance=((0.01, 0, 0), (0, 0.02, 0), (0, 0, 0.003)))
    for pose_type in ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped"):
        path = tmp_path / pose_type.split("/")[-1]
        _write_raw_bag(path, [10.1, 10.25], poses, pose_type)
        [batch] = read_bag(path, [sensor])
        # An all-zero covariance means "not estimated": the config's is used.
        assert not batch.has_pose_covariance
        np.testing.assert_allclose(batch.pose_covariances[0], sensor.pose_covariance_matrix)
        np.testing.assert_allclose(batch.poses[:, 0], [1.0, 2.5], atol=1e-9)
        np.testing.assert_allclose(batch.poses[:, 2], [0.1, 0.25], atol=1e-9)


def test_no_scan_near_a_pose_is_an_error(tmp_path: Path) -> None:
    poses = [(50.0 + 0.1 * k, (0.0, 0.0, _quat(0, 0, 0)), np.zeros(36)) for k in range(3)]
    path = tmp_path / "late"
    _write_raw_bag(path, [10.0, 11.0], poses, "geometry_msgs/msg/PoseStamped")
    with pytest.raises(GpoccError, match=r"late.*max_pose_gap_s"):
        read_bag(path, [SensorConfig(scan_topic="/scan", pose_topic="/odom")])


@pytest.mark.parametrize(("shift", "changes"), [(5e-7, False), (0.2, True)])
def test_a_scan_topic_that_changes_its_beam_layout_is_placed_on_one(
        tmp_path: Path, shift: float, changes: bool) -> None:
    # Within 1e-6 rad the layout is the same one (float rounding of a driver's angles).
    # Beyond, each beam goes to the nearest bearing of one layout and the shift's mean
    # square joins the bearing variance (gpocc.io.layouts; tests/io/test_layouts.py).
    poses = [(10.0 + 0.1 * k, (0.0, 0.0, _quat(0, 0, 0)), np.zeros(36)) for k in range(11)]
    path = tmp_path / "layout"
    _write_raw_bag(path, [10.1, 10.5, 10.9], poses, "geometry_msgs/msg/PoseStamped",
                   angle_min=[-1.0, -1.0, -1.0 + shift])
    sensor = SensorConfig(scan_topic="/scan", pose_topic="/odom")
    [batch] = read_bag(path, [sensor])
    assert len(batch.stamps) == 3
    np.testing.assert_allclose(batch.angles, [-1.0, 0.0, 1.0])
    np.testing.assert_array_equal(batch.ranges, np.tile([1.0, 2.0, 3.0], (3, 1)))
    notes = " ".join(batch.provenance.notes)
    if changes:
        # Three of nine beams moved by 0.2 rad.
        grown = sensor.bearing_variance_deg2 + math.degrees(0.2) ** 2 / 3
        assert batch.sensor_config.bearing_variance_deg2 == pytest.approx(grown)
        assert "varies from scan to scan (3 beams)" in notes
    else:
        assert batch.sensor_config is None and "varies" not in notes


# --------------------------------------------------------------------------- bad bags


@pytest.fixture(scope="module")
def good_bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("good")
    batch = make_batch("r", 30, 50, 5.0, 3)
    out = {}
    for fmt, name in FORMATS.items():
        out[fmt] = base / fmt / name
        write_bag(out[fmt], [batch], [("/scan", "/pose")], fmt)
    return out


def _cut_in_half(src: Path, dst: Path) -> None:
    data = src.read_bytes()
    dst.write_bytes(data[: len(data) // 2])


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_truncated_bag(tmp_path: Path, good_bags: dict[str, Path], fmt: str) -> None:
    src = good_bags[fmt]
    if src.is_dir():
        dst = tmp_path / "cut"
        shutil.copytree(src, dst)
        [storage] = [p for p in dst.iterdir() if p.name != "metadata.yaml"]
        _cut_in_half(src / storage.name, storage)
    else:
        dst = tmp_path / f"cut{src.suffix}"
        _cut_in_half(src, dst)
    with pytest.raises(GpoccError, match=f"{dst.name}.*(truncated|corrupt)"):
        read_inputs([dst], Config())


@pytest.mark.parametrize("name", ["noise.bag", "noise.mcap", "empty.bag", "empty.mcap"])
def test_random_or_empty_bytes(tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    path.write_bytes(b"" if name.startswith("empty") else os.urandom(3000))
    with pytest.raises(GpoccError, match=name.replace(".", r"\.")) as info:
        read_inputs([path], Config())
    assert "\n" not in str(info.value)


SAMPLE = Path(__file__).resolve().parents[2] / "data" / "sample"


def _flip_every(data: bytes, start: int, stop: int, step: int) -> bytes:
    out = bytearray(data)
    for k in range(start, stop, step):
        out[k] ^= 0xFF
    return bytes(out)


def test_a_corrupt_mcap_is_called_corrupt_not_blamed_on_a_field(tmp_path):
    # Every 97th byte of the data section flipped (header, summary and footer intact, so
    # the file opens): the scans' fields read as nonsense (an angle_max that disagrees
    # with its count), and the records no longer parse; the error says the file is
    # corrupt, not that the driver's angles are wrong.
    from gpocc.config import load_config

    config = load_config(SAMPLE / "sample.yaml")
    good = SAMPLE / "intel_sample.mcap"
    assert read_inputs([good], config)  # the intact file reads
    bad = tmp_path / "intel_sample.mcap"
    data = good.read_bytes()
    bad.write_bytes(_flip_every(data, 2000, len(data) - 2000, 97))
    with pytest.raises(GpoccError, match=r"intel_sample\.mcap: the file is corrupt "
                                         r"\(intel_sample\.mcap: its records do not parse"):
        read_inputs([bad], config)


def test_mcap_corruption_checks_the_crcs_a_writer_stored(tmp_path):
    from mcap.writer import CompressionType, Writer

    from gpocc.io.bags import mcap_corruption

    path = tmp_path / "crc.mcap"
    with open(path, "wb") as stream:
        # The mcap library's writer stores chunk and data-section CRCs.
        writer = Writer(stream, compression=CompressionType.NONE)
        writer.start()
        schema = writer.register_schema("raw", "none", b"")
        channel = writer.register_channel("/raw", "none", schema)
        for k in range(50):
            writer.add_message(channel, k, b"payload %03d" % k, k)
        writer.finish()
    data = path.read_bytes()
    assert mcap_corruption(path) is None
    at = data.index(b"payload 025")  # a byte inside the chunk's records
    path.write_bytes(data[:at] + b"q" + data[at + 1:])
    failure = mcap_corruption(path)
    assert failure is not None and failure.startswith("crc.mcap: crc validation failed")
    (tmp_path / "not.mcap").write_text("not an mcap file\n")
    assert mcap_corruption(tmp_path / "not.mcap") is None


def test_mcap_corruption_reports_bytes_no_record_holds(tmp_path):
    # A flipped high bit inside a record's text (a schema or channel name) does not
    # decode: records that do not parse, not an intact file.
    from gpocc.io.bags import mcap_corruption

    data = bytearray((SAMPLE / "intel_sample.mcap").read_bytes())
    data[64660] ^= 0x80
    path = tmp_path / "flipped.mcap"
    path.write_bytes(bytes(data))
    failure = mcap_corruption(path)
    assert failure is not None and failure.startswith("flipped.mcap: its records do not parse")


def test_the_corruption_check_never_hides_the_reads_own_error(tmp_path, monkeypatch):
    from gpocc.io import bags

    def broken(path):
        raise RuntimeError("the check itself failed")

    monkeypatch.setattr(bags, "mcap_corruption", broken)
    with pytest.raises(GpoccError, match="the angles"):
        with bags._corruption_named(tmp_path / "x.mcap"):
            raise GpoccError("x.mcap: the angles disagree")
