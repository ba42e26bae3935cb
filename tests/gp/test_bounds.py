"""Learned values on the bounds of their search: constructed fits that end on a bound and
fits that do not, `gpocc train`'s warnings and `gpocc info`'s lines."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.special import ndtr
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.config import Config, ModelConfig, TrainingConfig
from gpocc.gp.bounds import GUIDE_SECTION, side_on_bound, values_on_bounds
from gpocc.gp.classify import fit_platt
from gpocc.gp.kernels import make_kernel
from gpocc.gp.model import GPModel, load_model
from gpocc.samples.sampleset import SampleSet

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "data" / "sample" / "intel_sample.mcap"
SAMPLE_CONFIG = ROOT / "data" / "sample" / "sample.yaml"


def _samples(n: int = 40, seed: int = 0) -> SampleSet:
    rng = np.random.default_rng(seed)
    covs = np.einsum("n,ij->nij", rng.uniform(0.002, 0.02, n), np.eye(2))
    return SampleSet(rng.uniform(-1, 1, (n, 2)), covs, np.where(rng.random(n) < 0.3, 1.0, -1.0),
                     rng.integers(0, 4, n), np.zeros((n, 2, 3)), np.zeros(n, dtype=np.int16))


def _platt_case(separable: bool, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Held-out predictions: labels by the sign of mu (separable) or drawn from a Platt
    model with a = 2, b = 0.5 (a finite slope is the optimum)."""
    rng = np.random.default_rng(seed)
    mu = rng.normal(0, 1, 4000)
    var = rng.uniform(0.01, 0.2, mu.size)
    if separable:
        y = np.where(mu > 0, 1.0, -1.0)
    else:
        y = np.where(rng.random(mu.size) < ndtr((2 * mu + 0.5) / np.sqrt(1 + 4 * var)), 1.0, -1.0)
    return mu, var, y


def _model(**training: object) -> GPModel:
    config = Config(model=ModelConfig(training=TrainingConfig(
        **{"learn_input_noise_scale": True, **training})))
    cfg = config.model
    kernel = make_kernel(cfg.kernel, cfg.hyperparameters)
    classifier = fit_platt(*_platt_case(separable=False))
    return GPModel(kernel=kernel, noise_variance=0.5, classifier=classifier,
                   samples=_samples(), config=config, input_noise=True, input_noise_scale=1.3)


def test_side_on_bound_in_logs_and_linearly():
    assert side_on_bound(1000.0, 1e-3, 1e3) == "upper"
    assert side_on_bound(995.0, 1e-3, 1e3) == "upper"  # within 1 %
    assert side_on_bound(980.0, 1e-3, 1e3) is None
    assert side_on_bound(1.0e-3 * 1.005, 1e-3, 1e3) == "lower"
    assert side_on_bound(-99.5, -100.0, 100.0, log=False) == "lower"
    assert side_on_bound(0.0, -100.0, 100.0, log=False) is None


def test_a_separable_platt_fit_ends_on_the_slope_bound_and_a_noisy_one_does_not():
    # Separable labels: the held-out likelihood rises as a -> infinity, so the fit must
    # stop at the box (a = 1000); labels drawn with a = 2 have their optimum inside.
    sharp = fit_platt(*_platt_case(separable=True))
    smooth = fit_platt(*_platt_case(separable=False))
    assert smooth.a == pytest.approx(2.0, rel=0.15)
    base = _model()
    assert values_on_bounds(base) == []
    found = values_on_bounds(dataclasses.replace(base, classifier=sharp))
    assert [(b.name, b.side) for b in found] == [("classifier slope a", "upper")]
    assert found[0].bound == pytest.approx(1000.0)


def test_an_offset_on_the_latent_range_its_fit_had_is_named():
    """With ``classifier_offset_range: latent`` the offset's box is the largest latent
    mean among its points, which the training record states; files without it had the
    wide box."""
    base = _model()
    on = dataclasses.replace(base, classifier=dataclasses.replace(base.classifier, offset=-2.5),
                             training={"classifier_offset_bound": 2.5})
    [found] = [b for b in values_on_bounds(on) if b.name == "classifier offset c"]
    assert (found.side, found.bound) == ("lower", pytest.approx(-2.5))
    inside = dataclasses.replace(on, training={"classifier_offset_bound": 3.0})
    assert "classifier offset c" not in {b.name for b in values_on_bounds(inside)}
    older = dataclasses.replace(on, training={})
    assert "classifier offset c" not in {b.name for b in values_on_bounds(older)}


