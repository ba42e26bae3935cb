"""``model.diagonal: two-draw``: the training diagonal E[k(x_i, x_i')] over two draws that
share the scan's pose error and have independent sensor noise, against Girard's closed form
(SE), Monte Carlo (NN) and finite differences; wherever a training covariance is built."""

from __future__ import annotations

import math
import pickle
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.config import config_from_dict, config_to_dict
from gpocc.constants import JITTER
from gpocc.errors import GpoccError
from gpocc.gp import backends
from gpocc.gp.expected import (
    expected_kernel_cross,
    expected_kernel_diag,
    expected_kernel_matrix,
    expected_se_closed_form_pairs,
    two_draw_diag,
)
from gpocc.gp.kernels import NeuralNetworkKernel, SquaredExponentialKernel
from gpocc.gp.local import LocalProblem, predict_local, training_covariance
from gpocc.gp.model import load_model
from gpocc.samples.sampleset import SampleSet

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "data" / "sample" / "intel_sample.mcap"
SAMPLE_CONFIG = ROOT / "data" / "sample" / "sample.yaml"
TWO = backends.Choice("numpy", "two-draw")
BACKENDS = ["numpy", "compiled"]


def _inputs(n: int, seed: int, pose: bool = True, sensor_sd: float = 0.08):
    """Means (metres), sensor factors L, pose factors A and S = L L' + A A'."""
    rng = np.random.default_rng(seed)
    means = rng.uniform(-1.5, 1.5, (n, 2))
    sensor = rng.normal(size=(n, 2, 2)) * sensor_sd
    factors = rng.normal(size=(n, 2, 3)) * (0.06 if pose else 0.0)
    covs = sensor @ np.swapaxes(sensor, 1, 2) + factors @ np.swapaxes(factors, 1, 2)
    return means, sensor, factors, covs


def _monte_carlo(kernel, means, sensor, factors, draws, rng):
    """Mean of k(x, x') over pairs sharing the pose draw, independent sensor draws, and
    its standard error."""
    out, err = [], []
    for i in range(means.shape[0]):
        pose = rng.standard_normal((draws, 3)) @ factors[i].T
        x = means[i] + pose + rng.standard_normal((draws, 2)) @ sensor[i].T
        y = means[i] + pose + rng.standard_normal((draws, 2)) @ sensor[i].T
        values = kernel.pairwise(x, y)
        out.append(values.mean())
        err.append(values.std() / math.sqrt(draws))
    return np.array(out), np.array(err)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("pose", [True, False], ids=["pose", "no-pose"])
def test_se_two_draw_matches_girards_closed_form(backend, pose):
    kernel = SquaredExponentialKernel(1.3, (0.4, 0.5))
    means, _, factors, covs = _inputs(12, 1, pose)
    scan = np.zeros(12, dtype=np.int64)
    got = two_draw_diag(kernel, means, covs, 6, scan_ids=scan, pose_factors=factors,
                        backend=backend)
    cross = factors @ np.swapaxes(factors, 1, 2)  # Cov(x, x') = A A'
    want = expected_se_closed_form_pairs(kernel, means, covs, means, covs, cross)
    np.testing.assert_allclose(got, want, rtol=2e-3)
    # Below the one-point value s: the two draws are not the same point.
    assert (got < kernel.signal_variance - 1e-3).all()


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("pose", [True, False], ids=["pose", "no-pose"])
def test_nn_two_draw_matches_monte_carlo(backend, pose):
    kernel = NeuralNetworkKernel(1.5, 20.0, (3.0, 4.0))
    means, sensor, factors, covs = _inputs(6, 2, pose)
    scan = np.arange(6)
    got = two_draw_diag(kernel, means, covs, 5, scan_ids=scan, pose_factors=factors,
                        backend=backend)
    mc, err = _monte_carlo(kernel, means, sensor, factors, 200_000, np.random.default_rng(3))
    np.testing.assert_allclose(got, mc, atol=5 * err.max() + 1e-4)
    one = expected_kernel_diag(kernel, means, covs, 5)
    assert (one - got > 10 * err).all()  # the draws' difference is measurable


@pytest.mark.parametrize("backend", BACKENDS)
def test_without_sensor_noise_the_two_draws_are_one_point(backend):
    kernel = NeuralNetworkKernel(1.5, 20.0, (3.0, 4.0))
    means, _, factors, covs = _inputs(5, 4, sensor_sd=0.0)
    got = two_draw_diag(kernel, means, covs, 4, scan_ids=np.zeros(5, dtype=np.int64),
                        pose_factors=factors, backend=backend)
    np.testing.assert_allclose(got, expected_kernel_diag(kernel, means, covs, 4), rtol=1e-6)


@pytest.mark.parametrize("kernel", [SquaredExponentialKernel(1.3, (0.4, 0.5)),
                                    NeuralNetworkKernel(1.5, 20.0, (3.0, 4.0))],
                         ids=["se", "nn"])
