"""Real-shaped bags with no config: rounded covariances, broken header stamps, odometry in
the map frame, NaN covariances, and clean OS / network errors.

Each bag is built in tests/rosbag_scenes.py from a known truth (a robot driving the
simulated default world). Oracles: the truth's laser poses (within 1 mm), the held-out
AUC of the same scans with their exact laser poses (the clean twin, within 0.005),
brute-force rounding of PSD matrices, Monte Carlo for the covariance through the mount,
and the file system for what a failed write leaves.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Callable
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
    cov6,
    heldout_grid_auc,
    quat,
)
from test_io_tf import assert_covariances, lever_oracle
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.config import Config, SensorConfig
from gpocc.errors import GpoccError
from gpocc.io.inputs import read_inputs
from gpocc.io.poses import PoseSeries, check_covariances, psd_shortfall
from gpocc.io.scans import ScanBatch
from gpocc.io.stamps import choose_stamps

runner = CliRunner()
DEFAULT_P = SensorConfig().pose_covariance_matrix
# A near-singular covariance: x and y almost fully correlated (a corridor), as GMapping's
# particle spread gives; rounded to 2 significant digits it is no longer PSD.
TRUE_COV = np.array([[1.6e-4, 1.26e-4, 0.0], [1.26e-4, 1.0e-4, 0.0], [0.0, 0.0, 1e-3]])


def round_sig(a: np.ndarray, digits: int) -> np.ndarray:
    """Every entry rounded to ``digits`` significant digits, as printed by a recorder."""
    return np.vectorize(lambda v: float(f"{v:.{digits - 1}e}"))(a)


def block6(c3: np.ndarray) -> np.ndarray:
    c = cov6(0.0, 0.0, 0.0)
    c[np.ix_([0, 1, 5], [0, 1, 5])] = c3
    return c


def one_robot(prefix: str = "", scan_rate: float = 10.0) -> Robot:
    laser = Laser(f"/{prefix}scan", f"{prefix}laser")
    return Robot(Route(0.5), [laser], prefix=prefix, duration=16.0, scan_rate=scan_rate)


def clean_twin(robot: Robot) -> ScanBatch:
    """Every scan with its exact laser pose: what a perfect recording gives."""
    laser = robot.lasers[0]
    t, pose, ranges = robot.scans[laser.topic]
    return ScanBatch(sensor="scan", source="clean", stamps=T0 + t, angles=laser.angles,
                     ranges=ranges, poses=pose,
                     pose_covariances=np.broadcast_to(DEFAULT_P, (t.size, 3, 3)).copy(),
                     range_min=0.05, range_max=laser.max_range, has_pose_covariance=False)


def assert_like_clean_twin(batch: ScanBatch, robot: Robot) -> None:
    """Same scans, laser poses within 1 mm (2.5 mm with a receive-time clock) of the
    truth, held-out AUC within 0.005 of the clean twin's."""
    clean = clean_twin(robot)
    assert batch.n_scans == clean.n_scans and batch.skipped_scans == 0
    truth = clean.poses
    assert np.abs(batch.poses[:, :2] - truth[:, :2]).max() < 3e-3
    assert np.abs(np.angle(np.exp(1j * (batch.poses[:, 2] - truth[:, 2])))).max() < 3e-3
    clean_auc, auc = heldout_grid_auc(clean), heldout_grid_auc(batch)
    assert clean_auc > 0.9
    assert abs(auc - clean_auc) <= 0.005, (auc, clean_auc)


def info(path: Path) -> str:
    result = runner.invoke(app, ["info", str(path)])
    assert result.exit_code == 0, result.output
    return result.stdout


def one_error_line(result, *names: str) -> str:
    assert result.exit_code != 0
    lines = [line for line in result.stderr.splitlines() if "error:" in line]
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.output
    for name in names:
        assert name in lines[0], lines[0]
    return lines[0]


# ------------------------------------------------------------------ 1. rounded covariances


