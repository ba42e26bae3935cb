"""``gpocc update``: logs added to a saved model give the model of all logs at once.

The logs are synthetic CARMEN logs of a two-room world (ray-cast against wall segments),
so the oracle is training on every log in one run (``--relearn`` must give exactly that
model; kept hyperparameters the same samples) and brute-force label counts.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from modelfiles import read_model_file, write_model_file
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.config import Config, SamplesConfig, TransformConfig, load_config
from gpocc.gp.model import load_model
from gpocc.io.frames import transform_poses
from gpocc.io.inputs import read_inputs
from gpocc.samples.beams import build_samples
from gpocc.samples.coverage import coverage_of_segments, union_coverage
from gpocc.samples.sampleset import SampleSet

runner = CliRunner()

#: Outer walls of a 10 x 6 m box and a wall at x = 5 with a doorway at y in [2.5, 3.5].
WALLS = [((0, 0), (10, 0)), ((10, 0), (10, 6)), ((10, 6), (0, 6)), ((0, 6), (0, 0)),
         ((5, 0), (5, 2.5)), ((5, 3.5), (5, 6))]
DOOR = ((5, 2.5), (5, 3.5))
BEAMS = 60

CONFIG = """
seed: 3
samples:
  min_label_share: 0.1
model:
  neighbours: 48
  training: {patches: 3, patch_size: 48, anneal_maxfun: 4, lbfgs_maxiter: 4,
             learn_input_noise_scale: true}
