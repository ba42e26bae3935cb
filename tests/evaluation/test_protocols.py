"""Held-out protocols: the near-wall sampler against the geometry of a square room, the
per-protocol scores of `gpocc evaluate` against scikit-learn."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy import stats
from sklearn.metrics import brier_score_loss, log_loss, roc_auc_score, roc_curve
from test_evaluate import _sampled_with_rasterio
from test_split import HALF, MOUNT, SENSOR, _laser_origins, _room_ranges, _write_input, room_batch
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.config import SensorConfig
from gpocc.evaluation.calibration import LOG_LOSS_CLIP
from gpocc.evaluation.truth import load_truth, load_truth_kinds
from gpocc.gridspec import GridSpec
from gpocc.io.rasters import write_geotiff
from gpocc.io.scans import ScanBatch
from gpocc.samples.heldout import near_wall_points, protocol_points


def _beam_geometry(points: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each point's distance from the laser and the wall distance along its direction."""
    offset = points - origin
    phi = np.arctan2(offset[:, 1], offset[:, 0])
    wall = _room_ranges(origin[None, :], np.zeros(1), phi)[0]
    return np.linalg.norm(offset, axis=1), wall


def test_near_wall_points_are_uniform_in_the_band_before_each_hit():
    batch = room_batch(n_scans=1, n_beams=3000, seed=4)
    origin, _ = _laser_origins(batch.poses, MOUNT)
    points = near_wall_points(batch, SENSOR, 2, np.random.default_rng(3))
    d, wall = _beam_geometry(points, origin[0])
    short = wall - d  # how far in front of the wall, along the beam
    assert short.min() >= 0.05 - 1e-9 and short.max() <= 0.3 + 1e-9
    assert np.all(wall < batch.range_max)  # only hit beams give them
    # Uniform in the band: (short - 0.05) / 0.25 against U(0, 1).
    assert stats.kstest((short - 0.05) / 0.25, "uniform").pvalue > 1e-3
    # Counted from the ranges, independently of the sampler: 2 per valid hit (every hit
    # here is farther than 0.35 m from the laser).
    r = batch.ranges
    hits = np.isfinite(r) & (r >= batch.range_min) & (r < batch.range_max)
    assert len(points) == 2 * hits.sum()


def test_near_wall_band_is_clipped_at_the_laser():
    # One scan from the origin, no mount offset: distances are the points' norms.
    ranges = np.array([[0.12, 0.2, 0.3, 1.0, np.inf, np.nan, 0.04]])
    batch = ScanBatch(sensor="s", source="hand", stamps=np.zeros(1),
                      angles=np.linspace(0.0, 1.2, 7), ranges=ranges,
                      poses=np.zeros((1, 3)), pose_covariances=np.zeros((1, 3, 3)),
                      range_min=0.05, range_max=5.0, has_pose_covariance=False)
    sensor = SensorConfig(name="s")
    n = 4000
    points = near_wall_points(batch, sensor, n, np.random.default_rng(0)).reshape(-1, n, 2)
    # By hand: [max(r - 0.3, 0.1), r - 0.05] for r = 0.2, 0.3, 1.0; r = 0.12 gives an
    # empty band (0.1 > 0.07), no-return, NaN and too-short beams give nothing.
    assert points.shape[0] == 3
    for got, (lo, hi), angle in zip(points, [(0.1, 0.15), (0.1, 0.25), (0.7, 0.95)],
                                    batch.angles[1:4], strict=True):
        d = np.linalg.norm(got, axis=1)
        assert d.min() >= lo - 1e-12 and d.max() <= hi + 1e-12
        assert d.mean() == pytest.approx((lo + hi) / 2, abs=4 * (hi - lo) / math.sqrt(12 * n))
        np.testing.assert_allclose(np.arctan2(got[:, 1], got[:, 0]), angle, atol=1e-12)


def test_protocol_points_keep_the_free_draws_and_label_every_kind():
    batch = room_batch(seed=2)
    from gpocc.samples.heldout import labelled_points

    points, labels, kinds = protocol_points(batch, SENSOR, 3, 2, np.random.default_rng(5))
    old_points, old_labels = labelled_points(batch, SENSOR, 3, np.random.default_rng(5))
    # The hits and free points are those of the older protocol, draw for draw.
    np.testing.assert_array_equal(points[: len(old_points)], old_points)
    np.testing.assert_array_equal(labels[: len(old_labels)], old_labels)
    assert set(kinds[labels == 1]) == {"hit"}
    assert set(kinds[labels == 0]) == {"free", "near-wall"}
    assert (kinds == "near-wall").sum() == 2 * (kinds == "hit").sum()


def test_cli_split_writes_kinds_that_old_readers_still_read(tmp_path):
    bag, cfg = _write_input(tmp_path, [room_batch(n_scans=24, n_beams=90, seed=6)])
    out = tmp_path / "split"
    result = CliRunner().invoke(app, ["split", str(bag), "--every", "4", "--out", str(out),
                                      "--config", str(cfg), "--near-wall-per-beam", "2"])
    assert result.exit_code == 0, result.output
    assert (out / "heldout.csv").read_text().splitlines()[0] == "x,y,label,kind"
    points, labels, kinds = load_truth_kinds(out / "heldout.csv")
    old_points, old_labels = load_truth(out / "heldout.csv")
    np.testing.assert_array_equal(points, old_points)
    np.testing.assert_array_equal(labels, old_labels)
    near = points[kinds == "near-wall"]
    assert (kinds == "near-wall").sum() == 2 * (kinds == "hit").sum()
    # Near-wall points lie inside the room, at most 0.3 m (+ the file's rounding) from a
    # wall; free points along beams reach much deeper into the room.
    depth = HALF - np.abs(near).max(axis=1)
    assert depth.min() > 0 and depth.max() <= 0.3 + 1e-3
    free_depth = HALF - np.abs(points[kinds == "free"]).max(axis=1)
    assert free_depth.max() > 1.0
    assert f"{len(near)} near-wall free" in result.stdout


