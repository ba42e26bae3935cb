"""ROS bags of a known room, through ``gpocc build``: the map's walls are the room's walls.

A robot drives an ellipse in an 8 x 6 m room with an off-centre box; its laser is mounted
0.2 m ahead of the base, turned 180 degrees (or upside down), and its scans are ray cast
here against the room. The laser's 3-D mount is applied with scipy's rotations, not
gpocc's. The bags (written with rosbags' own writers, tests/rosbag_scenes.py) carry what
real ones do: TF recorded late, scans before the first pose, a driver that sweeps
clockwise (negative ``angle_increment``), NaN / inf / too-short ranges, no intensities.

Oracle: the room's geometry. Occupied map cells inside the room lie on its walls, no
free cell lies outside it, and the walls are found; the four storage formats read to
identical batches and two of them build byte-identical rasters.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rosbag_scenes import T0, BagWriter, compose, cov6, inverse
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.config import Config, MountConfig, SensorConfig, load_config
from gpocc.evaluation.world import cast_rays
from gpocc.io.inputs import read_inputs

ROOM = (0.0, 0.0, 8.0, 6.0)
BOX = (5.5, 3.8, 6.5, 4.6)


def _rect(x0: float, y0: float, x1: float, y1: float) -> list:
    return [[(x0, y0), (x1, y0)], [(x1, y0), (x1, y1)], [(x1, y1), (x0, y1)],
            [(x0, y1), (x0, y0)]]


SEGMENTS = np.array(_rect(*ROOM) + _rect(*BOX), float)
LAP_S = 20.0


def wall_distance(p: np.ndarray) -> np.ndarray:
    """(N,) metres from each (N, 2) point to the nearest wall (brute force)."""
    a, e = SEGMENTS[:, 0], SEGMENTS[:, 1] - SEGMENTS[:, 0]
    rel = p[:, None] - a[None]
    u = np.clip((rel * e[None]).sum(-1) / (e * e).sum(-1)[None], 0.0, 1.0)
    return np.linalg.norm(rel - u[..., None] * e[None], axis=-1).min(axis=1)


def in_free_space(p: np.ndarray) -> np.ndarray:
    """(N,) inside the room and outside the box."""
    def inside(r: tuple) -> np.ndarray:
        return (p[:, 0] > r[0]) & (p[:, 0] < r[2]) & (p[:, 1] > r[1]) & (p[:, 1] < r[3])
    return inside(ROOM) & ~inside(BOX)


def base_pose(t: np.ndarray) -> np.ndarray:
    """(N, 3) the base on an ellipse around (3.5, 2.5), heading along it, a lap in 20 s."""
    w = 2 * math.pi / LAP_S
    t = np.asarray(t, float)
    return np.column_stack([3.5 + 2.0 * np.cos(w * t), 2.5 + 1.3 * np.sin(w * t),
                            np.arctan2(1.3 * np.cos(w * t), -2.0 * np.sin(w * t))])


def drift(t: np.ndarray) -> np.ndarray:
    """(N, 3) map -> odom: the localiser's correction, growing with time."""
    t = np.asarray(t, float)
    return np.column_stack([0.03 * t, -0.02 * t, 0.01 * t])


class Laser:
    """A 270-degree laser at ``xyz`` on base_link, turned by roll / yaw (radians)."""

    def __init__(self, xyz=(0.2, 0.0, 0.3), roll=0.0, yaw=math.pi, clockwise=False):
        self.xyz = np.asarray(xyz, float)
        self.rot = Rotation.from_euler("ZYX", [yaw, 0.0, roll])
        self.yaw = yaw
        self.angles = np.linspace(-math.radians(135), math.radians(135), 91)
        if clockwise:
            self.angles = self.angles[::-1]
        self.max_range = 12.0

    def ranges(self, t: np.ndarray) -> np.ndarray:
        """(S, B) ray cast ranges at times ``t``: beams turned in 3-D, projected."""
        out = []
        dirs = np.column_stack([np.cos(self.angles), np.sin(self.angles),
                                np.zeros_like(self.angles)])
        for x, y, yaw in base_pose(t):
            body = Rotation.from_euler("z", yaw)
            origin = np.array([x, y, 0.0]) + body.apply(self.xyz)
            d = (body * self.rot).apply(dirs)
            phi = np.arctan2(d[:, 1], d[:, 0])
            out.append(cast_rays(SEGMENTS, np.zeros((0, 3)),
                                 np.repeat(origin[None, :2], phi.size, 0), phi, self.max_range))
        return np.asarray(out)


