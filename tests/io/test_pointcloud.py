"""3-D lidar clouds: decoding every layout, the height-band projection, bags of synthetic
rooms read into scans whose hits lie on the room's obstacles.

Oracles: ``struct``-packed bytes (decoding), a per-bin brute-force loop (projection), the
room's exact geometry (walls, a table top at 0.75 m, a sloping floor), cast in 3-D with
scipy's rotations (tests/cloud_scenes.py).
"""

from __future__ import annotations

import math
import struct
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from cloud_scenes import (
    BOX,
    ROOM_RECT,
    TABLE,
    Layout,
    Lidar,
    LidarRun,
    add_planar_laser,
    base_path,
    inside,
    obstacle_distance,
    rect,
    room,
)
from rosbag_scenes import T0, BagWriter
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.config import Config, config_from_dict, load_config
from gpocc.errors import GpoccError
from gpocc.io.cloudscan import bin_angles, project
from gpocc.io.inputs import read_inputs
from gpocc.io.pointcloud import decode_cloud
from gpocc.samples.beam_rules import laser_poses, mount_vector

# --------------------------------------------------------------------------- decoding


def _field(name: str, offset: int, datatype: int) -> SimpleNamespace:
    return SimpleNamespace(name=name, offset=offset, datatype=datatype, count=1)


@pytest.mark.parametrize("float64", [False, True])
@pytest.mark.parametrize("bigendian", [False, True])
@pytest.mark.parametrize("pad", [0, 3])
def test_decode_packed_points_any_type_offset_padding_and_endianness(float64, bigendian, pad):
    pts = [(1.5, -2.25, 0.5, 7), (float("nan"), 1.0, 1.0, 3), (0.0, 0.0, 0.0, 1),
           (-3.0, 4.0, -0.125, 15)]
    e = ">" if bigendian else "<"
    f = "d" if float64 else "f"
    size = 8 if float64 else 4
    # ring first, then padding, then z, y, x in reverse order: offsets are the message's.
    ring_off, z_off = 0, 2 + pad
    y_off, x_off = z_off + size, z_off + 2 * size
    step = x_off + size + pad
    data = bytearray()
    for x, y, z, ring in pts:
        rec = bytearray(step)
        struct.pack_into(e + "H", rec, ring_off, ring)
        for value, off in ((x, x_off), (y, y_off), (z, z_off)):
            struct.pack_into(e + f, rec, off, value)
        data += rec
    dt = 8 if float64 else 7
    msg = SimpleNamespace(height=1, width=len(pts), point_step=step, row_step=step * len(pts),
                          is_bigendian=bigendian, data=np.frombuffer(bytes(data), np.uint8),
                          fields=[_field("ring", ring_off, 4), _field("z", z_off, dt),
                                  _field("y", y_off, dt), _field("x", x_off, dt)])
    cloud = decode_cloud(msg, "bag: topic /points")
    # NaN and all-zero points are no returns.
    np.testing.assert_array_equal(cloud.xyz, [[1.5, -2.25, 0.5], [-3.0, 4.0, -0.125]])
    np.testing.assert_array_equal(cloud.ring, [7, 15])
    assert cloud.n_points == 4 and not cloud.organised


def test_decode_organised_cloud_with_row_padding_gives_rings_from_rows():
    rows, cols, step, row_step = 3, 2, 12, 12 * 2 + 5
    data = bytearray(row_step * rows)
    for r in range(rows):
        for c in range(cols):
            struct.pack_into("<fff", data, r * row_step + c * step, r + 1.0, c + 1.0, 0.5)
    msg = SimpleNamespace(height=rows, width=cols, point_step=step, row_step=row_step,
                          is_bigendian=False, data=np.frombuffer(bytes(data), np.uint8),
                          fields=[_field("x", 0, 7), _field("y", 4, 7), _field("z", 8, 7)])
    cloud = decode_cloud(msg, "bag")
    assert cloud.organised
    np.testing.assert_array_equal(cloud.xyz[:, 0], [1, 1, 2, 2, 3, 3])
    np.testing.assert_array_equal(cloud.ring, [0, 0, 1, 1, 2, 2])


