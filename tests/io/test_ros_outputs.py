"""``map.mcap`` and the Nav2 scale map of a map folder, read back by independent readers:
rosbags' AnyReader, the ``mcap`` package's reader, rasterio for the rasters, Pillow for the
PNG, and Nav2's map_io loading rules written out here from its documented behaviour."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import rasterio
import yaml
from mcap.reader import make_reader
from PIL import Image
from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosDurability, QosHistory, QosReliability
from rosbags.rosbag2.metadata import parse_qos
from rosbags.typesys import Stores, get_typestore
from sklearn.metrics import roc_auc_score
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.config import config_from_dict
from gpocc.errors import GpoccError
from gpocc.gp.classify import classify
from gpocc.gridspec import GridSpec
from gpocc.io.rosmap import read_map_mcap
from gpocc.mapping.folder import MapFolder, folder_metadata, write_metadata
from gpocc.mapping.mapper import last_scan_stamp

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "data" / "sample" / "intel_sample.mcap"
SAMPLE_CONFIG = ROOT / "data" / "sample" / "sample.yaml"
SPEC = GridSpec(x0=-3.15, y0=1.35, resolution=0.05, width=37, height=23)
TOPICS = ("/map", "/map_class", "/map_variance")
TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)


def _layers(spec: GridSpec, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Probability (with p = 0, 1, 0.005 and 0.995 cells and NaN holes), variance, classes."""
    rng = np.random.default_rng(seed)
    p = rng.random(spec.shape).astype(np.float32)
    p.flat[:4] = [0.0, 1.0, 0.005, 0.995]
    hole = rng.random(spec.shape) < 0.15
    hole.flat[:4] = False
    p[hole] = np.nan
    variance = (rng.random(spec.shape) * 0.7).astype(np.float32)
    variance[hole] = np.nan
    classes = classify(p, 0.65, 0.35, unsure=rng.random(spec.shape) < 0.1)
    return p, variance, classes


def _write_folder(out: Path, spec: GridSpec, seed: int, tile: int = 0,
                  stamp_s: float | None = 12.25,
                  max_message_side: int = 8192, config: dict | None = None) -> Path:
    """A map folder of synthetic layers, tiled ``tile`` cells a side when ``tile``."""
    cfg = config_from_dict(config or {})
    p, variance, classes = _layers(spec, seed)
    folder = MapFolder(out, spec, cfg, tiled=tile > 0, tile=tile, stamp_s=stamp_s,
                       max_message_side=max_message_side)
    step = tile or max(spec.width, spec.height)
    for r in range(0, spec.height, step):
        for c in range(0, spec.width, step):
            window = spec.window(r, c, step, step)
            sl = np.s_[r:r + window.height, c:c + window.width]
            folder.add(r, c, window, p[sl], variance[sl], classes[sl])
    counts = folder.finish("test")
    write_metadata(out, folder_metadata("grid", spec, cfg, counts, {}, {},
                                        ros=folder.ros_outputs))
    return out


def _raster(folder: Path, name: str) -> tuple[np.ndarray, rasterio.Affine]:
    path = folder / f"{name}.tif"
    if not path.exists():
        path = folder / f"{name}.vrt"
    with rasterio.open(path) as ds:
        return ds.read(1), ds.transform


def _expected(folder: Path) -> dict[str, np.ndarray]:
    """The OccupancyGrid data each topic must hold, from the rasters (rasterio), rows
    flipped to ROS order (row 0 south)."""
    p, _ = _raster(folder, "probability")
    var, _ = _raster(folder, "variance")
    cls, _ = _raster(folder, "class")
    scale = float(np.nanmax(var))
    occ = np.where(np.isnan(p), -1, np.floor(100 * p.astype(np.float64) + 0.5))
    # Ties sit at exact .5 only for p = k/200; none of the test values does.
    klass = np.select([cls == 0, cls == 1], [0, 100], -1)
    v = np.where(np.isnan(var), -1, np.floor(100 * var.astype(np.float64) / scale + 0.5))
    return {"/map": occ[::-1].ravel(), "/map_class": klass[::-1].ravel(),
            "/map_variance": v[::-1].ravel(), "scale": scale}


