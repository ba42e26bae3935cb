"""Poses from TF, covariances from AMCL / odometry, namespaced robots, several lasers.

Each bag is built in tests/rosbag_scenes.py from a known truth; the reader's laser poses
must match the truth within 1 mm, and the training samples must match those built from
the same scans with the exact laser poses.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from rosbag_scenes import (
    T0,
    BagWriter,
    Laser,
    Robot,
    Route,
    add_robot,
    amcl_stamps,
    compose,
    cov6,
    heldout_grid_auc,
    inverse,
    quat,
)

from gpocc.config import Config, MountConfig, SamplesConfig, SensorConfig
from gpocc.io.inputs import read_inputs
from gpocc.io.scans import ScanBatch
from gpocc.samples.beams import build_samples

# Every 5th scan, every 3rd beam: enough samples to compare, fast.
NO_THIN = Config(samples=SamplesConfig(thin_cell_m=0.0, scan_stride=5, beam_stride=3))
DEFAULT_P = SensorConfig().pose_covariance_matrix


def lever_oracle(cov: np.ndarray, base_yaw: np.ndarray, mount: tuple) -> np.ndarray:
    """Monte Carlo covariance of the laser pose when the base pose has covariance ``cov``."""
    rng = np.random.default_rng(0)
    out = []
    for yaw, c in zip(base_yaw, cov, strict=True):
        d = rng.multivariate_normal(np.zeros(3), c, size=200_000)
        base = np.column_stack([d[:, 0], d[:, 1], yaw + d[:, 2]])
        laser = compose(base, np.asarray(mount))
        out.append(np.cov(laser.T))
    return np.asarray(out)


def assert_covariances(got: np.ndarray, want: np.ndarray) -> None:
    """Equal up to Monte Carlo noise: differences in units of sqrt(c_ii c_jj) below 1%."""
    sd = np.sqrt(np.diagonal(want, axis1=1, axis2=2))
    scaled = (got - want) / (sd[:, :, None] * sd[:, None, :])
    assert np.abs(scaled).max() < 0.01, np.abs(scaled).max()


def clean_batch(read: ScanBatch, robot: Robot, laser: Laser) -> ScanBatch:
    """The same scans with the exact laser poses (and the read covariances)."""
    t = read.stamps - T0
    truth = robot.laser_pose(laser, t)
    return dataclasses.replace(read, poses=truth, provenance=None)


def assert_same_samples(read: ScanBatch, clean: ScanBatch) -> None:
    a = build_samples([read], NO_THIN)
    b = build_samples([clean], NO_THIN)
    assert len(a) == len(b) > 500
    np.testing.assert_array_equal(a.labels, b.labels)
    assert np.abs(a.means - b.means).max() < 1e-3


def assert_poses(read: ScanBatch, truth: np.ndarray) -> None:
    assert np.abs(read.poses[:, :2] - truth[:, :2]).max() < 1e-3
    assert np.abs(np.angle(np.exp(1j * (read.poses[:, 2] - truth[:, 2])))).max() < 1e-3


def one_robot(speed: float = 0.5, duration: float = 12.0, lasers: list | None = None) -> Robot:
    return Robot(Route(speed), lasers or [Laser("/scan", "laser")], duration=duration)


@pytest.mark.parametrize("fmt,name,compress", [
    ("ros2-mcap", "run", False), ("ros1", "run.bag", False), ("ros2-sqlite3", "run", True),
    ("mcap", "run.mcap", False), ("ros1", "run.bag", True)])
def test_tf_only_bag_with_drifting_odom_and_laser_offset(tmp_path: Path, fmt: str, name: str,
                                                         compress: bool) -> None:
    robot = one_robot()
    bag = BagWriter(fmt)
    add_robot(bag, robot)
    path = bag.write(tmp_path / name, compress=compress)
    [batch] = read_inputs([path], Config())  # no config: one laser + TF just works
    laser = robot.lasers[0]
    t_all = robot.scans["/scan"][0]
    assert batch.sensor == "scan" and batch.n_scans == t_all.size and batch.skipped_scans == 0
    assert_poses(batch, robot.laser_pose(laser, batch.stamps - T0))
    # Odometry alone drifts by up to 0.7 m: reading it would fail the 1 mm check above.
    assert_same_samples(batch, clean_batch(batch, robot, laser))
    prov = batch.provenance
    assert prov.pose_source == "TF map -> laser"
    assert prov.frame_chain.startswith("map -> odom (/tf) -> base_footprint (/tf) -> base_link")
    assert "laser (static)" in prov.frame_chain
    assert prov.covariance_source.startswith("config")
    # The config covariance is the base's; the laser 0.25 m ahead moves when the base turns.
    some = slice(0, None, 40)
    base_yaw = robot.route.base(batch.stamps[some] - T0)[:, 2]
    want = lever_oracle(np.broadcast_to(DEFAULT_P, (base_yaw.size, 3, 3)), base_yaw,
                        laser.mount)
    assert_covariances(batch.pose_covariances[some], want)


def test_no_map_frame_falls_back_to_odom_with_a_warning(tmp_path: Path, capsys) -> None:
    robot = one_robot()
    bag = BagWriter("ros2-mcap")
    add_robot(bag, robot, map_to_odom=False)
    [batch] = read_inputs([bag.write(tmp_path / "odom_only")], Config())
    assert capsys.readouterr().err.count("map will drift") == 1  # a warning, not a note too
    t = batch.stamps - T0
    in_odom = compose(compose(inverse(robot.correction(t)), robot.route.base(t)),
                      np.asarray(robot.lasers[0].mount))
    assert_poses(batch, in_odom)
    assert batch.provenance.frame_chain.startswith("odom -> base_footprint")


def test_slow_robot_with_amcl_at_its_motion_cadence(tmp_path: Path, capsys) -> None:
    # 5 cm/s: AMCL publishes every ~5 s, /odom at 50 Hz; both present, no config.
    robot = one_robot(speed=0.05, duration=40.0)
    bag = BagWriter("ros2-mcap")
    add_robot(bag, robot)
    t_amcl = amcl_stamps(robot)
    assert 5 <= t_amcl.size <= 12
    covs = []
    for k, t in enumerate(t_amcl):
        p = robot.route.base(np.array([t]))[0]
        c = cov6(0.01 + 0.002 * k, 0.02, 0.003 + 0.0005 * k, xy=0.004)
        covs.append(c[np.ix_([0, 1, 5], [0, 1, 5])])
        bag.pose_cov("/amcl_pose", T0 + t, "map", (p[0], p[1], 0.0), quat(yaw=p[2]), c)
    for t in np.arange(0, robot.duration, 0.02):
        bag.odom("/odom", T0 + t, "odom", "base_footprint", (0.0, 0.0, 0.0), quat(),
                 cov6(1e-3, 1e-3, 1e3))
    [batch] = read_inputs([bag.write(tmp_path / "amcl")], Config())
    assert "skipped" not in capsys.readouterr().err
    n_scans = robot.scans["/scan"][0].size
    assert batch.n_scans == n_scans and batch.skipped_scans == 0  # none lost to the cadence
    laser = robot.lasers[0]
    assert_poses(batch, robot.laser_pose(laser, batch.stamps - T0))
    assert batch.provenance.covariance_source.startswith("/amcl_pose")
    # Oracle: AMCL's covariance held before its first message, linear between messages,
    # carried to the laser through the mount lever arm.
    t = batch.stamps - T0
    covs = np.asarray(covs)
    held = np.stack([[np.interp(t, t_amcl, covs[:, i, j]) for j in range(3)]
                     for i in range(3)]).transpose(2, 0, 1)
    some = slice(0, None, 50)
    want = lever_oracle(held[some], robot.route.base(t[some])[:, 2], laser.mount)
    assert_covariances(batch.pose_covariances[some], want)
    assert_same_samples(batch, clean_batch(batch, robot, laser))


def _amcl_without_tf(tmp_path: Path, with_odom: bool) -> tuple[Robot, Path, np.ndarray]:
    robot = one_robot(speed=0.05, duration=40.0)
    bag = BagWriter("ros2-mcap")
    add_robot(bag, robot, map_to_odom=False, odom_tf=False, static_tf=False)
    t_amcl = amcl_stamps(robot)
    for t in t_amcl:
        p = robot.route.base(np.array([t]))[0]
        bag.pose_cov("/amcl_pose", T0 + t, "map", (p[0], p[1], 0.0), quat(yaw=p[2]),
                     cov6(0.01, 0.01, 0.002))
    if with_odom:
        for t in np.arange(0, robot.duration, 0.02):
            p = robot.odometry(np.array([t]))[0]
            bag.odom("/odom", T0 + t, "odom", "base_footprint", (p[0], p[1], 0.0),
                     quat(yaw=p[2]), cov6(1e-3, 1e-3, 1e3))
    return robot, bag.write(tmp_path / "amcl_no_tf"), t_amcl


def test_slow_amcl_without_tf_anchors_the_odometry(tmp_path: Path, capsys) -> None:
    robot, path, t_amcl = _amcl_without_tf(tmp_path, with_odom=True)
    mx, my, myaw = robot.lasers[0].mount
    mount = MountConfig(x_m=mx, y_m=my, yaw_deg=math.degrees(myaw))
    config = Config(sensors=(SensorConfig(name="r", scan_topic="/scan", mount=mount),))
    [batch] = read_inputs([path], config)
    assert "skipped" not in capsys.readouterr().err
    assert batch.n_scans == robot.scans["/scan"][0].size and batch.skipped_scans == 0
    assert batch.provenance.pose_source == "topic /amcl_pose anchoring odometry /odom"
    # Oracle: the correction of the latest fix (the first before the first fix) applied to
    # the odometry, which is what AMCL's map -> odom transform does between updates.
    t = batch.stamps - T0
    k = np.clip(np.searchsorted(t_amcl, t, side="right") - 1, 0, t_amcl.size - 1)
    fix = robot.route.base(t_amcl[k])
    want = compose(compose(fix, inverse(robot.odometry(t_amcl[k]))), robot.odometry(t))
    assert_poses(batch, want)
    # ... far nearer the truth than the odometry (off by up to 0.6 m and 0.15 rad here).
    truth = robot.route.base(t)[:, :2]
    odom_error = np.abs(compose(robot.odometry(t), np.asarray(robot.lasers[0].mount))[:, :2]
                        - robot.laser_pose(robot.lasers[0], t)[:, :2]).max()
    assert np.abs(batch.poses[:, :2] - truth).max() < 0.3 * odom_error


def test_many_skipped_scans_warn_with_reason_and_key(tmp_path: Path, capsys) -> None:
    # Odometry TF drops out from 3 s to 8 s of a 12 s log: those scans have no pose.
    robot = one_robot()
    bag = BagWriter("ros2-mcap")
    add_robot(bag, robot)
    bag.messages = [m for m in bag.messages if not (
        m[1] == "/tf" and m[3].transforms[0].child_frame_id == "base_footprint"
        and T0 + 3.0 < m[0] < T0 + 8.0)]
    [batch] = read_inputs([bag.write(tmp_path / "gap")], Config())
    t = robot.scans["/scan"][0]
    lost = int(np.count_nonzero((t > 3.0) & (t < 8.0)))
    assert batch.skipped_scans == lost and batch.n_scans == t.size - lost
    err = " ".join(capsys.readouterr().err.split())
    assert (f"sensor 'scan': {lost} of {t.size} scans" in err
            and "no TF odom->base_footprint within max_pose_gap_s" in err
            and "raise sensors[].max_pose_gap_s" in err)
    from gpocc.commands.info import provenance_lines

    lines = "\n".join(provenance_lines([batch]))
    assert (f"skipped {lost}: no TF odom->base_footprint within max_pose_gap_s of the scan "
            "(config key sensors[].max_pose_gap_s)") in lines


@pytest.mark.parametrize("sentinel", [1e3, 1e6, float("nan")])
def test_do_not_trust_odometry_covariance_uses_the_config(tmp_path: Path, capsys,
                                                          sentinel: float) -> None:
    robot = one_robot()
    bag = BagWriter("ros1")
    add_robot(bag, robot)
    for t in np.arange(0, robot.duration, 0.02):
        bag.odom("/odom", T0 + t, "odom", "base_footprint", (0.0, 0.0, 0.0), quat(),
                 cov6(1e-3, 1e-3, sentinel))
    own = ((0.01, 0.0, 0.0), (0.0, 0.02, 0.0), (0.0, 0.0, 0.004))
    config = Config(sensors=(SensorConfig(name="r", scan_topic="/scan", pose_covariance=own),))
    [batch] = read_inputs([bag.write(tmp_path / "odom.bag")], config)
    err = capsys.readouterr().err
    assert err.count("covariance unknown") + err.count("covariances unknown") == 1  # said once
    assert ("covariance_sentinel=1000" in err) == (sentinel >= 1e3)
    assert batch.provenance.covariance_source.startswith("config")
    laser = robot.lasers[0]
    some = slice(0, None, 40)
    yaw = robot.route.base(batch.stamps[some] - T0)[:, 2]
    want = lever_oracle(np.broadcast_to(np.asarray(own), (yaw.size, 3, 3)), yaw, laser.mount)
    assert_covariances(batch.pose_covariances[some], want)
    # Mean pose uncertainty stays at the config's centimetres, not 1000 rad^2.
    assert np.sqrt(batch.pose_covariances[:, 2, 2]).max() < 0.1


def test_odometry_covariance_is_turned_from_odom_into_map(tmp_path: Path) -> None:
    robot = one_robot()
    bag = BagWriter("ros2-mcap")
    add_robot(bag, robot)
    c = cov6(0.04, 0.001, 0.002)  # long along odom's x axis
    for t in np.arange(0, robot.duration, 0.02):
        bag.odom("/odom", T0 + t, "odom", "base_footprint", (0.0, 0.0, 0.0), quat(), c)
    [batch] = read_inputs([bag.write(tmp_path / "odom")], Config())
    t = batch.stamps - T0
    a = robot.correction(t)[:, 2]  # map -> odom yaw
    rot = np.zeros((t.size, 3, 3))
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1] = np.cos(a), -np.sin(a), np.sin(a), \
        np.cos(a)
    rot[:, 2, 2] = 1
    in_map = rot @ c[np.ix_([0, 1, 5], [0, 1, 5])] @ rot.transpose(0, 2, 1)
    some = slice(0, None, 40)
    want = lever_oracle(in_map[some], robot.route.base(t[some])[:, 2], robot.lasers[0].mount)
    assert_covariances(batch.pose_covariances[some], want)


def test_two_namespaced_robots_pair_by_namespace(tmp_path: Path) -> None:
    # robot1: prefixed frames on the shared /tf; robot2: its own /robot2/tf, plain frames.
    r1 = Robot(Route(0.5), [Laser("/robot1/scan", "robot1/laser")], prefix="robot1/")
    r2 = Robot(Route(0.8, route=1), [Laser("/robot2/scan", "laser2", mount=(-0.1, 0.0, 0.3))],
               drift=(-0.3, 0.5, -0.1))
    bag = BagWriter("ros1")
    add_robot(bag, r1)
    add_robot(bag, r2, tf_topic="/robot2/tf", static_topic="/robot2/tf_static")
    for robot, topic in ((r1, "/robot1/amcl_pose"), (r2, "/robot2/amcl_pose")):
        for t in amcl_stamps(robot):
            p = robot.route.base(np.array([t]))[0]
            bag.pose_cov(topic, T0 + t, "map", (p[0], p[1], 0), quat(yaw=p[2]),
                         cov6(0.01, 0.01, 0.002))
    batches = read_inputs([bag.write(tmp_path / "two.bag")], Config())
    assert [(b.sensor, b.n_scans) for b in batches] == [
        ("robot1/scan", r1.scans["/robot1/scan"][0].size),
        ("robot2/scan", r2.scans["/robot2/scan"][0].size)]
    for b, robot in zip(batches, (r1, r2), strict=True):
        assert b.provenance.covariance_source.startswith(f"/{b.sensor.split('/')[0]}/amcl_pose")
        assert_poses(b, robot.laser_pose(robot.lasers[0], b.stamps - T0))
        assert_same_samples(b, clean_batch(b, robot, robot.lasers[0]))


def test_front_and_back_laser_become_two_sensors(tmp_path: Path) -> None:
    # The back laser looks backwards and is mounted upside down: it scans clockwise.
    front = Laser("/front/scan", "front_laser", mount=(0.3, 0.0, 0.0))
    back = Laser("/back/scan", "back_laser", mount=(-0.3, 0.02, math.pi), upside_down=True)
    robot = one_robot(lasers=[front, back])
    bag = BagWriter("ros2-sqlite3")
    add_robot(bag, robot)
    for t in amcl_stamps(robot):
        p = robot.route.base(np.array([t]))[0]
        bag.pose_cov("/amcl_pose", T0 + t, "map", (p[0], p[1], 0), quat(yaw=p[2]),
                     cov6(0.01, 0.01, 0.002))
    batches = read_inputs([bag.write(tmp_path / "two_lasers")], Config())
    assert [b.sensor for b in batches] == ["back/scan", "front/scan"]
    for b, laser in zip(batches, (back, front), strict=True):
        assert b.n_scans == robot.scans[laser.topic][0].size
        assert_poses(b, robot.laser_pose(laser, b.stamps - T0))
        sign = -1.0 if laser.upside_down else 1.0
        np.testing.assert_allclose(b.angles, sign * laser.angles, atol=1e-6)
        clean = dataclasses.replace(clean_batch(b, robot, laser), angles=sign * laser.angles)
        assert_same_samples(b, clean)
    # Hits land on the world's walls: the bearings' mirroring is right.
    from rosbag_scenes import WORLD

    hits = build_samples([batches[0]], NO_THIN)
    hit_xy = hits.means[hits.labels > 0]
    assert np.median(np.abs(WORLD.clearance(hit_xy))) < 0.01


def test_config_mount_on_top_of_tf_is_an_error(tmp_path: Path) -> None:
    from gpocc.errors import GpoccError

    robot = one_robot()
    bag = BagWriter("ros2-mcap")
    add_robot(bag, robot)
    path = bag.write(tmp_path / "b")
    config = Config(sensors=(SensorConfig(name="r", scan_topic="/scan",
                                          mount=MountConfig(x_m=0.25)),))
    with pytest.raises(GpoccError, match=r"b: sensor 'r': TF already gives the laser's mount"):
        read_inputs([path], config)


def test_heldout_auc_of_the_tf_bag_matches_the_clean_bag(tmp_path: Path) -> None:
    from gpocc.io.bags import write_bag

    robot = one_robot(duration=20.0)
    bag = BagWriter("ros2-mcap")
    add_robot(bag, robot)
    [tf_batch] = read_inputs([bag.write(tmp_path / "tf")], Config())
    # The clean bag: the same scans with their exact laser poses on a pose topic.
    clean = clean_batch(tf_batch, robot, robot.lasers[0])
    write_bag(tmp_path / "clean.mcap", [clean], [("/scan", "/pose")], "mcap")
    [clean_read] = read_inputs([tmp_path / "clean.mcap"], Config())
    clean_auc, tf_auc = heldout_grid_auc(clean_read), heldout_grid_auc(tf_batch)
    assert clean_auc > 0.9
    assert abs(tf_auc - clean_auc) <= 0.005
    # Mapping in the odometry frame instead (what gpocc did before TF) is measurably worse.
    odom = dataclasses.replace(
        tf_batch, poses=compose(compose(inverse(robot.correction(tf_batch.stamps - T0)),
                                        robot.route.base(tf_batch.stamps - T0)),
                                np.asarray(robot.lasers[0].mount)))
    odom_auc = heldout_grid_auc(odom)
    print(f"held-out AUC: clean {clean_auc:.4f}, TF {tf_auc:.4f}, odometry frame {odom_auc:.4f}")
    assert odom_auc < clean_auc - 0.05


def _split_bag(bag: BagWriter, path: Path, at: float) -> Path:
    """A rosbag2 folder of two storage files (as ``ros2 bag record --max-bag-duration``)."""
    import yaml

    first, second = BagWriter(bag.fmt), BagWriter(bag.fmt)
    first.messages = [m for m in bag.messages if m[0] < at]
    second.messages = [m for m in bag.messages if m[0] >= at]
    first.write(path)
    other = second.write(path.parent / (path.name + "_part"))
    meta_a = yaml.safe_load((path / "metadata.yaml").read_text())
    meta_b = yaml.safe_load((other / "metadata.yaml").read_text())
    info_a, info_b = meta_a["rosbag2_bagfile_information"], meta_b["rosbag2_bagfile_information"]
    [name_b] = info_b["relative_file_paths"]
    new_name = f"{path.name}_1.mcap"
    (other / name_b).rename(path / new_name)
    info_a["relative_file_paths"].append(new_name)
    info_a["files"] += [{**f, "path": new_name} for f in info_b["files"]]
    info_a["message_count"] += info_b["message_count"]
    counts = {t["topic_metadata"]["name"]: t for t in info_a["topics_with_message_count"]}
    for t in info_b["topics_with_message_count"]:
        name = t["topic_metadata"]["name"]
        if name in counts:
            counts[name]["message_count"] += t["message_count"]
        else:
            info_a["topics_with_message_count"].append(t)
    end = (info_b["starting_time"]["nanoseconds_since_epoch"]
           + info_b["duration"]["nanoseconds"])
    info_a["duration"]["nanoseconds"] = end - info_a["starting_time"]["nanoseconds_since_epoch"]
    (path / "metadata.yaml").write_text(yaml.safe_dump(meta_a))
    return path


def test_split_rosbag2_bag_reads_as_one(tmp_path: Path) -> None:
    robot = one_robot()
    bag = BagWriter("ros2-mcap")
    add_robot(bag, robot)
    path = _split_bag(bag, tmp_path / "split", T0 + 6.0)
    assert len(list(path.glob("*.mcap"))) == 2
    [batch] = read_inputs([path], Config())
    assert batch.n_scans == robot.scans["/scan"][0].size and batch.skipped_scans == 0
    assert_poses(batch, robot.laser_pose(robot.lasers[0], batch.stamps - T0))


def test_info_shows_pose_source_chain_and_covariance(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from gpocc.cli import app

    robot = one_robot()
    bag = BagWriter("ros1")
    add_robot(bag, robot)
    for t in np.arange(0, robot.duration, 0.02):
        bag.odom("/odom", T0 + t, "odom", "base_footprint", (0.0, 0.0, 0.0), quat(),
                 cov6(1e-3, 1e-3, 1e6))
    path = bag.write(tmp_path / "run.bag")
    result = CliRunner().invoke(app, ["info", str(path)])
    assert result.exit_code == 0, result.output
    out = result.stdout
    n = robot.scans["/scan"][0].size
    assert f"scan: {n} scans used, 0 skipped" in out and "pose covariance from config" in out
    assert "run.bag: pose from TF map -> laser" in out
    assert ("frame chain: map -> odom (/tf) -> base_footprint (/tf) -> base_link (static) -> "
            "laser (static)") in out
    assert "covariance: config (sensors[].pose_covariance): /odom" in out
    assert "covariance_sentinel=1000" in out


def test_ambiguous_bag_prints_a_config_that_works(tmp_path: Path) -> None:
    import re

    import yaml

    from gpocc.config import config_from_dict
    from gpocc.errors import GpoccError

    # Two pose topics for one laser and no TF: gpocc cannot choose.
    bag = BagWriter("ros2-mcap")
    ang = np.linspace(-1, 1, 5)
    for k in range(5):
        bag.scan("/scan", "laser", T0 + 0.1 * k, ang, np.full(5, 2.0), 10.0)
        for topic in ("/amcl_pose", "/slam_pose"):
            bag.pose_cov(topic, T0 + 0.1 * k, "map", (0.1 * k, 0, 0), quat(),
                         cov6(0.01, 0.01, 0.001))
    path = bag.write(tmp_path / "amb")
    with pytest.raises(GpoccError, match="cannot choose the pose topic") as info:
        read_inputs([path], Config())
    text = re.search(r"(sensors: \[.*\])$", str(info.value)).group(1)
    config = config_from_dict(yaml.safe_load(text))
    [batch] = read_inputs([path], config)
    assert batch.n_scans == 5


@pytest.mark.parametrize("pitch_deg, upside_down", [(3.0, False), (3.0, True)])
def test_a_slightly_pitched_laser_is_mapped_flat(tmp_path: Path, pitch_deg: float,
                                                 upside_down: bool) -> None:
    robot = one_robot(lasers=[Laser("/scan", "laser", pitch=math.radians(pitch_deg),
                                    upside_down=upside_down)])
    bag = BagWriter("ros2-mcap")
    add_robot(bag, robot)
    [batch] = read_inputs([bag.write(tmp_path / "b")], Config())
    assert batch.n_scans == robot.scans["/scan"][0].size
    assert_poses(batch, robot.laser_pose(robot.lasers[0], batch.stamps - T0))


def _pitched_robot_bag(path: Path, pitch_deg: float, amcl: bool) -> Path:
    robot = one_robot(lasers=[Laser("/scan", "laser", pitch=math.radians(pitch_deg))])
    bag = BagWriter("ros2-mcap")
    add_robot(bag, robot, map_to_odom=not amcl)
    if amcl:
        for t in amcl_stamps(robot):
            p = robot.route.base(np.array([t]))[0]
            bag.pose_cov("/amcl_pose", T0 + t, "map", (p[0], p[1], 0), quat(yaw=p[2]),
                         cov6(0.01, 0.01, 0.002))
    return bag.write(path)


@pytest.mark.parametrize("amcl", [False, True])
def test_a_tilted_laser_is_refused_unless_max_tilt_allows_it(tmp_path: Path, amcl: bool) -> None:
    """Through the TF chain map -> laser, and (``amcl``) through a map-frame pose topic
    with the base -> laser mount from TF. Allowed, it keeps the scans a level one keeps."""
    from gpocc.errors import GpoccError

    path = _pitched_robot_bag(tmp_path / "b", 30.0, amcl)
    with pytest.raises(GpoccError, match=r"b: sensor .*tilts the laser frame 'laser' 30.0 "
                                         r"degrees from level.*max_tilt_deg \(5\)"):
        read_inputs([path], Config())
    config = Config(sensors=(SensorConfig(name="r", scan_topic="/scan", max_tilt_deg=45.0),))
    [batch] = read_inputs([path], config)
    [level] = read_inputs([_pitched_robot_bag(tmp_path / "level", 0.0, amcl)], config)
    assert batch.n_scans == level.n_scans > 0
    np.testing.assert_allclose(batch.poses, level.poses, atol=1e-9)
    assert batch.provenance.frame_chain.startswith("base_footprint" if amcl else "map")


def test_level_scans_skips_only_the_tilted_scans_with_a_pose() -> None:
    from gpocc.io.laserpose import ScanTopic, _level_scans

    sensor = SensorConfig(name="r", max_tilt_deg=5.0)
    valid = np.array([True, True, False, True, True])
    tilt = np.radians([0.0, 6.0, 40.0, 4.9, 90.0])
    laser = ScanTopic(frame_id="laser")
    kept, skips = _level_scans("b", sensor, laser, "map -> laser", valid, tilt)
    np.testing.assert_array_equal(kept, [True, False, False, True, False])
    assert [(key, count) for _, key, count in skips] == [("sensors[].max_tilt_deg", 2)]
    projected = ScanTopic(frame_id="velodyne:plane", levelled=True)  # a cloud's, levelled
    kept, skips = _level_scans("b", sensor, projected, "map -> velodyne", valid, tilt)
    np.testing.assert_array_equal(kept, valid)
    assert skips == []
    kept, skips = _level_scans("b", sensor, laser, "map -> laser", valid, np.zeros(5))
    np.testing.assert_array_equal(kept, valid)
    assert skips == []


def test_tf_that_misses_the_laser_frame_is_an_error_not_a_zero_mount(tmp_path: Path) -> None:
    """/tf_static not recorded: TF moves the base but never reaches the laser, so the
    laser's place on the pose topic's frame is unknown. It was taken as zero (the map
    shifted by the mount, mirrored for a laser facing backwards); the config's mount, or
    position_from_tf: false for a pose topic that is the laser's own pose, says it."""
    from gpocc.errors import GpoccError

    laser = Laser("/scan", "laser", mount=(-0.3, 0.1, math.pi))
    robot = one_robot(lasers=[laser])
    bag = BagWriter("ros2-mcap")
    add_robot(bag, robot, static_tf=False)
    for t in amcl_stamps(robot, dist=0.05, turn=0.05):
        p = robot.route.base(np.array([t]))[0]
        bag.pose_cov("/amcl_pose", T0 + t, "map", (p[0], p[1], 0), quat(yaw=p[2]),
                     cov6(0.01, 0.01, 0.002))
    path = bag.write(tmp_path / "b")
    with pytest.raises(GpoccError, match=r"b: sensor .*the bag has TF, but it does not place "
                                         r"the scan frame 'laser'.*record /tf_static"):
        read_inputs([path], Config())
    mount = MountConfig(x_m=-0.3, y_m=0.1, yaw_deg=180.0)
    [batch] = read_inputs([path], Config(sensors=(SensorConfig(
        name="r", scan_topic="/scan", pose_topic="/amcl_pose", mount=mount,
        max_pose_gap_s=1.0),)))
    # The mount applies when samples are built: the back laser's hits land on the walls.
    from rosbag_scenes import WORLD

    hits = build_samples([batch], NO_THIN)
    assert np.median(np.abs(WORLD.clearance(hits.means[hits.labels > 0]))) < 0.02
    [as_laser] = read_inputs([path], Config(sensors=(SensorConfig(
        name="r", scan_topic="/scan", pose_topic="/amcl_pose", position_from_tf=False,
        max_pose_gap_s=1.0),)))
    assert as_laser.n_scans == batch.n_scans
    off = build_samples([as_laser], NO_THIN)  # the zero mount: hits off the walls
    assert np.median(np.abs(WORLD.clearance(off.means[off.labels > 0]))) > 0.1


