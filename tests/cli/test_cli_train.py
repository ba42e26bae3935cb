"""`gpocc train` end to end on the sample bag, and the one real-data end-to-end test."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.gp.model import load_model
from gpocc.io.records import content_hash

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "data" / "sample" / "intel_sample.mcap"
SAMPLE_CONFIG = ROOT / "data" / "sample" / "sample.yaml"
INTEL = ROOT.parent / "shared" / "data" / "carmen" / "intel.gfs.log"
runner = CliRunner()


def invoke(*args: str | Path):
    result = runner.invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, result.output
    return result


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("train") / "model.npz"
    result = invoke("train", SAMPLE, "--config", SAMPLE_CONFIG, "--out", out)
    return out, result.output


def test_train_writes_a_self_contained_model(trained):
    path, output = trained
    assert "log marginal likelihood" in output and "classifier: a=" in output
    model = load_model(path)
    count, size = model.training["patches"]
    assert f"; {count} patches of {size} samples)" in output
    assert count == max(model.config.model.training.patches,
                        model.config.model.training.patches_per_sensor
                        * len(np.unique(model.samples.sensor_ids)))
    assert model.input_noise
    assert len(model.samples) > 1000
    assert model.samples.covariances.any() and model.samples.pose_factors.any()
    # The learned likelihood is reported and better than at the initial values.
    assert model.training["log_marginal_likelihood"] > model.training[
        "initial_log_marginal_likelihood"]
    assert model.inputs == (str(SAMPLE),)
    # The summary says how the classifier was fitted: the published leave-one-out, then
    # its offset and temperature on points of held-out scans.
    assert model.training["classifier_holdout"] == "sample"
    assert model.training["classifier_offset"] == "beams"
    assert model.training["classifier_temperature"] == "beams"
    points = model.training["classifier_points"]
    assert points > 100
    assert (f"fitted leaving one sample out; offset and temperature from {points} points "
            "of held-out scans") in output


def test_train_can_keep_the_offset_of_the_left_out_samples(tmp_path):
    config = tmp_path / "holdout.yaml"
    data = yaml.safe_load(SAMPLE_CONFIG.read_text())
    data.setdefault("model", {}).setdefault("training", {})["classifier_offset"] = "holdout"
    config.write_text(yaml.safe_dump(data))
    out = tmp_path / "holdout.npz"
    output = invoke("train", SAMPLE, "--config", config, "--out", out).output
    model = load_model(out)
    points = model.training["classifier_points"]
    assert model.training["classifier_offset"] == "holdout" and points > 100
    assert f"fitted leaving one sample out; temperature from {points} points" in output


def test_train_fits_the_classifier_on_the_configured_targets(trained, tmp_path):
    """``classifier_targets: hard`` (the labels themselves) against the default Platt
    targets: the same GP, and a classifier no steeper than the hard one's."""
    path, _ = trained
    config = tmp_path / "hard.yaml"
    data = yaml.safe_load(SAMPLE_CONFIG.read_text())
    data.setdefault("model", {}).setdefault("training", {})["classifier_targets"] = "hard"
    config.write_text(yaml.safe_dump(data))
    out = tmp_path / "hard.npz"
    invoke("train", SAMPLE, "--config", config, "--out", out)
    platt, hard = load_model(path), load_model(out)
    assert platt.config.model.training.classifier_targets == "platt"
    assert hard.config.model.training.classifier_targets == "hard"
    assert platt.kernel == hard.kernel and platt.noise_variance == hard.noise_variance
    assert platt.classifier != hard.classifier
    assert platt.classifier.temperature >= hard.classifier.temperature


def test_training_is_reproducible_with_a_seed(trained, tmp_path):
    path, _ = trained
    again = tmp_path / "again.npz"
    invoke("train", SAMPLE, "--config", SAMPLE_CONFIG, "--out", again)
    a, b = load_model(path), load_model(again)
    assert a.kernel == b.kernel and a.classifier == b.classifier
    np.testing.assert_array_equal(a.samples.means, b.samples.means)


def test_input_noise_off_trains_the_baseline(tmp_path):
    out = tmp_path / "baseline.npz"
    result = invoke("train", SAMPLE, "--config", SAMPLE_CONFIG, "--out", out,
                    "--input-noise", "off")
    assert "input noise: off" in result.output
    model = load_model(out)
    assert not model.input_noise
    assert not model.samples.covariances.any()


def test_existing_model_needs_force(trained):
    path, _ = trained
    result = runner.invoke(app, ["train", str(SAMPLE), "--config", str(SAMPLE_CONFIG),
                                 "--out", str(path)])
    assert result.exit_code != 0 and "--force" in result.output


def test_bad_input_is_one_line_and_leaves_no_model(tmp_path):
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(SAMPLE.read_bytes()[: 4000])
    out = tmp_path / "m.npz"
    result = runner.invoke(app, ["train", str(broken), "--out", str(out)])
    assert result.exit_code == 2
    assert "Traceback" not in result.output
    assert str(broken) in result.output
    assert not out.exists()


