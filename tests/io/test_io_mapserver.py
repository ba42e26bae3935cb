"""ROS map_server export / import, checked against map_server's rules written out here."""

from __future__ import annotations

import errno
import os

import numpy as np
import pytest
import yaml

from gpocc.errors import GpoccError
from gpocc.gridspec import GridSpec
from gpocc.io.mapserver import read_map_server, write_map_server


def ros_map_server_value(pixel_mean: int, negate: bool, occ_th: float, free_th: float,
                         mode: str) -> int:
    """map_server's image_loader for one pixel, transliterated from its C++ (ROS 1).

    Returns the OccupancyGrid value: 100 occupied, 0 free, -1 unknown, 1..99 scaled.
    """
    color_avg = pixel_mean
    if negate:
        color_avg = 255 - color_avg
    occ = (255 - color_avg) / 255.0
    if occ > occ_th:
        return 100
    if occ < free_th:
        return 0
    if mode == "trinary":
        return -1
    ratio = (occ - free_th) / (occ_th - free_th)
    return int(1 + 98 * ratio)


def grid_value_to_class(value: int) -> int:
    """0 free, 1 occupied, 2 anything else (unknown or graded cost)."""
    return {0: 0, 100: 1}.get(value, 2)


def parse_pgm(path):
    data = path.read_bytes()
    tokens = []
    pos = 0
    while len(tokens) < 4:
        line_end = data.index(b"\n", pos)
        line = data[pos:line_end]
        pos = line_end + 1
        if line.startswith(b"#"):
            continue
        tokens += line.split()
    magic, width, height, maxval = tokens
    pixels = np.frombuffer(data[pos:], dtype=np.uint8)
    return magic, int(width), int(height), int(maxval), pixels


def _probability(spec, rng, occupied, free):
    p = rng.random(spec.shape)
    p.flat[:4] = [occupied, free, np.nan, 0.5 * (occupied + free)]  # edges of the classes
    p[-3:, :5] = np.nan
    return p


def _our_classes(p, occupied, free):
    classes = np.full(p.shape, 2, dtype=np.uint8)
    classes[p > occupied] = 1
    classes[p < free] = 0
    return classes


@pytest.mark.parametrize(("occupied", "free"), [(0.65, 0.35), (0.9, 0.1), (0.5, 0.5)])
def test_classes_round_trip_through_map_server(tmp_path, occupied, free):
    spec = GridSpec(-12.35, -3.05, 0.05, 67, 41)
    p = _probability(spec, np.random.default_rng(0), occupied, free)
    expected = _our_classes(p, occupied, free)
    assert set(np.unique(expected)) == {0, 1, 2}
    write_map_server(tmp_path / "map.yaml", p, spec, occupied, free)
    assert sorted(f.name for f in tmp_path.iterdir()) == ["map.pgm", "map.yaml"]

    classes, back = read_map_server(tmp_path / "map.yaml")
    assert classes.dtype == np.uint8
    np.testing.assert_array_equal(classes, expected)
    assert back == spec  # origin, resolution and size exactly


def test_written_files_follow_the_map_server_format(tmp_path):
    spec = GridSpec(3.5, -7.25, 0.1, 30, 20)
    p = _probability(spec, np.random.default_rng(1), 0.65, 0.35)
    write_map_server(tmp_path / "floor.yaml", p, spec, 0.65, 0.35)

    meta = yaml.safe_load((tmp_path / "floor.yaml").read_text())
    assert meta["image"] == "floor.pgm"  # relative to the yaml
    assert meta["mode"] == "trinary"
    assert meta["resolution"] == 0.1
    assert meta["origin"] == [3.5, -7.25, 0.0]  # lower-left corner, no rotation
    assert meta["negate"] == 0
    assert meta["occupied_thresh"] == 0.65
    assert meta["free_thresh"] == 0.196

    magic, width, height, maxval, pixels = parse_pgm(tmp_path / "floor.pgm")
    assert (magic, width, height, maxval) == (b"P5", 30, 20, 255)
    assert pixels.size == 30 * 20
    image = pixels.reshape(20, 30)
    expected = _our_classes(p, 0.65, 0.35)
    # Row 0 of the image is the north row, as in the probability array.
    np.testing.assert_array_equal(image == 0, expected == 1)
    np.testing.assert_array_equal(image == 254, expected == 0)
    np.testing.assert_array_equal(image == 205, expected == 2)

    # map_server itself (its rule, applied to the file) sees exactly our classes.
    ros = np.vectorize(lambda v: grid_value_to_class(ros_map_server_value(
        int(v), bool(meta["negate"]), meta["occupied_thresh"], meta["free_thresh"],
        meta["mode"])))(image)
    np.testing.assert_array_equal(ros, expected)
    assert ros_map_server_value(205, False, 0.65, 0.196, "trinary") == -1


