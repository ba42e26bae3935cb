"""Held-out points labelled by a truth raster (``gpocc evaluate --labels-from``): the
lookup against rasterio, the scores against scikit-learn."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
from sklearn.metrics import brier_score_loss, roc_auc_score
from test_evaluate import _sampled_with_rasterio
from test_protocols import protocol_subsets
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.errors import GpoccError
from gpocc.evaluation.truth import labels_at, load_truth_kinds, write_points
from gpocc.gridspec import GridSpec
from gpocc.io.rasters import write_geotiff

SPEC = GridSpec(x0=-2.05, y0=1.1, resolution=0.1, width=50, height=40)
UNKNOWN = 255


def _truth(seed: int) -> np.ndarray:
    """(H, W) uint8: a wall band (1) across free space (0), unknown patches (255)."""
    rng = np.random.default_rng(seed)
    xs, ys = SPEC.cell_centres()
    labels = (np.abs(xs - 0.3 * ys) < 0.25).astype(np.uint8)
    labels[rng.random(labels.shape) < 0.1] = UNKNOWN
    return labels


def _points(seed: int, n: int = 600) -> np.ndarray:
    """Points over the raster and a margin around it."""
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(SPEC.x0 - 0.4, SPEC.x1 + 0.4, n),
                            rng.uniform(SPEC.y0 - 0.4, SPEC.y1 + 0.4, n)])


def _labels_by_rasterio(tif: Path, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each point's cell value by rasterio's own row/column lookup; known where it is 0/1."""
    with rasterio.open(tif) as ds:
        band = ds.read(1)
        rows, cols = rasterio.transform.rowcol(ds.transform, points[:, 0], points[:, 1])
    rows, cols = np.asarray(rows), np.asarray(cols)
    inside = (rows >= 0) & (rows < band.shape[0]) & (cols >= 0) & (cols < band.shape[1])
    values = np.full(len(points), UNKNOWN)
    values[inside] = band[rows[inside], cols[inside]]
    known = values != UNKNOWN
    return np.where(known, values, 0), known


def test_labels_at_reads_the_cell_under_each_point_like_rasterio(tmp_path):
    tif = tmp_path / "truth.tif"
    write_geotiff(tif, _truth(0), SPEC, nodata=UNKNOWN)
    points = _points(1)
    labels, known = labels_at(points, tif)
    expected, expected_known = _labels_by_rasterio(tif, points)
    np.testing.assert_array_equal(known, expected_known)
    np.testing.assert_array_equal(labels[known], expected[known])
    # The sample holds every case: outside, on unknown cells, on each label.
    assert (~known).sum() > 20 and set(labels[known].tolist()) == {0, 1}


def test_labels_at_refuses_a_raster_of_other_values(tmp_path):
    tif = tmp_path / "p.tif"
    write_geotiff(tif, np.full(SPEC.shape, 0.5, dtype=np.float32), SPEC, nodata=-1.0)
    with pytest.raises(GpoccError, match="must hold 1 \\(occupied\\), 0 \\(free\\)"):
        labels_at(_points(2), tif)
    csv = tmp_path / "points.csv"
    csv.write_text("x,y,label\n0,0,1\n")
    with pytest.raises(GpoccError, match="pass a truth raster"):
        labels_at(_points(2), csv)


def _heldout(tmp_path: Path, seed: int) -> tuple[Path, np.ndarray, np.ndarray, np.ndarray]:
    """A held-out point file with kinds: hits near the wall band, free points along beams
    and near-wall points, each stated label partly wrong (as noisy scans make them)."""
    rng = np.random.default_rng(seed + 100)  # not _points' stream: kinds apart from x
    points = _points(seed, 900)
    kinds = rng.choice(np.array(["hit", "free", "near-wall"]), size=len(points),
                       p=[0.3, 0.5, 0.2])
    stated = (kinds == "hit").astype(int)
    path = tmp_path / "heldout.csv"
    rows = [f"{x:.5f},{y:.5f},{label},{kind}"
            for (x, y), label, kind in zip(points, stated, kinds, strict=True)]
    path.write_text("x,y,label,kind\n" + "\n".join(rows) + "\n")
    return path, points, stated, kinds


def test_evaluate_labels_from_scores_the_truths_labels_like_sklearn(tmp_path):
    truth = tmp_path / "truth.tif"
    write_geotiff(truth, _truth(3), SPEC, nodata=UNKNOWN)
    heldout, points, stated, kinds = _heldout(tmp_path, 4)
    folder = tmp_path / "map"
    folder.mkdir()
    xs, ys = SPEC.cell_centres()
    rng = np.random.default_rng(5)
    p_map = 1.0 / (1.0 + np.exp(4.0 * np.abs(xs - 0.3 * ys) - 1.0 + rng.normal(0, 1, xs.shape)))
    write_geotiff(folder / "probability.tif", p_map.astype(np.float32), SPEC, nodata=np.nan)
    out = tmp_path / "eval"
    result = CliRunner().invoke(app, ["evaluate", str(folder), "--ground-truth", str(heldout),
                                      "--labels-from", str(truth), "--out", str(out)])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "results.json").read_text())

    labels, known = _labels_by_rasterio(truth, np.round(points, 5))
    p, _ = _sampled_with_rasterio(folder / "probability.tif", np.round(points, 5))
    relabelled = int((labels[known] != stated[known]).sum())
    assert f"{relabelled} of {int(known.sum())} points relabelled" in result.output
    assert f"{int((~known).sum())} on unknown cells or outside it left out" in result.output
    # The files say so too: results.json and results.md, not only stderr.
    assert summary["labels_from"] == {"raster": str(truth), "relabelled": relabelled,
                                      "left_out": int((~known).sum())}
    assert (f"labelled by `{truth}` ({relabelled} relabelled, {int((~known).sum())} on"
            in (out / "results.md").read_text())
    # Protocols keep their kinds whatever the truth says of a point: a hit the truth
    # calls free stays in hits+free and hits+near-wall.
    y, p, k = labels[known], p[known], kinds[known]
    subsets = protocol_subsets(k)
    got = {g["name"]: g["maps"][0] for g in summary["protocols"]}
    assert list(got) == list(subsets)
    for name, m in subsets.items():
        assert got[name]["auc"] == pytest.approx(roc_auc_score(y[m], p[m]), rel=1e-9)
        assert got[name]["brier"] == pytest.approx(brier_score_loss(y[m], p[m]), rel=1e-9)
    # The stated labels score differently: the truth changed the answer.
    plain = CliRunner().invoke(app, ["evaluate", str(folder), "--ground-truth",
                                     str(heldout)])
    assert plain.exit_code == 0, plain.output
    assert f"{got['union']['auc']:.4f}" not in plain.stdout.splitlines()[-1]