def _map_yaml(folder: Path) -> dict:
    return yaml.safe_load((folder / "map.yaml").read_text())


def _check_message(msg, folder: Path, stamp_ns: int) -> None:
    meta = _map_yaml(folder)
    p, transform = _raster(folder, "probability")
    assert msg.header.frame_id == "map"
    assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == stamp_ns
    info = msg.info
    assert info.map_load_time.sec * 10**9 + info.map_load_time.nanosec == stamp_ns
    assert info.resolution == np.float32(meta["resolution"])
    assert (info.width, info.height) == (p.shape[1], p.shape[0])
    assert [info.origin.position.x, info.origin.position.y, 0.0] == meta["origin"]
    assert info.origin.position.z == 0.0
    q = info.origin.orientation
    assert (q.x, q.y, q.z, q.w) == (0.0, 0.0, 0.0, 1.0)
    # The origin is the raster's lower-left corner (rasterio: top-left + height cells).
    assert math.isclose(info.origin.position.x, transform.c, abs_tol=1e-12)
    assert math.isclose(info.origin.position.y, transform.f + transform.e * p.shape[0],
                        abs_tol=1e-9)


def test_map_mcap_read_by_rosbags_matches_the_rasters(tmp_path: Path) -> None:
    folder = _write_folder(tmp_path / "m", SPEC, seed=1, stamp_s=12.25)
    expected = _expected(folder)
    seen = {}
    with AnyReader([folder / "map.mcap"]) as reader:
        for conn, timestamp, raw in reader.messages():
            assert conn.msgtype == "nav_msgs/msg/OccupancyGrid"
            assert timestamp == 12_250_000_000
            msg = reader.deserialize(raw, conn.msgtype)
            _check_message(msg, folder, 12_250_000_000)
            seen[conn.topic] = np.asarray(msg.data)
    assert sorted(seen) == sorted(TOPICS)
    for topic in TOPICS:
        assert seen[topic].dtype == np.int8
        np.testing.assert_array_equal(seen[topic], expected[topic], err_msg=topic)
    # Every level is used as documented: p = 0 -> 0, p = 1 -> 100.
    p, _ = _raster(folder, "probability")
    south_up = seen["/map"].reshape(p.shape)[::-1]
    assert south_up.flat[0] == 0 and south_up.flat[1] == 100
    assert south_up.flat[2] in (0, 1) and south_up.flat[3] in (99, 100)


def test_map_mcap_read_by_the_mcap_reader_with_channel_metadata(tmp_path: Path) -> None:
    folder = _write_folder(tmp_path / "m", SPEC, seed=2, stamp_s=1_700_000_000.5)
    expected = _expected(folder)
    stamp_ns = 1_700_000_000_500_000_000
    with open(folder / "map.mcap", "rb") as fh:
        reader = make_reader(fh)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary.statistics.message_count == 3
        seen = {}
        for schema, channel, message in reader.iter_messages():
            assert schema.name == "nav_msgs/msg/OccupancyGrid"
            assert schema.encoding == "ros2msg"
            assert channel.message_encoding == "cdr"
            assert message.log_time == message.publish_time == stamp_ns
            msg = TYPESTORE.deserialize_cdr(message.data, schema.name)
            _check_message(msg, folder, stamp_ns)
            seen[channel.topic] = (np.asarray(msg.data), channel.metadata)
    for topic in TOPICS:
        np.testing.assert_array_equal(seen[topic][0], expected[topic], err_msg=topic)
    # MCAP's ros2 profile requires the QoS; a map is offered latched, as Nav2 offers it.
    for topic in TOPICS:
        (qos,) = parse_qos(seen[topic][1]["offered_qos_profiles"])
        assert qos.durability == QosDurability.TRANSIENT_LOCAL
        assert qos.reliability == QosReliability.RELIABLE
        assert (qos.history, qos.depth) == (QosHistory.KEEP_LAST, 1)
    scale = float(seen["/map_variance"][1]["variance_scale"])
    assert scale == pytest.approx(expected["scale"], rel=1e-7)
    # The documented inverse gives the variance back within half a level.
    var, _ = _raster(folder, "variance")
    back = seen["/map_variance"][0].reshape(var.shape)[::-1] / 100.0 * scale
    known = np.isfinite(var)
    assert np.all(np.abs(back[known] - var[known]) <= 0.005 * scale + 1e-6)
    meta = json.loads((folder / "metadata.json").read_text())["ros"]["map_mcap"]
    assert meta["variance_scale"] == scale and meta["frame_id"] == "map"
    assert meta["stamp_ns"] == stamp_ns and meta["topics"] == list(TOPICS)