def test_hyperparameters_on_the_box_of_the_search_are_named():
    base = _model(log_bounds_width=2.0, min_noise_variance=0.1, max_input_noise_scale=4.0)
    theta = base.kernel.theta.copy()
    theta[1] += 2.0  # bias variance at exp(2) times its initial value: the upper bound
    theta[0] -= 1.0  # signal variance well inside
    on = dataclasses.replace(base, kernel=base.kernel.with_theta(theta), noise_variance=0.1,
                             input_noise_scale=4.0)
    found = {b.name: b for b in values_on_bounds(on)}
    assert set(found) == {"kernel bias_variance", "label-noise variance", "input-noise scale g"}
    assert found["kernel bias_variance"].side == "upper"
    assert found["kernel bias_variance"].bound == pytest.approx(
        base.kernel.bias_variance * math.exp(2.0))
    assert (found["label-noise variance"].side, found["label-noise variance"].bound) == (
        "lower", pytest.approx(0.1))
    assert found["input-noise scale g"].side == "upper"
    # Not learned, nothing but the classifier is checked; no input covariance, no g.
    fixed = dataclasses.replace(on, config=dataclasses.replace(on.config, model=dataclasses.replace(
        on.config.model, training=dataclasses.replace(on.config.model.training, learn=False))))
    assert values_on_bounds(fixed) == []
    exact = dataclasses.replace(on, samples=dataclasses.replace(
        on.samples, covariances=np.zeros_like(on.samples.covariances)))
    assert "input-noise scale g" not in {b.name for b in values_on_bounds(exact)}


def _independent_box(model: GPModel) -> dict[str, tuple[float, float, float]]:
    """name -> (value, lower, upper), from the config as documented (not the code's box)."""
    cfg = model.config.model
    t = cfg.training
    w = math.exp(t.log_bounds_width)
    h = cfg.hyperparameters
    box = {"classifier slope a": (model.classifier.a, 1e-3, 1e3),
           "kernel signal_variance": (model.kernel.signal_variance, h.signal_variance / w,
                                      h.signal_variance * w),
           "label-noise variance": (model.noise_variance,
                                    max(h.noise_variance / w, t.min_noise_variance),
                                    max(h.noise_variance * w, t.min_noise_variance * math.e)),
           "input-noise scale g": (model.input_noise_scale, t.min_input_noise_scale,
                                   t.max_input_noise_scale)}
    if cfg.kernel == "nn":
        box["kernel bias_variance"] = (model.kernel.bias_variance, h.bias_variance / w,
                                       h.bias_variance * w)
        for i in range(2):
            v0 = h.weight_variance[i] if isinstance(h.weight_variance, list | tuple) \
                else h.weight_variance
            box[f"kernel weight_variance[{i}]"] = (model.kernel.weight_variance[i], v0 / w,
                                                   v0 * w)
    return box


def test_train_warns_and_info_shows_exactly_the_values_on_their_bounds(tmp_path):
    out = tmp_path / "m.npz"
    config = yaml.safe_load(SAMPLE_CONFIG.read_text())  # with g learned: one more value
    config.setdefault("model", {}).setdefault("training", {})["learn_input_noise_scale"] = True
    (tmp_path / "learned-g.yaml").write_text(yaml.safe_dump(config))
    result = CliRunner().invoke(app, ["train", str(SAMPLE), "--config",
                                      str(tmp_path / "learned-g.yaml"), "--out", str(out)])
    assert result.exit_code == 0, result.output
    model = load_model(out)
    assert model.config.model.training.learn_input_noise_scale
    expected = set()
    for name, (value, lo, hi) in _independent_box(model).items():
        if abs(math.log(value / lo)) <= math.log1p(0.01) or abs(math.log(hi / value)) <= \
                math.log1p(0.01):
            expected.add(name)
    warned = {line.split("warning: ", 1)[1].split(" = ")[0]
              for line in result.stderr.splitlines() if " bound " in line}
    assert warned == expected
    assert (GUIDE_SECTION in result.stderr) == bool(expected)
    info = CliRunner().invoke(app, ["info", str(out)])
    assert info.exit_code == 0, info.output
    assert f"learned values on a bound: {len(expected) or 'none'}" in info.stdout
    assert (GUIDE_SECTION in info.stdout) == bool(expected)
    for name in expected:
        assert f"    {name} = " in info.stdout


def test_the_guide_section_the_warnings_point_to_exists():
    path, title = GUIDE_SECTION.split(", ", 1)
    text = (Path(__file__).resolve().parents[2] / path).read_text()
    assert f"### {title.strip(chr(39))}\n" in text