def test_evaluate_labels_from_a_raster_in_another_frame_is_one_error_line(tmp_path):
    far = GridSpec(x0=100.0, y0=100.0, resolution=0.1, width=10, height=10)
    truth = tmp_path / "truth.tif"
    write_geotiff(truth, np.zeros(far.shape, dtype=np.uint8), far, nodata=UNKNOWN)
    heldout, *_ = _heldout(tmp_path, 6)
    folder = tmp_path / "map"
    folder.mkdir()
    write_geotiff(folder / "probability.tif", np.full(SPEC.shape, 0.3, dtype=np.float32),
                  SPEC, nodata=np.nan)
    out = tmp_path / "eval"
    result = CliRunner().invoke(app, ["evaluate", str(folder), "--ground-truth", str(heldout),
                                      "--labels-from", str(truth), "--out", str(out)])
    assert result.exit_code != 0
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "lies on a labelled cell" in lines[0] and str(truth) in lines[0]
    assert "Traceback" not in result.output and not out.exists()


def test_a_protocol_the_truth_leaves_one_label_is_not_scored():
    from gpocc.evaluation.report import score_protocols

    # Stated: two hits and four free points of two kinds; the truth calls both hits free
    # and one free point occupied, so hits+near-wall holds free points only.
    kinds = np.array(["hit", "hit", "free", "free", "near-wall", "near-wall"])
    stated = np.array([1, 1, 0, 0, 0, 0])
    truth = np.array([0, 0, 1, 0, 0, 0])
    scores = np.array([0.9, 0.8, 0.7, 0.1, 0.2, 0.3])
    scored = score_protocols(["m"], [(scores, np.ones(6, bool))], truth, kinds, stated)
    assert [s.name for s in scored] == ["hits+free", "union"]
    free_mask = np.array([True, True, True, True, False, False])
    assert scored[0].results[0].auc == pytest.approx(roc_auc_score(truth[free_mask],
                                                                   scores[free_mask]))
    assert scored[1].results[0].auc == pytest.approx(roc_auc_score(truth, scores))


def test_labels_at_reads_a_map_server_map_by_its_image_rows(tmp_path):
    from test_evaluate import _write_map_server

    spec = GridSpec(x0=-1.5, y0=2.1, resolution=0.25, width=18, height=13)
    rng = np.random.default_rng(7)
    pgm = rng.choice(np.array([0, 254, 205], dtype=np.uint8), size=spec.shape)
    yaml_path = _write_map_server(tmp_path, pgm, spec)
    points = np.column_stack([rng.uniform(spec.x0 - 0.5, spec.x1 + 0.5, 400),
                              rng.uniform(spec.y0 - 0.5, spec.y1 + 0.5, 400)])
    labels, known = labels_at(points, yaml_path)
    # By hand: image row 0 is the top; the origin is the lower-left corner; a black pixel
    # (0) is occupied, white (254) free, 205 unknown.
    cols = np.floor((points[:, 0] - spec.x0) / spec.resolution).astype(int)
    rows = spec.height - 1 - np.floor((points[:, 1] - spec.y0) / spec.resolution).astype(int)
    inside = (cols >= 0) & (cols < spec.width) & (rows >= 0) & (rows < spec.height)
    pixel = np.full(len(points), 205)
    pixel[inside] = pgm[rows[inside], cols[inside]]
    np.testing.assert_array_equal(known, pixel != 205)
    np.testing.assert_array_equal(labels[known], (pixel[known] == 0).astype(int))


def test_written_points_read_back_with_their_labels_and_kinds(tmp_path):
    rng = np.random.default_rng(5)
    points = rng.uniform(-50.0, 50.0, (40, 2))
    labels = rng.integers(0, 2, 40)
    kinds = np.where(labels == 1, "hit", rng.choice(["free", "near-wall"], 40))
    write_points(tmp_path / "points.csv", points, labels, kinds)
    got_points, got_labels, got_kinds = load_truth_kinds(tmp_path / "points.csv")
    np.testing.assert_allclose(got_points, points, rtol=0, atol=5e-5)  # 0.1 mm
    np.testing.assert_array_equal(got_labels, labels)
    np.testing.assert_array_equal(got_kinds, kinds)
