"""The held-out-scan split against a square room whose ranges are computed analytically."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy import stats
from typer.testing import CliRunner

from gpocc.config import MountConfig, SensorConfig, load_config
from gpocc.evaluation.split import heldout_mask, labelled_points, split_batch
from gpocc.io.scans import ScanBatch

HALF = 5.0  # the room is the square [-HALF, HALF]^2, metres
MOUNT = MountConfig(x_m=0.2, y_m=0.1, yaw_deg=10.0)
DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"


def _laser_origins(poses, mount):
    """Laser position and heading of each pose, with explicit rotation matrices."""
    origins, headings = [], []
    for x, y, th in poses:
        rot = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
        origins.append(np.array([x, y]) + rot @ np.array([mount.x_m, mount.y_m]))
        headings.append(th + math.radians(mount.yaw_deg))
    return np.array(origins), np.array(headings)


def _room_ranges(origins, headings, angles):
    """(S, B) distance from each laser to the room's walls along each beam."""
    phi = headings[:, None] + angles[None, :]
    c, s = np.cos(phi), np.sin(phi)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (HALF - origins[:, :1]) / c, (-HALF - origins[:, :1]) / c)
        ty = np.where(s > 0, (HALF - origins[:, 1:]) / s, (-HALF - origins[:, 1:]) / s)
    return np.minimum(np.abs(tx), np.abs(ty))


