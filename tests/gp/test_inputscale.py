"""The learned input-noise scale g (S -> g S, A -> sqrt(g) A): oracles and recovery."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from modelfiles import read_model_file, write_model_file

from gpocc.config import Config, ModelConfig, SamplesConfig, TrainingConfig
from gpocc.gp.expected import expected_kernel_matrix, expected_se_closed_form_pairs
from gpocc.gp.inputscale import scale_input_noise
from gpocc.gp.kernels import NeuralNetworkKernel, SquaredExponentialKernel
from gpocc.gp.local import LocalProblem
from gpocc.gp.model import load_model
from gpocc.gp.train import (
    learn_hyperparameters,
    make_patches,
    negative_log_likelihood,
    negative_log_likelihood_with_scale,
)
from gpocc.samples.sampleset import SampleSet


def scale_patches(patches: list[LocalProblem], scale: float,
                  part: str = "all") -> list[LocalProblem]:
    """The oracle of ``input_scale``: every patch's samples scaled before any node is built."""
    return [dataclasses.replace(p, samples=scale_input_noise(p.samples, scale, part))
            for p in patches]


def _samples(n: int, rng: np.random.Generator, scans: int = 4) -> SampleSet:
    means = rng.uniform(-1, 1, (n, 2))
    covs = np.einsum("n,ij->nij", rng.uniform(0.002, 0.02, n), np.eye(2))
    factors = rng.normal(0, 0.04, (n, 2, 3))
    covs = covs + np.einsum("nik,njk->nij", factors, factors)  # S_i includes A_i A_i'
    return SampleSet(means, covs, np.where(rng.random(n) < 0.3, 1.0, -1.0),
                     rng.integers(0, scans, n), factors, np.zeros(n, dtype=np.int16))


@pytest.mark.parametrize("part", ["all", "pose"])
@pytest.mark.parametrize("scale", [0.3, 2.5])
def test_scaled_samples_give_the_closed_form_of_the_scaled_joint_law(scale, part):
    # Girard's closed form with the scaled joint law: every covariance times g (``all``),
    # or the sensor part S_i - A_i A_i' as stated and the pose part times g (``pose``);
    # the same-scan cross-covariance A_i A_j' times g either way.
    rng = np.random.default_rng(0)
    s = _samples(12, rng, scans=2)
    scaled = scale_input_noise(s, scale, part)
    pose = np.einsum("nik,njk->nij", s.pose_factors, s.pose_factors)
    law = scale * s.covariances if part == "all" else s.covariances + (scale - 1) * pose
    kernel = SquaredExponentialKernel(1.3, (0.4, 0.6))
    k = expected_kernel_matrix(kernel, scaled.means, scaled.covariances, 8,
                               scan_ids=scaled.scan_ids, pose_factors=scaled.pose_factors)
    i, j = np.triu_indices(len(s), 1)
    cross = np.einsum("pik,pjk->pij", s.pose_factors[i], s.pose_factors[j])
    cross[s.scan_ids[i] != s.scan_ids[j]] = 0.0
    oracle = expected_se_closed_form_pairs(kernel, s.means[i], law[i], s.means[j], law[j],
                                           scale * cross)
    np.testing.assert_allclose(k[i, j], oracle, rtol=0, atol=2e-4)
    assert scale_input_noise(s, 1.0, part) is s
    with pytest.raises(ValueError, match="part"):
        scale_input_noise(s, scale, "sensor")


def test_scale_one_is_the_published_model_exactly():
    rng = np.random.default_rng(1)
    s = _samples(150, rng)
    assert scale_input_noise(s, 1.0) is s
    patches = make_patches(s, TrainingConfig(patches=2, patch_size=60), seed=0)
    kernel = SquaredExponentialKernel(1.0, (0.5, 0.5))
    params = np.append(kernel.theta, math.log(0.05))
    value, grad = negative_log_likelihood(params, kernel, patches, 2)
    value_g, grad_g = negative_log_likelihood_with_scale(np.append(params, 0.0), kernel,
                                                         patches, 2)
    assert value_g == value
    np.testing.assert_array_equal(grad_g[:-1], grad)


