"""``gpocc evaluate`` and ground-truth loading, checked with rasterio and scikit-learn."""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np
import pytest
import rasterio
from sklearn.metrics import brier_score_loss, log_loss, roc_auc_score
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.errors import GpoccError
from gpocc.evaluation.truth import load_truth
from gpocc.gridspec import GridSpec
from gpocc.io.rasters import write_geotiff, write_vrt

SPEC = GridSpec(x0=-1.3, y0=2.2, resolution=0.1, width=40, height=30)
NODATA = -1.0


def _probability(seed: int) -> np.ndarray:
    """(H, W) float32 probabilities rising to the east, with noise and no-data holes."""
    rng = np.random.default_rng(seed)
    xs, _ = SPEC.cell_centres()
    p = 1.0 / (1.0 + np.exp(-(xs - xs.mean()) * 1.5 + rng.normal(0, 0.7, xs.shape)))
    p[rng.random(p.shape) < 0.08] = NODATA
    return p.astype(np.float32)


def _truth_points(seed: int, n: int = 500) -> tuple[np.ndarray, np.ndarray]:
    """Points over and around the map (some outside), labelled mostly by their x."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(SPEC.x0 - 0.5, SPEC.x1 + 0.5, n)
    y = rng.uniform(SPEC.y0 - 0.3, SPEC.y1 + 0.3, n)
    labels = ((x - (SPEC.x0 + SPEC.x1) / 2 + rng.normal(0, 0.8, n)) > 0).astype(int)
    return np.column_stack([x, y]), labels


def _sampled_with_rasterio(tif: Path, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-cell probability (0.5 where outside or no data) and covered mask, by rasterio."""
    with rasterio.open(tif) as ds:
        band = ds.read(1)
        rows, cols = rasterio.transform.rowcol(ds.transform, points[:, 0], points[:, 1])
        nodata = ds.nodata
    rows, cols = np.asarray(rows), np.asarray(cols)
    inside = (rows >= 0) & (rows < band.shape[0]) & (cols >= 0) & (cols < band.shape[1])
    values = np.full(len(points), np.nan)
    values[inside] = band[rows[inside], cols[inside]]
    covered = inside & (values != nodata) & np.isfinite(values)
    return np.where(covered, values, 0.5), covered


@pytest.fixture()
def maps(tmp_path: Path) -> tuple[Path, Path]:
    folder = tmp_path / "gp_map"
    folder.mkdir()
    write_geotiff(folder / "probability.tif", _probability(1), SPEC, nodata=NODATA)
    bare = tmp_path / "grid_prob.tif"
    write_geotiff(bare, _probability(2), SPEC, nodata=NODATA)
    return folder, bare


