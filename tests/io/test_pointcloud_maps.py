"""Maps from a 3-D lidar's PointCloud2 bag with no config, against the synthetic room.

Oracles: the room's geometry (tests/cloud_scenes.py, cast in 3-D) for where walls and
the table top are; and the planar laser of the same run, mapped the same way, for how
good a map is: held-out truth points on the room's surfaces (occupied) and in its free
space (free), scored by ROC AUC (gpocc.evaluation.roc, checked against scikit-learn's
conventions in tests/evaluation/test_roc.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio
from cloud_scenes import (
    BOX,
    ROOM_RECT,
    TABLE,
    Lidar,
    LidarRun,
    add_planar_laser,
    inside,
    obstacle_distance,
    rect,
    room,
)
from rosbag_scenes import BagWriter
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.evaluation.roc import evaluate_scores

WALLS = np.array(rect(*ROOM_RECT) + rect(*BOX), float)


def build(path: Path, out: Path) -> None:
    result = CliRunner().invoke(app, ["build", str(path), "--resolution", "0.1", "--out",
                                      str(out), "--workers", "1", "--quiet"])
    assert result.exit_code == 0, result.output


def sample(out: Path, layer: str, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,) the layer's values at ``points`` (NaN outside the raster) and inside (N,)."""
    with rasterio.open(out / f"{layer}.tif") as ds:
        r, c = (np.asarray(v) for v in rasterio.transform.rowcol(ds.transform, points[:, 0],
                                                                   points[:, 1]))
        data = ds.read(1).astype(float)
    ok = (r >= 0) & (r < data.shape[0]) & (c >= 0) & (c < data.shape[1])
    values = np.full(points.shape[0], np.nan)
    values[ok] = data[r[ok], c[ok]]
    return values, ok


def test_lidar_bag_without_config_maps_walls_and_the_table_top(tmp_path):
    run = LidarRun(room(), Lidar(range_sd=0.02), cloud_t=0.31 + np.arange(12) * 1.6)
    bag = BagWriter("ros2-mcap")
    run.write(bag)
    path = bag.write(tmp_path / "run")
    build(path, tmp_path / "map")
    with rasterio.open(tmp_path / "map" / "class.tif") as ds:
        cls = ds.read(1)
        rows, cols = np.indices(cls.shape)
        xy = np.column_stack(rasterio.transform.xy(ds.transform, rows.ravel(), cols.ravel()))
    occupied = xy[cls.ravel() == 1]
    in_room = inside(occupied, ROOM_RECT)
    table = np.array(rect(*TABLE), float)
    # Occupied cells in the room are on a wall, in the cupboard or on the table top.
    near = np.minimum(obstacle_distance(occupied[in_room], WALLS),
                      obstacle_distance(occupied[in_room], table))
    near[inside(occupied[in_room], TABLE) | inside(occupied[in_room], BOX)] = 0.0
    assert in_room.sum() > 60 and near.max() <= 0.26
    # The table top at 0.75 m is in the band: where the lidar's rising rings reach its
    # height over its footprint they hit it (the lower rings pass under it, as a planar
    # laser at 0.45 m would, and clear the rest).
    assert inside(occupied, TABLE).sum() >= 5
    # The floor under the robot's path is free: no floor return became an obstacle.
    free_pts = np.column_stack([np.linspace(2.0, 5.0, 10), np.full(10, 2.5)])
    prob, _ = sample(tmp_path / "map", "probability", free_pts)
    assert np.nanmax(prob) < 0.35


def truth_points() -> tuple[np.ndarray, np.ndarray]:
    """Held-out truth: points on the walls (1) and in free space 0.15 m from them (0)."""
    occ = np.concatenate([a + np.linspace(0, 1, 200)[:, None] * (b - a) for a, b in WALLS])
    g = np.stack(np.meshgrid(np.arange(0.05, 8, 0.1), np.arange(0.05, 6, 0.1)),
                 -1).reshape(-1, 2)
    free = g[(obstacle_distance(g, WALLS) > 0.15) & ~inside(g, BOX)]
    return np.concatenate([occ, free]), np.r_[np.ones(len(occ)), np.zeros(len(free))]


@pytest.mark.parametrize("seed", [0])
def test_a_16_ring_lidar_maps_as_well_as_the_planar_laser_of_the_same_run(tmp_path, seed):
    run = LidarRun(room(table=False), Lidar(range_sd=0.02), cloud_t=0.31 + np.arange(16) * 1.25,
                   seed=seed)
    bag = BagWriter("mcap")
    run.write(bag)
    cloud = bag.write(tmp_path / "cloud.mcap")
    bag = BagWriter("mcap")
    run.write(bag)
    bag.messages = [m for m in bag.messages if m[1] != "/velodyne_points"]
    add_planar_laser(bag, run)
    laser = bag.write(tmp_path / "laser.mcap")
    points, labels = truth_points()
    aucs = {}
    for name, path in (("cloud", cloud), ("laser", laser)):
        build(path, tmp_path / name)
        scores, ok = sample(tmp_path / name, "probability", points)
        aucs[name] = evaluate_scores(name, labels, scores, ok).auc
    assert aucs["laser"] > 0.99
    assert aucs["cloud"] >= aucs["laser"] - 0.006, aucs