def test_rounding_any_psd_matrix_stays_within_the_tolerance() -> None:
    """Brute force: PSD matrices of every rank, scale and correlation, rounded to 2 and 3
    significant digits, all pass; matrices clearly not PSD do not."""
    rng = np.random.default_rng(1)
    worst = {2: 0.0, 3: 0.0}
    for k in range(3000):
        rank = 1 + k % 3
        a = rng.normal(size=(3, rank)) * np.array([1e-2, 1e-2, 3e-2])[:, None]
        c = a @ a.T * 10.0 ** rng.uniform(-3, 3)
        for digits in (2, 3):
            worst[digits] = max(worst[digits], float(psd_shortfall(round_sig(c, digits),
                                                                   digits)))
    # Rounding reaches a good share of the bound but never passes it.
    assert 0.2 < worst[2] <= 1.0 and 0.2 < worst[3] <= 1.0, worst
    # The largest correlation 2 digits can make, 1.05 / 0.95, passes; 1.2 does not.
    def corr(rho: float) -> np.ndarray:
        return np.array([[1.0, rho, 0.0], [rho, 1.0, 0.0], [0.0, 0.0, 1.0]])
    assert psd_shortfall(corr(1.05 / 0.95)) <= 1.0 < psd_shortfall(corr(1.2))
    # A zero variance with a non-zero covariance is no rounding.
    assert psd_shortfall(np.diag([0.0, 1.0, 1.0]) + 1e-6 * (1 - np.eye(3))) == np.inf


def _series(covs: np.ndarray) -> PoseSeries:
    n = covs.shape[0]
    return PoseSeries("/amcl_pose", "geometry_msgs/msg/PoseWithCovarianceStamped",
                      np.arange(n, dtype=float), np.zeros((n, 3)), covs, "map", "")


def test_within_rounding_is_clipped_and_counted_beyond_is_an_error() -> None:
    rounded = round_sig(TRUE_COV, 2)
    assert np.linalg.eigvalsh(rounded).min() < 0  # the case of the CSAIL log
    check = check_covariances(_series(np.stack([rounded, TRUE_COV])), Path("log.bag"), 1e3,
                              False, "sensors[]")
    assert check.rounded == 1 and check.known.all()
    assert np.linalg.eigvalsh(check.covariances).min() >= -1e-18
    # Clipping moves the matrix by no more than the rounding did (nearest PSD matrix).
    assert np.abs(check.covariances[0] - rounded).max() <= np.abs(rounded - TRUE_COV).max()
    beyond = rounded.copy()
    beyond[0, 1] = beyond[1, 0] = 1.8e-4  # correlation 1.42
    with pytest.raises(GpoccError, match=r"log.bag: topic /amcl_pose .* is not positive "
                                         r"semi-definite .*repair_pose_covariance"):
        check_covariances(_series(beyond[None]), Path("log.bag"), 1e3, False, "sensors[]")
    negative = TRUE_COV.copy()
    negative[2, 2] = -1e-6
    with pytest.raises(GpoccError, match="negative variance"):
        check_covariances(_series(negative[None]), Path("log.bag"), 1e3, False, "sensors[]")


def _amcl_bag(tmp_path: Path, cov: np.ndarray, name: str = "csail") -> tuple[Robot, Path]:
    """TF (map -> odom -> base -> laser) and /amcl_pose at 10 Hz with covariance ``cov``."""
    robot = one_robot()
    bag = BagWriter("ros1")
    add_robot(bag, robot)
    t = np.arange(0.0, robot.duration, 0.1) + 0.003
    for tk, p in zip(t, robot.route.base(t), strict=True):
        bag.pose_cov("/amcl_pose", T0 + tk, "map", (p[0], p[1], 0.0), quat(yaw=p[2]),
                     block6(cov))
    return robot, bag.write(tmp_path / f"{name}.bag")