@pytest.mark.slow
def test_intel_end_to_end_gp_beats_grid_on_held_out_scans(tmp_path):
    """split -> train -> map -> grid -> evaluate on the real Intel log (dense regime)."""
    if not INTEL.is_file():
        pytest.skip(f"{INTEL} not found: the real-data test needs ../shared/data/carmen/")
    split = tmp_path / "split"
    invoke("split", INTEL, "--every", "10", "--config", ROOT / "configs" / "carmen_intel.yaml",
           "--out", split)
    train, config, truth = split / "train.mcap", split / "train.yaml", split / "heldout.csv"
    invoke("train", train, "--config", config, "--out", tmp_path / "gp.npz")
    invoke("map", tmp_path / "gp.npz", "--resolution", "0.1", "--out", tmp_path / "gp")
    invoke("grid", train, "--config", config, "--resolution", "0.1", "--out", tmp_path / "grid")
    invoke("evaluate", tmp_path / "gp", tmp_path / "grid", "--ground-truth", truth,
           "--out", tmp_path / "eval")
    # The bar below was set on each beam's hit and free points along it (the
    # hits+free protocol); near-wall free points are scored by the other protocols.
    protocols = {g["name"]: g for g in json.loads(
        (tmp_path / "eval" / "results.json").read_text())["protocols"]}
    rows = {r["name"]: r for r in protocols["hits+free"]["maps"]}
    gp, grid = rows["gp"], rows["grid"]
    assert gp["coverage"] > 0.99
    # The dense-regime bar: the GP is at least the grid's AUC minus 0.005.
    assert gp["auc"] >= grid["auc"] - 0.005
    assert gp["auc"] > 0.95
    assert gp["fpr_at_tpr97"] < grid["fpr_at_tpr97"]


def test_two_robot_simulation_end_to_end(tmp_path):
    """simulate -> train (two sensors of different quality in one job) -> map -> evaluate."""

    from gpocc.io.rasters import read_raster

    sim = tmp_path / "sim"
    invoke("simulate", "--out", sim, "--seed", "5")
    # The default training budget: a starved one (4 patches, 10 + 10 evaluations) learned
    # hyperparameters that swung the AUC between 0.87 and 0.96 with which of two
    # equally certain samples thinning kept.
    bounds = [f"{v}" for v in read_raster(sim / "truth.tif")[1].bounds]
    invoke("train", sim / "sim.mcap", "--config", sim / "sim.yaml", "--out",
           tmp_path / "gp.npz")
    model = load_model(tmp_path / "gp.npz")
    assert set(model.samples.sensor_ids.tolist()) == {0, 1}
    # Platform II's samples are far less certain than platform I's.
    size = np.sqrt(np.trace(model.samples.covariances, axis1=1, axis2=2))
    assert np.median(size[model.samples.sensor_ids == 1]) > 10 * np.median(
        size[model.samples.sensor_ids == 0])
    invoke("map", tmp_path / "gp.npz", "--resolution", "0.25", "--bounds", *bounds,
           "--out", tmp_path / "gp")
    invoke("grid", sim / "sim.mcap", "--config", sim / "sim.yaml", "--resolution", "0.25",
           "--bounds", *bounds, "--out", tmp_path / "grid")
    invoke("evaluate", tmp_path / "gp", tmp_path / "grid", "--ground-truth",
           sim / "truth.tif", "--out", tmp_path / "eval")
    rows = {r["name"]: r for r in json.loads((tmp_path / "eval" / "results.json").read_text())
            ["maps"]}
    assert rows["gp"]["auc"] > rows["grid"]["auc"]


def test_a_log_given_twice_under_two_names_is_warned_about(tmp_path):
    # Not refused (a site may place one log twice with config transforms), but its scans
    # count twice: the warning names both. The model records the inputs' hashes as before.
    copy = tmp_path / "copy.mcap"
    shutil.copyfile(SAMPLE, copy)
    out = tmp_path / "twice.npz"
    result = invoke("train", SAMPLE, copy, "--config", SAMPLE_CONFIG, "--out", out)
    assert result.exit_code == 0, result.output
    assert f"warning: {copy} has the same content as {SAMPLE}" in result.stderr
    model = load_model(out)
    assert [r.sha256 for r in model.growth.records] == [content_hash(SAMPLE)] * 2
    alone = invoke("train", SAMPLE, "--config", SAMPLE_CONFIG, "--out", tmp_path / "one.npz")
    assert "same content" not in alone.stderr
    # gpocc info says what train would do: the same warning, and scans counted twice.
    info = invoke("info", SAMPLE, copy, "--config", SAMPLE_CONFIG)
    assert info.exit_code == 0, info.output
    assert f"warning: {copy} has the same content as {SAMPLE}" in info.stderr
    # Placed apart by the config's inputs entries: one log twice on a site, no warning.
    site = tmp_path / "site.yaml"
    site.write_text(Path(SAMPLE_CONFIG).read_text()
                    + "\ninputs: [{path: copy.mcap, transform: {x_m: 100.0}}]\n")
    apart = invoke("info", SAMPLE, copy, "--config", site)
    assert "same content" not in apart.stderr
    twice = runner.invoke(app, ["info", str(SAMPLE), str(SAMPLE), "--config",
                                str(SAMPLE_CONFIG)])
    assert twice.exit_code == 2 and "given twice; pass each input once" in twice.stderr



def test_a_log_whose_beams_never_hit_is_trained_with_a_warning(tmp_path):
    # Every reading at CARMEN's no-return value (81.8 m and more): free samples only, so
    # the map can only say free; the user is told why, once.
    log = tmp_path / "nohit.log"
    lines = []
    for i in range(30):
        ranges = " ".join(["82.0"] * 180)
        pose = f"{0.05 * i:.2f} 0.0 0.0"
        lines.append(f"FLASER 180 {ranges} {pose} {pose} {100 + i} host {100 + i}\n")
    log.write_text("".join(lines))
    result = invoke("train", log, "--out", tmp_path / "m.npz")
    assert result.stderr.count("warning: every sample is free") == 1, result.stderr
    hits = invoke("train", SAMPLE, "--config", SAMPLE_CONFIG, "--out", tmp_path / "s.npz")
    assert "every sample is" not in hits.stderr