def test_a_scan_topic_whose_frame_id_changes_is_an_error(tmp_path: Path) -> None:
    """TF poses a topic by one frame's mount: a topic that switches lasers mapped every
    scan with the first one's. Scans whose frame_id is empty (a driver's first few) take
    the topic's frame."""
    from gpocc.errors import GpoccError

    robot = one_robot(lasers=[Laser("/scan", "laser"), Laser("/old", "laser_old")])
    robot.simulate()
    t, _, ranges = robot.scans["/scan"]
    laser = robot.lasers[0]
    paths = {}
    none = (t[:0], None, ranges[:0])
    for first in ("", "laser_old"):
        bag = BagWriter("ros2-mcap")
        add_robot(bag, dataclasses.replace(robot, scans={"/scan": none, "/old": none}))
        for k, (tk, r) in enumerate(zip(t, ranges, strict=True)):
            bag.scan("/scan", first if k < 3 else "laser", T0 + tk, laser.angles, r,
                     laser.max_range)
        paths[first] = bag.write(tmp_path / f"b{len(first)}")
    with pytest.raises(GpoccError, match=r"topic /scan changes its header.frame_id from "
                                         r"'laser_old' to 'laser' at t="):
        read_inputs([paths["laser_old"]], Config())
    [batch] = read_inputs([paths[""]], Config())
    assert batch.n_scans == t.size
    assert_poses(batch, robot.laser_pose(laser, batch.stamps - T0))