def test_map_messages_are_those_of_the_whole_humble_type_store(tmp_path: Path) -> None:
    """map.mcap's types come from a store of the map's own types only: its schema text and
    every message's CDR bytes are what rosbags' full ROS 2 Humble store gives."""
    from gpocc.io.rosmap import OCCUPANCY_GRID, _typestore, grid_message

    ours = _typestore()
    assert (ours.generate_msgdef(OCCUPANCY_GRID, ros_version=2)
            == TYPESTORE.generate_msgdef(OCCUPANCY_GRID, ros_version=2))
    rng = np.random.default_rng(5)
    cells = rng.integers(-1, 101, size=SPEC.shape).astype(np.int8)
    data = grid_message(SPEC, cells, 1_700_000_000_123_456_789)
    t = TYPESTORE.types
    stamp = t["builtin_interfaces/msg/Time"](sec=1_700_000_000, nanosec=123_456_789)
    msg = t[OCCUPANCY_GRID](
        header=t["std_msgs/msg/Header"](stamp=stamp, frame_id="map"),
        info=t["nav_msgs/msg/MapMetaData"](
            map_load_time=stamp, resolution=SPEC.resolution, width=SPEC.width,
            height=SPEC.height, origin=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=SPEC.x0, y=SPEC.y0, z=0.0),
                orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))),
        data=np.ascontiguousarray(cells[::-1]).reshape(-1))
    assert data == bytes(TYPESTORE.serialize_cdr(msg, OCCUPANCY_GRID))


def test_a_map_larger_than_one_message_is_tiled_and_mosaics_back(tmp_path: Path) -> None:
    spec = GridSpec(x0=10.0, y0=-4.0, resolution=0.25, width=45, height=31)
    # Raster tiles of 16 cells, messages of at most 20: the two tilings cut differently.
    folder = _write_folder(tmp_path / "m", spec, seed=3, tile=16, max_message_side=20)
    expected = _expected(folder)
    p, _ = _raster(folder, "probability")
    mosaic = {t: np.full(p.shape, -2, dtype=np.int64) for t in TOPICS}
    with AnyReader([folder / "map.mcap"]) as reader:
        topics = sorted(c.topic for c in reader.connections)
        for conn, _, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            info = msg.info
            assert max(info.width, info.height) <= 20
            base, tile = conn.topic.rsplit("/tile_", 1)
            row, col = (int(v) for v in tile.split("_"))
            # Tile (row, col) is counted from the north-west, its origin is its SW corner.
            col0 = round((info.origin.position.x - spec.x0) / spec.resolution)
            row0 = spec.height - round((info.origin.position.y - spec.y0) / spec.resolution)
            assert col0 == col * 20 and row0 - info.height == row * 20
            data = np.asarray(msg.data).reshape(info.height, info.width)[::-1]
            mosaic[base][row0 - info.height:row0, col0:col0 + info.width] = data
    assert len(topics) == 3 * 3 * 2  # 45 / 20 -> 3 columns, 31 / 20 -> 2 rows
    for topic in TOPICS:
        np.testing.assert_array_equal(mosaic[topic][::-1].ravel(), expected[topic])
    # gpocc's own reader (gpocc evaluate) mosaics the tiles back too.
    values, read_spec, _ = read_map_mcap(folder / "map.mcap")
    assert read_spec == spec
    np.testing.assert_array_equal(np.isnan(values), np.isnan(p))
    assert np.nanmax(np.abs(values - p)) <= 0.005 + 1e-6