def room_batch(n_scans=23, n_beams=60, range_max=7.0, seed=0, sensor="bot"):
    """Scans in the square room; beams past range_max read +inf; a few NaN and -inf."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-2, 2, (n_scans, 2))
    poses = np.column_stack([xy, rng.uniform(-np.pi, np.pi, n_scans)])
    angles = np.linspace(-np.pi / 2, np.pi / 2, n_beams)
    origins, headings = _laser_origins(poses, MOUNT)
    ranges = _room_ranges(origins, headings, angles)
    ranges[ranges >= range_max] = np.inf
    ranges[rng.random(ranges.shape) < 0.05] = np.nan
    ranges[rng.random(ranges.shape) < 0.03] = -np.inf
    return ScanBatch(
        sensor=sensor,
        source="room",
        stamps=np.arange(n_scans) * 0.5 + 100.0,
        angles=angles,
        ranges=ranges,
        poses=poses,
        pose_covariances=np.zeros((n_scans, 3, 3)),
        range_min=0.05,
        range_max=range_max,
        has_pose_covariance=False,
    )


SENSOR = SensorConfig(name="bot", mount=MOUNT, no_return_free_m=3.0)


def test_heldout_indices():
    mask = heldout_mask(23, 4)
    np.testing.assert_array_equal(np.flatnonzero(mask), [3, 7, 11, 15, 19])
    assert heldout_mask(910, 10).sum() == 91


def test_labelled_points_lie_on_walls_and_inside_the_room():
    batch = room_batch()
    points, labels = labelled_points(batch, SENSOR, 4, np.random.default_rng(1))
    occupied = points[labels == 1]
    free = points[labels == 0]
    # Hits are exactly on a wall; free points strictly inside, at least 0.1 m from the
    # wall along their beam (so at least 0.1 * |cos| from the wall in the worst case).
    np.testing.assert_allclose(np.abs(occupied).max(axis=1), HALF, atol=1e-9)
    assert np.abs(free).max() < HALF
    # Counts from the ranges, independently of the code under test.
    r = batch.ranges
    hit = np.isfinite(r) & (r >= batch.range_min) & (r < batch.range_max)
    assert len(occupied) == hit.sum()
    free_beams = (hit & (r - 0.1 > 0.1)) | (r == np.inf)
    assert len(free) == 4 * free_beams.sum()


def test_free_distances_are_uniform_in_the_documented_interval():
    batch = room_batch(n_scans=1, n_beams=2000, seed=4)
    origin, heading = _laser_origins(batch.poses, MOUNT)
    points, labels = labelled_points(batch, SENSOR, 3, np.random.default_rng(2))
    offset = points[labels == 0] - origin[0]
    d = np.linalg.norm(offset, axis=1)
    # Each free point's beam, recovered from its direction, tells where it may lie.
    phi = np.arctan2(offset[:, 1], offset[:, 0])
    wall = _room_ranges(origin, np.zeros(1), phi)[0]
    end = np.where(wall < batch.range_max, wall - 0.1, SENSOR.no_return_free_m)
    assert d.min() >= 0.1 - 1e-9
    assert np.all(d < end + 1e-9)
    u = (d - 0.1) / (end - 0.1)
    assert stats.kstest(u, "uniform").pvalue > 1e-3
    # Both kinds of beam contributed free points.
    assert (wall < batch.range_max).any() and (wall >= batch.range_max).any()


def test_held_out_hits_are_the_endpoints_of_the_held_out_scans():
    batch = room_batch()
    result = split_batch(batch, SENSOR, every=4, rng=np.random.default_rng(0))
    held = [i for i in range(batch.n_scans) if i % 4 == 3]
    origins, headings = _laser_origins(batch.poses, MOUNT)
    expected = []
    for i in held:
        for b, r in enumerate(batch.ranges[i]):
            if np.isfinite(r) and batch.range_min <= r < batch.range_max:
                phi = headings[i] + batch.angles[b]
                expected.append(origins[i] + r * np.array([math.cos(phi), math.sin(phi)]))
    got = result.points[result.labels == 1]
    np.testing.assert_allclose(got, np.array(expected), atol=1e-9)
    assert result.n_heldout == len(held)


@pytest.mark.parametrize("every, keep, beams", [(4, 1, 1), (4, 2, 3), (3, 3, 7), (2, 1, 60)])
def test_training_counts_follow_every_keep_and_beam_strides(every, keep, beams):
    batch = room_batch()
    result = split_batch(
        batch, SENSOR, every=every, keep_every=keep, beam_every=beams,
        rng=np.random.default_rng(0),
    )
    remaining = [i for i in range(batch.n_scans) if i % every != every - 1]
    kept = remaining[::keep]
    assert result.train.n_scans == len(kept)
    assert result.train.n_beams == len(range(0, batch.n_beams, beams))
    np.testing.assert_array_equal(result.train.stamps, batch.stamps[kept])
    np.testing.assert_array_equal(result.train.ranges, batch.ranges[kept][:, ::beams])
    # The input had no pose covariance: the config's is filled in for the bag.
    assert result.train.has_pose_covariance
    np.testing.assert_array_equal(
        result.train.pose_covariances[0], SENSOR.pose_covariance_matrix
    )


def _write_input(tmp_path: Path, batches: list[ScanBatch]) -> tuple[Path, Path]:
    from gpocc.io.bags import write_bag

    bag = tmp_path / "room.mcap"
    topics = [(f"/{b.sensor}/scan_in", f"/{b.sensor}/pose_in") for b in batches]
    write_bag(bag, batches, topics, "mcap")
    sensors = [
        {
            "name": b.sensor,
            "scan_topic": t[0],
            "pose_topic": t[1],
            "mount": {"x_m": MOUNT.x_m, "y_m": MOUNT.y_m, "yaw_deg": MOUNT.yaw_deg},
            "no_return_free_m": 3.0,
            "range_variance_m2": 0.01 * (i + 1),
            "pose_covariance": [[0.01, 0, 0], [0, 0.02, 0], [0, 0, 0.001 * (i + 1)]],
        }
        for i, (b, t) in enumerate(zip(batches, topics, strict=True))
    ]
    cfg = tmp_path / "room.yaml"
    cfg.write_text(yaml.safe_dump({"seed": 3, "sensors": sensors}))
    return bag, cfg


def test_cli_split_writes_a_self_contained_training_bag(tmp_path):
    from gpocc.cli import app
    from gpocc.evaluation.truth import load_truth
    from gpocc.io.inputs import read_inputs

    batches = [
        room_batch(sensor="alpha"),
        room_batch(n_scans=17, n_beams=45, seed=5, sensor="beta"),
    ]
    bag, cfg = _write_input(tmp_path, batches)
    out = tmp_path / "split"
    args = ["split", str(bag), "--every", "4", "--out", str(out), "--config", str(cfg),
            "--keep-every", "2", "--beam-every", "3", "--free-per-beam", "2"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert {p.name for p in out.iterdir()} == {"train.mcap", "train.yaml", "heldout.csv"}

    train_config = load_config(out / "train.yaml")
    original = load_config(cfg)
    train = {b.sensor: b for b in read_inputs([out / "train.mcap"], train_config)}
    assert set(train) == {"alpha", "beta"}
    for b in batches:
        kept = [i for i in range(b.n_scans) if i % 4 != 3][::2]
        got = train[b.sensor]
        assert got.n_scans == len(kept)
        assert got.n_beams == len(range(0, b.n_beams, 3))
        np.testing.assert_allclose(got.poses, b.poses[kept], atol=1e-9)
        # LaserScan stores float32 ranges.
        expected = b.ranges[kept][:, ::3].astype(np.float32)
        np.testing.assert_array_equal(got.ranges.astype(np.float32), expected)
        # The config's pose covariance now travels in the bag itself.
        sensor = next(s for s in original.sensors if s.name == b.sensor)
        assert got.has_pose_covariance
        np.testing.assert_allclose(
            got.pose_covariances, np.broadcast_to(sensor.pose_covariance_matrix, (len(kept), 3, 3))
        )
        # Noise settings carried over; topics point into the training bag.
        trained = next(s for s in train_config.sensors if s.name == b.sensor)
        assert trained.range_variance_m2 == sensor.range_variance_m2
        assert trained.mount == sensor.mount
        assert trained.scan_topic == f"/{b.sensor}/scan"
    assert train_config.seed == original.seed
    # Only what differs from the defaults is written: a newer gpocc's defaults apply.
    written = yaml.safe_load((out / "train.yaml").read_text())
    assert set(written) == {"seed", "sensors"}

    points, labels = load_truth(out / "heldout.csv")
    np.testing.assert_allclose(np.abs(points[labels == 1]).max(axis=1), HALF, atol=1e-3)
    assert np.abs(points[labels == 0]).max() < HALF
    n_hits = sum(
        int((np.isfinite(b.ranges[3::4]) & (b.ranges[3::4] >= 0.05) & (b.ranges[3::4] < 7.0)).sum())
        for b in batches
    )
    assert (labels == 1).sum() == n_hits
    assert "held out" in result.stdout


def _heldout(folder: Path) -> str:
    return (folder / "heldout.csv").read_text()


def test_cli_split_is_seeded_and_refuses_existing_output(tmp_path):
    from gpocc.cli import app

    bag, cfg = _write_input(tmp_path, [room_batch()])
    runner = CliRunner()
    base = ["split", str(bag), "--every", "5", "--config", str(cfg)]
    assert runner.invoke(app, [*base, "--out", str(tmp_path / "a"), "--seed", "7"]).exit_code == 0
    assert runner.invoke(app, [*base, "--out", str(tmp_path / "b"), "--seed", "7"]).exit_code == 0
    assert _heldout(tmp_path / "a") == _heldout(tmp_path / "b")
    again = runner.invoke(app, [*base, "--out", str(tmp_path / "a")])
    assert again.exit_code == 2
    assert "--force" in again.stderr and "Traceback" not in again.output
    forced = runner.invoke(app, [*base, "--out", str(tmp_path / "a"), "--seed", "8", "--force"])
    assert forced.exit_code == 0
    assert _heldout(tmp_path / "a") != _heldout(tmp_path / "b")
    bad = runner.invoke(app, [*base, "--out", str(tmp_path / "c"), "--every", "1"])
    assert bad.exit_code == 2 and "--every" in bad.stderr and "Traceback" not in bad.output


def test_intel_split_holds_out_91_scans(tmp_path):
    log = DATA / "carmen" / "intel.gfs.log"
    if not log.is_file():
        pytest.skip(f"real data not found at {log}")
    from gpocc.cli import app
    from gpocc.evaluation.truth import load_truth
    from gpocc.io.inputs import read_inputs

    out = tmp_path / "intel"
    result = CliRunner().invoke(app, ["split", str(log), "--every", "10", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "scans held out:   91" in result.stdout
    train = read_inputs([out / "train.mcap"], load_config(out / "train.yaml"))
    assert sum(b.n_scans for b in train) == 910 - 91
    assert all(b.n_beams == 180 for b in train)
    points, labels = load_truth(out / "heldout.csv")
    assert 0 < (labels == 1).sum() <= 91 * 180
    assert len(points) == len(labels)


def test_cli_split_that_holds_out_no_scan_is_an_error_and_writes_nothing(tmp_path):
    from gpocc.cli import app

    batch = room_batch()
    bag, cfg = _write_input(tmp_path, [batch])
    out = tmp_path / "none"
    result = CliRunner().invoke(app, ["split", str(bag), "--every", str(batch.n_scans + 1),
                                      "--config", str(cfg), "--out", str(out)])
    assert result.exit_code == 2, result.output
    errors = [x for x in result.stderr.splitlines() if "error" in x]
    assert len(errors) == 1
    line = errors[0]
    assert "holds out no scan" in line and str(bag) in line
    assert f"{batch.n_scans}" in line and "Traceback" not in result.output
    assert not out.exists() and list(tmp_path.glob(".none*")) == []
    # The largest --every that holds a scan out still works.
    ok = CliRunner().invoke(app, ["split", str(bag), "--every", str(batch.n_scans),
                                  "--config", str(cfg), "--out", str(out)])
    assert ok.exit_code == 0, ok.output