def test_the_fix_for_tf_that_misses_the_laser_names_the_cause() -> None:
    from gpocc.io.laserpose import _tf_fix
    from gpocc.io.tf import Edge, TfBuffer

    def edge(parent: str, child: str) -> Edge:
        return Edge(parent=parent, child=child, static=True, topic="/tf_static",
                    stamps=np.zeros(1), translations=np.zeros((1, 3)),
                    quaternions=np.array([[0.0, 0.0, 0.0, 1.0]]))

    tree = TfBuffer({"odom": edge("world", "odom"), "base": edge("odom", "base"),
                     "laser": edge("base", "laser")})
    assert "map_frame to 'world'" in _tf_fix(tree, "laser")
    assert "record /tf_static" in _tf_fix(tree, "lidar")
    assert "fix the driver's header.frame_id" in _tf_fix(tree, "")
    loop = TfBuffer({"a": edge("b", "a"), "b": edge("a", "b"), "laser": edge("a", "laser")})
    assert "remove the TF cycle through 'a'" in _tf_fix(loop, "laser")
    torn = TfBuffer({"laser": edge("base", "laser")}, conflicts={"base": "odom and map"})
    assert "one publisher of 'base'" in _tf_fix(torn, "laser")
    # Another robot's conflict is not this laser's cause.
    elsewhere = TfBuffer(tree.edges, conflicts={"robot2/base": "odom and map"})
    assert "record /tf_static" in _tf_fix(elsewhere, "lidar")