# ----------------------------------------------------------------- Nav2 scale map


def nav2_load(yaml_path: Path) -> tuple[np.ndarray, dict]:
    """An OccupancyGrid's data as Nav2's map_io builds it from a map yaml, written out from
    its documented rules: the pixel's shade is the mean of its colour channels over 255
    (inverted with ``negate``); occ = 1 - shade. In ``scale`` mode a pixel that is not
    opaque is unknown (-1); else occ > occupied_thresh is 100, occ < free_thresh is 0,
    and between, rint of 100 (occ - free) / (occupied - free). In ``trinary`` mode alpha
    joins the mean as (255 - alpha), and between the thresholds is unknown. Image row y
    lands in data row height - 1 - y (data row 0 is the south row).
    """
    meta = yaml.safe_load(yaml_path.read_text())
    image = Image.open(yaml_path.parent / meta["image"])
    rgba = np.asarray(image.convert("RGBA"), dtype=np.float64)
    has_alpha = image.mode in ("LA", "RGBA", "PA") or "transparency" in image.info
    channels = [rgba[..., 0], rgba[..., 1], rgba[..., 2]]
    mode = meta.get("mode", "trinary")
    if mode == "trinary" and has_alpha:
        channels.append(255.0 - rgba[..., 3])
    shade = sum(channels) / len(channels) / 255.0
    occ = shade if int(meta["negate"]) else 1.0 - shade
    free, occupied = float(meta["free_thresh"]), float(meta["occupied_thresh"])
    cells = np.full(occ.shape, -1, dtype=np.int64)
    if mode == "scale":
        opaque = rgba[..., 3] == 255
        between = opaque & (occ <= occupied) & (occ >= free)
        cells[between] = np.rint((occ[between] - free) / (occupied - free) * 100.0)
        cells[opaque & (occ > occupied)] = 100
        cells[opaque & (occ < free)] = 0
    else:
        cells[occ > occupied] = 100
        cells[occ < free] = 0
    return cells[::-1].ravel(), meta


def test_scale_map_loads_in_nav2_as_the_probability(tmp_path: Path) -> None:
    folder = _write_folder(tmp_path / "m", SPEC, seed=4)
    p, _ = _raster(folder, "probability")
    data, meta = nav2_load(folder / "map_scale.yaml")
    trinary = _map_yaml(folder)
    assert meta["mode"] == "scale" and trinary["mode"] == "trinary"
    assert meta["resolution"] == trinary["resolution"] and meta["origin"] == trinary["origin"]
    assert meta["image"] == "map_scale.png"
    known = np.isfinite(p)[::-1].ravel()
    np.testing.assert_array_equal(data == -1, ~known)
    # Nav2's value is round(100 p), exactly map.mcap's /map...
    p_south = p[::-1].ravel().astype(np.float64)
    np.testing.assert_array_equal(data[known], np.rint(100 * p_south[known]))
    with AnyReader([folder / "map.mcap"]) as reader:
        conn = next(c for c in reader.connections if c.topic == "/map")
        _, _, raw = next(reader.messages(connections=[conn]))
        mcap_data = np.asarray(reader.deserialize(raw, conn.msgtype).data, dtype=np.int64)
    np.testing.assert_array_equal(data, mcap_data)
    # ... and the PNG gives p back within 1/255: p = (255 - grey) / 255 on opaque pixels.
    la = np.asarray(Image.open(folder / "map_scale.png"))
    assert la.shape == p.shape + (2,)
    assert np.all((la[..., 1] == 0) == ~np.isfinite(p))
    back = (255.0 - la[..., 0]) / 255.0
    assert np.nanmax(np.abs(back - p)[np.isfinite(p)]) <= 1 / 255 + 1e-7