def test_a_log_with_rounded_covariances_maps_like_its_clean_twin(tmp_path: Path,
                                                                 capsys) -> None:
    robot, path = _amcl_bag(tmp_path, round_sig(TRUE_COV, 2))
    [batch] = read_inputs([path], Config())
    assert "rounding" not in capsys.readouterr().err  # silent: no fault of the log
    assert batch.provenance.covariance_source.startswith("/amcl_pose")
    assert_like_clean_twin(batch, robot)
    assert np.linalg.eigvalsh(batch.pose_covariances).min() > -1e-15
    out = info(path)
    assert "160 covariances on /amcl_pose PSD only within the rounding of 2 significant " \
           "digits: clipped to PSD" in out


def test_a_covariance_beyond_rounding_is_still_one_error_line(tmp_path: Path) -> None:
    beyond = round_sig(TRUE_COV, 2)
    beyond[0, 1] = beyond[1, 0] = 1.8e-4
    _, path = _amcl_bag(tmp_path, beyond, "broken")
    out = tmp_path / "grid"
    result = runner.invoke(app, ["grid", str(path), "--resolution", "0.2", "--out", str(out)])
    line = one_error_line(result, "broken.bag", "/amcl_pose", "repair_pose_covariance")
    assert "not positive semi-definite" in line
    assert not out.exists()


# ------------------------------------------------------------------ 2. stamps


def test_choose_stamps_rules() -> None:
    log_t = np.arange(5.0) + 100.004
    good = np.arange(5.0) + 100.0
    assert choose_stamps(good, log_t, False).source == "header stamps"
    for header, words in ((np.zeros(5), "5 of 5 header stamps are zero"),
                          (np.full(5, 100.0), "all 5 header stamps are equal"),
                          (good[[0, 1, 3, 2, 4]], "1 of 4 header stamps repeat or go back"),
                          (good[[0, 1, 1, 2, 3]], "1 of 4 header stamps repeat or go back")):
        chosen = choose_stamps(header, log_t, False)
        assert chosen.reason.startswith(words) and np.array_equal(chosen.times, log_t)
    # A pose topic may repeat a message (dropped later as a duplicate), not go back.
    assert choose_stamps(good[[0, 1, 1, 2, 3]], log_t, True).reason == ""


def test_a_few_bad_stamps_are_dropped_and_the_rest_keep_their_header_stamps() -> None:
    """A glitch (a zero, a repeated and an out-of-order stamp in 100) drops those
    messages, not the header clock; the kept ones are the longest increasing run."""
    import itertools

    from gpocc.io.stamps import MAX_DROPPED_SHARE, _increasing

    header = np.arange(100.0) + 100.0
    header[10] = 0.0
    header[40] = header[39]
    header[70] = 500.0  # one stamp far ahead: it, not the 29 after it, is the bad one
    chosen = choose_stamps(header, header + 0.4, False)
    assert chosen.source == "header stamps" and np.array_equal(chosen.times, header)
    assert np.flatnonzero(~chosen.keep).tolist() == [10, 40, 70]
    assert chosen.reason == "3 of 100 header stamps are zero, repeat or go back"
    assert 3 <= MAX_DROPPED_SHARE * 100
    # Brute force: no larger strictly increasing subsequence exists.
    rng = np.random.default_rng(0)
    for _ in range(200):
        values = rng.integers(0, 6, rng.integers(1, 10)).astype(float)
        keep = _increasing(values)
        assert np.all(np.diff(values[keep]) > 0)
        best = max(k for k in range(values.size + 1)
                   for sub in itertools.combinations(values.tolist(), k)
                   if all(a < b for a, b in itertools.pairwise(sub)))
        assert keep.sum() == best