@pytest.mark.parametrize("part", ["all", "pose"])
@pytest.mark.parametrize("kernel", [SquaredExponentialKernel(1.0, (0.3, 0.3)),
                                    NeuralNetworkKernel(1.5, 20.0, (30.0, 50.0))],
                         ids=["se", "nn"])
def test_log_scale_gradient_matches_the_likelihood_of_scaled_patches(kernel, part):
    # Value and gradient against the plain likelihood of patches scaled by hand, the
    # last entry against its difference (a wider step than the implementation's). The
    # NN kernel's whole-covariance scale has an analytic derivative, the rest differences.
    rng = np.random.default_rng(2)
    patches = make_patches(_samples(150, rng), TrainingConfig(patches=2, patch_size=60), 0)
    params = np.append(kernel.theta, math.log(0.05))
    log_g, h = math.log(1.7), 1e-2

    def by_hand(g: float) -> tuple[float, np.ndarray]:
        return negative_log_likelihood(params, kernel, scale_patches(patches, g, part), 2)

    value, grad = negative_log_likelihood_with_scale(np.append(params, log_g), kernel,
                                                     patches, 2, scale_part=part)
    ref, ref_grad = by_hand(math.exp(log_g))
    assert value == pytest.approx(ref, rel=1e-12)
    np.testing.assert_allclose(grad[:-1], ref_grad, rtol=1e-10, atol=1e-12)
    slope = (by_hand(math.exp(log_g + h))[0] - by_hand(math.exp(log_g - h))[0]) / (2 * h)
    assert grad[-1] == pytest.approx(slope, rel=1e-3, abs=1e-3)


def _synthetic(true_scale: float, seed: int) -> tuple[SampleSet, SquaredExponentialKernel]:
    """GP labels at true positions; means drawn around them with true_scale * S, and S
    (half the samples 3 cm, half 14 cm standard deviation) labelled as their covariance."""
    rng = np.random.default_rng(seed)
    n = 700
    truth = rng.uniform(-3, 3, (n, 2))
    kernel = SquaredExponentialKernel(1.0, (0.6, 0.6))
    cov = kernel(truth, truth) + 1e-8 * np.eye(n)
    labels = np.linalg.cholesky(cov) @ rng.standard_normal(n) + rng.normal(0, 0.1, n)
    sd = np.where(np.arange(n) % 2 == 0, 0.03, 0.14)
    stated = np.einsum("n,ij->nij", sd**2, np.eye(2))
    means = truth + rng.standard_normal((n, 2)) * (sd * math.sqrt(true_scale))[:, None]
    samples = SampleSet(means, stated, labels, np.arange(n), np.zeros((n, 2, 3)),
                        np.zeros(n, dtype=np.int16))
    return samples, kernel


@pytest.mark.parametrize("true_scale", [0.25, 3.0])
def test_learned_scale_recovers_the_input_noise_that_made_the_data(true_scale):
    # Kernel and label noise start at the truth and may move by a factor e^0.5 (the
    # label-noise floor below the true 0.01); g is free in [0.05, 4]. Oracles: the truth
    # (to the sampling error of 700 samples), and a brute-force profile of the same
    # likelihood over g (the optimiser's job).
    samples, kernel = _synthetic(true_scale, seed=3)
    config = TrainingConfig(patches=4, patch_size=100, anneal_maxfun=20, lbfgs_maxiter=40,
                            log_bounds_width=0.5, min_noise_variance=0.001,
                            learn_input_noise_scale=True)
    result = learn_hyperparameters(kernel, 0.01, samples, 2, config, seed=0)
    assert result.input_noise_scale == pytest.approx(true_scale, rel=0.5)
    patches = make_patches(samples, config, 0)
    params = np.append(result.kernel.theta, math.log(result.noise_variance))
    grid = np.geomspace(0.05, 4.0, 41)
    profile = [negative_log_likelihood(params, result.kernel, scale_patches(patches, g), 2)[0]
               for g in grid]
    best = grid[int(np.argmin(profile))]
    assert result.input_noise_scale == pytest.approx(best, rel=0.12)  # grid ratio 1.116
    assert -result.log_marginal_likelihood <= min(profile) + 1e-6