def test_a_tf_edge_published_once_is_named_in_the_error(tmp_path: Path) -> None:
    from gpocc.errors import GpoccError

    robot = one_robot()
    bag = BagWriter("ros2-mcap")
    add_robot(bag, robot, map_to_odom=False)
    bag.tf("/tf", T0 + 0.5, [("map", "odom", (0.0, 0.0, 0.0), quat())])
    with pytest.raises(GpoccError, match=r"TF map->odom on /tf has 1 message: publish a "
                                         r"transform that never changes on /tf_static$"):
        read_inputs([bag.write(tmp_path / "once")], Config())


def test_an_odometry_topic_with_only_static_tf_takes_the_mount_from_tf(tmp_path: Path) -> None:
    """/odom (odom -> base_footprint) and /tf_static, no /tf: TF reaches the laser from no
    map frame, but it holds the mount; the scans take the odometry pose and that mount."""
    laser = Laser("/scan", "laser", mount=(-0.3, 0.1, math.pi))
    robot = one_robot(lasers=[laser])
    bag = BagWriter("ros2-mcap")
    add_robot(bag, robot, map_to_odom=False, odom_tf=False)
    t_odom = np.arange(0.0, robot.duration, 0.02)
    for tk, p in zip(t_odom, robot.odometry(t_odom), strict=True):
        bag.odom("/odom", T0 + tk, "odom", "base_footprint", (p[0], p[1], 0.0), quat(yaw=p[2]),
                 cov6(0.01, 0.01, 0.002))
    [batch] = read_inputs([bag.write(tmp_path / "odom")], Config())
    assert batch.provenance.frame_chain.startswith("base_footprint")
    t = batch.stamps - T0
    truth = compose(robot.odometry(t), np.asarray(laser.mount))
    assert np.abs(batch.poses[:, :2] - truth[:, :2]).max() < 1e-3