def _write_pgm(path, image, comment=True, ascii_=False):
    h, w = image.shape
    head = b"P2\n" if ascii_ else b"P5\n"
    if comment:
        head += b"# made by hand\n"
    head += f"{w} {h}\n255\n".encode()
    if ascii_:
        body = "\n".join(" ".join(str(v) for v in row) for row in image).encode()
    else:
        body = image.astype(np.uint8).tobytes()
    path.write_bytes(head + body)


@pytest.mark.parametrize(("negate", "mode", "occ_th", "free_th", "ascii_"), [
    (0, "trinary", 0.65, 0.196, False),
    (1, "trinary", 0.7, 0.2, False),
    (0, "scale", 0.55, 0.3, True),
    (1, "scale", 0.9, 0.05, False),
])
def test_read_matches_map_server_rules_for_any_grey(tmp_path, negate, mode, occ_th, free_th,
                                                    ascii_):
    image = np.arange(256, dtype=np.uint8).reshape(16, 16)
    _write_pgm(tmp_path / "m.pgm", image, ascii_=ascii_)
    (tmp_path / "m.yaml").write_text(
        f"image: m.pgm\nresolution: 0.05\norigin: [-1.0, 2.0, 0.0]\nnegate: {negate}\n"
        f"occupied_thresh: {occ_th}\nfree_thresh: {free_th}\nmode: {mode}\n")
    classes, spec = read_map_server(tmp_path / "m.yaml")
    expected = np.array([[grid_value_to_class(ros_map_server_value(int(v), bool(negate), occ_th,
                                                                     free_th, mode))
                          for v in row] for row in image], dtype=np.uint8)
    np.testing.assert_array_equal(classes, expected)
    assert spec == GridSpec(-1.0, 2.0, 0.05, 16, 16)


def test_reads_colour_png_maps(tmp_path):
    matplotlib_image = pytest.importorskip("matplotlib.image")
    rng = np.random.default_rng(2)
    rgb = rng.integers(0, 256, size=(9, 14, 3), dtype=np.uint8)
    matplotlib_image.imsave(tmp_path / "m.png", rgb)
    (tmp_path / "m.yaml").write_text(
        "image: m.png\nresolution: 0.1\norigin: [0.0, 0.0, 0.0]\nnegate: 0\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n")
    classes, spec = read_map_server(tmp_path / "m.yaml")
    mean = rgb.astype(int).sum(axis=2) // 3
    expected = np.vectorize(lambda v: grid_value_to_class(
        ros_map_server_value(int(v), False, 0.65, 0.196, "trinary")))(mean)
    np.testing.assert_array_equal(classes, expected)
    assert spec.shape == (9, 14)