def test_a_pose_topic_keeps_its_repeats_but_drops_a_stale_stamp() -> None:
    """A pose topic may repeat the message just before (dropped later as a duplicate),
    but a stamp equal to an earlier one is stale: for [1, 2, 3, 2, 4] the 2 after the 3
    goes, not the 3 (which left two different poses at one stamp: an error)."""
    from gpocc.io.stamps import _ordered

    def kept(values: list[float]) -> list[float]:
        header = np.asarray(values, float)
        return header[_ordered(header, np.zeros(header.size, bool), True)].tolist()

    assert kept([1, 2, 3, 2, 4]) == [1, 2, 3, 4]
    assert kept([1, 2, 2, 3, 4]) == [1, 2, 2, 3, 4]
    assert kept([1, 2, 2, 5, 3, 4]) == [1, 2, 2, 3, 4]
    rng = np.random.default_rng(1)
    for _ in range(300):
        values = rng.integers(0, 8, rng.integers(1, 30)).astype(float)
        mask = _ordered(values, np.zeros(values.size, bool), True)
        index = np.flatnonzero(mask)
        steps = np.diff(values[index])
        assert np.all(steps >= 0)
        # An equal kept pair is two neighbours of the original order.
        assert np.all(np.diff(index)[steps == 0] == 1)


def test_a_stale_pose_stamp_drops_that_pose_only(tmp_path: Path, capsys) -> None:
    robot = one_robot()
    bag = BagWriter("ros2-mcap")
    add_robot(bag, robot, map_to_odom=False, odom_tf=False)
    t_pose = np.arange(0.0, robot.duration, 0.05)
    for k, (tk, p) in enumerate(zip(t_pose, robot.route.base(t_pose), strict=True)):
        stamp = t_pose[k - 2] if k == 100 else tk  # one message with a stale stamp
        bag.pose_cov("/amcl_pose", T0 + tk, "map", (p[0], p[1], 0), quat(yaw=p[2]),
                     cov6(0.01, 0.01, 0.002))
        msg = bag.messages[-1][3]
        msg.header.stamp.sec = int(T0 + stamp)
        msg.header.stamp.nanosec = round((T0 + stamp - int(T0 + stamp)) * 1e9)
    [batch] = read_inputs([bag.write(tmp_path / "stale")], Config())
    assert f"1 of {t_pose.size} header stamps are zero or go back" in capsys.readouterr().err
    truth = robot.laser_pose(robot.lasers[0], batch.stamps - T0)
    assert np.abs(batch.poses[:, :2] - truth[:, :2]).max() < 2e-3


def _relog_scans(bag: BagWriter, delay_s: float,
                 restamp: Callable[[int, float, object, list], None]) -> list:
    """Take the bag's /scan messages out, let ``restamp(k, t, msg, scans)`` edit the k-th
    one's header stamp, and log each ``delay_s`` seconds after its time ``t``; the scans
    as they were listed, ``(t, topic, msgtype, msg)``."""
    scans = [m for m in bag.messages if m[1] == "/scan"]
    bag.messages = [m for m in bag.messages if m[1] != "/scan"]
    for k, (t, topic, msgtype, msg) in enumerate(scans):
        restamp(k, t, msg, scans)
        bag.add(topic, msgtype, t + delay_s, msg)
    return scans


def test_a_repeated_scan_stamp_keeps_the_scans_on_the_tf_clock(tmp_path: Path, capsys) -> None:
    """The recorder logs each scan 0.4 s late and one stamp repeats: timing the whole topic
    by log time put every scan 0.4 s off TF (a ghost of every wall); now that one scan is
    dropped and the others keep their exact poses."""
    robot = one_robot()
    bag = BagWriter("ros2-mcap")
    add_robot(bag, robot)

    def repeat_20th(k: int, t: float, msg, scans: list) -> None:
        if k == 20:
            msg.header.stamp = scans[19][3].header.stamp

    scans = _relog_scans(bag, 0.4, repeat_20th)
    [batch] = read_inputs([bag.write(tmp_path / "late")], Config())
    err = capsys.readouterr().err
    assert f"1 of {len(scans)} header stamps are zero, repeat or go back; those messages " \
           "are dropped" in err.replace("\n", "")
    t_true = np.delete(robot.scans["/scan"][0], 20)
    np.testing.assert_allclose(batch.stamps - T0, t_true, atol=1e-6)
    truth = robot.laser_pose(robot.lasers[0], t_true)
    assert np.abs(batch.poses[:, :2] - truth[:, :2]).max() < 1e-3