"""


def _ranges(x: float, y: float, yaw: float, walls: list) -> list[float]:
    """Ranges of a CARMEN fan (even count: -90 deg in steps of 180/n) to the nearest wall."""
    out = []
    for k in range(BEAMS):
        a = yaw - math.pi / 2 + k * math.pi / BEAMS
        d = np.array([math.cos(a), math.sin(a)])
        best = 81.9
        for (x1, y1), (x2, y2) in walls:
            e = np.array([x2 - x1, y2 - y1])
            m = np.array([[d[0], -e[0]], [d[1], -e[1]]])
            if abs(np.linalg.det(m)) < 1e-12:
                continue
            t, u = np.linalg.solve(m, [x1 - x, y1 - y])
            if t > 1e-9 and -1e-9 <= u <= 1 + 1e-9:
                best = min(best, t)
        out.append(best)
    return out


def write_log(path: Path, n_scans: int, door_closed: bool, start: float = 0.0,
              frame: TransformConfig | None = None) -> Path:
    """A robot driving along y = 3 in the left room, looking towards the door (east),
    as a CARMEN log; ``frame``: poses written in a frame this transform maps to the
    world (the recording's own map frame)."""
    walls = WALLS + ([DOOR] if door_closed else [])
    lines = []
    for i in range(n_scans):
        x, y, yaw = 1.0 + 3.0 * i / max(n_scans - 1, 1), 3.0 + 0.6 * math.sin(i), 0.2 * math.cos(i)
        r = _ranges(x, y, yaw, walls)
        px, py, pyaw = x, y, yaw
        if frame is not None:  # world -> recording frame: the transform's inverse
            c, s = math.cos(math.radians(frame.yaw_deg)), math.sin(math.radians(frame.yaw_deg))
            dx, dy = x - frame.x_m, y - frame.y_m
            px, py, pyaw = c * dx + s * dy, -s * dx + c * dy, yaw - math.radians(frame.yaw_deg)
        stamp = start + i
        lines.append(f"FLASER {BEAMS} {' '.join(f'{v:.4f}' for v in r)} {px:.6f} {py:.6f} "
                     f"{pyaw:.6f} {px:.6f} {py:.6f} {pyaw:.6f} {stamp} host {stamp}")
    path.write_text("\n".join(lines) + "\n")
    return path


def gpocc(*args: str, ok: bool = True):
    result = runner.invoke(app, [*args, "--quiet"])
    if ok:
        assert result.exit_code == 0, result.output
    return result


@pytest.fixture()
def logs(tmp_path: Path) -> dict[str, Path]:
    (tmp_path / "job.yaml").write_text(CONFIG)
    return {"config": tmp_path / "job.yaml",
            "a": write_log(tmp_path / "room_a.log", 14, door_closed=False),
            "b": write_log(tmp_path / "room_b.log", 10, door_closed=False, start=100.0)}


def train_a(logs: dict[str, Path], tmp_path: Path) -> None:
    gpocc("train", str(logs["a"]), "--config", str(logs["config"]),
          "--out", str(tmp_path / "a.npz"))


def _same_samples(one, two) -> None:
    for name in ("means", "covariances", "labels", "scan_ids", "pose_factors", "sensor_ids"):
        np.testing.assert_array_equal(getattr(one, name), getattr(two, name), err_msg=name)
    assert one.sensor_names == two.sensor_names


def test_relearned_update_is_the_model_of_all_logs(logs, tmp_path):
    train_a(logs, tmp_path)
    gpocc("train", str(logs["a"]), str(logs["b"]), "--config", str(logs["config"]),
          "--out", str(tmp_path / "ab.npz"))
    gpocc("update", str(tmp_path / "a.npz"), str(logs["b"]), "--relearn",
          "--out", str(tmp_path / "up.npz"))
    both, up = load_model(tmp_path / "ab.npz"), load_model(tmp_path / "up.npz")
    _same_samples(both.samples, up.samples)
    _same_samples(both.growth.pool.samples, up.growth.pool.samples)
    np.testing.assert_array_equal(both.growth.pool.vote_counts, up.growth.pool.vote_counts)
    assert both.kernel == up.kernel and both.noise_variance == up.noise_variance
    assert both.classifier == up.classifier
    # ... its temperature included, fitted on the same held-out beam points.
    assert both.training["classifier_points"] == up.training["classifier_points"] > 0
    assert both.classifier.temperature != 1.0
    assert both.input_noise_scale == up.input_noise_scale
    # Coverage: the union of A's raster and B's is the raster of all beams.
    np.testing.assert_array_equal(both.coverage.covered, up.coverage.covered)
    assert (both.coverage.x0, both.coverage.y0) == pytest.approx((up.coverage.x0,
                                                                  up.coverage.y0))
    assert [r.path for r in up.growth.records] == [str(logs["a"]), str(logs["b"])]
    assert [r.scans for r in up.growth.records] == [14, 10]
    assert up.growth.records[1].start_s == 100.0 and up.growth.records[1].end_s == 109.0


def _trained_and_relearned(logs: dict[str, Path], tmp_path: Path, config: str):
    """The models of ``train a b`` and of ``train a`` then ``update --relearn`` with b,
    both under ``config``."""
    (tmp_path / "job.yaml").write_text(config)
    job = str(tmp_path / "job.yaml")
    gpocc("train", str(logs["a"]), "--config", job, "--out", str(tmp_path / "a.npz"))
    gpocc("train", str(logs["a"]), str(logs["b"]), "--config", job,
          "--out", str(tmp_path / "ab.npz"))
    gpocc("update", str(tmp_path / "a.npz"), str(logs["b"]), "--relearn",
          "--out", str(tmp_path / "up.npz"))
    return tuple(load_model(tmp_path / n) for n in ("ab.npz", "up.npz"))


@pytest.mark.parametrize("weights", ["share", "count"])
def test_label_weights_of_an_update_count_every_log(logs, tmp_path, weights):
    """With ``samples.label_weights`` (and no ``min_label_share``, so the votes are kept
    for the weights alone) the updated model's factors are those of training on all
    logs: the votes of both logs add up."""
    both, up = _trained_and_relearned(logs, tmp_path, CONFIG.replace(
        "min_label_share: 0.1", f"label_weights: {weights}"))
    _same_samples(both.samples, up.samples)
    assert both.samples.noise_factors is not None and both.samples.noise_factors.max() > 1
    np.testing.assert_array_equal(both.samples.noise_factors, up.samples.noise_factors)
    assert both.kernel == up.kernel and both.classifier == up.classifier


def test_refined_update_lands_on_the_optimum_of_training_on_all_logs(logs, tmp_path):
    """The default update takes Fisher-scoring steps from the model's values on the
    patches training on all logs draws (same samples, same seed): it stops within a
    hundredth of a nat of the point training reaches by annealing from the initial values
    and L-BFGS-B run to convergence, not at the model's own."""
    (tmp_path / "job.yaml").write_text(CONFIG.replace("lbfgs_maxiter: 4", "lbfgs_maxiter: 200"))
    job = str(tmp_path / "job.yaml")
    gpocc("train", str(logs["a"]), "--config", job, "--out", str(tmp_path / "a.npz"))
    gpocc("train", str(logs["a"]), str(logs["b"]), "--config", job,
          "--out", str(tmp_path / "ab.npz"))
    gpocc("update", str(tmp_path / "a.npz"), str(logs["b"]), "--refine-iterations", "200",
          "--out", str(tmp_path / "up.npz"))
    gpocc("update", str(tmp_path / "a.npz"), str(logs["b"]), "--keep",
          "--out", str(tmp_path / "kept.npz"))
    cut = runner.invoke(app, ["update", str(tmp_path / "a.npz"), str(logs["b"]),
                              "--refine-iterations", "1", "--out", str(tmp_path / "short.npz")])
    assert cut.exit_code == 0, cut.output
    # One step cannot reach the optimum (below): the log says so and how to go on.
    assert "Fisher scoring stopped after 1 steps, its budget" in cut.output
    assert "--refine-iterations raises it" in cut.output
    a, both, up, kept, short = (load_model(tmp_path / n)
                                for n in ("a.npz", "ab.npz", "up.npz", "kept.npz", "short.npz"))
    assert up.training["hyperparameters"] == "refined"
    assert up.training["refine_iterations"] == 200
    assert kept.training["hyperparameters"] == "kept" and kept.kernel == a.kernel
    assert "refine_iterations" not in kept.training
    # One step from the model's values, short of the optimum (its evaluations: the
    # initial values, the model's, and the step's).
    assert short.training["refine_iterations"] == 1
    assert short.training["evaluations"] < up.training["evaluations"]
    assert short.training["log_marginal_likelihood"] < up.training["log_marginal_likelihood"]

    def values(m):
        return np.append(m.kernel.theta, [math.log(m.noise_variance),
                                          math.log(m.input_noise_scale)])

    # The model of A alone is elsewhere; the refined update is at training's optimum (in
    # value: along a flat direction a hundredth of a nat leaves the parameters some room).
    away = np.abs(values(a) - values(both)).max()
    assert away > 0.05
    assert np.abs(values(up) - values(both)).max() < 0.2 * away
    assert up.training["log_marginal_likelihood"] == pytest.approx(
        both.training["log_marginal_likelihood"], abs=0.02)
    assert up.training["evaluations"] < both.training["evaluations"]
    assert short.training["evaluations"] == 3
    assert np.abs(values(short) - values(both)).max() > 1e-3


def test_no_refine_iterations_is_one_error_line(logs, tmp_path):
    train_a(logs, tmp_path)
    result = runner.invoke(app, ["update", str(tmp_path / "a.npz"), str(logs["b"]),
                                 "--refine-iterations", "0", "--out", str(tmp_path / "up.npz")])
    assert result.exit_code != 0
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "--refine-iterations must be at least 1" in lines[0]
    assert not (tmp_path / "up.npz").exists()


def test_relearn_and_keep_together_are_one_error_line(logs, tmp_path):
    train_a(logs, tmp_path)
    result = runner.invoke(app, ["update", str(tmp_path / "a.npz"), str(logs["b"]),
                                 "--relearn", "--keep", "--out", str(tmp_path / "up.npz")])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "exclude each other" in lines[0]
    assert not (tmp_path / "up.npz").exists()


def test_kept_hyperparameters_ids_and_sensors_continue(logs, tmp_path):
    train_a(logs, tmp_path)
    kept = gpocc("update", str(tmp_path / "a.npz"), str(logs["b"]), "--keep",
                 "--out", str(tmp_path / "ab.npz")).output
    c = write_log(tmp_path / "room_a_again.log", 6, door_closed=False, start=200.0)
    gpocc("update", str(tmp_path / "ab.npz"), str(c), "--out", str(tmp_path / "abc.npz"))
    a, ab, abc = (load_model(tmp_path / n) for n in ("a.npz", "ab.npz", "abc.npz"))
    if ab.training["hyperparameters"] == "kept":
        assert ab.kernel == a.kernel and ab.input_noise_scale == a.input_noise_scale
        # Its likelihood is A's, on A's patches: said so, not shown as the update's own.
        assert "(kept with the hyperparameters: the model's own, on its own patches)" in kept
        assert "(kept by the last update" in gpocc("info", str(tmp_path / "ab.npz")).output
    # Without sensors in the config a CARMEN log's sensor is its file stem: B and C add
    # sensors after A's, and their scan ids follow all scans read before.
    assert abc.samples.sensor_names == ("room_a", "room_b", "room_a_again")
    ids, sensors = abc.growth.pool.samples.scan_ids, abc.growth.pool.samples.sensor_ids
    assert set(np.unique(ids[sensors == 0])) <= set(range(14))
    assert set(np.unique(ids[sensors == 1])) <= set(range(14, 24))
    assert set(np.unique(ids[sensors == 2])) <= set(range(24, 30))
    assert abc.growth.pool.n_scans == 30
    # The samples are those of training on all three logs (scaled by the model's g).
    cfg = load_config(logs["config"])
    direct = build_samples(read_inputs([logs["a"], logs["b"], c], cfg), cfg)
    np.testing.assert_array_equal(abc.samples.means, direct.means)
    np.testing.assert_array_equal(abc.samples.scan_ids, direct.scan_ids)
    np.testing.assert_allclose(abc.samples.covariances,
                               direct.covariances * abc.input_noise_scale, rtol=1e-12)
    info = gpocc("info", str(tmp_path / "abc.npz")).output
    assert "room_b.log: 10 scans, time span 100.000 .. 109.000 s" in info
    labels = [u["hyperparameters"] for u in abc.training["updates"]]
    assert labels[0] == ab.training["hyperparameters"]
    assert (f"updates: 2 (1 input(s), hyperparameters {labels[0]}; 1 input(s), "
            f"hyperparameters {labels[1]})") in info


def test_coverage_union_is_the_coverage_of_all_segments():
    rng = np.random.default_rng(5)
    start, end = rng.uniform(-3, 7, (40, 2)), rng.uniform(-5, 4, (40, 2))
    whole = coverage_of_segments(start, end)
    parts = union_coverage(coverage_of_segments(start[:25], end[:25]),
                           coverage_of_segments(start[25:] + 9.0, end[25:] + 9.0))
    moved = coverage_of_segments(np.vstack([start[:25], start[25:] + 9.0]),
                                 np.vstack([end[:25], end[25:] + 9.0]))
    assert parts.covered.shape == moved.covered.shape
    assert (parts.x0, parts.y0) == pytest.approx((moved.x0, moved.y0))
    mismatched = np.count_nonzero(parts.covered != moved.covered)
    assert mismatched <= 2  # beam points on a cell edge may round to either side
    assert whole.covered.sum() > 0 and parts.covered.sum() >= whole.covered.sum() - 2


def test_an_older_model_file_loads_and_updates(logs, tmp_path):
    train_a(logs, tmp_path)
    arrays, meta = read_model_file(tmp_path / "a.npz")
    old = tmp_path / "old.npz"
    meta["format_version"] = 2
    del meta["growth"]
    del meta["classifier"]["temperature"]  # since format 4
    del meta["config"]["model"]["training"]["classifier_temperature"]
    write_model_file(old, {k: v for k, v in arrays.items() if not k.startswith(
        ("pool_", "vote_", "calibration_"))}, meta)
    loaded = load_model(old)
    assert loaded.growth is None
    # Trained before the temperature existed: it had none, and an update adds none.
    assert loaded.config.model.training.classifier_temperature == "none"
    assert loaded.classifier.temperature == 1.0
    result = runner.invoke(app, ["update", str(old), str(logs["b"]), "--out",
                                 str(tmp_path / "new.npz")])
    assert result.exit_code == 0, result.output
    assert "does not keep the label votes" in result.output
    new = load_model(tmp_path / "new.npz")
    assert new.classifier.temperature == 1.0
    first_new = int(loaded.samples.scan_ids.max()) + 1
    b_ids = new.growth.pool.samples.scan_ids[new.growth.pool.samples.sensor_ids == 1]
    assert b_ids.min() >= first_new
    assert new.growth.pool.n_scans == first_new + 10
    info = gpocc("info", str(tmp_path / "new.npz")).output
    assert "not recorded: added by an older gpocc" in info


SENSOR = "sensors: [{name: room_a, inputs: ['room_a*'], range_variance_m2: %s}]\n"


@pytest.mark.parametrize("config, words", [
    (CONFIG.replace("neighbours: 48", "neighbours: 48\n  kernel: se"),
     "key 'model.kernel' differs from the model"),
    (CONFIG.replace("min_label_share: 0.1", "min_label_share: 0.2"),
     "key 'samples.min_label_share' differs"),
    (CONFIG + SENSOR % "0.01", "sensors[0] ('room_a') differs from the sensor"),
])
def test_a_config_at_odds_with_the_model_is_one_error_line(logs, tmp_path, config, words):
    """A model of another kernel, other sample rules or another sensor set-up."""
    (tmp_path / "job.yaml").write_text(CONFIG + SENSOR % "0.0004")
    gpocc("train", str(logs["a"]), "--out", str(tmp_path / "a.npz"),
          "--config", str(tmp_path / "job.yaml"))
    (tmp_path / "other.yaml").write_text(config)
    result = runner.invoke(app, ["update", str(tmp_path / "a.npz"), str(logs["b"]),
                                 "--config", str(tmp_path / "other.yaml"),
                                 "--out", str(tmp_path / "new.npz")])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and words in lines[0] and "Traceback" not in result.output
    assert not (tmp_path / "new.npz").exists()


def test_a_setting_the_job_config_does_not_state_is_the_models(logs, tmp_path):
    """A model trained with settings other than today's defaults (as one trained before a
    default changed): the job's config, which does not state them, updates it with the
    model's settings; the same config stating another value is refused."""
    (tmp_path / "old.yaml").write_text(CONFIG.replace(
        "min_label_share: 0.1", "min_label_share: 0.1\n  label_weights: share").replace(
        "learn_input_noise_scale: true}", "learn_input_noise_scale: true,\n"
        "             classifier_offset_range: wide}"))
    gpocc("train", str(logs["a"]), "--out", str(tmp_path / "a.npz"),
          "--config", str(tmp_path / "old.yaml"))
    (tmp_path / "job.yaml").write_text(CONFIG)
    gpocc("update", str(tmp_path / "a.npz"), str(logs["b"]), "--config",
          str(tmp_path / "job.yaml"), "--out", str(tmp_path / "new.npz"))
    updated = load_model(tmp_path / "new.npz").config
    assert updated.samples.label_weights == "share"
    assert updated.model.training.classifier_offset_range == "wide"
    (tmp_path / "other.yaml").write_text(CONFIG.replace(
        "min_label_share: 0.1", "min_label_share: 0.1\n  label_weights: count"))
    result = gpocc("update", str(tmp_path / "a.npz"), str(logs["b"]), "--config",
                   str(tmp_path / "other.yaml"), "--out", str(tmp_path / "other.npz"), ok=False)
    assert result.exit_code == 2 and "key 'samples.label_weights' differs" in result.output
    (tmp_path / "empty.yaml").write_text("")
    gpocc("update", str(tmp_path / "a.npz"), str(logs["b"]), "--config",
          str(tmp_path / "empty.yaml"), "--out", str(tmp_path / "empty.npz"))


def test_an_input_already_in_the_model_is_one_error_line(logs, tmp_path):
    gpocc("train", str(logs["a"]), "--out", str(tmp_path / "a.npz"),
          "--config", str(logs["config"]))
    copy = tmp_path / "renamed.log"
    shutil.copy(logs["a"], copy)
    for args in ([str(logs["a"])], [str(copy)], [str(logs["b"]), str(logs["b"])]):
        result = runner.invoke(app, ["update", str(tmp_path / "a.npz"), *args,
                                     "--out", str(tmp_path / "new.npz")])
        assert result.exit_code == 2
        lines = result.output.strip().splitlines()
        assert len(lines) == 1 and "already in the model" in lines[0], result.output
        assert not (tmp_path / "new.npz").exists()


def test_update_then_map_is_deterministic(logs, tmp_path):
    gpocc("train", str(logs["a"]), "--out", str(tmp_path / "a.npz"),
          "--config", str(logs["config"]))
    maps = []
    for k in range(2):
        gpocc("update", str(tmp_path / "a.npz"), str(logs["b"]), "--out",
              str(tmp_path / f"u{k}.npz"))
        gpocc("map", str(tmp_path / f"u{k}.npz"), "--resolution", "0.25", "--workers", "1",
              "--out", str(tmp_path / f"m{k}"))
        maps.append(tmp_path / f"m{k}")
    import rasterio

    for layer in ("probability.tif", "variance.tif", "class.tif"):
        with rasterio.open(maps[0] / layer) as one, rasterio.open(maps[1] / layer) as two:
            np.testing.assert_array_equal(one.read(), two.read())
    meta = json.loads((maps[0] / "metadata.json").read_text())
    assert [e["path"] for e in meta["inputs"]] == [str(logs["a"]), str(logs["b"])]
    assert meta["inputs"][1]["scans"] == 10
    assert meta["inputs"][1]["transform"] == {"x_m": 0.0, "y_m": 0.0, "yaw_deg": 0.0}


def _door_labels(samples, cell_m: float) -> np.ndarray:
    """Labels of the samples in the doorway (x within a cell of 5, 2.6 < y < 3.4)."""
    near = (np.abs(samples.means[:, 0] - 5.0) < cell_m) & \
        (np.abs(samples.means[:, 1] - 3.0) < 0.4)
    return samples.labels[near]


@pytest.mark.parametrize("open_scans, closed_scans", [(30, 2), (2, 30)])
def test_label_votes_across_recordings_decide_a_door(tmp_path, open_scans, closed_scans):
    """Door open in log A, closed in log B: as within one log, a cell's label seen in
    under min_label_share of its samples (over all logs) is dropped."""
    # No clearance: it would drop free samples near kept hits, which the votes do not see.
    (tmp_path / "job.yaml").write_text(CONFIG.replace(
        "min_label_share: 0.1", "min_label_share: 0.1\n  free_clearance_m: 0.0"))
    a = write_log(tmp_path / "open.log", open_scans, door_closed=False)
    b = write_log(tmp_path / "closed.log", closed_scans, door_closed=True, start=500.0)
    gpocc("train", str(a), "--config", str(tmp_path / "job.yaml"),
          "--out", str(tmp_path / "a.npz"))
    gpocc("update", str(tmp_path / "a.npz"), str(b), "--out", str(tmp_path / "ab.npz"))
    model = load_model(tmp_path / "ab.npz")
    # Brute force: every sample of both logs, unthinned, counted per doorway cell.
    cfg = load_config(tmp_path / "job.yaml")
    raw = build_samples(read_inputs([a, b], cfg), Config(samples=SamplesConfig(
        thin_cell_m=0.0, free_clearance_m=0.0)))
    cell = cfg.samples.thin_cell_m
    keys = np.floor(raw.means / cell).astype(np.int64)
    door_cells = {tuple(k) for k in np.floor(model.samples.means[
        (np.abs(model.samples.means[:, 0] - 5.0) < cell)
        & (np.abs(model.samples.means[:, 1] - 3.0) < 0.4)] / cell).astype(np.int64)}
    assert door_cells
    for cell_key in door_cells:
        inside = (keys == cell_key).all(axis=1)
        share_hit = np.mean(raw.labels[inside] > 0)
        kept = model.samples.labels[(np.floor(model.samples.means / cell).astype(np.int64)
                                     == cell_key).all(axis=1)]
        assert (1.0 in kept) == (share_hit >= 0.1), (cell_key, share_hit)
        assert (-1.0 in kept) == (np.mean(raw.labels[inside] < 0) >= 0.1), (cell_key,
                                                                           share_hit)
    # What a user gets: the state seen most often holds most of the doorway; the other
    # keeps the cells where free samples (every free_spacing_m along a beam) are sparse.
    labels = _door_labels(model.samples, cell)
    assert (np.count_nonzero(labels > 0) > np.count_nonzero(labels < 0)) == \
        (closed_scans > open_scans)


def test_a_recording_in_another_frame_lands_in_place(tmp_path):
    frame = TransformConfig(x_m=2.0, y_m=-1.5, yaw_deg=35.0)
    world = write_log(tmp_path / "room_w.log", 8, door_closed=True)
    other = write_log(tmp_path / "room_o.log", 8, door_closed=True, frame=frame)
    (tmp_path / "job.yaml").write_text(
        "inputs: [{path: room_o.log, transform: {x_m: 2.0, y_m: -1.5, yaw_deg: 35.0}}]\n")
    cfg = load_config(tmp_path / "job.yaml")
    moved, = read_inputs([other], cfg)
    direct, = read_inputs([world], cfg)
    np.testing.assert_allclose(moved.poses, direct.poses, atol=2e-6)
    gpocc("train", str(world), "--config", str(tmp_path / "job.yaml"), "--out",
          str(tmp_path / "w.npz"))
    gpocc("update", str(tmp_path / "w.npz"), str(other), "--config",
          str(tmp_path / "job.yaml"), "--out", str(tmp_path / "wo.npz"))
    record = load_model(tmp_path / "wo.npz").growth.records[1]
    assert record.transform == (2.0, -1.5, 35.0)
    assert "transform x 2 m, y -1.5 m, yaw 35 deg" in gpocc("info", str(tmp_path / "wo.npz")).output


def test_transformed_pose_covariance_matches_monte_carlo():
    rng = np.random.default_rng(2)
    t = TransformConfig(x_m=-3.0, y_m=4.0, yaw_deg=120.0)
    pose = np.array([1.0, 2.0, 0.3])
    cov = np.array([[0.04, 0.01, 0.002], [0.01, 0.09, -0.003], [0.002, -0.003, 0.01]])
    draws = rng.multivariate_normal(pose, cov, 200_000)
    moved, _ = transform_poses(draws, np.zeros((len(draws), 3, 3)), t)
    _, got = transform_poses(pose[None], cov[None], t)
    np.testing.assert_allclose(got[0], np.cov(moved.T), atol=2e-3)


def test_kept_hyperparameters_worse_than_the_initial_values_are_learned_again(logs, tmp_path):
    """A model whose learning ended in a kernel far too smooth for the walls: on all logs
    it explains the data worse than learning's starting point, so the update learns the
    hyperparameters again and gives the model of training on all logs."""
    import dataclasses

    from gpocc.gp.kernels import NeuralNetworkKernel
    from gpocc.gp.model import save_model

    train_a(logs, tmp_path)
    model = load_model(tmp_path / "a.npz")
    smooth = dataclasses.replace(model, kernel=NeuralNetworkKernel(
        signal_variance=100.0, bias_variance=500.0, weight_variance=(0.05, 0.05)))
    save_model(smooth, tmp_path / "smooth.npz")
    result = runner.invoke(app, ["update", str(tmp_path / "smooth.npz"), str(logs["b"]),
                                 "--out", str(tmp_path / "up.npz")])
    assert result.exit_code == 0, result.output
    assert "worse than the config's initial values" in result.output
    gpocc("train", str(logs["a"]), str(logs["b"]), "--config", str(logs["config"]),
          "--out", str(tmp_path / "ab.npz"))
    up, both = load_model(tmp_path / "up.npz"), load_model(tmp_path / "ab.npz")
    assert up.kernel == both.kernel and up.classifier == both.classifier
    assert up.training["hyperparameters"].startswith("relearned")
    # The trained model's own hyperparameters pass the check: they are kept.
    gpocc("update", str(tmp_path / "a.npz"), str(logs["b"]), "--keep",
          "--out", str(tmp_path / "k.npz"))
    kept = load_model(tmp_path / "k.npz")
    assert kept.kernel == model.kernel and kept.training["hyperparameters"] == "kept"


@pytest.mark.parametrize("edit, words", [
    (lambda meta, arrays: meta["growth"].update(n_scans=3), "n_scans is 3"),
    (lambda meta, arrays: arrays.pop("vote_counts"), "lacks the arrays ['vote_counts']"),
    (lambda meta, arrays: arrays.update(vote_counts=-arrays["vote_counts"]), "label votes"),
    (lambda meta, arrays: meta["growth"]["inputs"].append({"scans": 1}), "has no path"),
    (lambda meta, arrays: meta.pop("growth"), "growth arrays without their record"),
])
def test_a_damaged_update_state_is_one_error_line(logs, tmp_path, edit, words):
    train_a(logs, tmp_path)
    arrays, meta = read_model_file(tmp_path / "a.npz")
    arrays.pop("metadata")
    edit(meta, arrays)
    write_model_file(tmp_path / "bad.npz", arrays, meta)
    result = runner.invoke(app, ["update", str(tmp_path / "bad.npz"), str(logs["b"]),
                                 "--out", str(tmp_path / "new.npz")])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and words in lines[0] and "re-create it" in lines[0], lines
    assert not (tmp_path / "new.npz").exists()


def test_calibration_points_of_beams_offsets_join(logs, tmp_path):
    """``classifier_offset: beams``: the held-out scans of every log calibrate the
    refitted classifier, numbered like the samples' scans."""
    (tmp_path / "beams.yaml").write_text(CONFIG.replace(
        "  training: {", "  training: {classifier_offset: beams, calibration_every: 3, "))
    gpocc("train", str(logs["a"]), "--config", str(tmp_path / "beams.yaml"),
          "--out", str(tmp_path / "a.npz"))
    gpocc("update", str(tmp_path / "a.npz"), str(logs["b"]), "--out", str(tmp_path / "ab.npz"))
    a, ab = load_model(tmp_path / "a.npz"), load_model(tmp_path / "ab.npz")
    held = np.unique(ab.growth.calibration.scan_ids)
    # Every 3rd scan of each log (index % 3 == 2): A's 14 scans, then B's 10 after them.
    np.testing.assert_array_equal(held, [2, 5, 8, 11, 14 + 2, 14 + 5, 14 + 8])
    assert len(ab.growth.calibration.points) > len(a.growth.calibration.points)
    assert ab.training["classifier_offset"] == "beams"


def test_split_of_a_moved_recording_writes_poses_in_the_job_frame(tmp_path):
    frame = TransformConfig(x_m=2.0, y_m=-1.5, yaw_deg=35.0)
    other = write_log(tmp_path / "room_o.log", 12, door_closed=True, frame=frame)
    (tmp_path / "job.yaml").write_text(
        "inputs: [{path: '*', transform: {x_m: 2.0, y_m: -1.5, yaw_deg: 35.0}}]\n")
    gpocc("split", str(other), "--every", "4", "--config", str(tmp_path / "job.yaml"),
          "--out", str(tmp_path / "held"))
    cfg = load_config(tmp_path / "held" / "train.yaml")
    assert cfg.inputs == ()
    moved, = read_inputs([tmp_path / "held" / "train.mcap"], cfg)
    world, = read_inputs([write_log(tmp_path / "room_w.log", 12, door_closed=True)], Config())
    kept = np.flatnonzero(np.arange(12) % 4 != 3)
    np.testing.assert_allclose(moved.poses[:, :2], world.poses[kept, :2], atol=1e-5)


def test_a_pose_only_scale_survives_an_update(logs, tmp_path):
    """A model that scales the pose part of its inputs only: relearned on all logs by
    ``update`` it is the model of training on all logs (samples, scale, kernel)."""
    both, up = _trained_and_relearned(logs, tmp_path, CONFIG.replace(
        "learn_input_noise_scale: true}",
        "learn_input_noise_scale: true, input_noise_scale_part: pose}"))
    assert up.config.model.training.input_noise_scale_part == "pose"
    _same_samples(both.samples, up.samples)
    assert both.input_noise_scale == up.input_noise_scale != 1.0
    assert both.kernel == up.kernel and both.classifier == up.classifier


def _raw_arrays(path: Path) -> tuple[dict[str, np.ndarray], dict]:
    with np.load(path) as data:
        arrays = dict(data)
    return arrays, json.loads(bytes(arrays.pop("metadata")).decode())


@pytest.mark.parametrize("config_text", [
    CONFIG,
    CONFIG.replace("neighbours: 48", "neighbours: 48\n  input_noise: false"),
    CONFIG.replace("learn_input_noise_scale: true}",
                   "learn_input_noise_scale: true, input_noise_scale_part: pose}"),
])
def test_a_model_file_stores_its_samples_as_rows_of_its_pool(logs, tmp_path, config_text):
    from gpocc.commands.train import learn_model
    from gpocc.gp.model import save_model

    (tmp_path / "job.yaml").write_text(config_text)
    config = load_config(tmp_path / "job.yaml")
    model = learn_model([logs["a"], logs["b"]], config)
    assert model.growth is not None and len(model.samples) < len(model.growth.pool.samples)
    save_model(model, tmp_path / "m.npz")
    arrays, _ = _raw_arrays(tmp_path / "m.npz")
    assert "sample_index" in arrays and "means" not in arrays and "covariances" not in arrays
    loaded = load_model(tmp_path / "m.npz")
    # Bit for bit the samples the model was learned and calibrated on.
    for name in ("means", "covariances", "labels", "scan_ids", "pose_factors", "sensor_ids"):
        mine, theirs = getattr(model.samples, name), getattr(loaded.samples, name)
        assert mine.dtype == theirs.dtype, name
        np.testing.assert_array_equal(mine, theirs, err_msg=name)
    assert loaded.samples.sensor_names == model.samples.sensor_names
    assert (loaded.samples.noise_factors is None) == (model.samples.noise_factors is None)
    if not config.model.input_noise:
        assert not loaded.samples.covariances.any()


def test_samples_that_are_not_rows_of_the_pool_are_stored_whole(logs, tmp_path):
    train_a(logs, tmp_path)
    model = load_model(tmp_path / "a.npz")
    from gpocc.gp.model import save_model

    # A model whose samples training did not make from its pool (here: moved 1 mm).
    moved = dataclasses.replace(model, samples=dataclasses.replace(
        model.samples, means=model.samples.means + 1e-3))
    save_model(moved, tmp_path / "moved.npz")
    arrays, _ = _raw_arrays(tmp_path / "moved.npz")
    assert "sample_index" not in arrays and "means" in arrays
    np.testing.assert_array_equal(load_model(tmp_path / "moved.npz").samples.means,
                                  moved.samples.means)


def test_pool_rows_agree_with_a_brute_force_search():
    from gpocc.gp.modelfile import pool_rows

    rng = np.random.default_rng(5)
    n = 300
    pool = SampleSet(
        means=np.round(rng.uniform(-5, 5, (n, 2)), 1), covariances=np.zeros((n, 2, 2)),
        labels=rng.choice([-1.0, 1.0], n), scan_ids=rng.integers(0, 20, n),
        pose_factors=np.zeros((n, 2, 3)), sensor_ids=rng.integers(0, 2, n).astype(np.int16),
        sensor_names=("a", "b"))
    kept = np.sort(rng.choice(n, 120, replace=False))
    samples = pool.subset(kept)

    def brute_force(sub):
        rows, start = [], 0
        for i in range(len(sub)):
            for j in range(start, n):
                if (np.array_equal(pool.means[j], sub.means[i])
                        and pool.labels[j] == sub.labels[i]
                        and pool.scan_ids[j] == sub.scan_ids[i]
                        and pool.sensor_ids[j] == sub.sensor_ids[i]):
                    rows.append(j)
                    start = j + 1
                    break
            else:
                return None
        return np.array(rows)

    np.testing.assert_array_equal(pool_rows(pool, samples), brute_force(samples))
    assert pool_rows(pool, samples.subset(np.arange(len(samples))[::-1])) is None
    relabelled = dataclasses.replace(samples, labels=-samples.labels)
    assert brute_force(relabelled) is None and pool_rows(pool, relabelled) is None


@pytest.mark.parametrize("edit, words", [
    (lambda arrays: arrays.update(sample_index=arrays["sample_index"][::-1].copy()),
     "not ascending rows"),
    (lambda arrays: arrays.update(sample_index=arrays["sample_index"] + 10**6),
     "not ascending rows"),
    (lambda arrays: arrays.update(sample_index=arrays["sample_index"].astype(float)),
     "not ascending rows"),
    (lambda arrays: [arrays.pop(k) for k in list(arrays) if k.startswith(
        ("pool_", "vote_", "calibration_"))], "growth pool it lacks"),
])
def test_a_damaged_sample_index_is_one_error_line(logs, tmp_path, edit, words):
    train_a(logs, tmp_path)
    arrays, meta = _raw_arrays(tmp_path / "a.npz")
    edit(arrays)
    if "pool_means" not in arrays:
        meta.pop("growth")
    write_model_file(tmp_path / "bad.npz", arrays, meta)
    result = runner.invoke(app, ["map", str(tmp_path / "bad.npz"), "--resolution", "0.2",
                                 "--out", str(tmp_path / "map")])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and words in lines[0] and "re-create it" in lines[0], lines
    assert not (tmp_path / "map").exists()


def test_rows_of_the_pool_are_checked_in_blocks(logs, tmp_path, monkeypatch):
    from gpocc.gp import model as model_module

    train_a(logs, tmp_path)
    model = load_model(tmp_path / "a.npz")
    monkeypatch.setattr(model_module, "_CHECK_ROWS", 7)  # many blocks, a short last one
    assert len(model.samples) % 7
    model_module.save_model(model, tmp_path / "blocks.npz")
    assert "sample_index" in _raw_arrays(tmp_path / "blocks.npz")[0]
    np.testing.assert_array_equal(load_model(tmp_path / "blocks.npz").samples.covariances,
                                  model.samples.covariances)
    # A covariance in the last block that the pool does not give: stored whole.
    covariances = model.samples.covariances.copy()
    covariances[-1] *= 1.5
    changed = dataclasses.replace(model, samples=dataclasses.replace(
        model.samples, covariances=covariances))
    model_module.save_model(changed, tmp_path / "changed.npz")
    arrays, _ = _raw_arrays(tmp_path / "changed.npz")
    assert "sample_index" not in arrays
    np.testing.assert_array_equal(arrays["covariances"], covariances)


def test_an_inputs_entry_matches_by_trailing_folders_and_a_stray_one_is_noted(tmp_path,
                                                                              capsys):
    """An entry written relative to the config's folder (``o/room.log``) names the input
    wherever the job runs from; an entry that names no input says so (its transform
    applied to nothing, silently)."""
    from gpocc.io.frames import entry_matches

    assert entry_matches("o/room.log", Path("/data/site/o/room.log"))
    assert entry_matches("room*.log", Path("x/room_2.log"))
    assert entry_matches("site/*/room.log", Path("/data/site/o/room.log"))
    assert not entry_matches("p/room.log", Path("/data/site/o/room.log"))
    assert not entry_matches("room.log", Path("/data/site/o/room.log.bak"))
    frame = TransformConfig(x_m=2.0, y_m=-1.5, yaw_deg=35.0)
    (tmp_path / "o").mkdir()
    world = write_log(tmp_path / "room_w.log", 8, door_closed=True)
    other = write_log(tmp_path / "o" / "room.log", 8, door_closed=True, frame=frame)
    (tmp_path / "job.yaml").write_text(
        "inputs: [{path: o/room.log, transform: {x_m: 2.0, y_m: -1.5, yaw_deg: 35.0}},\n"
        "         {path: gone.log, transform: {x_m: 9.0}}]\n")
    cfg = load_config(tmp_path / "job.yaml")
    moved, direct = read_inputs([other, world], cfg)
    np.testing.assert_allclose(moved.poses, direct.poses, atol=2e-6)
    err = capsys.readouterr().err
    assert "inputs entry 'gone.log' matches none of these inputs" in err
    assert "'o/room.log' matches none" not in err


def test_an_update_keeps_the_models_anchor_origin_unless_its_config_states_one(logs,
                                                                              tmp_path):
    """A pinned anchor lattice (map.anchor_origin_m) is what lets the maps of a model and
    of its update share their local problems' anchors."""
    (tmp_path / "job.yaml").write_text(CONFIG + "map:\n  anchor_origin_m: [0.25, -0.75]\n")
    gpocc("train", str(logs["a"]), "--out", str(tmp_path / "a.npz"),
          "--config", str(tmp_path / "job.yaml"))
    (tmp_path / "plain.yaml").write_text(CONFIG)
    (tmp_path / "moved.yaml").write_text(CONFIG + "map:\n  anchor_origin_m: [0.5, 0.5]\n")
    for name, config, origin in [("kept", "plain.yaml", (0.25, -0.75)),
                                 ("moved", "moved.yaml", (0.5, 0.5))]:
        gpocc("update", str(tmp_path / "a.npz"), str(logs["b"]), "--config",
              str(tmp_path / config), "--out", str(tmp_path / f"{name}.npz"))
        assert load_model(tmp_path / f"{name}.npz").config.map.anchor_origin_m == origin