def test_a_pose_topic_of_the_laser_itself_needs_no_mount_from_tf(tmp_path: Path) -> None:
    """Odometry whose child frame is the scan's frame poses the laser itself: TF for other
    frames (a camera) does not make its mount unknown."""
    laser = Laser("/scan", "laser", mount=(0.25, 0.05, 0.1))
    robot = one_robot(lasers=[laser])
    bag = BagWriter("ros2-mcap")
    add_robot(bag, robot, map_to_odom=False, odom_tf=False, static_tf=False)
    bag.tf("/tf_static", T0, [("base_link", "camera", (0.1, 0.0, 0.5), quat())])
    t_pose = np.arange(0.0, robot.duration, 0.02)
    for tk, p in zip(t_pose, robot.laser_pose(laser, t_pose), strict=True):
        bag.odom("/laser_odom", T0 + tk, "map", "laser", (p[0], p[1], 0.0), quat(yaw=p[2]),
                 cov6(0.01, 0.01, 0.002))
    [batch] = read_inputs([bag.write(tmp_path / "self")], Config())
    truth = robot.laser_pose(laser, batch.stamps - T0)
    assert np.abs(batch.poses[:, :2] - truth[:, :2]).max() < 1e-3


def test_a_changing_frame_id_is_harmless_where_tf_does_not_pose_the_scans(tmp_path: Path
                                                                         ) -> None:
    robot = one_robot()
    robot.simulate()
    t, _, ranges = robot.scans["/scan"]
    laser = robot.lasers[0]
    bag = BagWriter("ros2-mcap")
    for k, (tk, r) in enumerate(zip(t, ranges, strict=True)):
        bag.scan("/scan", "" if k < 3 else "laser", T0 + tk, laser.angles, r, laser.max_range)
    for tk, p in zip(t, robot.laser_pose(laser, t), strict=True):
        bag.pose_cov("/pose", T0 + tk, "map", (p[0], p[1], 0), quat(yaw=p[2]),
                     cov6(0.01, 0.01, 0.002))
    [batch] = read_inputs([bag.write(tmp_path / "no_tf")], Config())
    assert batch.n_scans == t.size