# heldout.csv holds 4 decimals: cell edges at 5 decimals (...997) are never a tie for the
# nearest cell, whichever sampler rounds which way.
SPEC = GridSpec(x0=-HALF - 0.25003, y0=-HALF - 0.25003, resolution=0.1, width=105, height=105)


def _wall_map(seed: int) -> np.ndarray:
    """p rising towards the walls, noisy, with a no-data hole."""
    rng = np.random.default_rng(seed)
    xs, ys = SPEC.cell_centres()
    depth = HALF - np.maximum(np.abs(xs), np.abs(ys))
    p = 1.0 / (1.0 + np.exp(4.0 * (depth - 0.3) + rng.normal(0, 1.0, xs.shape)))
    p[40:45, 40:45] = np.nan
    return p.astype(np.float32)


def _sklearn_scores(labels: np.ndarray, p: np.ndarray) -> dict[str, float]:
    fpr, tpr, _ = roc_curve(labels, p, drop_intermediate=False)
    return {"auc": roc_auc_score(labels, p),
            "fpr_at_tpr97": float(np.interp(0.97, tpr, fpr)),
            "brier": brier_score_loss(labels, p),
            "log_loss": log_loss(labels, np.clip(p, LOG_LOSS_CLIP, 1 - LOG_LOSS_CLIP))}


def _ece(labels: np.ndarray, p: np.ndarray) -> float:
    """Expected calibration error by an explicit loop over the ten bins (k/10, (k+1)/10]."""
    total = 0.0
    for k in range(10):
        inside = (p > k / 10) & (p <= (k + 1) / 10) if k else (p <= 0.1)
        if inside.any():
            total += inside.sum() * abs(labels[inside].mean() - p[inside].mean())
    return total / len(p)


def protocol_subsets(kinds: np.ndarray) -> dict[str, np.ndarray]:
    """Each protocol's points, by the kinds `gpocc split` writes (written out here, apart
    from gpocc.evaluation.report.protocols)."""
    return {"hits+free": (kinds == "hit") | (kinds == "free"),
            "hits+near-wall": (kinds == "hit") | (kinds == "near-wall"),
            "union": np.ones(len(kinds), bool)}


def test_evaluate_scores_every_protocol_like_sklearn(tmp_path):
    bag, cfg = _write_input(tmp_path, [room_batch(n_scans=40, n_beams=120, seed=7)])
    split = tmp_path / "split"
    assert CliRunner().invoke(app, ["split", str(bag), "--every", "4", "--out", str(split),
                                    "--config", str(cfg)]).exit_code == 0
    folder = tmp_path / "walls"
    folder.mkdir()
    p_map = _wall_map(1)
    write_geotiff(folder / "probability.tif", p_map, SPEC, nodata=np.nan)
    out = tmp_path / "eval"
    result = CliRunner().invoke(app, ["evaluate", str(folder), "--ground-truth",
                                      str(split / "heldout.csv"), "--out", str(out)])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "results.json").read_text())

    points, labels, kinds = load_truth_kinds(split / "heldout.csv")
    # The map's p at each point, sampled by rasterio (0.5 on no data).
    p, _ = _sampled_with_rasterio(folder / "probability.tif", points)
    subsets = protocol_subsets(kinds)
    got = {g["name"]: g["maps"][0] for g in summary["protocols"]}
    assert list(got) == list(subsets)
    for name, m in subsets.items():
        expected = _sklearn_scores(labels[m], p[m])
        for key, value in expected.items():
            assert got[name][key] == pytest.approx(value, rel=1e-9, abs=1e-12), (name, key)
        assert got[name]["ece"] == pytest.approx(_ece(labels[m], p[m]), rel=1e-9)
        assert f"{name}" in result.stdout
    # The protocols differ as they should: the near-wall points sit where this map is
    # greyest, so they are scored worse than free points along whole beams.
    assert got["hits+near-wall"]["brier"] > got["hits+free"]["brier"]
    # The union is also the top-level "maps" entry older readers use.
    assert summary["maps"][0]["auc"] == got["union"]["auc"]
    near = kinds == "near-wall"
    assert summary["kinds"]["near-wall"]["maps"]["walls"]["mean_p"] == pytest.approx(
        p[near].mean())
    assert "Protocol `hits+near-wall`" in (out / "results.md").read_text()


def test_a_truth_without_kinds_is_one_protocol(tmp_path):
    folder = tmp_path / "walls"
    folder.mkdir()
    write_geotiff(folder / "probability.tif", _wall_map(2), SPEC, nodata=np.nan)
    truth = tmp_path / "truth.csv"
    truth.write_text("x,y,label\n0,0,0\n4.95,0,1\n1,1,0\n-4.95,2,1\n")
    result = CliRunner().invoke(app, ["evaluate", str(folder), "--ground-truth", str(truth)])
    assert result.exit_code == 0, result.output
    assert result.stdout.splitlines()[0].startswith("map ")
    assert "union" not in result.stdout