def test_decode_errors_name_the_field():
    base = dict(height=1, width=1, point_step=12, row_step=12, is_bigendian=False,
                data=np.zeros(12, np.uint8))
    with pytest.raises(GpoccError, match="no field z"):
        decode_cloud(SimpleNamespace(**base, fields=[_field("x", 0, 7), _field("y", 4, 7)]),
                     "b: topic /p")
    with pytest.raises(GpoccError, match="field y at offset 10"):
        decode_cloud(SimpleNamespace(**base, fields=[_field("x", 0, 7), _field("y", 10, 7),
                                                     _field("z", 8, 7)]), "b")
    with pytest.raises(GpoccError, match="cut off"):
        decode_cloud(SimpleNamespace(**{**base, "width": 2}, fields=[
            _field("x", 0, 7), _field("y", 4, 7), _field("z", 8, 7)]), "b")
    # A default-constructed PointCloud2 (no fields, no points) is an empty cloud, skipped
    # as others are, not a reason to refuse the whole topic.
    empty = decode_cloud(SimpleNamespace(height=0, width=0, point_step=0, row_step=0,
                                         is_bigendian=False, data=np.zeros(0, np.uint8),
                                         fields=[]), "b")
    assert empty.n_points == 0 and empty.points.shape == (0, 3)
    with pytest.raises(GpoccError, match="no field x"):  # fields missing, points present
        decode_cloud(SimpleNamespace(**base, fields=[]), "b")


# --------------------------------------------------------------------------- projection


def test_projection_keeps_the_nearest_in_band_return_per_bin_brute_force():
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-6, 6, 3000), rng.uniform(-6, 6, 3000),
                           rng.uniform(-0.3, 2.8, 3000)])
    origin, band, bins, rmin = np.array([0.2, -0.1, 0.4]), (0.1, 2.0), 72, 0.3
    got = project(pts, origin, band, bins, rmin)
    centres = bin_angles(bins)
    expected = np.full(bins, np.inf)
    for x, y, z in pts:
        d = math.hypot(x - origin[0], y - origin[1])
        if not band[0] <= z <= band[1] or d < rmin:
            continue
        phi = math.atan2(y - origin[1], x - origin[0])
        k = int(np.argmin(np.abs(np.angle(np.exp(1j * (centres - phi))))))
        expected[k] = min(expected[k], d)
    np.testing.assert_allclose(got, expected)


# --------------------------------------------------------------------------- bags

FORMATS = {"ros1": "run.bag", "ros2-sqlite3": "run", "ros2-mcap": "run", "mcap": "run.mcap"}
OBSTACLES = np.array(rect(*ROOM_RECT) + rect(*BOX) + rect(*TABLE), float)


def hits(batch) -> np.ndarray:
    """(H, 2) map-frame endpoints of the batch's hits."""
    r = batch.ranges
    ok = np.isfinite(r)
    phi = batch.poses[:, 2:3] + batch.angles[None, :]
    x = batch.poses[:, 0:1] + r * np.cos(phi)
    y = batch.poses[:, 1:2] + r * np.sin(phi)
    return np.column_stack([x[ok], y[ok]])


def write_run(tmp: Path, run: LidarRun, fmt: str = "mcap") -> Path:
    bag = BagWriter(fmt)
    run.write(bag)
    tmp.mkdir(parents=True, exist_ok=True)
    return bag.write(tmp / FORMATS[fmt])


def check_hits(batch, bin_width: float) -> None:
    p = hits(batch)
    # Every hit lies on a wall, the cupboard or the table top (its edge, or its underside
    # seen by rising rays) within the bearing bin's half-width at its range plus TF
    # interpolation: never on the floor or the ceiling.
    reach = np.hypot(*(p - np.repeat(batch.poses[:, :2], np.isfinite(batch.ranges).sum(1),
                                     0)).T)
    off = np.where(inside(p, TABLE), 0.0, obstacle_distance(p, OBSTACLES))
    assert (off <= 0.5 * bin_width * reach + 2e-3).all()
    # Every bearing hits something in a closed room.
    assert np.isfinite(batch.ranges).mean() > 0.99
    # The table top is seen (occupied in the band) from where the lidar's rays reach 0.75 m.
    assert (obstacle_distance(p, np.array(rect(*TABLE), float)) < 0.05).sum() > 50


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_tilted_lidar_in_every_bag_kind_hits_walls_and_the_table_not_the_floor(tmp_path, fmt):
    run = LidarRun(room(), Lidar(rpy=(0.0, math.radians(10), 0.0)),
                   cloud_t=0.31 + np.arange(8) * 2.5)
    [batch] = read_inputs([write_run(tmp_path / fmt, run, fmt)], Config())
    assert batch.n_scans == 8 and batch.n_beams == 900
    truth = base_path(batch.stamps - T0)
    lidar_xy = truth[:, :2] + np.column_stack([np.cos(truth[:, 2]), np.sin(truth[:, 2])]) * 0.15
    # TF at 30 Hz is interpolated linearly along the curved path.
    np.testing.assert_allclose(batch.poses[:, :2], lidar_xy, atol=1e-3)
    check_hits(batch, 2 * math.pi / 900)