@pytest.mark.parametrize("kind", ["zero", "constant", "backwards"])
def test_broken_scan_stamps_fall_back_to_log_time_with_one_warning(tmp_path: Path, capsys,
                                                                    kind: str) -> None:
    robot = one_robot()
    bag = BagWriter("ros2-mcap")
    add_robot(bag, robot)
    # The recorder logs each scan 4 ms after it was taken; the driver's stamps are broken.
    def break_stamp(k: int, t: float, msg, scans: list) -> None:
        stamp = {"zero": 0.0, "constant": T0, "backwards": t - 2.0 * (k % 10 == 9)}[kind]
        sec = int(stamp)
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, round((stamp - sec) * 1e9)

    scans = _relog_scans(bag, 0.004, break_stamp)
    path = bag.write(tmp_path / "stamps")
    [batch] = read_inputs([path], Config())
    err = capsys.readouterr().err
    warnings = [line for line in err.splitlines() if "header stamps" in line]
    assert len(warnings) == 1, err
    n = len(scans)
    count = {"zero": f"{n} of {n} header stamps are zero",
             "constant": f"all {n} header stamps are equal",
             "backwards": f"{n // 10} of {n - 1} header stamps repeat or go back"}[kind]
    assert f"topic /scan: {count}" in warnings[0] and "log (receive) time" in warnings[0]
    np.testing.assert_allclose(batch.stamps - T0, robot.scans["/scan"][0] + 0.004, atol=1e-6)
    # Poses at the log time are 4 ms late: 2 mm at 0.5 m/s.
    assert_like_clean_twin(batch, robot)
    assert "stamps: /scan: log (receive) time" in info(path)


def _slam_bag(tmp_path: Path, early_scans: int = 0,
              zero_pose_stamps: bool = False) -> tuple[Robot, Path]:
    """A scan matcher's pose per scan (PoseWithCovarianceStamped in map, stamped with the
    scan's acquisition time) at 3 Hz, longer gaps than max_pose_gap_s; scans with zero
    header stamps, logged 5 ms late; the laser mount only in /tf_static."""
    robot = one_robot(scan_rate=3.0)
    bag = BagWriter("ros2-mcap")
    add_robot(bag, robot, map_to_odom=False, odom_tf=False)
    for m in bag.messages:
        if m[1] == "/scan":
            m[3].header.stamp.sec, m[3].header.stamp.nanosec = 0, 0
    bag.messages = [(m[0] + 0.005, *m[1:]) if m[1] == "/scan" else m for m in bag.messages]
    t = robot.scans["/scan"][0][early_scans:]
    for tk, p in zip(t, robot.route.base(t), strict=True):
        bag.pose_cov("/slam_toolbox/pose", T0 + tk, "map", (p[0], p[1], 0.0), quat(yaw=p[2]),
                     cov6(0.004, 0.003, 0.001))
        if zero_pose_stamps:
            bag.messages[-1][3].header.stamp.sec = bag.messages[-1][3].header.stamp.nanosec = 0
    return robot, bag.write(tmp_path / "slam")


def test_scans_take_the_pose_within_the_stamp_tolerance(tmp_path: Path, capsys) -> None:
    robot, path = _slam_bag(tmp_path)
    [batch] = read_inputs([path], Config())
    prov = batch.provenance
    assert prov.pose_source == ("topic /slam_toolbox/pose (PoseWithCovarianceStamped) with the "
                                "mount TF base_footprint -> laser")
    assert_like_clean_twin(batch, robot)
    # Exact matching (no tolerance) finds no pose for any scan: the gaps are 0.33 s.
    exact = Config(sensors=(SensorConfig(name="scan", scan_topic="/scan",
                                         stamp_tolerance_s=0.0),))
    with pytest.raises(GpoccError, match="none of the .* scans on /scan"):
        read_inputs([path], exact)