def test_scale_pixels_read_in_nav2_as_the_percent_of_every_probability() -> None:
    """Every float32 probability on a fine grid: Nav2's scale-mode decoding of its grey
    (rint(100 (1 - grey / 255))) is rint(100 p), and the grey is within 1 of 255 - 255 p."""
    from gpocc.io.scalemap import scale_pixels

    p = np.linspace(0.0, 1.0, 200_001, dtype=np.float32).astype(np.float64)
    grey = scale_pixels(p[None, :])[0, :, 0].astype(np.float64)
    np.testing.assert_array_equal(np.rint(100.0 * (1.0 - grey / 255.0)), np.rint(100.0 * p))
    assert np.abs(grey - (255.0 - 255.0 * p)).max() <= 1.0
    # The map's float32 tiles as they are (NaN: no data, grey 205 and transparent).
    single = p.astype(np.float32)
    single[::1000] = np.nan
    pixels = scale_pixels(single[None, :])[0]
    known = np.isfinite(single)
    np.testing.assert_array_equal(pixels[known, 0], grey[known])
    assert (pixels[~known, 0] == 205).all() and (pixels[:, 1] == np.where(known, 255, 0)).all()


def test_mcap_values_of_float32_layers_follow_their_formulas() -> None:
    """round(100 p) and round(100 variance / scale) clipped to 0..100, from the float32
    layers as stored, in double precision; -1 where no data."""
    from gpocc.io.rosmap import occupancy_values, variance_values

    rng = np.random.default_rng(12)
    p = np.concatenate([np.linspace(0.0, 1.0, 10_001), rng.uniform(-0.1, 1.1, 999)]
                       ).astype(np.float32)
    p[::97] = np.nan
    known = np.isfinite(p)
    want = np.full(p.shape, -1)
    want[known] = np.rint(100.0 * np.clip(p[known].astype(np.float64), 0.0, 1.0))
    np.testing.assert_array_equal(occupancy_values(p[None, :])[0], want)
    v = rng.uniform(0.0, 3.0, p.shape).astype(np.float32)
    v[::89] = np.nan
    known = np.isfinite(v)
    want = np.full(v.shape, -1)
    want[known] = np.rint(np.clip(100.0 * v[known].astype(np.float64) / 1.7, 0.0, 100.0))
    np.testing.assert_array_equal(variance_values(v[None, :], 1.7)[0], want)


def test_trinary_map_yaml_is_unchanged_by_the_scale_map(tmp_path: Path) -> None:
    folder = _write_folder(tmp_path / "m", SPEC, seed=5)
    cls, _ = _raster(folder, "class")
    data, _ = nav2_load(folder / "map.yaml")
    np.testing.assert_array_equal(data, np.select([cls == 0, cls == 1], [0, 100], -1)[::-1]
                                  .ravel())


# ----------------------------------------------------------------- georeference


