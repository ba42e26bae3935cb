"""Config validation: every mistake names the key and the file; the CLI prints one line."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.config import (
    Config,
    changed_settings,
    config_from_dict,
    config_to_dict,
    load_config,
)
from gpocc.errors import GpoccError

runner = CliRunner()


def test_defaults_and_round_trip():
    config = load_config(None)
    assert config == Config()
    assert config_from_dict(config_to_dict(config)) == config
    nested = config_from_dict({"sensors": [{"name": "a", "bearing_variance_deg2": 0.5}],
                               "model": {"hyperparameters": {"weight_variance": [2, 3]},
                                         "training": {"isotropic": False}}})
    assert nested.sensors[0].bearing_variance_rad2 == pytest.approx(0.5 * (math.pi / 180) ** 2)
    assert nested.model.hyperparameters.weight_variance == (2.0, 3.0)
    assert config_from_dict(config_to_dict(nested)) == nested


@pytest.mark.parametrize("path", sorted((Path(__file__).parents[2] / "configs").glob("*.yaml")),
                         ids=lambda p: p.name)
def test_changed_settings_give_back_the_config_and_leave_defaults_out(path):
    config = load_config(path)
    changed = changed_settings(config)
    assert config_from_dict(changed) == config

    def leaves(data: dict, prefix: str = "") -> dict:
        out = {}
        for key, value in data.items():
            if isinstance(value, dict):
                out.update(leaves(value, f"{prefix}{key}."))
            else:
                out[prefix + key] = value
        return out

    defaults = leaves(config_to_dict(Config()))
    kept = leaves(changed)
    assert kept and all(defaults.get(key) != value for key, value in kept.items())


def test_changed_settings_keep_what_differs_and_drop_what_does_not():
    assert changed_settings(Config()) == {}
    config = config_from_dict({
        "seed": 0, "sensors": [{"name": "a"}],
        "samples": {"hit_gap_m": 0.25, "thin_cell_m": Config().samples.thin_cell_m},
        "model": {"training": {"patches": 20}, "neighbours": Config().model.neighbours}})
    changed = changed_settings(config)
    assert changed == {"sensors": config_to_dict(config)["sensors"],
                       "samples": {"hit_gap_m": 0.25},
                       "model": {"training": {"patches": 20}}}
    assert config_from_dict(changed) == config


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("seed: 0\nsensorz: []\n", "unknown key 'sensorz'"),
        ("model:\n  neighbours: many\n", "'model.neighbours' must be an integer"),
        ("model:\n  input_noise: 1\n", "'model.input_noise' must be true or false"),
        ("model:\n  covariance_precision: half\n",
         "'model.covariance_precision' must be one of single, double"),
        ("sensors:\n  - range_variance_m2: -0.1\n", "'sensors[0].range_variance_m2' must not"),
        ("sensors:\n  - max_tilt_deg: 0\n", "'sensors[0].max_tilt_deg' must be in (0, 90]"),
        ("sensors:\n  - max_tilt_deg: 95\n", "'sensors[0].max_tilt_deg' must be in (0, 90]"),
        ("sensors:\n  - bearing_variance_deg2: -1\n", "'sensors[0].bearing_variance_deg2'"),
        ("sensors:\n  - pose_covariance: [[1, 2, 0], [2, 1, 0], [0, 0, 1]]\n",
         "not positive semi-definite"),
        ("sensors:\n  - pose_covariance: [[1, 0.5, 0], [0, 1, 0], [0, 0, 1]]\n",
         "must be symmetric"),
        ("sensors:\n  - pose_covariance: [[1, 0], [0, 1]]\n", "must be a 3x3 matrix"),
        ("sensors:\n  - name: a\n  - name: a\n", "sensor names must be unique"),
        ("classify:\n  occupied: 0.3\n  free: 0.6\n", "free <= occupied"),
        ("model:\n  kernel: matern\n", "'model.kernel' must be 'nn' or 'se'"),
        ("model:\n  training:\n    classifier_holdout: beam\n",
         "'model.training.classifier_holdout' must be 'scan' or 'sample'"),
        ("model:\n  training:\n    input_noise_scale_part: sensor\n",
         "'model.training.input_noise_scale_part' must be 'all' or 'pose'"),
        ("model:\n  training:\n    fixed: [lengthscale_x]\n",
         "'model.training.fixed' names 'lengthscale_x', which the 'nn' kernel does not learn"),
        ("model:\n  hyperparameters:\n    noise_variance: 0.05\n  training:\n"
         "    fixed: [noise_variance]\n", "below model.training.min_noise_variance (0.1)"),
        ("model:\n  training:\n    classifier_offset: beam\n",
         "'model.training.classifier_offset' must be 'holdout' or 'beams'"),
        ("model:\n  training:\n    patch_centres: walls\n",
         "'model.training.patch_centres' must be 'hits' or 'samples'"),
        ("model:\n  training:\n    classifier_variance: noisy\n",
         "'model.training.classifier_variance' must be 'label', 'label-map' or 'latent'"),
        ("model:\n  training:\n    classifier_temperature: always\n",
         "'model.training.classifier_temperature' must be 'none', 'samples' or 'beams'"),
        ("model:\n  training:\n    classifier_variance: label-map\n"
         "    classifier_temperature: samples\n",
         "set classifier_temperature to 'beams' or 'none'"),
        ("samples:\n  free_clearance_m: -0.1\n", "free_clearance_m"),
        ("model:\n  training:\n    patch_offset_m: -1\n",
         "'model.training.patch_offset_m' must not be negative"),
        ("model:\n  training:\n    calibration_every: 1\n",
         "'model.training.calibration_every' must be at least 2"),
        ("model:\n  training:\n    calibration_blocks: 0\n",
         "'model.training.calibration_blocks' must be positive"),
        ("model:\n  training:\n    local_search: newton\n",
         "'model.training.local_search' must be 'lbfgs' or 'scoring'"),
        ("model:\n  training:\n    local_starts: 0\n",
         "'model.training.local_starts' must be positive"),
        ("map:\n  resolution_m: 0\n", "'map.resolution_m' must be positive"),
        ("samples:\n  free_spacing_m: .nan\n", "must be finite"),
        ("samples: [1, 2]\n", "'samples' must be a mapping"),
        ("- just\n- a list\n", "must be a YAML mapping"),
        ("model: {kernel: nn\n", "not valid YAML at line"),
        # PyYAML keeps the last of repeated keys: the first model block would be dropped.
        ("seed: 1\nseed: 2\n", "key 'seed' is given twice"),
        ("model:\n  kernel: se\nmodel:\n  neighbours: 10\n", "line 3 (key 'model' is given"),
        ("samples:\n  beam_stride: 100000000000000000000\n", "must be at most"),
        ("samples:\n  min_label_share: 2\n", "in [0, 1]"),
        ("grid:\n  clamp_min: 4\n  clamp_max: -4\n", "clamp_min < 0 < clamp_max"),
        ("grid:\n  log_odds_occupied: -1.0\n", "log_odds_free < 0 < log_odds_occupied"),
        ("sensors:\n  - pose_covariance: [[1.0e300, 0, 0], [0, 1, 0], [0, 0, 1]]\n",
         "check its units"),
        ("sensors:\n  - range_variance_m2: 1.0e300\n", "must be at most"),
        ("sensors:\n  - mount: {x_m: 1.0e12}\n", "from the robot base"),
    ],
)
def test_bad_config_names_key_and_file(tmp_path, text, words):
    path = tmp_path / "job.yaml"
    path.write_text(text)
    with pytest.raises(GpoccError) as err:
        load_config(path)
    message = str(err.value)
    assert str(path) in message
    assert words in message


def test_numbers_in_exponent_form_are_numbers(tmp_path):
    """YAML 1.1 reads 1e-3 (no dot) as a string; written unquoted it is the number."""
    path = tmp_path / "job.yaml"
    path.write_text("samples:\n  thin_cell_m: 1e-1\n  hit_gap_m: 25E-2\n"
                    "map:\n  max_cells: 300000000\n  margin_m: +2e0\n")
    config = load_config(path)
    assert (config.samples.thin_cell_m, config.samples.hit_gap_m) == (0.1, 0.25)
    assert (config.map.margin_m, config.map.max_cells) == (2.0, 300_000_000)
    path.write_text("samples:\n  thin_cell_m: '1e-1'\n")  # quoted: still a string
    with pytest.raises(GpoccError, match="must be a number"):
        load_config(path)
    # merge keys are not repeated keys
    path.write_text("samples:\n  <<: {thin_cell_m: 0.2, hit_gap_m: 0.1}\n  hit_gap_m: 0.3\n")
    config = load_config(path)
    assert (config.samples.thin_cell_m, config.samples.hit_gap_m) == (0.2, 0.3)


def test_cli_reports_bad_config_in_one_line(tmp_path):
    path = tmp_path / "job.yaml"
    path.write_text("sensors:\n  - range_variance_m2: -1\n")
    result = runner.invoke(app, ["train", "in.bag", "--config", str(path), "--out",
                                 str(tmp_path / "m.npz")])
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and str(path) in lines[0]
    assert "Traceback" not in result.output
    assert not (tmp_path / "m.npz").exists()


def test_missing_config_file(tmp_path):
    with pytest.raises(GpoccError, match="config file not found"):
        load_config(tmp_path / "nope.yaml")


@pytest.mark.parametrize("text", ["", "# seed: 3\n\n"])
def test_a_config_that_sets_nothing_warns_and_gives_the_defaults(tmp_path, capfd, text):
    path = tmp_path / "empty.yaml"
    path.write_text(text)
    assert load_config(path) == Config()
    err = capfd.readouterr().err
    assert f"warning: {path}: the config sets nothing" in err.replace("\n", "")


def test_a_config_that_sets_something_does_not_warn(tmp_path, capfd):
    path = tmp_path / "seed.yaml"
    path.write_text("seed: 3\n")
    assert load_config(path).seed == 3
    assert "sets nothing" not in capfd.readouterr().err


def test_map_epsg_alone_is_retired_and_georef_is_validated():
    with pytest.raises(GpoccError, match=r"c.yaml: key 'map.epsg' is retired.*map.georef"):
        config_from_dict({"map": {"epsg": 32633}}, "c.yaml")
    with pytest.raises(GpoccError, match="map.georef.epsg' must be a projected EPSG code"):
        config_from_dict({"map": {"georef": {"easting_m": 1.0}}}, "c.yaml")
    with pytest.raises(GpoccError, match="unknown key 'origin' under 'map.georef'"):
        config_from_dict({"map": {"georef": {"epsg": 32633, "origin": [1, 2]}}}, "c.yaml")
    cfg = config_from_dict({"map": {"georef": {"epsg": 32633, "easting_m": 400000,
                                               "northing_m": 5800000.5, "yaw_deg": 12}}})
    assert cfg.map.georef.easting_m == 400000.0 and cfg.map.georef.yaw_deg == 12.0
    assert config_from_dict({"map": {"epsg": None}}).map.georef is None


def test_limits_hold_for_configs_but_not_for_a_model_files_stored_config(tmp_path):
    # A model trained with a value an older gpocc allowed keeps loading: only configs a
    # user writes now are held to the limits.
    import numpy as np

    from gpocc.config import ModelConfig, TrainingConfig
    from gpocc.gp.model import build_model, load_model, save_model
    from gpocc.samples.sampleset import SampleSet

    rng = np.random.default_rng(2)
    means = rng.uniform(-2, 2, (60, 2))
    labels = np.where(np.abs(means[:, 0]) > 1.6, 1.0, -1.0)
    samples = SampleSet(means, np.zeros((60, 2, 2)), labels, np.arange(60),
                        np.zeros((60, 2, 3)), np.zeros(60, dtype=np.int16))
    beyond = Config(model=ModelConfig(
        neighbours=5000, training=TrainingConfig(learn=False, patches=1, patch_size=40,
                                                 log_bounds_width=25.0)))
    save_model(build_model(samples, beyond), tmp_path / "old.npz")
    assert load_model(tmp_path / "old.npz").config.model.neighbours == 5000
    with pytest.raises(GpoccError, match="model.neighbours' must be at most 4096"):
        config_from_dict({"model": {"neighbours": 5000}}, "c.yaml")
    with pytest.raises(GpoccError, match="log_bounds_width' must be above 0 and at most 20"):
        config_from_dict({"model": {"training": {"log_bounds_width": 25.0}}}, "c.yaml")


def test_anchor_origin_is_a_pair_of_metres_within_reach(tmp_path):
    path = tmp_path / "job.yaml"
    path.write_text("map:\n  anchor_origin_m: [-0.5, 25.5]\n")
    assert load_config(path).map.anchor_origin_m == (-0.5, 25.5)
    for bad, message in [("[1.0]", "must have 2 entries"), ("[0, .nan]", "must be finite"),
                         ("[2e7, 0]", "within 1e\\+07 m"), ("3.0", "must be a list")]:
        path.write_text(f"map:\n  anchor_origin_m: {bad}\n")
        with pytest.raises(GpoccError, match=message):
            load_config(path)