def test_model_applies_the_learned_scale_and_files_keep_it(tmp_path):
    from gpocc.gp.model import build_model, load_model, save_model

    samples, kernel = _synthetic(3.0, seed=4)
    samples = dataclasses.replace(samples, labels=np.where(samples.labels > 0, 1.0, -1.0))
    config = Config(model=ModelConfig(kernel="se", quadrature_level=3, training=TrainingConfig(
        patches=3, patch_size=80, anneal_maxfun=5, lbfgs_maxiter=10,
        learn_input_noise_scale=True)))
    model = build_model(samples, config)
    g = model.input_noise_scale
    assert g != 1.0
    np.testing.assert_allclose(model.samples.covariances, g * samples.covariances)
    save_model(model, tmp_path / "m.npz")
    again = load_model(tmp_path / "m.npz")
    assert again.input_noise_scale == g
    np.testing.assert_array_equal(again.samples.covariances, model.samples.covariances)


def test_files_without_a_scale_load_with_the_stated_covariances(tmp_path):

    from gpocc.gp.classify import PlattClassifier
    from gpocc.gp.model import GPModel, load_model, save_model

    rng = np.random.default_rng(5)
    samples = _samples(40, rng)
    samples = dataclasses.replace(samples, covariances=samples.covariances * 3.0)
    model = GPModel(kernel=SquaredExponentialKernel(), noise_variance=0.1,
                    classifier=PlattClassifier(), samples=samples,
                    config=Config(model=ModelConfig(kernel="se"),
                                  samples=SamplesConfig(label_weights="none")), input_noise=True,
                    input_noise_scale=3.0)
    path = tmp_path / "m.npz"
    save_model(model, path)
    arrays, meta = read_model_file(path)
    assert meta["input_noise_scale"] == 3.0
    del meta["input_noise_scale"]
    write_model_file(path, arrays, meta)
    old = load_model(path)
    assert old.input_noise_scale == 1.0
    np.testing.assert_array_equal(old.samples.covariances, samples.covariances)


@pytest.mark.parametrize("low, high", [(1.5, 4.0), (0.05, 0.9)])
def test_scale_bounds_must_enclose_one(low, high):
    from gpocc.config import config_from_dict
    from gpocc.errors import GpoccError

    with pytest.raises(GpoccError, match="min_input_noise_scale"):
        config_from_dict({"model": {"training": {"min_input_noise_scale": low,
                                                 "max_input_noise_scale": high}}})


def test_scaled_likelihood_equals_the_likelihood_of_scaled_patches():
    """input_scale (cached nodes moved by sqrt(g)) against patches whose samples were
    scaled before any node was built."""
    rng = np.random.default_rng(7)
    n = 200
    means = rng.uniform(-3, 3, (n, 2))
    covs = np.einsum("n,ij->nij", rng.uniform(0.001, 0.02, n), np.eye(2))
    covs[:10] = 0.0  # exact points keep one node
    samples = SampleSet(means=means, covariances=covs,
                        labels=np.where(rng.random(n) < 0.3, 1.0, -1.0),
                        scan_ids=rng.integers(0, 15, n),
                        pose_factors=rng.normal(0, 0.03, (n, 2, 3)),
                        sensor_ids=np.zeros(n, dtype=np.int16))
    patches = make_patches(samples, TrainingConfig(patches=3, patch_size=50), seed=2)
    kernel = NeuralNetworkKernel(1.0, 0.8, (2.0, 3.0))
    params = np.append(kernel.theta, math.log(0.2))
    for g in (0.25, 3.0):
        value, grad = negative_log_likelihood(params, kernel, patches, 2, input_scale=g)
        ref, ref_grad = negative_log_likelihood(params, kernel, scale_patches(patches, g), 2)
        assert value == pytest.approx(ref, rel=1e-12)
        np.testing.assert_allclose(grad, ref_grad, rtol=1e-10, atol=1e-12)