def yaw_quat(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


SCAN_T = 0.313 + np.arange(20) * 1.0  # one lap, between the TF and pose stamps


def add_robot(bag: BagWriter, laser: Laser, pose: str, prefix: str = "",
              scan_t: np.ndarray = SCAN_T, tf_delay_s: float = 0.0, ranges_hook=None) -> None:
    """One robot's /scan and its pose: ``tf`` (map -> odom -> base_link -> laser) or ``amcl``
    (PoseWithCovarianceStamped at 10 Hz), topics and frames under ``prefix``."""
    ns = "/" + prefix.rstrip("/") if prefix else ""
    ranges = laser.ranges(scan_t)
    if ranges_hook is not None:
        ranges = ranges_hook(ranges)
    for t, r in zip(scan_t, ranges, strict=True):
        bag.scan(f"{ns}/scan", f"{prefix}laser", T0 + t, laser.angles, r, laser.max_range,
                 angle_min=float(laser.angles[0]), angle_max=float(laser.angles[-1]),
                 angle_increment=float(laser.angles[1] - laser.angles[0]))
    end = LAP_S + 0.5
    if pose == "tf":
        ot = np.arange(0.0, end, 1 / 30)
        odom = compose(inverse(drift(ot)), base_pose(ot))
        for t, p in zip(ot, odom, strict=True):
            bag.tf("/tf", T0 + t, [(f"{prefix}odom", f"{prefix}base_link", (p[0], p[1], 0.0),
                                    yaw_quat(p[2]))])
        for t in np.arange(0.0, end, 0.2) + 0.007:
            c = drift(np.array([t]))[0]
            bag.tf("/tf", T0 + t, [("map", f"{prefix}odom", (c[0], c[1], 0.0), yaw_quat(c[2]))])
        if tf_delay_s:  # recorded after its stamp, as through a slow bridge
            bag.messages = [(m[0] + tf_delay_s, *m[1:]) if m[1] == "/tf" else m
                            for m in bag.messages]
        bag.tf("/tf_static", T0, [(f"{prefix}base_link", f"{prefix}laser", tuple(laser.xyz),
                                   tuple(laser.rot.as_quat()))])
        return
    for t, p in zip(np.arange(0.0, end, 0.1), base_pose(np.arange(0.0, end, 0.1)), strict=True):
        bag.pose_cov(f"{ns}/amcl_pose", T0 + t, "map", (p[0], p[1], 0.0), yaw_quat(p[2]),
                     cov6(0.004, 0.003, 0.001))


def special_ranges(ranges: np.ndarray) -> np.ndarray:
    """Every REP 117 kind of range: NaN, -inf, too short, and +inf / beyond range_max where
    the wall is farther than ``no_return_free_m`` (5 m), so the free space they vouch for
    is true."""
    r = ranges.copy()
    k = np.arange(r.size).reshape(r.shape) % 11
    far = r > 5.2
    r[k == 1] = np.nan
    r[k == 3] = -np.inf
    r[k == 5] = 0.01  # below range_min (0.05)
    r[(k == 7) & far] = np.inf
    r[(k == 9) & far] = 30.0  # beyond range_max (12)
    return r


FORMATS = {"ros1": "run.bag", "ros2-sqlite3": "run", "ros2-mcap": "run", "mcap": "run.mcap"}
ROT180 = Laser(yaw=math.pi)
UPSIDE_DOWN = Laser(xyz=(0.2, 0.05, 0.3), roll=math.pi, yaw=0.0, clockwise=True)


def tf_bag(fmt: str, folder: Path) -> Path:
    """TF only, the laser 0.2 m ahead and turned 180 degrees; TF recorded 0.5 s late; two
    scans before the first TF."""
    bag = BagWriter(fmt)
    add_robot(bag, ROT180, "tf", scan_t=np.concatenate([[-1.2, -0.6], SCAN_T]), tf_delay_s=0.5)
    folder.mkdir()
    return bag.write(folder / FORMATS[fmt])


def two_robot_bag(folder: Path) -> Path:
    """robot1: TF, an upside-down laser sweeping clockwise, every special range value;
    robot2: /robot2/amcl_pose, the 180-degree laser, its mount given in the config."""
    bag = BagWriter("ros2-sqlite3")
    add_robot(bag, UPSIDE_DOWN, "tf", prefix="robot1/", ranges_hook=special_ranges)
    add_robot(bag, ROT180, "amcl", prefix="robot2/", scan_t=SCAN_T + 0.41)
    return bag.write(folder / "two")


runner = CliRunner()


def build(path: Path, out: Path, config: Path | None = None) -> dict[str, np.ndarray]:
    args = ["build", str(path), "--resolution", "0.1", "--out", str(out), "--workers", "1",
            "--quiet"]
    if config is not None:
        args += ["--config", str(config)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    layers = {}
    for name in ("probability", "class"):
        with rasterio.open(out / f"{name}.tif") as ds:
            layers[name] = ds.read(1)
            transform = ds.transform
    rows, cols = np.indices(layers["class"].shape)
    x, y = rasterio.transform.xy(transform, rows.ravel(), cols.ravel())
    layers["xy"] = np.column_stack([x, y]).reshape(*rows.shape, 2)
    return layers


def assert_walls(layers: dict[str, np.ndarray]) -> None:
    cls, xy = layers["class"], layers["xy"]
    occupied, free = xy[cls == 1], xy[cls == 0]
    inside = in_free_space(occupied)
    # Occupied cells in the room hug its walls (behind a wall the GP has only hits to go
    # on, so occupied cells there are not errors): no obstacle in the open room.
    assert wall_distance(occupied[inside]).max(initial=0.0) <= 0.26
    # A free cell beyond a wall (more than half a cell) would be a beam through it.
    assert (wall_distance(free[~in_free_space(free)]) <= 0.051).all()
    # The walls are found: an occupied cell within 1.5 cells of 80% of the points of the
    # walls the route sees (not the box's top and right sides). The class layer's walls
    # are one or two cells thick with g = 1, and the classifier's temperature, fitted on
    # Platt's targets, keeps a stretch seen by few beams below the occupied threshold
    # (unsure) rather than sure.
    from scipy.spatial import cKDTree

    walls = np.concatenate([a + np.linspace(0, 1, 50)[:, None] * (b - a)
                            for a, b in SEGMENTS[[0, 1, 2, 3, 4, 7]]])
    near, _ = cKDTree(occupied).query(walls)
    assert np.mean(near <= 0.15) > 0.8


@pytest.fixture(scope="module")
def tf_bags(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("tf_bags")
    return {fmt: tf_bag(fmt, base / fmt) for fmt in FORMATS}


def test_tf_bag_reads_the_same_from_every_storage_format(tf_bags: dict[str, Path]) -> None:
    batches = {fmt: read_inputs([path], Config()) for fmt, path in tf_bags.items()}
    ref = batches["ros1"][0]
    # The two scans before the first TF are dropped and counted, not fatal.
    assert ref.n_scans == SCAN_T.size and ref.skipped_scans == 2
    assert ref.provenance.skipped[0][2] == 2
    truth = compose(base_pose(ref.stamps - T0), np.array([[0.2, 0.0, math.pi]]))
    assert np.abs(ref.poses[:, :2] - truth[:, :2]).max() < 1e-3
    assert np.abs(np.angle(np.exp(1j * (ref.poses[:, 2] - truth[:, 2])))).max() < 1e-3
    for fmt, [batch] in batches.items():
        for field in ("stamps", "angles", "ranges", "poses", "pose_covariances"):
            np.testing.assert_array_equal(getattr(batch, field), getattr(ref, field),
                                          err_msg=f"{fmt} {field}")


def test_tf_bag_maps_the_room_identically_from_ros1_and_mcap(tf_bags: dict[str, Path],
                                                            tmp_path: Path) -> None:
    ros1 = build(tf_bags["ros1"], tmp_path / "ros1")
    mcap = build(tf_bags["mcap"], tmp_path / "mcap")
    assert_walls(ros1)
    np.testing.assert_array_equal(ros1["probability"], mcap["probability"])


def test_two_robots_upside_down_laser_and_pose_topic_map_the_room(tmp_path: Path) -> None:
    path = two_robot_bag(tmp_path)
    mount = MountConfig(x_m=0.2, yaw_deg=180.0)
    sensors = (SensorConfig(name="r1", scan_topic="/robot1/scan"),
               SensorConfig(name="r2", scan_topic="/robot2/scan", mount=mount))
    [r1, r2] = read_inputs([path], Config(sensors=sensors))
    assert r1.provenance.pose_source == "TF map -> robot1/laser"
    assert r2.provenance.pose_source == "topic /robot2/amcl_pose (PoseWithCovarianceStamped)"
    assert r1.n_scans == r2.n_scans == SCAN_T.size
    # Upside down: the bearings, read in the bag's (clockwise) order, turn the other way.
    np.testing.assert_allclose(r1.angles, -UPSIDE_DOWN.angles, atol=1e-6)
    config = tmp_path / "two.yaml"
    config.write_text(
        "sensors:\n"
        "  - {name: r1, scan_topic: /robot1/scan}\n"
        "  - {name: r2, scan_topic: /robot2/scan, mount: {x_m: 0.2, yaw_deg: 180.0}}\n")
    assert_walls(build(path, tmp_path / "map", config))


def test_pose_topic_covariance_notes_name_the_bound_used_and_skip_dropped_scans(
        tmp_path: Path) -> None:
    # AMCL at 10 Hz without TF; its covariance is "do not trust" from 8 s to 12 s, and two
    # scans come before its first message.
    bag = BagWriter("ros2-mcap")
    scan_t = np.concatenate([[-1.2, -0.6], SCAN_T])
    for t, r in zip(scan_t, ROT180.ranges(scan_t), strict=True):
        bag.scan("/scan", "laser", T0 + t, ROT180.angles, r, ROT180.max_range)
    pose_t = np.round(np.arange(0.0, LAP_S + 0.5, 0.1), 6)
    unknown = (pose_t >= 8.0) & (pose_t <= 12.0)
    for t, p, bad in zip(pose_t, base_pose(pose_t), unknown, strict=True):
        bag.pose_cov("/amcl_pose", T0 + t, "map", (p[0], p[1], 0.0), yaw_quat(p[2]),
                     cov6(0.004, 0.003, 1e6 if bad else 0.001))
    sensor = SensorConfig(name="r", scan_topic="/scan", mount=MountConfig(x_m=0.2,
                                                                          yaw_deg=180.0))
    [batch] = read_inputs([bag.write(tmp_path / "amcl")], Config(sensors=(sensor,)))
    assert batch.skipped_scans == 2 and batch.n_scans == SCAN_T.size
    # Without TF a scan's pose and covariance come from the messages around it: the bound
    # is max_pose_gap_s (0.25 s), not max_covariance_age_s (30 s by default).
    gap = sensor.max_pose_gap_s
    prov = batch.provenance
    assert prov.covariance_source == (
        f"/amcl_pose (held or interpolated up to max_pose_gap_s={gap:g} s)")
    # Stale: used scans farther than the bound from every known covariance (brute force);
    # the two scans without a pose are skipped, not stale too.
    far = np.abs(SCAN_T[:, None] - pose_t[~unknown][None]).min(axis=1) > gap
    assert far.sum() == 4
    stale = [n for n in prov.notes if "from a known covariance" in n]
    assert stale == [f"{far.sum()} scans more than max_pose_gap_s={gap:g} s from a known "
                     "covariance on /amcl_pose use the config's pose_covariance"]
    config_cov = sensor.pose_covariance_matrix
    np.testing.assert_array_equal(batch.pose_covariances[far],
                                  np.broadcast_to(config_cov, (far.sum(), 3, 3)))


def test_an_upside_down_laser_without_tf_is_set_in_the_config_mount(tmp_path: Path) -> None:
    """The upside-down laser with a pose topic and no TF: ``mount.upside_down`` mirrors
    its bearings (as TF's roll does) and the room's walls come out where they are; the
    same mount without it puts them elsewhere."""
    bag = BagWriter("mcap")
    add_robot(bag, UPSIDE_DOWN, "amcl")
    path = bag.write(tmp_path / "flipped.mcap")
    laser = "  - {name: r, scan_topic: /scan, mount: {x_m: 0.2, y_m: 0.05%s}}\n"
    flipped, level = tmp_path / "flipped.yaml", tmp_path / "level.yaml"
    flipped.write_text("sensors:\n" + laser % ", upside_down: true")
    level.write_text("sensors:\n" + laser % "")
    [batch] = read_inputs([path], load_config(flipped))
    np.testing.assert_allclose(batch.angles, -UPSIDE_DOWN.angles, atol=1e-6)
    assert "sensors[].mount.upside_down: bearings mirrored" in batch.provenance.notes
    assert_walls(build(path, tmp_path / "flipped", flipped))
    with pytest.raises(AssertionError):
        assert_walls(build(path, tmp_path / "level", level))


def test_a_split_of_an_upside_down_laser_reads_back_unmirrored(tmp_path: Path) -> None:
    """``gpocc split`` writes the scans as read (bearings already mirrored by
    ``mount.upside_down``); its train.yaml must not mirror them a second time."""
    bag = BagWriter("mcap")
    add_robot(bag, UPSIDE_DOWN, "amcl")
    path = bag.write(tmp_path / "flipped.mcap")
    config = tmp_path / "flipped.yaml"
    config.write_text("sensors:\n  - {name: r, scan_topic: /scan, "
                      "mount: {x_m: 0.2, y_m: 0.05, upside_down: true}}\n")
    [read] = read_inputs([path], load_config(config))
    result = runner.invoke(app, ["split", str(path), "--config", str(config), "--every", "4",
                                 "--out", str(tmp_path / "split"), "--quiet"])
    assert result.exit_code == 0, result.output
    train = load_config(tmp_path / "split" / "train.yaml")
    assert train.sensors[0].mount == MountConfig(x_m=0.2, y_m=0.05)
    [again] = read_inputs([tmp_path / "split" / "train.mcap"], train)
    np.testing.assert_allclose(again.angles, read.angles, atol=1e-6)


def rplidar_bag(folder: Path) -> Path:
    """A 360-degree laser publishing each revolution as it came (rplidar_ros with
    ``angle_compensate: false``): every scan its own beam count (175-180) and first angle
    (jittered by up to a beam), with AMCL poses; the laser 0.2 m ahead, turned 180 deg."""
    bag = BagWriter("mcap")
    laser = Laser(yaw=math.pi)
    rng = np.random.default_rng(5)
    for t in SCAN_T:
        n = 180 - int(rng.integers(0, 6))
        first = -math.pi + rng.uniform(-1.0, 1.0) * 2 * math.pi / 180
        laser.angles = first + np.arange(n) * (2 * math.pi / n)
        [ranges] = laser.ranges(np.array([t]))
        bag.scan("/scan", "laser", T0 + t, laser.angles, ranges, laser.max_range)
    add_robot(bag, laser, "amcl", scan_t=np.array([]))
    return bag.write(folder / "rplidar.mcap")


def test_a_laser_whose_beam_layout_changes_every_scan_maps_the_room(tmp_path: Path) -> None:
    path = rplidar_bag(tmp_path)
    config = tmp_path / "rplidar.yaml"
    config.write_text("sensors:\n  - {name: r, scan_topic: /scan, "
                      "mount: {x_m: 0.2, yaw_deg: 180.0}}\n")
    [batch] = read_inputs([path], load_config(config))
    assert batch.n_scans == SCAN_T.size
    # One layout 2 pi / 180 apart (the finest increment; LaserScan's angles are float32)
    # holding every beam of every scan.
    np.testing.assert_allclose(np.diff(batch.angles), 2 * math.pi / 180, rtol=1e-6)
    assert 175 * SCAN_T.size <= np.count_nonzero(~np.isnan(batch.ranges)) <= 180 * SCAN_T.size
    assert batch.sensor_config.bearing_variance_deg2 > SensorConfig().bearing_variance_deg2
    assert any("varies from scan to scan (175-180 beams)" in n for n in batch.provenance.notes)
    assert_walls(build(path, tmp_path / "map", config))
    # A split writes one layout, and its train.yaml the grown bearing variance: reading it
    # back moves nothing again.
    result = runner.invoke(app, ["split", str(path), "--config", str(config), "--every", "4",
                                 "--out", str(tmp_path / "split"), "--quiet"])
    assert result.exit_code == 0, result.output
    train = load_config(tmp_path / "split" / "train.yaml")
    assert train.sensors[0].bearing_variance_deg2 == pytest.approx(
        batch.sensor_config.bearing_variance_deg2)
    [again] = read_inputs([tmp_path / "split" / "train.mcap"], train)
    np.testing.assert_allclose(again.angles, batch.angles, atol=1e-6)
    assert again.sensor_config.bearing_variance_deg2 == train.sensors[0].bearing_variance_deg2
    assert not any("varies" in n for n in again.provenance.notes)