def test_georeferenced_map_keeps_the_map_frame_and_states_its_place(tmp_path: Path) -> None:
    georef = {"epsg": 32633, "easting_m": 400123.5, "northing_m": 5001234.25, "yaw_deg": 30.0}
    folder = _write_folder(tmp_path / "m", SPEC, seed=6, config={"map": {"georef": georef}})
    with AnyReader([folder / "map.mcap"]) as reader:
        for conn, _, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            assert msg.header.frame_id == "map"
            assert (msg.info.origin.position.x, msg.info.origin.position.y) == (SPEC.x0,
                                                                                 SPEC.y0)
    relation = json.loads((folder / "metadata.json").read_text())["ros"]["map_mcap"][
        "frame_in_crs"]
    assert relation["epsg"] == 32633
    # The stated transform, applied to cell centres of the map frame, lands where the
    # GeoTIFF (read by rasterio, with its CRS) puts those cells.
    yaw = math.radians(relation["x_axis_yaw_deg"])
    with rasterio.open(folder / "probability.tif") as ds:
        assert ds.crs.to_epsg() == 32633
        for row, col in [(0, 0), (5, 30), (22, 36)]:
            x = SPEC.x0 + (col + 0.5) * SPEC.resolution
            y = SPEC.y0 + (SPEC.height - row - 0.5) * SPEC.resolution
            east = relation["origin_easting_m"] + math.cos(yaw) * x - math.sin(yaw) * y
            north = relation["origin_northing_m"] + math.sin(yaw) * x + math.cos(yaw) * y
            e_tif, n_tif = rasterio.transform.xy(ds.transform, row, col)  # cell centre
            assert (east, north) == pytest.approx((e_tif, n_tif), abs=1e-6)


# ----------------------------------------------------------------- evaluate


def test_evaluate_reads_map_mcap_as_the_quantised_probability(tmp_path: Path) -> None:
    folder = _write_folder(tmp_path / "m", SPEC, seed=7)
    rng = np.random.default_rng(8)
    n = 400
    x = rng.uniform(SPEC.x0 - 0.2, SPEC.x1 + 0.2, n)
    y = rng.uniform(SPEC.y0 - 0.2, SPEC.y1 + 0.2, n)
    p, transform = _raster(folder, "probability")
    rows, cols = rasterio.transform.rowcol(transform, x, y)
    rows, cols = np.asarray(rows), np.asarray(cols)
    inside = (rows >= 0) & (rows < p.shape[0]) & (cols >= 0) & (cols < p.shape[1])
    values = np.full(n, np.nan)
    values[inside] = p[rows[inside], cols[inside]]
    labels = (rng.random(n) < np.where(np.isfinite(values), values, 0.5)).astype(int)
    truth = tmp_path / "truth.csv"
    truth.write_text("x,y,label\n" + "".join(
        f"{a:.17g},{b:.17g},{lab}\n" for a, b, lab in zip(x, y, labels, strict=True)))
    quantised = np.where(np.isfinite(values), np.floor(100 * values + 0.5) / 100, 0.5)
    expected_auc = roc_auc_score(labels, quantised)
    out = tmp_path / "eval"
    result = CliRunner().invoke(app, ["evaluate", str(folder / "map.mcap"), "--ground-truth",
                                      str(truth), "--out", str(out)])
    assert result.exit_code == 0, result.output
    scored = json.loads((out / "results.json").read_text())["maps"][0]
    assert scored["auc"] == pytest.approx(expected_auc, abs=1e-12)
    assert scored["coverage"] == pytest.approx(np.isfinite(values).mean(), abs=1e-12)


def test_an_mcap_without_a_map_is_one_clear_error(tmp_path: Path) -> None:
    with pytest.raises(GpoccError, match=r"no nav_msgs/msg/OccupancyGrid on topic /map"):
        read_map_mcap(SAMPLE)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"\x89MCAP0\r\nnot really")
    truth = tmp_path / "truth.csv"
    truth.write_text("x,y,label\n0,0,1\n1,1,0\n")
    result = CliRunner().invoke(app, ["evaluate", str(bad), "--ground-truth", str(truth)])
    assert result.exit_code != 0
    assert "bad.mcap: not a readable MCAP file" in result.stderr
    assert "Traceback" not in result.output


# ----------------------------------------------------------------- end to end


def _last_scan_stamp_ns(bag: Path) -> int:
    """The largest LaserScan header stamp of ``bag``, read with rosbags."""
    last = 0
    with AnyReader([bag]) as reader:
        scans = [c for c in reader.connections if c.msgtype == "sensor_msgs/msg/LaserScan"]
        for conn, _, raw in reader.messages(connections=scans):
            stamp = reader.deserialize(raw, conn.msgtype).header.stamp
            last = max(last, stamp.sec * 10**9 + stamp.nanosec)
    return last