@pytest.mark.parametrize("backend", BACKENDS)
def test_training_matrix_gradients_match_finite_differences(kernel, backend):
    means, _, factors, covs = _inputs(10, 5)
    scan = np.repeat([0, 1], 5)
    choice = backends.Choice(backend, "two-draw")
    g = 1.6
    scaled = backends.get(choice).loops(kernel).scale_gradient
    k, dk = expected_kernel_matrix(kernel, means, covs, 3, scan_ids=scan, pose_factors=factors,
                                   with_gradient=True, input_scale=g,
                                   with_scale_gradient=scaled, backend=choice)
    one = expected_kernel_matrix(kernel, means, covs, 3, scan_ids=scan, pose_factors=factors,
                                 input_scale=g, backend=backend)
    off = ~np.eye(10, dtype=bool)
    np.testing.assert_allclose(k[off], one[off], rtol=1e-12)  # only the diagonal changes
    np.testing.assert_allclose(
        np.diag(k), two_draw_diag(kernel, means, covs * g, 3, scan_ids=scan,
                                  pose_factors=factors * math.sqrt(g)), rtol=1e-10)
    h = 1e-5
    theta = kernel.theta
    for p in range(theta.shape[0]):
        step = np.zeros_like(theta)
        step[p] = h
        up, down = (expected_kernel_matrix(kernel.with_theta(theta + s), means, covs, 3,
                                           scan_ids=scan, pose_factors=factors,
                                           input_scale=g, backend=choice)
                    for s in (step, -step))
        np.testing.assert_allclose(dk[p], (up - down) / (2 * h), atol=1e-6, rtol=1e-5)
    if scaled:  # d/dlog g, a wider step than the implementation's difference
        h = 1e-2
        up, down = (expected_kernel_matrix(kernel, means, covs, 3, scan_ids=scan,
                                           pose_factors=factors, input_scale=g * math.exp(s),
                                           backend=choice) for s in (h, -h))
        np.testing.assert_allclose(dk[-1], (up - down) / (2 * h), atol=1e-4, rtol=1e-3)


def _samples(n: int, seed: int) -> SampleSet:
    means, _, factors, covs = _inputs(n, seed)
    labels = np.where(np.random.default_rng(seed).random(n) < 0.4, 1.0, -1.0)
    return SampleSet(means, covs, labels, np.arange(n) // 8, factors,
                     np.zeros(n, dtype=np.int16))


@pytest.mark.parametrize("backend", BACKENDS)
def test_map_local_systems_use_the_two_draw_diagonal(backend):
    # The compiled one-pass system and the separate calls of the numpy path against the
    # training covariance: the same prediction.
    kernel = NeuralNetworkKernel(1.5, 20.0, (3.0, 4.0))
    s = _samples(40, 6)
    queries = np.random.default_rng(7).uniform(-1, 1, (9, 2))
    choice = backends.Choice(backend, "two-draw")
    system = backends.get(choice).loops(kernel).local_system(
        kernel, s.means, s.covariances, queries, 3, 0.05 + JITTER, s.scan_ids, s.pose_factors)
    if system is not None:
        want = training_covariance(kernel, 0.05, s, 3, backend=TWO)
        np.testing.assert_allclose(np.diag(system[0]), np.diag(want), rtol=1e-10)
    problem = LocalProblem(np.zeros(2), s, np.arange(len(s)))
    got = predict_local(kernel, 0.05, problem, queries, 3, choice)
    chol = np.linalg.cholesky(training_covariance(kernel, 0.05, s, 3, backend=TWO))
    kx = expected_kernel_cross(kernel, queries, s.means, s.covariances, 3)
    mean = kx @ np.linalg.solve(chol.T, np.linalg.solve(chol, s.labels))
    np.testing.assert_allclose(got.mean, mean, rtol=1e-6, atol=1e-9)
    default = predict_local(kernel, 0.05, problem, queries, 3, backend)
    assert np.abs(default.mean - got.mean).max() > 1e-3


def test_config_key_is_validated_and_defaults_to_one_point():
    assert config_from_dict({}).model.diagonal == "one-point"
    assert config_from_dict({"model": {"diagonal": "two-draw"}}).model.diagonal == "two-draw"
    with pytest.raises(GpoccError, match="model.diagonal"):
        config_from_dict({"model": {"diagonal": "two"}}, "x.yaml")
    # A config written before the key (an older model's) loads as one-point.
    data = config_to_dict(config_from_dict({}))
    del data["model"]["diagonal"]
    assert config_from_dict(data).model.diagonal == "one-point"
    assert backends.choose("auto") == "auto"
    assert backends.choose("auto", "two-draw") == backends.Choice("auto", "two-draw")
    # It crosses process pools: the wrapped backend pickles as its choice.
    wrapped = backends.get(TWO)
    assert pickle.loads(pickle.dumps(wrapped)) is wrapped
    assert pickle.loads(pickle.dumps(TWO)) == TWO


def test_cli_trains_and_maps_with_the_two_draw_diagonal(tmp_path):
    config = yaml.safe_load(SAMPLE_CONFIG.read_text()) or {}
    config.setdefault("model", {})["diagonal"] = "two-draw"
    path = tmp_path / "two.yaml"
    path.write_text(yaml.safe_dump(config))
    runner = CliRunner()
    model_path = tmp_path / "model.npz"
    result = runner.invoke(app, ["train", str(SAMPLE), "--config", str(path), "--out",
                                 str(model_path)])
    assert result.exit_code == 0, result.output
    model = load_model(model_path)
    assert model.config.model.diagonal == "two-draw"
    assert model.backend == backends.Choice(model.config.model.backend, "two-draw",
                                            model.config.model.covariance_precision)
    result = runner.invoke(app, ["map", str(model_path), "--out", str(tmp_path / "map"),
                                 "--resolution", "0.2", "--workers", "1"])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "map" / "metadata.json").exists()