def test_bad_map_server_files_give_clear_errors(tmp_path):
    with pytest.raises(GpoccError, match="missing.yaml: map yaml not found"):
        read_map_server(tmp_path / "missing.yaml")

    (tmp_path / "syntax.yaml").write_text("image: [unclosed\n")
    with pytest.raises(GpoccError, match="syntax.yaml: not valid YAML"):
        read_map_server(tmp_path / "syntax.yaml")

    good = ("image: m.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\nnegate: 0\n"
            "occupied_thresh: 0.65\nfree_thresh: 0.196\n")
    (tmp_path / "noimage.yaml").write_text(good)
    with pytest.raises(GpoccError, match=r"noimage\.yaml: its image .*m\.pgm is not found"):
        read_map_server(tmp_path / "noimage.yaml")

    _write_pgm(tmp_path / "m.pgm", np.zeros((4, 5), np.uint8))
    (tmp_path / "nores.yaml").write_text(good.replace("resolution: 0.05\n", ""))
    with pytest.raises(GpoccError, match="nores.yaml: missing key 'resolution'"):
        read_map_server(tmp_path / "nores.yaml")

    (tmp_path / "yaw.yaml").write_text(good.replace("[0.0, 0.0, 0.0]", "[0.0, 0.0, 0.3]"))
    with pytest.raises(GpoccError, match="yaw"):
        read_map_server(tmp_path / "yaw.yaml")

    # Swapped thresholds would call the free cells occupied and the walls free.
    for occupied, free in (("0.1", "0.9"), ("0.5", "0.5"), ("1.5", "0.2"), ("0.65", "-0.1")):
        (tmp_path / "swapped.yaml").write_text(
            good.replace("0.65", occupied).replace("0.196", free))
        with pytest.raises(GpoccError, match="swapped.yaml: needs 0 <= free_thresh < occ"):
            read_map_server(tmp_path / "swapped.yaml")

    (tmp_path / "raw.yaml").write_text(good + "mode: raw\n")
    with pytest.raises(GpoccError, match="mode 'raw'"):
        read_map_server(tmp_path / "raw.yaml")

    data = (tmp_path / "m.pgm").read_bytes()
    (tmp_path / "m.pgm").write_bytes(data[:-3])
    (tmp_path / "cut.yaml").write_text(good)
    with pytest.raises(GpoccError, match="m.pgm: truncated"):
        read_map_server(tmp_path / "cut.yaml")


# --------------------------------------------------------------------------- Nav2


def nav2_load_map(yaml_path):
    """Nav2's map_io (nav2_map_server/src/map_io.cpp) loadMapYaml + loadMapFromFile, in Python.

    Re-implemented from its rules, for 8-bit grey images: the image path is relative to
    the yaml's folder; ``mode`` defaults to trinary; ``negate`` is an int or a bool;
    ``normalized = grey / 255`` (float32), inverted unless negate; occupied (100) where
    ``normalized >= occupied_thresh``, free (0) where ``<= free_thresh``, else unknown
    (-1); rows are flipped so data row 0 is the image's bottom row.

    Returns ``(data (H, W) int8 with row 0 south, resolution, origin [x, y, yaw])``.
    """
    doc = yaml.safe_load(yaml_path.read_text())
    image = doc["image"]
    if not image:
        raise ValueError("The image tag was empty.")
    if not image.startswith("/"):
        image = str(yaml_path.parent / image)
    resolution = float(doc["resolution"])
    origin = [float(v) for v in doc["origin"]]
    if len(origin) != 3:
        raise ValueError("value of the 'origin' tag should have 3 elements")
    free_thresh = float(doc["free_thresh"])
    occupied_thresh = float(doc["occupied_thresh"])
    mode = doc.get("mode", "trinary")
    assert mode == "trinary"
    negate = int(doc["negate"])
    _, width, height, maxval, pixels = parse_pgm(type(yaml_path)(image))
    assert maxval == 255
    grey = pixels[: width * height].reshape(height, width)
    normalized = grey.astype(np.float32) / np.float32(255.0)
    if not negate:
        normalized = np.float32(1.0) - normalized
    result = np.full((height, width), -1, dtype=np.int8)
    result[normalized >= occupied_thresh] = 100
    result[normalized <= free_thresh] = 0
    return result[::-1], resolution, origin


def _nav2_cell_of(points, resolution, origin, shape):
    """Row (from the south) and column of each (N, 2) point in a loaded Nav2 grid."""
    col = np.floor((points[:, 0] - origin[0]) / resolution).astype(int)
    row = np.floor((points[:, 1] - origin[1]) / resolution).astype(int)
    assert ((col >= 0) & (col < shape[1]) & (row >= 0) & (row < shape[0])).all()
    return row, col


