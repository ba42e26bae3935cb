"""``model.training.classifier_temperature``: end to end from the CLI, the map's
probabilities move and their ranking (hence the AUC) does not."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from sklearn.metrics import roc_auc_score
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.gp.model import load_model
from gpocc.io.rasters import read_raster

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "data" / "sample" / "intel_sample.mcap"
SAMPLE_CONFIG = ROOT / "data" / "sample" / "sample.yaml"


def _train_and_map(tmp_path: Path, name: str, temperature: str) -> tuple[Path, np.ndarray]:
    config = yaml.safe_load(SAMPLE_CONFIG.read_text()) or {}
    training = config.setdefault("model", {}).setdefault("training", {})
    training["classifier_temperature"] = temperature
    # The offset of the leave-one-out fit, so that the temperature is all that differs.
    training["classifier_offset"] = "holdout"
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(config))
    runner = CliRunner()
    model = tmp_path / f"{name}.npz"
    result = runner.invoke(app, ["train", str(SAMPLE), "--config", str(path), "--out",
                                 str(model)])
    assert result.exit_code == 0, result.output
    assert (", temperature " in result.output) == (temperature != "none")
    result = runner.invoke(app, ["map", str(model), "--out", str(tmp_path / name),
                                 "--resolution", "0.2", "--workers", "1"])
    assert result.exit_code == 0, result.output
    return model, read_raster(tmp_path / name / "probability.tif")[0]


@pytest.fixture(scope="module")
def plain_map(tmp_path_factory) -> tuple[Path, np.ndarray]:
    return _train_and_map(tmp_path_factory.mktemp("plain"), "plain", "none")


@pytest.mark.parametrize("fitted_on", ["samples", "beams"])
def test_temperature_keeps_the_map_ranking_and_moves_its_probabilities(tmp_path, plain_map,
                                                                        fitted_on):
    plain_model, plain = plain_map
    warm_model, warm = _train_and_map(tmp_path, "warm", fitted_on)
    before, after = load_model(plain_model), load_model(warm_model)
    # Same samples, hyperparameters, offset and extra variance: only T differs.
    assert after.kernel == before.kernel and after.noise_variance == before.noise_variance
    assert (after.classifier.offset, after.classifier.extra_variance) == \
        (before.classifier.offset, before.classifier.extra_variance)
    assert before.classifier.temperature == 1.0 and after.classifier.temperature != 1.0
    valid = np.isfinite(plain)
    np.testing.assert_array_equal(valid, np.isfinite(warm))
    p, q = plain[valid].astype(float), warm[valid].astype(float)
    assert np.abs(p - q).max() > 0.05
    # Ordered by the map without T, the map with T never goes down where the first went
    # strictly up: the ranking is kept (ties of the first may be separated).
    order = np.lexsort((q, p))
    rising = np.diff(p[order]) > 0
    assert np.all(np.diff(q[order])[rising] >= -1e-6)
    # So any labels score the same AUC against both, to ties (sklearn as the oracle).
    labels = (np.random.default_rng(0).random(p.size) < p).astype(int)
    assert abs(roc_auc_score(labels, p) - roc_auc_score(labels, q)) < 1e-3