def test_zero_pose_stamps_fall_back_to_log_time_with_one_warning(tmp_path: Path,
                                                               capsys) -> None:
    robot, path = _slam_bag(tmp_path, zero_pose_stamps=True)
    [batch] = read_inputs([path], Config())
    n = robot.scans["/scan"][0].size
    err = capsys.readouterr().err
    assert err.count(f"topic /slam_toolbox/pose: {n} of {n} header stamps are zero") == 1
    assert batch.provenance.stamps == (
        f"/scan: log (receive) time ({n} of {n} header stamps are zero); "
        f"/slam_toolbox/pose: log (receive) time ({n} of {n} header stamps are zero)")
    assert_like_clean_twin(batch, robot)


def test_no_scan_is_dropped_without_a_count_reason_and_key(tmp_path: Path, capsys) -> None:
    robot, path = _slam_bag(tmp_path, early_scans=2)
    [batch] = read_inputs([path], Config())
    assert batch.skipped_scans == 2
    err = capsys.readouterr().err
    assert (f"2 of {robot.scans['/scan'][0].size} scans skipped for no pose on "
            "/slam_toolbox/pose within stamp_tolerance_s of the scan") in err
    assert "(config key sensors[].max_pose_gap_s)" in err


# ------------------------------------------------------------------ 3. pose sources


def _fused_odometry_bag(tmp_path: Path, topic: str, prefix: str = "",
                        local: bool = True) -> tuple[Robot, Path]:
    """robot_localization: TF odom -> base (local EKF, drifting), no map -> odom TF; the
    global EKF's Odometry in ``map`` on ``topic``; the local one on /odometry/filtered."""
    robot = one_robot(prefix)
    bag = BagWriter("ros2-sqlite3")
    add_robot(bag, robot, map_to_odom=False)
    t = np.arange(0.0, robot.duration, 1 / 30)
    ns = f"/{prefix.rstrip('/')}" if prefix else ""
    cov = cov6(0.002, 0.003, 0.0005, xy=0.0008)
    for tk, p, o in zip(t, robot.route.base(t), robot.odometry(t), strict=True):
        bag.odom(f"{ns}{topic}", T0 + tk, "map", robot.frame("base_footprint"),
                 (p[0], p[1], 0.0), quat(yaw=p[2]), cov)
        if local:
            bag.odom(f"{ns}/odometry/filtered", T0 + tk + 0.001, robot.frame("odom"),
                     robot.frame("base_footprint"), (o[0], o[1], 0.0), quat(yaw=o[2]),
                     cov6(1e-3, 1e-3, 1e-3))
    return robot, bag.write(tmp_path / "fused")


@pytest.mark.parametrize("topic,prefix", [("/odometry/global", ""), ("/ekf/fused", ""),
                                          ("/odometry/global", "robot1/")])
def test_odometry_in_the_map_frame_is_the_pose_source_with_the_tf_mount(
        tmp_path: Path, capsys, topic: str, prefix: str) -> None:
    robot, path = _fused_odometry_bag(tmp_path, topic, prefix)
    [batch] = read_inputs([path], Config())
    ns = f"/{prefix.rstrip('/')}" if prefix else ""
    prov = batch.provenance
    assert prov.pose_source == (f"topic {ns}{topic} (Odometry) with the mount TF "
                                f"{prefix}base_footprint -> {prefix}laser")
    assert "map will drift" not in capsys.readouterr().err
    assert_like_clean_twin(batch, robot)
    # The base covariance carried through the 0.25 m mount lever (Monte Carlo oracle).
    some = slice(0, None, 40)
    base_yaw = robot.route.base(batch.stamps[some] - T0)[:, 2]
    cov = cov6(0.002, 0.003, 0.0005, xy=0.0008)[np.ix_([0, 1, 5], [0, 1, 5])]
    want = lever_oracle(np.broadcast_to(cov, (base_yaw.size, 3, 3)), base_yaw,
                        robot.lasers[0].mount)
    assert_covariances(batch.pose_covariances[some], want)
    out = info(path)
    assert f"pose from topic {ns}{topic} (Odometry) with the mount TF" in out
    assert f"frame chain: {prefix}base_footprint -> {prefix}base_link (static)" in out