@pytest.mark.skipif(not SAMPLE.exists(), reason="data/sample/intel_sample.mcap is absent")
@pytest.mark.parametrize("command", ["build", "grid"])
def test_cli_map_folders_hold_map_mcap_stamped_with_the_last_scan(tmp_path: Path,
                                                                  command: str) -> None:
    out = tmp_path / "map"
    result = CliRunner().invoke(app, [command, str(SAMPLE), "--config", str(SAMPLE_CONFIG),
                                      "--resolution", "0.2", "--out", str(out)])
    assert result.exit_code == 0, result.output
    stamp_ns = _last_scan_stamp_ns(SAMPLE)
    expected = _expected(out)
    with AnyReader([out / "map.mcap"]) as reader:
        for conn, timestamp, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            _check_message(msg, out, stamp_ns)
            assert timestamp == stamp_ns
            np.testing.assert_array_equal(msg.data, expected[conn.topic])
    data, meta = nav2_load(out / "map_scale.yaml")
    assert meta["mode"] == "scale"
    np.testing.assert_array_equal(data == -1, expected["/map"] == -1)


def test_a_map_of_a_model_without_scan_times_is_stamped_zero_and_says_so(tmp_path: Path
                                                                          ) -> None:
    # Model files written before gpocc recorded the scans' time span.
    old_model = SimpleNamespace(training={"timings_s": {}})
    assert last_scan_stamp(old_model) is None
    assert last_scan_stamp(SimpleNamespace(training={"scan_stamps_s": [1.5, 9.75]})) == 9.75
    folder = _write_folder(tmp_path / "m", SPEC, seed=9, stamp_s=None)
    with AnyReader([folder / "map.mcap"]) as reader:
        for conn, timestamp, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            assert timestamp == 0 and (msg.header.stamp.sec, msg.header.stamp.nanosec) == (0, 0)
    meta = json.loads((folder / "metadata.json").read_text())["ros"]["map_mcap"]
    assert meta["stamp_ns"] == 0 and meta["stamp"].startswith("unknown")


def test_the_map_reader_takes_the_last_map_of_a_recorded_bag(tmp_path: Path) -> None:
    """A /map recorded by ROS 2 (here written by rosbags' rosbag2 MCAP writer): the last
    message counts, its origin and south-first rows as ROS defines them."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    t = TYPESTORE.types
    width, height, res, x0, y0 = 6, 4, 0.5, -1.0, 2.0
    final = np.arange(width * height, dtype=np.int8).reshape(height, width) * 4  # 0..92
    final[0, 0] = -1

    def grid(values: np.ndarray, sec: int):
        stamp = t["builtin_interfaces/msg/Time"](sec=sec, nanosec=0)
        origin = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=x0, y=y0, z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
        return t["nav_msgs/msg/OccupancyGrid"](
            header=t["std_msgs/msg/Header"](stamp=stamp, frame_id="map"),
            info=t["nav_msgs/msg/MapMetaData"](map_load_time=stamp, resolution=res,
                                               width=width, height=height, origin=origin),
            data=values.reshape(-1))

    bag = tmp_path / "recorded"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/map", "nav_msgs/msg/OccupancyGrid", typestore=TYPESTORE)
        for sec, values in ((1, np.zeros_like(final)), (2, final)):
            writer.write(conn, sec * 10**9, TYPESTORE.serialize_cdr(
                grid(values, sec), "nav_msgs/msg/OccupancyGrid"))
    values, spec, _ = read_map_mcap(bag / "recorded.mcap")
    assert spec == GridSpec(x0, y0, res, width, height)
    # Data row 0 is the south row: row 0 of the (north-first) result is the last data row.
    expected = np.where(final < 0, np.nan, final / 100.0)[::-1]
    np.testing.assert_array_equal(values, expected.astype(np.float32))