def test_a_pose_only_scale_leaves_inputs_without_pose_error_as_stated():
    rng = np.random.default_rng(4)
    s = _samples(20, rng)
    s = dataclasses.replace(s, pose_factors=np.zeros_like(s.pose_factors))
    scaled = scale_input_noise(s, 3.0, "pose")
    np.testing.assert_allclose(scaled.covariances, s.covariances, rtol=0, atol=1e-15)


def test_a_pose_only_scale_differs_from_a_whole_one_where_sensors_are_noisy():
    rng = np.random.default_rng(5)
    patches = make_patches(_samples(150, rng), TrainingConfig(patches=2, patch_size=60), 0)
    kernel = SquaredExponentialKernel(1.0, (0.3, 0.3))
    params = np.append(kernel.theta, [math.log(0.05), math.log(1.7)])
    whole, pose = (negative_log_likelihood_with_scale(params, kernel, patches, 2,
                                                      scale_part=part)[0]
                   for part in ("all", "pose"))
    assert abs(whole - pose) > 1e-3


def test_a_model_scales_the_pose_part_when_told_to(tmp_path):
    from gpocc.gp.model import build_model, load_model, save_model

    samples, _ = _synthetic(3.0, seed=4)
    # The stated noise as the pose part (one scan per sample), plus a small sensor part.
    sd = np.sqrt(samples.covariances[:, 0, 0])
    factors = np.zeros((len(samples), 2, 3))
    factors[:, 0, 0] = factors[:, 1, 1] = sd
    samples = dataclasses.replace(samples, labels=np.where(samples.labels > 0, 1.0, -1.0),
                                  covariances=samples.covariances + 1e-4 * np.eye(2),
                                  pose_factors=factors)
    config = Config(model=ModelConfig(kernel="se", quadrature_level=3, training=TrainingConfig(
        patches=3, patch_size=80, anneal_maxfun=5, lbfgs_maxiter=10,
        learn_input_noise_scale=True, input_noise_scale_part="pose")))
    model = build_model(samples, config)
    g = model.input_noise_scale
    assert g != 1.0
    pose = np.einsum("nik,njk->nij", samples.pose_factors, samples.pose_factors)
    np.testing.assert_allclose(model.samples.covariances,
                               samples.covariances + (g - 1.0) * pose, atol=1e-15)
    save_model(model, tmp_path / "m.npz")
    again = load_model(tmp_path / "m.npz")
    assert again.config.model.training.input_noise_scale_part == "pose"
    np.testing.assert_array_equal(again.samples.covariances, model.samples.covariances)


def test_train_and_info_say_when_g_scales_the_pose_part(tmp_path):
    import yaml
    from typer.testing import CliRunner

    from gpocc.cli import app

    sample = Path(__file__).resolve().parents[2] / "data" / "sample"
    config = yaml.safe_load((sample / "sample.yaml").read_text())
    training = config.setdefault("model", {}).setdefault("training", {})
    training.update(input_noise_scale_part="pose", learn_input_noise_scale=True)
    (tmp_path / "pose.yaml").write_text(yaml.safe_dump(config))
    out = tmp_path / "m.npz"
    trained = CliRunner().invoke(app, ["train", str(sample / "intel_sample.mcap"), "--config",
                                       str(tmp_path / "pose.yaml"), "--out", str(out)])
    assert trained.exit_code == 0, trained.output
    info = CliRunner().invoke(app, ["info", str(out)])
    assert load_model(out).input_noise_scale != 1.0  # the sample's g is learned off 1
    assert "(pose part of the input covariances)" in trained.stdout
    assert "input covariances (pose part) scaled by" in info.stdout