@pytest.mark.parametrize("tiled", [False, True])
def test_nav2_loads_every_cell_at_the_requested_resolution(tmp_path, tiled):
    from gpocc.gp.classify import classify
    from gpocc.io.mapserver import class_pixels, write_map_server_tiles

    # A 130 m long building at 0.05 m: 2600 cells a side, over the old 2000 px limit.
    spec = GridSpec(-40.0, -30.0, 0.05, 2600, 230)
    rng = np.random.default_rng(7)
    p = rng.random(spec.shape).astype(np.float32)
    p[rng.random(spec.shape) < 0.05] = np.nan  # cells without data
    occupied, free = 0.65, 0.35
    classes = classify(p, occupied, free)
    yaml_path = tmp_path / "map.yaml"
    if tiled:  # the mapper's path: one tile at a time, from class tiles
        tile = 96
        tiles = ((spec.window(r, c, tile, tile),
                  class_pixels(classes[r:r + tile, c:c + tile]))
                 for r in range(0, spec.height, tile) for c in range(0, spec.width, tile))
        write_map_server_tiles(yaml_path, spec, tiles, occupied, free)
    else:
        write_map_server(yaml_path, p, spec, occupied, free)

    data, resolution, origin = nav2_load_map(yaml_path)
    assert resolution == spec.resolution
    assert origin == [spec.x0, spec.y0, 0.0]
    assert data.shape == spec.shape
    # Every cell, looked up by its centre in Nav2's grid, keeps its class.
    xs, ys = spec.cell_centres()
    row, col = _nav2_cell_of(np.column_stack([xs.ravel(), ys.ravel()]), resolution, origin,
                             data.shape)
    loaded = data[row, col].reshape(spec.shape)
    np.testing.assert_array_equal(loaded == 100, classes == 1)
    np.testing.assert_array_equal(loaded == 0, classes == 0)
    np.testing.assert_array_equal(loaded == -1, (classes == 2) | (classes == 255))
    assert (classes == 1).sum() > 1000 and (classes == 255).sum() > 100


def test_size_limit_errors_and_writes_nothing(tmp_path):
    spec = GridSpec(0.0, 0.0, 0.05, 2001, 10)
    p = np.zeros(spec.shape)
    with pytest.raises(GpoccError, match="2001 x 10 pixels, over map.max_pgm_pixels = 2000"):
        write_map_server(tmp_path / "map.yaml", p, spec, 0.65, 0.35, max_pixels=2000)
    assert list(tmp_path.iterdir()) == []
    write_map_server(tmp_path / "map.yaml", p, spec, 0.65, 0.35, max_pixels=2001)
    assert parse_pgm(tmp_path / "map.pgm")[1:3] == (2001, 10)


_NO_FALLOCATE = pytest.mark.skipif(not hasattr(os, "posix_fallocate"),
                                   reason="no posix_fallocate here")
_IMAGE_SPEC = GridSpec(0.0, 0.0, 0.05, 40, 30)


def _fallocate_failing_with(monkeypatch, err: int) -> None:
    def fail(fd, offset, length):
        raise OSError(err, os.strerror(err))

    monkeypatch.setattr(os, "posix_fallocate", fail)


@_NO_FALLOCATE
def test_a_full_disk_is_an_os_error_on_the_image_and_leaves_nothing(tmp_path, monkeypatch):
    # The image is memory-mapped: without its blocks reserved first, a full disk killed
    # the process with SIGBUS. Reserving them must turn it into ENOSPC, naming the image.
    _fallocate_failing_with(monkeypatch, errno.ENOSPC)
    with pytest.raises(OSError) as raised:
        write_map_server(tmp_path / "map.yaml", np.zeros(_IMAGE_SPEC.shape), _IMAGE_SPEC,
                         0.65, 0.35)
    assert raised.value.errno == errno.ENOSPC
    assert str(raised.value.filename).endswith(".pgm")  # the image (its temporary)
    assert list(tmp_path.iterdir()) == []


@_NO_FALLOCATE
def test_a_file_system_without_fallocate_still_gets_its_map(tmp_path, monkeypatch):
    _fallocate_failing_with(monkeypatch, errno.EOPNOTSUPP)
    write_map_server(tmp_path / "map.yaml", np.zeros(_IMAGE_SPEC.shape), _IMAGE_SPEC,
                     0.65, 0.35)
    assert parse_pgm(tmp_path / "map.pgm")[1:3] == (40, 30)