LAYOUTS = {
    "float64-padded-bigendian": Layout(float64=True, pad=4, bigendian=True),
    "unorganised-ring": Layout(organised=False),
    "unorganised-no-ring": Layout(organised=False, ring=False, extras=False),
    "organised-zero-no-return": Layout(zero_no_return=True, extras=False),
}


@pytest.mark.parametrize("name", list(LAYOUTS))
def test_every_cloud_layout_gives_the_same_scan(tmp_path, name):
    def read(layout: Layout, folder: str):
        run = LidarRun(room(), Lidar(rpy=(0.05, 0.0, 0.3), max_range=6.0), layout=layout,
                       cloud_t=0.31 + np.arange(4) * 5.0)
        return read_inputs([write_run(tmp_path / folder, run)], Config())[0]

    ref = read(Layout(), "ref")
    batch = read(LAYOUTS[name], name)
    if name == "unorganised-no-ring":
        # No layout to tell the resolution: the documented 0.4-degree default.
        assert batch.n_beams == 900
    np.testing.assert_allclose(batch.ranges, ref.ranges, atol=1e-5)
    # Beyond max_range (6 m) there is no return: such bins are cleared, not hit.
    assert np.isinf(ref.ranges).any()
    check = batch.sensor_config
    assert check.range_variance_m2 == 0.0009


def test_sloping_floor_with_the_base_tilted_on_it_is_never_an_obstacle(tmp_path):
    # A 6-degree ramp: relative to a level plane the floor rises 0.6 m over 6 m.
    run = LidarRun(room(table=False, slope=0.1), Lidar(), cloud_t=0.31 + np.arange(6) * 3.0)
    [batch] = read_inputs([write_run(tmp_path, run)], Config())
    p = hits(batch)
    walls = np.array(rect(*ROOM_RECT) + rect(*BOX), float)
    reach = np.hypot(*(p - np.repeat(batch.poses[:, :2], np.isfinite(batch.ranges).sum(1),
                                     0)).T)
    # Hits are on the walls (the floor never is): levelled by the base's pitch in the map
    # frame, a wall point 1.5 m up is not pushed 0.15 m off its wall by the 6-degree tilt.
    assert (obstacle_distance(p, walls) <= 0.5 * 2 * math.pi / 900 * reach + 0.01).all()
    assert np.isfinite(batch.ranges).mean() > 0.99


def test_info_shows_the_cloud_and_a_missing_tf_names_topic_and_fix(tmp_path):
    path = write_run(tmp_path / "a", LidarRun(room(), Lidar(), cloud_t=np.array([0.31, 1.31])))
    result = CliRunner().invoke(app, ["info", str(path)])
    assert result.exit_code == 0, result.output
    out = result.output
    assert "point cloud /velodyne_points: 2 clouds, 14400 points per message" in out
    assert "rings 16" in out and "fields: x, y, z, intensity, t, ring" in out
    assert "equivalent scan: 900 bins of 0.400 deg" in out
    assert "band [0.1, 2] keeps" in out and "not de-skewed" in out
    # Without /tf_static the lidar's mount is unknown: one line naming topic and fix.
    bag = BagWriter("mcap")
    LidarRun(room(), Lidar(), cloud_t=np.array([0.31])).write(bag)
    bag.messages = [m for m in bag.messages if m[1] != "/tf_static"]
    (tmp_path / "b").mkdir()
    bad = bag.write(tmp_path / "b" / "run.mcap")
    result = CliRunner().invoke(app, ["info", str(bad)])
    assert result.exit_code != 0
    assert "topic /velodyne_points" in result.output and "/tf_static" in result.output
    assert "Traceback" not in result.output