def test_pose_topics_pair_by_type_frame_and_known_names() -> None:
    from gpocc.io.autodetect import pose_candidates
    from gpocc.io.bags import BagContents, TopicSummary

    odom, amcl = "nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseWithCovarianceStamped"
    scan = "sensor_msgs/msg/LaserScan"

    def bag(*topics: tuple[str, str, str, str]) -> BagContents:
        return BagContents("mcap", tuple(TopicSummary(n, t, 1) for n, t, _, _ in topics),
                           0.0, 1.0, tuple((n, f, c) for n, t, f, c in topics if f))

    # robot_localization: the global EKF (map) wins over the local one (odom).
    one = bag(("/scan", scan, "", ""), ("/odometry/filtered", odom, "odom", "base_link"),
              ("/odometry/global", odom, "map", "base_link"))
    assert pose_candidates(one, "/scan") == ["/odometry/global"]
    # Any name, in the map frame; the odom-frame Odometry alone stays a candidate.
    any_name = bag(("/scan", scan, "", ""), ("/odometry/filtered", odom, "odom", "base_link"),
                   ("/ekf/fused", odom, "map", "base_link"))
    assert pose_candidates(any_name, "/scan") == ["/ekf/fused"]
    assert pose_candidates(bag(("/scan", scan, "", ""),
                               ("/odometry/filtered", odom, "odom", "base_link")),
                           "/scan") == ["/odometry/filtered"]
    # Namespaced robots: each pairs with its own, by known name or by the frame it moves;
    # robot1's fused pose under its namespace is not robot2's.
    two = bag(("/robot1/scan", scan, "", ""), ("/robot2/scan", scan, "", ""),
              ("/robot1/odometry/global", odom, "map", "base_link"),
              ("/robot1/ekf/fused", odom, "map", "base_link"),
              ("/fused2", odom, "map", "robot2/base_link"))
    assert pose_candidates(two, "/robot1/scan") == ["/robot1/ekf/fused",
                                                    "/robot1/odometry/global"]
    assert pose_candidates(two, "/robot2/scan") == ["/fused2"]
    slam = bag(("/robot1/scan", scan, "", ""), ("/robot1/slam_toolbox/pose", amcl, "", ""),
               ("/slam_toolbox/pose", amcl, "", ""))
    assert pose_candidates(slam, "/robot1/scan") == ["/robot1/slam_toolbox/pose"]


def test_two_map_pose_sources_without_tf_name_both(tmp_path: Path) -> None:
    robot = one_robot()
    bag = BagWriter("mcap")
    add_robot(bag, robot, map_to_odom=False, odom_tf=False, static_tf=False)
    t = np.arange(0.0, robot.duration, 0.1)
    for tk, p in zip(t, robot.route.base(t), strict=True):
        for topic in ("/odometry/global", "/amcl_pose"):
            if topic == "/amcl_pose":
                bag.pose_cov(topic, T0 + tk, "map", (p[0], p[1], 0.0), quat(yaw=p[2]),
                             cov6(0.01, 0.01, 0.001))
            else:
                bag.odom(topic, T0 + tk, "map", "base_footprint", (p[0], p[1], 0.0),
                         quat(yaw=p[2]), cov6(0.01, 0.01, 0.001))
    path = bag.write(tmp_path / "two.mcap")
    result = runner.invoke(app, ["info", str(path)])
    line = one_error_line(result, "two.mcap", "/amcl_pose, /odometry/global", "sensors: [")
    assert line.rstrip().endswith("}]")


def test_a_scan_without_any_pose_source_lists_candidates_and_the_key(tmp_path: Path) -> None:
    robot = one_robot("robot2/")
    bag = BagWriter("mcap")
    add_robot(bag, robot, map_to_odom=False, odom_tf=False, static_tf=False)
    for k in range(3):
        bag.odom("/robot1/odom", T0 + k, "odom", "robot1/base_link", (0, 0, 0), quat(),
                 cov6(0.1, 0.1, 0.1))
    path = bag.write(tmp_path / "nopose.mcap")
    out = tmp_path / "g"
    result = runner.invoke(app, ["grid", str(path), "--resolution", "0.2", "--out", str(out)])
    line = one_error_line(result, "nopose.mcap", "/robot2/scan",
                          "candidate topics: /robot1/odom (nav_msgs/msg/Odometry)",
                          "sensors[].pose_topic")
    assert "pose_topic: POSE_TOPIC" in line
    assert not out.exists()