def _write_csv(path: Path, points: np.ndarray, labels: np.ndarray) -> Path:
    rows = zip(points, labels, strict=True)
    lines = ["x,y,label"] + [f"{x:.17g},{y:.17g},{lab}" for (x, y), lab in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def _error_lines(result) -> list[str]:
    """The error lines on stderr (progress lines aside)."""
    return [line for line in result.stderr.splitlines() if line.startswith("gpocc evaluate: ")]


def _invoke(*args: str):
    return CliRunner().invoke(app, ["evaluate", *args])


def test_csv_truth_auc_matches_sklearn_and_outputs_are_written(tmp_path, maps):
    folder, bare = maps
    points, labels = _truth_points(3)
    truth = _write_csv(tmp_path / "truth.csv", points, labels)
    out = tmp_path / "eval"
    result = _invoke(str(folder), str(bare), "--ground-truth", str(truth), "--out", str(out))
    assert result.exit_code == 0, result.output

    summary = json.loads((out / "results.json").read_text())
    by_name = {m["name"]: m for m in summary["maps"]}
    assert set(by_name) == {"gp_map", "grid_prob"}
    for name, tif in (("gp_map", folder / "probability.tif"), ("grid_prob", bare)):
        scores, covered = _sampled_with_rasterio(tif, points)
        assert by_name[name]["auc"] == pytest.approx(roc_auc_score(labels, scores), abs=1e-9)
        assert by_name[name]["coverage"] == pytest.approx(covered.mean())
        # Calibration of the same scores (uncovered points at 0.5), scikit-learn as oracle.
        assert by_name[name]["brier"] == pytest.approx(brier_score_loss(labels, scores),
                                                       rel=1e-9)
        clip = summary["calibration"]["log_loss_clip"]
        assert by_name[name]["log_loss"] == pytest.approx(
            log_loss(labels, np.clip(scores, clip, 1 - clip)), rel=1e-9)
        assert 0.0 <= by_name[name]["ece"] <= 1.0
        assert 0.5 < covered.mean() < 1.0  # the fixture does put points outside / on holes
        # The table on stdout shows the same numbers.
        row = next(line for line in result.stdout.splitlines() if line.startswith(name))
        assert f"{roc_auc_score(labels, scores):.4f}" in row
    assert summary["n_occupied"] == labels.sum() and summary["n_free"] == (1 - labels).sum()

    assert (out / "roc.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "reliability.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = (out / "roc.csv").read_text().splitlines()
    assert rows[0] == "map,fpr,tpr"
    curve = np.array([r.split(",")[1:] for r in rows[1:] if r.startswith("gp_map")], dtype=float)
    assert curve[0].tolist() == [0.0, 0.0] and curve[-1].tolist() == [1.0, 1.0]
    assert np.trapezoid(curve[:, 1], curve[:, 0]) == pytest.approx(by_name["gp_map"]["auc"])
    md = (out / "results.md").read_text()
    assert "| gp_map |" in md and "| grid_prob |" in md


def test_text_truth_with_minus_one_labels_and_comments(tmp_path, maps):
    folder, _ = maps
    points, labels = _truth_points(4)
    csv_truth = _write_csv(tmp_path / "truth.csv", points, labels)
    txt = tmp_path / "truth.txt"
    body = [f"{x:.17g}  {y:.17g}\t{1 if lab else -1}  # point" for (x, y), lab in
            zip(points, labels, strict=True)]
    txt.write_text("# x y label\n\n" + "\n".join(body) + "\n")
    p_txt, l_txt = load_truth(txt)
    p_csv, l_csv = load_truth(csv_truth)
    np.testing.assert_array_equal(p_txt, p_csv)
    np.testing.assert_array_equal(l_txt, labels)
    np.testing.assert_array_equal(l_csv, labels)
    a = _invoke(str(folder), "--ground-truth", str(txt))
    b = _invoke(str(folder), "--ground-truth", str(csv_truth))
    assert a.exit_code == 0 and a.stdout == b.stdout


def test_csv_header_order_and_extra_columns(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text("label,id,y,x\n1,a,2.5,-1\n0,b,3.5,4\n")
    points, labels = load_truth(path)
    np.testing.assert_array_equal(points, [[-1.0, 2.5], [4.0, 3.5]])
    np.testing.assert_array_equal(labels, [1, 0])


def test_geotiff_truth_uses_labelled_cell_centres(tmp_path, maps):
    folder, _ = maps
    rng = np.random.default_rng(5)
    # Offset by a fraction of a map cell, so no truth centre sits on a map cell edge
    # (where the nearest cell is a tie that rasterio and we may break differently).
    truth_spec = GridSpec(x0=-1.03, y0=2.02, resolution=0.2, width=15, height=12)
    xs, _ = truth_spec.cell_centres()
    classes = (xs + rng.normal(0, 0.5, xs.shape) > 0.7).astype(np.uint8)
    classes[rng.random(classes.shape) < 0.2] = 255
    truth = tmp_path / "truth.tif"
    write_geotiff(truth, classes, truth_spec, nodata=255)

    points, labels = load_truth(truth)
    with rasterio.open(truth) as ds:
        band = ds.read(1)
        rows, cols = np.nonzero(band != 255)
        x, y = rasterio.transform.xy(ds.transform, rows, cols)
    expected = np.column_stack([x, y])
    order = np.lexsort((points[:, 1], points[:, 0]))
    expected_order = np.lexsort((expected[:, 1], expected[:, 0]))
    np.testing.assert_allclose(points[order], expected[expected_order], atol=1e-9)
    np.testing.assert_array_equal(labels[order], band[rows, cols][expected_order])

    result = _invoke(str(folder), "--ground-truth", str(truth), "--out", str(tmp_path / "o"))
    assert result.exit_code == 0, result.output
    scores, _ = _sampled_with_rasterio(folder / "probability.tif", expected)
    auc = json.loads((tmp_path / "o" / "results.json").read_text())["maps"][0]["auc"]
    assert auc == pytest.approx(roc_auc_score(band[rows, cols], scores), abs=1e-9)


def _write_map_server(folder: Path, pgm_values: np.ndarray, spec: GridSpec) -> Path:
    """A trinary map_server map written directly (P5 PGM + YAML), independent of gpocc."""
    h, w = pgm_values.shape
    (folder / "truth.pgm").write_bytes(f"P5\n{w} {h}\n255\n".encode() + pgm_values.tobytes())
    (folder / "truth.yaml").write_text(
        f"image: truth.pgm\nmode: trinary\nresolution: {spec.resolution}\n"
        f"origin: [{spec.x0}, {spec.y0}, 0.0]\nnegate: 0\noccupied_thresh: 0.65\n"
        f"free_thresh: 0.196\n"
    )
    return folder / "truth.yaml"


def test_map_server_truth(tmp_path, maps):
    folder, _ = maps
    truth_spec = GridSpec(x0=-1.5, y0=2.1, resolution=0.25, width=18, height=13)
    rng = np.random.default_rng(6)
    pgm = rng.choice(np.array([0, 254, 205], dtype=np.uint8), size=truth_spec.shape)
    yaml_path = _write_map_server(tmp_path, pgm, truth_spec)
    points, labels = load_truth(yaml_path)
    # map_server: row 0 of the image is the top; the origin is the lower-left corner.
    rows, cols = np.nonzero(pgm != 205)
    x = truth_spec.x0 + (cols + 0.5) * truth_spec.resolution
    y = truth_spec.y0 + (truth_spec.height - rows - 0.5) * truth_spec.resolution
    np.testing.assert_allclose(points, np.column_stack([x, y]), atol=1e-9)
    np.testing.assert_array_equal(labels, (pgm[rows, cols] == 0).astype(int))

    result = _invoke(str(folder), "--ground-truth", str(yaml_path), "--out", str(tmp_path / "o"))
    assert result.exit_code == 0, result.output
    scores, _ = _sampled_with_rasterio(folder / "probability.tif", points)
    auc = json.loads((tmp_path / "o" / "results.json").read_text())["maps"][0]["auc"]
    assert auc == pytest.approx(roc_auc_score(labels, scores), abs=1e-9)


def test_tiled_map_folder_with_a_vrt(tmp_path, maps):
    folder, _ = maps
    prob = _probability(1)
    tiled = tmp_path / "tiled_map"
    (tiled / "tiles").mkdir(parents=True)
    tiles = []
    for row0, col0 in ((0, 0), (0, 25), (17, 0), (17, 25)):
        spec = SPEC.window(row0, col0, 17, 25)
        tile = tiled / "tiles" / f"probability_{row0}_{col0}.tif"
        write_geotiff(tile, prob[row0 : row0 + spec.height, col0 : col0 + spec.width], spec,
                      nodata=NODATA)
        tiles.append((tile, spec))
    write_vrt(tiled / "probability.vrt", tiles, SPEC, "float32", NODATA)
    points, labels = _truth_points(9)
    truth = _write_csv(tmp_path / "truth.csv", points, labels)
    result = _invoke(str(tiled), "--ground-truth", str(truth), "--out", str(tmp_path / "o"))
    assert result.exit_code == 0, result.output
    scores, covered = _sampled_with_rasterio(folder / "probability.tif", points)
    (row,) = json.loads((tmp_path / "o" / "results.json").read_text())["maps"]
    assert row["name"] == "tiled_map"
    assert row["auc"] == pytest.approx(roc_auc_score(labels, scores), abs=1e-9)
    assert row["coverage"] == pytest.approx(covered.mean())


def test_existing_out_is_refused_without_force(tmp_path, maps):
    folder, _ = maps
    truth = _write_csv(tmp_path / "truth.csv", *_truth_points(7))
    out = tmp_path / "eval"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    refused = _invoke(str(folder), "--ground-truth", str(truth), "--out", str(out))
    assert refused.exit_code == 2
    assert "--force" in refused.stderr and "Traceback" not in refused.output
    assert (out / "keep.txt").read_text() == "mine"
    # --force replaces only a previous gpocc output, never a folder of the user's (#12).
    forced = _invoke(str(folder), "--ground-truth", str(truth), "--out", str(out), "--force")
    assert forced.exit_code == 2 and "not one" in forced.stderr
    assert (out / "keep.txt").read_text() == "mine"
    out = tmp_path / "eval2"
    for _ in range(2):
        forced = _invoke(str(folder), "--ground-truth", str(truth), "--out", str(out),
                         "--force")
        assert forced.exit_code == 0, forced.output
    assert sorted(p.name for p in out.iterdir()) == [
        "reliability.png", "results.json", "results.md", "roc.csv", "roc.png",
    ]


def test_force_never_replaces_a_folder_it_reads(tmp_path, maps):
    """--out naming the evaluated map folder, or the folder of the ground truth, would
    delete an input when --force replaces it: one error line, both left intact."""
    folder, _ = maps
    (folder / "metadata.json").write_text(json.dumps({"gpocc_version": "0.1.0"}))
    truth = _write_csv(tmp_path / "truth.csv", *_truth_points(9))
    before = sorted(p.name for p in folder.iterdir())
    result = _invoke(str(folder), "--ground-truth", str(truth), "--out", str(folder), "--force")
    assert result.exit_code == 2 and "Traceback" not in result.output
    lines = _error_lines(result)
    assert len(lines) == 1 and "is the input" in lines[0] and str(folder) in lines[0]
    assert sorted(p.name for p in folder.iterdir()) == before
    out = tmp_path / "eval"
    assert _invoke(str(folder), "--ground-truth", str(truth), "--out", str(out)).exit_code == 0
    inside = _write_csv(out / "truth.csv", *_truth_points(9))
    result = _invoke(str(folder), "--ground-truth", str(inside), "--out", str(out), "--force")
    assert result.exit_code == 2 and len(_error_lines(result)) == 1
    assert str(inside) in _error_lines(result)[0] and inside.is_file()


@pytest.mark.parametrize(
    "name, content, message",
    [
        ("bad.csv", "x,y,label\n1,2,1\n3,oops,0\n", "line 3"),
        ("bad.csv", "x,y,label\n1,2,1\n3,4,2\n", "line 3"),
        ("bad.csv", "a,b,c\n1,2,1\n", "header"),
        ("short.txt", "1 2 1\n3 4\n", "line 2"),
        # Rows wider than the header (or than x y label): which value is which is unknown.
        ("wide.csv", "x,y,label\n1,2,1\n3,4,0,1\n", "line 3: expected 3 values"),
        ("wide.txt", "1 2 1\n3 4 0 1\n", "line 2: expected 3 values"),
        ("narrow.csv", "label,id,y,x\n1,a,2,3\n0,4,5\n", "line 3: expected 4 values"),
        ("empty.csv", "# nothing\n", "no points"),
        ("one_class.csv", "x,y,label\n1,2,1\n3,4,1\n", "both"),
        ("blob.bin", b"\x00\xff\xfe\x01binary", "accepted ground truth"),
    ],
)
def test_bad_truth_gives_one_error_line(tmp_path, maps, name, content, message):
    folder, _ = maps
    path = tmp_path / name
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    result = _invoke(str(folder), "--ground-truth", str(path))
    assert result.exit_code == 2
    assert "Traceback" not in result.output
    lines = _error_lines(result)
    assert len(lines) == 1 and str(path) in lines[0] and message in lines[0], result.stderr
    assert result.stderr.rstrip().splitlines()[-1] == lines[0]  # nothing after it


def test_missing_inputs_and_non_probability_maps(tmp_path, maps):
    folder, _ = maps
    truth = _write_csv(tmp_path / "truth.csv", *_truth_points(8))
    missing = _invoke(str(folder), "--ground-truth", str(tmp_path / "nope.csv"))
    assert missing.exit_code == 2 and "not found" in missing.stderr
    # A pipe (say, a shell's <(...)) with no writer would block the read for ever.
    os.mkfifo(tmp_path / "pipe.csv")
    pipe = _invoke(str(folder), "--ground-truth", str(tmp_path / "pipe.csv"))
    assert pipe.exit_code == 2 and "pipe.csv: not a regular file" in pipe.stderr
    no_map = _invoke(str(tmp_path / "absent_map"), "--ground-truth", str(truth))
    assert no_map.exit_code == 2 and "absent_map" in no_map.stderr
    empty = tmp_path / "empty_folder"
    empty.mkdir()
    no_prob = _invoke(str(empty), "--ground-truth", str(truth))
    assert no_prob.exit_code == 2 and "probability.tif" in no_prob.stderr
    variance = tmp_path / "variance.tif"
    write_geotiff(variance, np.full(SPEC.shape, 3.0, np.float32), SPEC, nodata=NODATA)
    wrong = _invoke(str(variance), "--ground-truth", str(truth))
    assert wrong.exit_code == 2 and "[0, 1]" in wrong.stderr
    for r in (missing, no_map, no_prob, wrong):
        assert "Traceback" not in r.output and len(_error_lines(r)) == 1


def test_probability_raster_value_other_than_classes_is_rejected_as_truth(tmp_path):
    truth = tmp_path / "prob_as_truth.tif"
    write_geotiff(truth, np.full(SPEC.shape, 0.3, np.float32), SPEC, nodata=NODATA)
    with pytest.raises(GpoccError, match="prob_as_truth.tif"):
        load_truth(truth)


@pytest.mark.parametrize(("map_options", "truth_options"), [
    (dict(compress="lzw"), dict(compress="lzw", predictor=2)),
    (dict(compress="zstd", predictor=3, tiled=True, blockxsize=16, blockysize=16),
     dict(compress="deflate")),
])
def test_evaluate_scores_geotiffs_written_by_gdal(tmp_path, map_options, truth_options):
    """Map and truth written by GDAL itself (LZW, ZSTD, predictors) score like ours."""
    transform = rasterio.Affine(SPEC.resolution, 0, SPEC.x0, 0, -SPEC.resolution, SPEC.y1)
    folder = tmp_path / "gdal_map"
    folder.mkdir()
    prob = _probability(3)
    with rasterio.open(folder / "probability.tif", "w", driver="GTiff", width=SPEC.width,
                       height=SPEC.height, count=1, dtype="float32", transform=transform,
                       nodata=NODATA, **map_options) as ds:
        ds.write(prob, 1)
    rng = np.random.default_rng(8)
    xs, _ = SPEC.cell_centres()
    classes = (xs + rng.normal(0, 0.5, xs.shape) > 0.7).astype(np.uint8)
    classes[rng.random(classes.shape) < 0.2] = 255
    truth = tmp_path / "truth.tif"
    with rasterio.open(truth, "w", driver="GTiff", width=SPEC.width, height=SPEC.height,
                       count=1, dtype="uint8", transform=transform, nodata=255,
                       **truth_options) as ds:
        ds.write(classes, 1)

    result = _invoke(str(folder), "--ground-truth", str(truth), "--out", str(tmp_path / "o"))
    assert result.exit_code == 0, result.output
    rows, cols = np.nonzero(classes != 255)
    labels = classes[rows, cols]
    scores = prob[rows, cols].astype(float)
    scores[scores == NODATA] = 0.5
    auc = json.loads((tmp_path / "o" / "results.json").read_text())["maps"][0]["auc"]
    assert auc == pytest.approx(roc_auc_score(labels, scores), abs=1e-9)


def test_truth_that_misses_every_map_is_an_error_and_writes_nothing(tmp_path, maps):
    """Points 100 m east of the maps (another frame): every score would be p = 0.5's."""
    gp_folder, bare = maps
    points, labels = _truth_points(3)
    truth = _write_csv(tmp_path / "far.csv", points + [100.0, 0.0], labels)
    out = tmp_path / "scores"
    result = _invoke(str(gp_folder), str(bare), "--ground-truth", str(truth),
                     "--out", str(out))
    assert result.exit_code == 2
    errors = _error_lines(result)
    assert len(errors) == 1 and "none of its 500 points (x " in errors[0]
    assert "lies on a cell with data in any of the 2 maps" in errors[0]
    assert "Traceback" not in result.output and not out.exists()
    warnings = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 2  # one per map, with both extents
    x0, y0, x1, y1 = SPEC.bounds
    assert f"the map spans x {x0:.1f} .. {x1:.1f}, y {y0:.1f} .. {y1:.1f} m" in warnings[0]
    assert f"the points x {points[:, 0].min() + 100:.1f} .. " in warnings[0]
    # One map: the error alone gives both extents, without a warning saying it first.
    for flags in ([], ["--quiet"]):
        one = _invoke(str(bare), "--ground-truth", str(truth), *flags)
        assert one.exit_code == 2 and "warning" not in one.stderr
        assert len(_error_lines(one)) == 1
    quiet = _invoke(str(bare), "--ground-truth", str(truth), "--quiet")
    assert quiet.exit_code == 2 and quiet.stderr.count("\n") == 1
    assert (f"(x {points[:, 0].min() + 100:.1f} .. " in quiet.stderr
            and f"in the map (x {x0:.1f} .. {x1:.1f}, y {y0:.1f} .. {y1:.1f} m)" in quiet.stderr)


def test_the_same_map_given_twice_is_refused(tmp_path, maps):
    """Two rows of one name, and roc.csv's two curves joined into one series."""
    gp_folder, _ = maps
    points, labels = _truth_points(5)
    truth = _write_csv(tmp_path / "t.csv", points, labels)
    result = _invoke(str(gp_folder), str(gp_folder), "--ground-truth", str(truth),
                     "--out", str(tmp_path / "e"))
    assert result.exit_code == 2
    [line] = _error_lines(result)
    assert "given twice; pass each input once, or it is scored twice" in line
    assert not (tmp_path / "e").exists()


def test_a_map_that_misses_the_truth_is_scored_with_a_warning(tmp_path, maps):
    """One map covers the points, the other (moved 100 m west) none: the covered map is
    scored as before, the other at p = 0.5 everywhere (AUC 0.5), with a warning."""
    gp_folder, _ = maps
    moved = GridSpec(x0=SPEC.x0 - 100.0, y0=SPEC.y0, resolution=SPEC.resolution,
                     width=SPEC.width, height=SPEC.height)
    elsewhere = tmp_path / "elsewhere.tif"
    write_geotiff(elsewhere, _probability(2), moved, nodata=NODATA)
    points, labels = _truth_points(4)
    truth = _write_csv(tmp_path / "t.csv", points, labels)
    result = _invoke(str(gp_folder), str(elsewhere), "--ground-truth", str(truth))
    assert result.exit_code == 0, result.output
    warnings = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and str(elsewhere) in warnings[0]
    rows = {line.split()[0]: line.split() for line in result.stdout.splitlines()[1:]}
    scores, _ = _sampled_with_rasterio(gp_folder / "probability.tif", points)
    assert float(rows["gp_map"][1]) == pytest.approx(roc_auc_score(labels, scores), abs=1e-4)
    assert rows["elsewhere"][1] == "0.5000" and rows["elsewhere"][-1] == "0.0%"


def test_a_bom_csv_scores_as_the_same_csv_without_it(tmp_path, maps):
    # Spreadsheets save CSVs with a UTF-8 byte-order mark; its header was read as
    # "\ufeffx" and refused as missing x.
    folder, _ = maps
    plain = _write_csv(tmp_path / "plain.csv", *_truth_points(5))
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + plain.read_bytes())
    a = _invoke(str(folder), "--ground-truth", str(plain))
    b = _invoke(str(folder), "--ground-truth", str(bom))
    assert a.exit_code == 0 and b.exit_code == 0, b.output
    assert a.stdout.splitlines()[-1] == b.stdout.splitlines()[-1]


def test_points_too_far_for_a_cell_are_outside_without_warnings(tmp_path, maps):
    folder, _ = maps
    points, labels = _truth_points(6)
    points[:3] = [[1e308, 1e308], [-1e308, 0.0], [1e19, -1e19]]
    truth = _write_csv(tmp_path / "far.csv", points, labels)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's overflow warnings became errors
        result = _invoke(str(folder), "--ground-truth", str(truth), "--out",
                         str(tmp_path / "ev"))
    assert result.exit_code == 0, result.output
    summary = json.loads((tmp_path / "ev" / "results.json").read_text())
    _, covered = _sampled_with_rasterio(folder / "probability.tif", points[3:])
    n = len(points)
    assert summary["maps"][0]["coverage"] == pytest.approx(covered.sum() / n)


@pytest.mark.parametrize("layer", ["variance", "class"])
def test_another_layer_of_a_gpocc_map_is_refused(tmp_path, layer):
    # A variance layer holds values in [0, 1] too: it was scored as if it were p.
    from gpocc.io.rasters import CLASS_BAND, VARIANCE_BAND

    path = tmp_path / f"{layer}.tif"
    if layer == "variance":
        write_geotiff(path, np.full(SPEC.shape, 0.3, np.float32), SPEC, nodata=NODATA,
                      band=VARIANCE_BAND)
    else:
        write_geotiff(path, np.ones(SPEC.shape, np.uint8), SPEC, nodata=255, band=CLASS_BAND)
    truth = _write_csv(tmp_path / "t.csv", *_truth_points(7))
    result = _invoke(str(path), "--ground-truth", str(truth))
    assert result.exit_code == 2
    assert f"{layer}.tif: a gpocc {layer} layer, not a probability" in result.stderr