def test_base_frame_above_the_floor_with_base_height_gives_the_same_scans(tmp_path):
    run = LidarRun(room(), Lidar(rpy=(0.0, 0.1, 0.0)), cloud_t=0.31 + np.arange(3) * 5.0)
    [ref] = read_inputs([write_run(tmp_path / "ref", run)], Config())
    bag = BagWriter("mcap")
    run.write(bag, base="base_link", base_height=0.3)
    (tmp_path / "up").mkdir()
    path = bag.write(tmp_path / "up" / "run.mcap")
    config = config_from_dict({"sensors": [{"name": "lidar", "scan_topic": "/velodyne_points",
                                            "base_height_m": 0.3}]})
    [batch] = read_inputs([path], config)
    np.testing.assert_allclose(batch.ranges, ref.ranges, atol=1e-5)
    kept = [line for line in batch.provenance.sensor_lines if "keeps" in line]
    assert kept == [line for line in ref.provenance.sensor_lines if "keeps" in line]
    # Without it the band starts 0.3 m higher: low obstacles' returns are lost.
    [high] = read_inputs([path], Config())
    assert not np.allclose(np.nan_to_num(high.ranges, posinf=99), np.nan_to_num(
        ref.ranges, posinf=99), atol=1e-5)


def test_horizontal_resolution_key_bins_coarser(tmp_path):
    path = write_run(tmp_path, LidarRun(room(), Lidar(), cloud_t=np.array([0.31, 5.31])))
    [fine] = read_inputs([path], Config())
    config = config_from_dict({"sensors": [{"name": "lidar", "scan_topic": "/velodyne_points",
                                            "horizontal_resolution_deg": 0.8}]})
    [coarse] = read_inputs([path], config)
    assert coarse.n_beams == 450
    # An 0.8-degree bin is two 0.4-degree bins: its hit is the nearer of theirs (a fine
    # bin no return fell into is unknown, NaN).
    np.testing.assert_allclose(coarse.ranges, np.fmin.reduce(fine.ranges.reshape(2, 450, 2),
                                                             axis=2))
    # Its bearing noise carries the wider bin's quantisation: (0.8 deg)^2 / 12.
    assert coarse.sensor_config.bearing_variance_deg2 == pytest.approx(0.01 + 0.64 / 12)


@pytest.mark.parametrize("position_from_tf", [True, False])
def test_pose_topic_and_static_mount_pose_the_scans_like_tf(tmp_path, position_from_tf):
    run = LidarRun(room(), Lidar(), cloud_t=0.31 + np.arange(4) * 4.0)
    [ref] = read_inputs([write_run(tmp_path / "ref", run)], Config())
    bag = BagWriter("mcap")
    run.write(bag, amcl=True)
    (tmp_path / "amcl").mkdir()
    config = config_from_dict({"sensors": [{"name": "lidar", "scan_topic": "/velodyne_points",
                                            "position_from_tf": position_from_tf}]})
    [batch] = read_inputs([bag.write(tmp_path / "amcl" / "run.mcap")], config)
    # The base pose from /amcl_pose, the lidar's offset on it from /tf_static: as TF's
    # mount chain, or (TF not used for positions) as the entry's mount.
    assert batch.provenance.pose_source.startswith("topic /amcl_pose")
    assert batch.sensor_config.mount.x_m == pytest.approx(0.0 if position_from_tf else 0.15)
    np.testing.assert_allclose(batch.ranges, ref.ranges, atol=1e-5)
    lidar = laser_poses(batch.poses, mount_vector(batch.sensor_config))
    np.testing.assert_allclose(lidar[:, :2], ref.poses[:, :2], atol=1e-3)
    assert batch.has_pose_covariance


def test_a_narrow_field_of_view_leaves_unseen_bearings_unknown(tmp_path):
    # A 70-degree solid-state lidar: bins it never looked into are not cleared as free.
    lidar = Lidar(columns=350, azimuth_deg=(-35.0, 35.0), max_range=6.0)
    run = LidarRun(room(), lidar, cloud_t=np.array([0.31, 5.31]))
    [batch] = read_inputs([write_run(tmp_path, run)], Config())
    front = np.abs(batch.angles) < math.radians(34)
    back = np.abs(batch.angles) > math.radians(36)
    assert np.isnan(batch.ranges[:, back]).all()
    assert not np.isnan(batch.ranges[:, front]).any()


def test_height_band_must_be_ordered():
    with pytest.raises(GpoccError, match=r"height_band_m.*min < max"):
        config_from_dict({"sensors": [{"name": "l", "height_band_m": [2.0, 0.1]}]})


