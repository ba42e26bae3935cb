"""The experiment suite's OctoMap row (bench/octomap_map.py) on one scan in a square room:
OctoMap's sensor model (one hit 0.7, one miss 0.4) where the beams end and pass."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

pytest.importorskip("pyoctomap", reason="the bench extra (pyoctomap) is not installed")
from bench.octomap_map import octomap_probability  # noqa: E402
from gpocc.gridspec import GridSpec  # noqa: E402
from gpocc.io.bags import write_bag  # noqa: E402
from gpocc.io.rasters import read_raster, write_geotiff  # noqa: E402
from gpocc.io.scans import ScanBatch  # noqa: E402

HALF = 2.0


def test_one_scan_gives_octomap_hit_and_miss_probabilities(tmp_path):
    # One scan from (0.05, 0.05) (inside a cell, off its edges): 720 beams to the walls
    # of the square [-HALF, HALF]^2.
    origin = np.array([0.05, 0.05])
    angles = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    c, s = np.cos(angles), np.sin(angles)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (HALF - origin[0]) / c, (-HALF - origin[0]) / c)
        ty = np.where(s > 0, (HALF - origin[1]) / s, (-HALF - origin[1]) / s)
    ranges = np.minimum(np.abs(tx), np.abs(ty))[None, :] - 0.01  # just inside the wall
    batch = ScanBatch(sensor="bot", source="room", stamps=np.array([1.0]), angles=angles,
                      ranges=ranges, poses=np.array([[*origin, 0.0]]),
                      pose_covariances=np.zeros((1, 3, 3)), range_min=0.05, range_max=10.0,
                      has_pose_covariance=False)
    bag = tmp_path / "room.mcap"
    write_bag(bag, [batch], [("/scan", "/pose")], "mcap")
    cfg = tmp_path / "room.yaml"
    cfg.write_text(yaml.safe_dump({"sensors": [{"name": "bot", "scan_topic": "/scan",
                                                "pose_topic": "/pose"}]}))
    spec = GridSpec(x0=-3.0, y0=-3.0, resolution=0.1, width=60, height=60)
    like = tmp_path / "like.tif"
    write_geotiff(like, np.zeros((60, 60), np.float32), spec, nodata=np.nan)
    octomap_probability([bag], cfg, tmp_path / "octo", like)
    p, got_spec, _ = read_raster(tmp_path / "octo" / "probability.tif")
    assert got_spec == spec
    xs, ys = spec.cell_centres()
    depth = HALF - np.maximum(np.abs(xs), np.abs(ys))
    # Well inside the room every cell was passed once: OctoMap's miss probability.
    inner = (depth > 0.3) & (np.hypot(xs - origin[0], ys - origin[1]) < 1.2)
    np.testing.assert_allclose(p[inner], 0.4, atol=1e-6)
    # The cells holding the beam ends (the wall's inner row) were hit: 0.7.
    wall_row = (depth > 0.0) & (depth < 0.1) & (np.minimum(np.abs(xs), np.abs(ys)) < 1.5)
    assert np.nanmedian(p[wall_row]) == pytest.approx(0.7, abs=1e-6)
    # Behind the walls nothing was seen.
    assert np.all(np.isnan(p[depth < -0.2]))