# ------------------------------------------------------------------ 4. NaN covariances


def test_nan_covariances_are_unknown_with_a_warning_naming_topic_and_count(
        tmp_path: Path, capsys) -> None:
    robot = one_robot()
    bag = BagWriter("ros1")
    add_robot(bag, robot)
    t = np.arange(0.0, robot.duration, 0.1) + 0.003
    nan = np.zeros(t.size, bool)
    nan[40:60] = True
    for tk, p, bad in zip(t, robot.route.base(t), nan, strict=True):
        c = cov6(0.004, 0.003, 0.001)
        if bad:
            c[0, 0] = np.nan if tk < 5.0 else np.inf
        bag.pose_cov("/amcl_pose", T0 + tk, "map", (p[0], p[1], 0.0), quat(yaw=p[2]), c)
    path = bag.write(tmp_path / "nan.bag")
    [batch] = read_inputs([path], Config())
    err = capsys.readouterr().err
    assert (f"warning: {path}: sensor 'scan': /amcl_pose: 20 of {t.size} covariances have "
            "NaN or infinite entries") in err
    assert np.isfinite(batch.pose_covariances).all()
    assert_like_clean_twin(batch, robot)


# ------------------------------------------------------------------ 5. OS and network errors


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory) -> Path:
    robot = one_robot()
    robot.duration = 4.0
    bag = BagWriter("mcap")
    add_robot(bag, robot)
    return bag.write(tmp_path_factory.mktemp("small") / "small.mcap")


def _full_disk(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # a write() names no file


@pytest.mark.parametrize("target,command", [("os.pwrite", "grid"), ("os.replace", "grid"),
                                            ("numpy.lib.format.write_array", "train"),
                                            ("os.replace", "split")])
def test_a_full_disk_is_one_line_naming_the_path_and_leaves_nothing(
        tmp_path: Path, small_bag: Path, monkeypatch, target: str, command: str) -> None:
    import importlib

    module, name = target.rsplit(".", 1)
    monkeypatch.setattr(importlib.import_module(module), name, _full_disk)
    out = tmp_path / "out"
    out.mkdir()
    argv = {  # the model file's arrays; the claim's pid (pwrite) or a file of the
              # folder (replace); the bag written by split
        "train": ["train", str(small_bag), "--out", str(out / "model.npz")],
        "grid": ["grid", str(small_bag), "--resolution", "0.2", "--out", str(out / "grid")],
        "split": ["split", str(small_bag), "--every", "3", "--out", str(out / "split")],
    }[command]
    result = runner.invoke(app, argv)
    line = one_error_line(result, argv[-1])
    assert "no space left on device" in line and ".gpocc-tmp" not in line
    assert list(out.iterdir()) == []  # no claim, no temporary, no partial output


def test_an_unreachable_scheduler_names_the_option_and_the_address(
        tmp_path: Path, small_bag: Path, monkeypatch) -> None:
    import distributed

    model = tmp_path / "m.npz"
    result = runner.invoke(app, ["train", str(small_bag), "--out", str(model), "--quiet"])
    assert result.exit_code == 0, result.output

    def refused(address, timeout=None, **kwargs):
        # What Dask raises after its timeout (the real wait is 10 s).
        raise OSError(f"Timed out trying to connect to {address} after {timeout}")

    monkeypatch.setattr(distributed, "Client", refused)
    out = tmp_path / "map"
    result = runner.invoke(app, ["map", str(model), "--resolution", "0.3", "--scheduler",
                                 "tcp://10.255.255.1:8786", "--out", str(out)])
    one_error_line(result, "--scheduler tcp://10.255.255.1:8786", "Timed out")
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["m.npz"]