def test_without_config_a_laser_beside_a_cloud_is_the_sensor(tmp_path):
    # A depth camera's cloud beside a planar laser is not mapped unless named.
    run = LidarRun(room(), Lidar(), cloud_t=np.array([0.31, 5.31]))
    bag = BagWriter("mcap")
    run.write(bag)
    add_planar_laser(bag, run, beams=360)
    [batch] = read_inputs([bag.write(tmp_path / "both.mcap")], Config())
    assert batch.sensor == "scan" and batch.n_beams == 360


def test_configs_lidar_3d_spells_out_the_defaults(tmp_path):
    path = write_run(tmp_path, LidarRun(room(), Lidar(), cloud_t=np.array([0.31, 5.31])))
    [auto] = read_inputs([path], Config())
    config = load_config(Path(__file__).resolve().parents[2] / "configs" / "lidar_3d.yaml")
    [named] = read_inputs([path], config)
    for field in ("ranges", "poses", "pose_covariances", "angles"):
        np.testing.assert_array_equal(getattr(named, field), getattr(auto, field))
    for key in ("range_variance_m2", "bearing_variance_deg2", "range_min_m", "range_max_m",
                "height_band_m", "no_return_free_m"):
        assert getattr(named.sensor_config, key) == getattr(auto.sensor_config, key), key


def test_a_cloud_changing_its_frame_is_one_error_naming_the_topic(tmp_path):
    bag = BagWriter("mcap")
    LidarRun(room(), Lidar(), cloud_t=np.array([0.31, 1.31])).write(bag)
    last = bag.messages[-1][3]
    last.header.frame_id = "other"
    (tmp_path / "b").mkdir()
    result = CliRunner().invoke(app, ["info", str(bag.write(tmp_path / "b" / "run.mcap"))])
    assert result.exit_code != 0 and "Traceback" not in result.output
    assert "topic /velodyne_points" in result.output and "frame_id changes" in result.output


def test_info_names_base_height_when_the_floor_is_below_the_base_frame(tmp_path):
    bag = BagWriter("mcap")
    LidarRun(room(), Lidar(), cloud_t=np.array([0.31, 5.31])).write(bag, base="base_link",
                                                                    base_height=0.3)
    (tmp_path / "b").mkdir()
    [batch] = read_inputs([bag.write(tmp_path / "b" / "run.mcap")], Config())
    hint = [line for line in batch.provenance.sensor_lines if "base_height_m" in line]
    assert len(hint) == 1 and "base_height_m: 0.30" in hint[0], hint
    path = write_run(tmp_path / "a", LidarRun(room(), Lidar(), cloud_t=np.array([0.31])))
    [ok] = read_inputs([path], Config())
    assert not [line for line in ok.provenance.sensor_lines if "base_height_m" in line]


def test_a_masked_sector_of_a_spinning_lidar_is_never_cleared(tmp_path):
    """A 330-degree lidar (its back 30 degrees masked by the robot): the bins of the mask
    got no return at any height. They were cleared as no-returns, through the walls behind
    the robot, because the rest covered 90% of the bins."""
    lidar = Lidar(columns=1100, azimuth_deg=(-165.0, 165.0), max_range=6.0)
    run = LidarRun(room(), lidar, cloud_t=np.array([0.31, 5.31]))
    [batch] = read_inputs([write_run(tmp_path, run)], Config())
    back = np.abs(batch.angles) > math.radians(166)
    front = np.abs(batch.angles) < math.radians(164)
    assert back.any() and np.isnan(batch.ranges[:, back]).all()
    assert np.isfinite(batch.ranges[:, front]).mean() > 0.9  # the room's walls


def _moving_base_bag(until_s: float = 6.0) -> BagWriter:
    """A bag with TF map -> base_footprint along the test route at 30 Hz, no mount."""
    from cloud_scenes import base_rotation, tf_item

    bag = BagWriter("mcap")
    for t in np.arange(0.0, until_s, 1 / 30):
        x, y, yaw = base_path(np.array([t]))[0]
        bag.tf("/tf", T0 + t, [tf_item("map", "base_footprint", (x, y, 0.0),
                                       base_rotation(yaw, 0.0))])
    return bag


def _add_clouds(bag: BagWriter, run: LidarRun, topic: str, frame: str,
                to_frame=lambda pts: pts) -> None:
    """The run's clouds on ``topic`` in ``frame``, their (rings, columns, 3) points in the
    lidar frame moved by ``to_frame``."""
    from cloud_scenes import add_cloud, pack_cloud, scan_cloud

    rng = np.random.default_rng(0)
    for t, pose in zip(run.cloud_t, base_path(run.cloud_t), strict=True):
        add_cloud(bag, topic, frame, T0 + t,
                  pack_cloud(to_frame(scan_cloud(run.world, run.lidar, pose, rng)),
                             run.layout))


def test_a_registered_cloud_in_the_map_frame_is_refused(tmp_path):
    """A cloud already in the map frame (a lidar odometry's registered cloud) was taken
    with the map's origin as the sensor, beams cast from the map's corner."""
    run = LidarRun(room(), Lidar(), cloud_t=np.array([0.31, 5.31]))
    bag = _moving_base_bag()
    _add_clouds(bag, run, "/cloud_registered", "map")
    path = bag.write(tmp_path / "registered.mcap")
    with pytest.raises(GpoccError, match=r"the cloud's frame 'map' is not on the robot"):
        read_inputs([path], Config())


def test_a_partial_first_cloud_does_not_set_the_bins(tmp_path):
    """A driver's first cloud of a point or two set 36 bins of 10 degrees for the whole
    topic (its layout); clouds before the first one of MIN_BINS points are skipped."""
    from cloud_scenes import add_cloud, pack_cloud, scan_cloud

    from gpocc.io.cloudread import MIN_BINS

    run = LidarRun(room(), Lidar(), cloud_t=np.array([0.31, 5.31]))
    [full] = read_inputs([write_run(tmp_path / "full", run)], Config())
    bag = BagWriter("mcap")
    run.write(bag)
    pts = scan_cloud(run.world, run.lidar, base_path(np.array([0.2]))[0],
                     np.random.default_rng(1))
    add_cloud(bag, "/velodyne_points", "velodyne", T0 + 0.2,
              pack_cloud(pts[:1, :1], run.layout))
    [batch] = read_inputs([bag.write(tmp_path / "partial.mcap")], Config())
    assert batch.n_beams == full.n_beams > MIN_BINS
    assert batch.n_scans == full.n_scans
    np.testing.assert_array_equal(batch.ranges, full.ranges)


def test_a_lidar_mount_published_once_on_tf_is_named(tmp_path):
    from cloud_scenes import tf_item

    run = LidarRun(room(), Lidar(), cloud_t=np.array([0.31, 5.31]))
    bag = _moving_base_bag()
    bag.tf("/tf", T0, [tf_item("base_footprint", "velodyne", run.lidar.xyz,
                               run.lidar.rotation)])
    _add_clouds(bag, run, "/velodyne_points", "velodyne")
    with pytest.raises(GpoccError, match=r"TF base_footprint->velodyne on /tf has 1 message: "
                                         r"publish a mount that never changes on /tf_static$"):
        read_inputs([bag.write(tmp_path / "once.mcap")], Config())


def test_clouds_without_a_frame_id_take_the_topics_or_are_one_error(tmp_path):
    """As for LaserScan: a cloud whose header.frame_id is empty takes the topic's frame;
    those before the first cloud with a frame are skipped; none with a frame is one
    error line naming the driver's frame_id (it said to record a mount for frame '')."""
    from cloud_scenes import add_cloud, pack_cloud, scan_cloud

    run = LidarRun(room(), Lidar(), cloud_t=np.array([0.31, 2.31, 4.31, 6.31]))

    rng = np.random.default_rng(0)
    clouds = [pack_cloud(scan_cloud(run.world, run.lidar, pose, rng), run.layout)
              for pose in base_path(run.cloud_t)]
    paths = {}
    for name, frames in (("mixed", ["", "velodyne", "", "velodyne"]), ("none", [""] * 4)):
        bag = BagWriter("mcap")
        LidarRun(room(), Lidar(), cloud_t=np.zeros(0)).write(bag)
        for t, frame, cloud in zip(run.cloud_t, frames, clouds, strict=True):
            add_cloud(bag, "/velodyne_points", frame, T0 + t, cloud)
        paths[name] = bag.write(tmp_path / f"{name}.mcap")
    [batch] = read_inputs([paths["mixed"]], Config())
    assert batch.n_scans == 3  # the first, frameless, skipped; the third takes 'velodyne'
    with pytest.raises(GpoccError, match=r"none of its 4 clouds has a header.frame_id"):
        read_inputs([paths["none"]], Config())


def test_a_cloud_already_in_the_base_frame_is_mapped(tmp_path):
    """A filter's output in base_footprint (the frame TF moves) was refused as having no
    base frame under it; it is taken as seen from the base's origin, as a cloud in
    base_link already was."""
    run = LidarRun(room(), Lidar(), cloud_t=np.array([0.31, 5.31]))

    def in_base(pts: np.ndarray) -> np.ndarray:
        moved = run.lidar.rotation.apply(pts.reshape(-1, 3)) + np.asarray(run.lidar.xyz)
        return moved.reshape(pts.shape)

    bag = _moving_base_bag()
    _add_clouds(bag, run, "/velodyne_points", "base_footprint", in_base)
    [batch] = read_inputs([bag.write(tmp_path / "in_base.mcap")], Config())
    assert batch.n_scans == 2
    p = hits(batch)
    off = np.where(inside(p, TABLE), 0.0, obstacle_distance(p, OBSTACLES))
    assert np.median(off) < 0.02


def test_cloud_stamps_that_are_all_equal_fall_back_to_log_time(tmp_path, capsys):
    """A driver that stamps every cloud alike posed every scan at the first one's pose;
    clouds follow LaserScan's clock rules now."""
    run = LidarRun(room(), Lidar(), cloud_t=np.array([0.31, 2.31, 4.31, 6.31]))
    [ref] = read_inputs([write_run(tmp_path / "ref", run)], Config())
    bag = BagWriter("mcap")
    run.write(bag)
    first = None
    for _, topic, _, msg in bag.messages:
        if topic == "/velodyne_points":
            first = first or (msg.header.stamp.sec, msg.header.stamp.nanosec)
            msg.header.stamp.sec, msg.header.stamp.nanosec = first
    [batch] = read_inputs([bag.write(tmp_path / "equal.mcap")], Config())
    assert "all 4 header stamps are equal" in capsys.readouterr().err
    np.testing.assert_allclose(batch.stamps, ref.stamps, atol=1e-6)
    np.testing.assert_allclose(batch.poses, ref.poses, atol=1e-6)


def test_no_base_frame_names_the_clouds_own_parents(tmp_path):
    """The error listed every TF frame as the cloud's parents."""
    from cloud_scenes import add_cloud, pack_cloud, scan_cloud, tf_item
    from scipy.spatial.transform import Rotation

    run = LidarRun(room(), Lidar(), cloud_t=np.array([0.31]))
    bag = BagWriter("mcap")
    still = Rotation.identity()
    bag.tf("/tf_static", T0, [tf_item("world", "mast", (0.0, 0.0, 1.0), still),
                              tf_item("mast", "lidar", (0.0, 0.0, 0.5), still),
                              tf_item("world", "camera", (1.0, 0.0, 1.0), still)])
    pts = scan_cloud(run.world, run.lidar, base_path(run.cloud_t)[0],
                     np.random.default_rng(0))
    add_cloud(bag, "/points", "lidar", T0 + 0.31, pack_cloud(pts, run.layout))
    with pytest.raises(GpoccError, match=r"under the cloud's frame 'lidar' \(its TF parents: "
                                         r"mast, world\)"):
        read_inputs([bag.write(tmp_path / "mast.mcap")], Config())


def test_bins_that_saw_only_a_near_floor_are_not_cleared_to_the_free_extent(tmp_path):
    """A lidar pitched down: in many bearings every ray meets the floor a metre or two
    away. Those bins were no-returns, cleared to no_return_free_m (5 m) through the
    walls beyond; now they are unknown."""
    lidar = Lidar(rings=8, columns=360, fov_deg=(-10.0, 10.0), xyz=(0.15, 0.0, 0.45),
                  rpy=(0.0, math.radians(35.0), 0.0))
    run = LidarRun(room(), lidar, cloud_t=np.array([0.31, 5.31]))
    [batch] = read_inputs([write_run(tmp_path, run)], Config())
    front = np.abs(batch.angles) < math.radians(45.0)  # pitched down: toward the floor
    assert np.isnan(batch.ranges[:, front]).any()  # the floor-only bearings
    # None cleared past where its rays stopped (behind, rays rise to the far ceiling).
    assert not np.isposinf(batch.ranges[:, front]).any()
