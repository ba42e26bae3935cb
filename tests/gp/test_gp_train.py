"""Hyperparameter learning and the Platt classifier."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from modelfiles import read_model_file, write_model_file
from samplesets import samples_from
from scipy.special import ndtr

from gpocc.config import TrainingConfig, load_config
from gpocc.errors import GpoccError
from gpocc.gp.classify import (
    PlattClassifier,
    classify,
    fit_classifier,
    held_out_log_probability,
)
from gpocc.gp.kernels import NeuralNetworkKernel, SquaredExponentialKernel, axis_pairs
from gpocc.gp.local import leave_one_out, training_covariance
from gpocc.gp.train import (
    learn_hyperparameters,
    make_patches,
    negative_log_likelihood,
    resident_patch_pool,
)


@pytest.mark.parametrize("weighted", [False, True])
def test_likelihood_gradient_matches_finite_differences(weighted):
    """``weighted``: label-noise factors (``samples.label_weights: share``) on the samples,
    so the noise derivative is a weighted trace."""
    rng = np.random.default_rng(0)
    n = 300
    means = rng.uniform(-3, 3, (n, 2))
    covs = np.einsum("n,ij->nij", rng.uniform(0.001, 0.02, n), np.eye(2))
    scan_ids = rng.integers(0, 20, n)
    pose_factors = rng.normal(0, 0.03, (n, 2, 3))
    labels = np.where(rng.random(n) < 0.3, 1.0, -1.0)
    samples = samples_from(means, labels, covs, scan_ids, pose_factors)
    if weighted:
        samples = dataclasses.replace(samples, noise_factors=1.0 / rng.uniform(0.05, 1.0, n))
    patches = make_patches(samples, TrainingConfig(patches=2, patch_size=40), seed=1)
    assert all((p.samples.noise_factors is not None) == weighted for p in patches)
    kernel = NeuralNetworkKernel(1.0, 0.8, (2.0, 3.0))
    x = np.append(kernel.theta, math.log(0.2))
    _, grad = negative_log_likelihood(x, kernel, patches, 3)
    for i in range(len(x)):
        step = np.zeros_like(x)
        step[i] = 1e-5
        plus, _ = negative_log_likelihood(x + step, kernel, patches, 3)
        minus, _ = negative_log_likelihood(x - step, kernel, patches, 3)
        assert grad[i] == pytest.approx((plus - minus) / 2e-5, rel=1e-4, abs=1e-5)


def _correlated_problem():
    rng = np.random.default_rng(0)
    n = 300
    means = rng.uniform(-3, 3, (n, 2))
    covs = np.einsum("n,ij->nij", rng.uniform(0.001, 0.02, n), np.eye(2))
    labels = np.where(rng.random(n) < 0.3, 1.0, -1.0)
    return samples_from(means, labels, covs, rng.integers(0, 20, n),
                        rng.normal(0, 0.03, (n, 2, 3)))


def test_value_only_path_and_threads_give_the_same_likelihood():
    from concurrent.futures import ThreadPoolExecutor

    patches = make_patches(_correlated_problem(), TrainingConfig(patches=4, patch_size=40),
                           seed=1)
    kernel = NeuralNetworkKernel(1.0, 0.8, (2.0, 3.0))
    x = np.append(kernel.theta, math.log(0.2))
    value, grad = negative_log_likelihood(x, kernel, patches, 2)
    value_only, zeros = negative_log_likelihood(x, kernel, patches, 2, with_gradient=False)
    assert value_only == pytest.approx(value, rel=1e-12)
    assert not zeros.any()
    with ThreadPoolExecutor(2) as pool:
        threaded, threaded_grad = negative_log_likelihood(x, kernel, patches, 2, executor=pool)
    assert threaded == value
    np.testing.assert_array_equal(threaded_grad, grad)


def test_workers_holding_the_patches_give_the_serial_likelihood():
    """Patches installed in the workers once and handed out most expensive first: the
    terms are still summed in patch order, so the value is the serial one exactly."""
    patches = make_patches(_correlated_problem(), TrainingConfig(patches=5, patch_size=40),
                           seed=2)
    kernel = NeuralNetworkKernel(1.0, 0.8, (2.0, 3.0))
    x = np.append(kernel.theta, math.log(0.2))
    value, grad = negative_log_likelihood(x, kernel, patches, 2)
    with resident_patch_pool(patches, 2, level=2) as pool:
        assert sorted(pool.order) == list(range(len(patches)))
        assert pool.order != tuple(range(len(patches)))  # the costs do reorder them here
        held, held_grad = negative_log_likelihood(x, kernel, patches, 2, executor=pool)
        with pytest.raises(ValueError, match="other patches"):
            negative_log_likelihood(x, kernel, patches[:-1], 2, executor=pool)
    assert held == value
    np.testing.assert_array_equal(held_grad, grad)


@pytest.mark.parametrize("centres", ["hits", "samples"])
def test_patch_centres_are_hits_or_any_samples(centres):
    """``hits``: every patch is centred on an occupied sample, so it holds a boundary;
    ``samples``: centres come from all samples (here mostly free ones). The centres as
    drawn: no ``patch_offset_m``."""
    rng = np.random.default_rng(3)
    n = 2000
    means = rng.uniform(-10, 10, (n, 2))
    labels = np.where(rng.random(n) < 0.05, 1.0, -1.0)
    samples = samples_from(means, labels)
    patches = make_patches(samples, TrainingConfig(patches=12, patch_size=30,
                                                   patch_centres=centres, patch_offset_m=0.0),
                           seed=0)
    assert len(patches) == 12
    on_hit = [bool(np.any(np.all(means[labels > 0] == p.centre, axis=1))) for p in patches]
    if centres == "hits":
        assert all(on_hit)
    else:
        assert sum(on_hit) < 6
    for p in patches:
        assert np.any(np.all(means == p.centre, axis=1))
        np.testing.assert_allclose(p.samples.means + p.centre, means[p.index])
    # Fewer hits than patches: centres from all samples, still 12 patches.
    few = samples_from(means, np.where(np.arange(n) < 3, 1.0, -1.0))
    assert len(make_patches(few, TrainingConfig(patches=12, patch_size=30,
                                                patch_centres=centres), seed=0)) == 12


def test_patch_offsets_follow_the_blend_tent_and_patches_are_nearest_the_moved_centre():
    """``patch_offset_m``: each hit centre moves by a tent-distributed offset per axis
    (Kolmogorov-Smirnov against the triangular law on [-o, o]), the centres before the
    move are those drawn without it (same seed), and a patch is the ``patch_size``
    samples nearest its moved centre (brute force)."""
    from scipy.stats import kstest, triang

    rng = np.random.default_rng(5)
    n = 6000
    means = rng.uniform(-40, 40, (n, 2))
    labels = np.where(rng.random(n) < 0.5, 1.0, -1.0)
    samples = samples_from(means, labels)
    config = TrainingConfig(patches=1500, patch_size=12, patch_offset_m=0.0)
    still = make_patches(samples, config, seed=2)
    moved = make_patches(samples, dataclasses.replace(config, patch_offset_m=0.8), seed=2)
    offsets = np.array([m.centre - s.centre for m, s in zip(moved, still, strict=True)])
    assert np.all(np.abs(offsets) <= 0.8)
    tent = triang(c=0.5, loc=-0.8, scale=1.6)
    for axis in range(2):
        assert kstest(offsets[:, axis], tent.cdf).pvalue > 1e-3
    # A uniform law on the same interval is told apart: the test has power.
    assert kstest(rng.uniform(-0.8, 0.8, len(offsets)), tent.cdf).pvalue < 1e-3
    for patch in moved[:50]:
        nearest = np.argsort(np.linalg.norm(means - patch.centre, axis=1))[:12]
        assert set(patch.index.tolist()) == set(nearest.tolist())
        np.testing.assert_allclose(patch.samples.means + patch.centre, means[patch.index])


def test_an_unset_patch_offset_follows_the_block_size_in_learning_and_the_classifier():
    """``patch_offset_m`` unset: learning's and the classifier's patches move as with the
    offset set to ``model.block_size_m``, and the model equals the one trained with it
    stated; a different offset gives a different model (the comparison has power)."""
    from gpocc.config import Config, ModelConfig
    from gpocc.gp.model import build_model

    samples = _correlated_problem()
    training = TrainingConfig(patches=3, patch_size=40, anneal_maxfun=6, lbfgs_maxiter=3,
                              classifier_offset="holdout", classifier_temperature="none")

    def trained(block_m, offset_m):
        model = ModelConfig(block_size_m=block_m, training=dataclasses.replace(
            training, patch_offset_m=offset_m))
        result = build_model(samples, Config(model=model))
        return (*result.kernel.theta, result.noise_variance, result.classifier.a,
                result.classifier.b)

    assert ModelConfig(block_size_m=0.5).effective_training.patch_offset_m == 0.5
    assert ModelConfig(block_size_m=0.5, training=TrainingConfig(
        patch_offset_m=0.0)).effective_training.patch_offset_m == 0.0
    assert trained(0.5, None) == trained(0.5, 0.5)
    assert trained(0.5, None) != trained(0.5, 1.0)
    assert trained(1.0, None) == trained(1.0, 1.0)


@pytest.mark.parametrize("per_sensor", [0, 1, 2])
def test_a_site_of_many_sensors_gets_a_patch_on_every_building(per_sensor):
    """20 buildings 60 m apart, each its own sensor: with ``patches_per_sensor: k`` there
    are 20 k patches and every building holds one (farthest-point spreading over
    well-separated clusters); with 0 only ``patches`` (10), so half the buildings get
    none."""
    rng = np.random.default_rng(5)
    per, side = 200, 5
    centres = np.array([(60.0 * (k % side), 60.0 * (k // side)) for k in range(20)])
    building = np.repeat(np.arange(20), per)
    means = centres[building] + rng.uniform(-10, 10, (building.size, 2))
    labels = np.where(rng.random(building.size) < 0.2, 1.0, -1.0)
    samples = dataclasses.replace(samples_from(means, labels),
                                  sensor_ids=building.astype(np.int16))
    config = TrainingConfig(patches=10, patch_size=30, patches_per_sensor=per_sensor)
    patches = make_patches(samples, config, seed=0)
    held = {int(np.argmin(np.linalg.norm(centres - p.centre, axis=1))) for p in patches}
    if per_sensor:
        assert len(patches) == 20 * per_sensor and held == set(range(20))
    else:
        assert len(patches) == 10 and len(held) == 10
    # One sensor: the count stays ``patches`` whatever ``patches_per_sensor`` is.
    one = make_patches(samples_from(means, labels), config, seed=0)
    assert len(one) == 10


def test_learned_hyperparameters_do_not_depend_on_the_worker_count():
    samples = _correlated_problem()
    config = TrainingConfig(patches=3, patch_size=40, anneal_maxfun=8, lbfgs_maxiter=5)
    start = NeuralNetworkKernel(1.0, 0.8, (2.0, 3.0))
    one = learn_hyperparameters(start, 0.2, samples, 2, config, seed=0, workers=1)
    two = learn_hyperparameters(start, 0.2, samples, 2, config, seed=0, workers=2)
    np.testing.assert_array_equal(one.kernel.theta, two.kernel.theta)
    assert one.noise_variance == two.noise_variance
    assert one.log_marginal_likelihood == two.log_marginal_likelihood


def test_recovers_known_hyperparameters():
    """Draw labels from a GP with known SE hyperparameters and learn them back."""
    rng = np.random.default_rng(42)
    n = 900
    means = rng.uniform(0, 12, (n, 2))
    truth = SquaredExponentialKernel(1.5, (0.8, 0.8))
    noise = 0.05
    cov = truth(means, means) + noise * np.eye(n)
    labels = np.linalg.cholesky(cov + 1e-9 * np.eye(n)) @ rng.standard_normal(n)
    samples = samples_from(means, labels)
    start = SquaredExponentialKernel(0.5, (2.0, 2.0))
    # The true noise (0.05) is below the default floor: the published floor of 0.01.
    config = TrainingConfig(patches=8, patch_size=120, anneal_maxfun=40, lbfgs_maxiter=60,
                            min_noise_variance=0.01)
    result = learn_hyperparameters(start, 0.5, samples, 3, config, seed=0)
    assert result.log_marginal_likelihood > result.initial_log_marginal_likelihood
    assert result.kernel.lengthscale[0] == pytest.approx(0.8, rel=0.3)
    assert result.kernel.lengthscale[1] == pytest.approx(0.8, rel=0.3)
    assert result.noise_variance == pytest.approx(noise, rel=0.5)
    # Signal variance is the least identifiable from local patches; a factor of two.
    assert 0.5 * 1.5 < result.kernel.signal_variance < 2.0 * 1.5


def _se_draw(seed: int, lengthscale: tuple[float, float]):
    """300 samples on 8 x 8 m labelled by a draw of an SE GP (signal variance 1.5, noise
    variance 0.05)."""
    rng = np.random.default_rng(seed)
    means = rng.uniform(0, 8, (300, 2))
    truth = SquaredExponentialKernel(1.5, lengthscale)
    cov = truth(means, means) + 0.05 * np.eye(300)
    return samples_from(means, np.linalg.cholesky(cov) @ rng.standard_normal(300))


@pytest.mark.parametrize("isotropic", [True, False])
def test_a_warm_start_reaches_the_optimum_of_the_full_search(isotropic):
    """Fisher scoring from another start (``warm_start``, as ``gpocc update`` refines a
    model's values) ends within its tolerance (0.01 nats) of where annealing then
    L-BFGS-B from the initial values ends on the same patches, in fewer evaluations; a
    start that fits worse than the initial values is dropped for the full search. An
    isotropic search starts from the geometric mean of the start's two length scales
    (0.3 and 1.5 here: from 0.3 alone it fits worse than the initial values)."""
    samples = _se_draw(7, (0.7, 0.7))
    config = TrainingConfig(patches=4, patch_size=60, anneal_maxfun=30, lbfgs_maxiter=200,
                            min_noise_variance=0.01, isotropic=isotropic)
    start = SquaredExponentialKernel(0.5, (2.0, 2.0))
    full = learn_hyperparameters(start, 0.5, samples, 1, config, seed=0, workers=1)
    assert not full.warm_started
    warm = dataclasses.replace(full, kernel=SquaredExponentialKernel(4.0, (0.3, 1.5)),
                               noise_variance=0.2)
    refined = learn_hyperparameters(start, 0.5, samples, 1, config, seed=0, workers=1,
                                    warm_start=warm)
    assert refined.warm_started
    # In value, to a few hundredths: along the signal variance's flat direction a
    # hundredth of a nat leaves it that much room (the start is 1.4 away in log).
    np.testing.assert_allclose(refined.kernel.theta, full.kernel.theta, atol=5e-2)
    assert refined.noise_variance == pytest.approx(full.noise_variance, rel=2e-2)
    assert refined.log_marginal_likelihood == pytest.approx(full.log_marginal_likelihood,
                                                            abs=0.01)
    assert refined.evaluations < full.evaluations
    poor = dataclasses.replace(full, kernel=SquaredExponentialKernel(1e4, (0.7, 0.7)))
    dropped = learn_hyperparameters(start, 0.5, samples, 1, config, seed=0, workers=1,
                                    warm_start=poor)
    assert not dropped.warm_started
    np.testing.assert_array_equal(dropped.kernel.theta, full.kernel.theta)
    assert dropped.noise_variance == full.noise_variance


@pytest.mark.parametrize("fixed", [("signal_variance",), ("lengthscale_y", "noise_variance")])
def test_fixed_values_stay_and_the_others_reach_a_stationary_point(fixed):
    """``fixed`` values end where they started; the likelihood's gradient in the others
    vanishes at the result (central differences of the plain likelihood, an oracle
    independent of the optimiser's own gradient), unless a bound holds them."""
    samples = _se_draw(11, (0.7, 0.9))
    config = TrainingConfig(patches=4, patch_size=60, anneal_maxfun=10, lbfgs_maxiter=200,
                            min_noise_variance=0.01, fixed=fixed, isotropic=False)
    # x's length scale starts well off the optimum (the truth's is 0.7): with y's held,
    # its optimum on these patches lies near 1.0.
    start = SquaredExponentialKernel(1.0, (1.6, 1.0))
    result = learn_hyperparameters(start, 0.2, samples, 1, config, seed=0, workers=1)
    names = [*start.parameter_names, "noise_variance"]
    initial = np.append(start.theta, math.log(0.2))
    learned = np.append(result.kernel.theta, math.log(result.noise_variance))
    held = np.array([n in fixed for n in names])
    np.testing.assert_array_equal(learned[held], initial[held])
    assert np.all(np.abs(learned[~held] - initial[~held]) > 1e-3)
    patches = make_patches(samples, config, 0)
    step = 1e-4
    for i in np.flatnonzero(~held):
        up, down = learned.copy(), learned.copy()
        up[i] += step
        down[i] -= step
        slope = (negative_log_likelihood(up, start, patches, 1, with_gradient=False)[0]
                 - negative_log_likelihood(down, start, patches, 1, with_gradient=False)[0])
        assert abs(slope / (2 * step)) < 0.05, names[i]


def test_holding_every_value_is_learning_nothing():
    # fixed naming every learned value left the optimisers nothing to search (an
    # IndexError); it must give what learn: false gives, the initial values.
    samples = _se_draw(12, (0.7, 0.9))
    start = SquaredExponentialKernel(1.0, (1.0, 1.0))
    names = (*start.parameter_names, "noise_variance")
    held = learn_hyperparameters(
        start, 0.2, samples, 1, TrainingConfig(patches=2, patch_size=40, fixed=names),
        seed=0, workers=1)
    off = learn_hyperparameters(
        start, 0.2, samples, 1, TrainingConfig(patches=2, patch_size=40, learn=False),
        seed=0, workers=1)
    np.testing.assert_array_equal(held.kernel.theta, start.theta)
    assert held.noise_variance == 0.2 and held.evaluations == off.evaluations == 1
    assert held.log_marginal_likelihood == off.log_marginal_likelihood


def test_classifier_maximises_loo_log_probability():
    rng = np.random.default_rng(5)
    n = 200
    means = rng.uniform(-3, 3, (n, 2))
    labels = np.where(np.abs(means[:, 0]) > 2.2, 1.0, -1.0)
    flip = rng.random(n) < 0.05
    labels[flip] *= -1
    samples = samples_from(means, labels)
    patches = make_patches(samples, TrainingConfig(patches=2, patch_size=100), seed=0)
    kernel = NeuralNetworkKernel(1.0, 1.0, (2.0, 2.0))
    fitted = fit_classifier(kernel, 0.1, patches, 3)
    mu, var, y = [], [], []
    for p in patches:
        chol = np.linalg.cholesky(training_covariance(kernel, 0.1, p.samples, 3))
        m, v = leave_one_out(chol, p.samples.labels)
        mu.append(m)
        var.append(v)
        y.append(p.samples.labels)
    mu, var, y = map(np.concatenate, (mu, var, y))
    best = held_out_log_probability(fitted.offset, fitted.extra_variance, mu, var, y)
    # Brute-force grid search cannot beat the optimiser by more than its resolution.
    grid = max(held_out_log_probability(b / a, 1 / a**2, mu, var, y)
               for a in np.linspace(0.05, 10, 60) for b in np.linspace(-3, 3, 61))
    assert best >= grid - 1e-6


def test_probability_formula_and_classes():
    clf = PlattClassifier.from_ab(2.0, 0.5)
    mean = np.array([-1.0, 0.0, 1.0])
    var = np.array([0.5, 0.1, 2.0])
    expected = ndtr((2.0 * mean + 0.5) / np.sqrt(1 + 4.0 * var))
    np.testing.assert_allclose(clf.probability(mean, var), expected)
    p = np.array([0.1, 0.5, 0.9, np.nan])
    np.testing.assert_array_equal(classify(p, 0.65, 0.35), [0, 2, 1, 255])


def _scan_case(seed: int, n: int = 90, scans: int = 9, noisy: bool = True):
    rng = np.random.default_rng(seed)
    means = rng.uniform(-3, 3, (n, 2))
    labels = np.where(np.abs(means[:, 0]) > 2.0, 1.0, -1.0)
    scan_ids = rng.integers(0, scans, n)
    if noisy:
        covs = np.einsum("n,ij->nij", rng.uniform(0.001, 0.03, n), np.eye(2))
        factors = rng.normal(0, 0.05, (n, 2, 3))
    else:
        covs, factors = None, None
    return samples_from(means, labels, covs, scan_ids, factors)


@pytest.mark.parametrize("noisy", [False, True])
def test_leave_one_scan_out_matches_brute_force_refit(noisy):
    from gpocc.gp.classify import leave_one_scan_out
    from gpocc.gp.local import LocalProblem, predict_local

    samples = _scan_case(3, noisy=noisy)
    patch = LocalProblem(centre=np.zeros(2), samples=samples, index=np.arange(len(samples)))
    kernel = NeuralNetworkKernel(1.5, 1.0, (2.0, 2.5))
    mean, var, mask = leave_one_scan_out(kernel, 0.05, patch, 3)
    assert mask.all()
    for scan in np.unique(samples.scan_ids):
        held = samples.scan_ids == scan
        rest = samples.subset(~held)
        refit = LocalProblem(centre=np.zeros(2), samples=rest, index=np.flatnonzero(~held))
        oracle = predict_local(kernel, 0.05, refit, samples.means[held], 3)
        np.testing.assert_allclose(mean[held], oracle.mean, rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(var[held], oracle.variance, rtol=1e-6, atol=1e-8)


def test_latent_leave_one_out_variance_is_a_brute_force_refit_at_the_sample():
    """``classifier_variance: latent``: each sample's held-out variance is that of the
    latent function at its position (what a map cell gets), here checked by refitting
    the GP on the other samples and predicting there exactly; ``label`` is that plus
    the label noise."""
    from gpocc.gp.classify import patch_holdout_predictions
    from gpocc.gp.local import LocalProblem, predict_local

    samples = _scan_case(5, n=40, noisy=False)
    patch = LocalProblem(centre=np.zeros(2), samples=samples, index=np.arange(len(samples)))
    kernel = NeuralNetworkKernel(1.5, 1.0, (2.0, 2.5))
    noise = 0.07
    mean, var, _ = patch_holdout_predictions(kernel, noise, patch, 3, "sample", latent=True)
    _, label_var, _ = patch_holdout_predictions(kernel, noise, patch, 3, "sample")
    for i in range(len(samples)):
        keep = np.arange(len(samples)) != i
        refit = LocalProblem(centre=np.zeros(2), samples=samples.subset(keep),
                             index=np.flatnonzero(keep))
        oracle = predict_local(kernel, noise, refit, samples.means[i:i + 1], 3)
        np.testing.assert_allclose(mean[i], oracle.mean[0], rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(var[i], oracle.variance[0], rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(label_var[i], oracle.variance[0] + noise, rtol=1e-6)


def test_scan_holdout_classifier_maximises_held_out_log_probability():
    from gpocc.gp.classify import holdout_predictions

    samples = _scan_case(4, n=200, scans=12)
    patches = make_patches(samples, TrainingConfig(patches=2, patch_size=100), seed=0)
    kernel = NeuralNetworkKernel(1.0, 1.0, (2.0, 2.0))
    fitted = fit_classifier(kernel, 0.1, patches, 3, holdout="scan")
    mu, var, y = holdout_predictions(kernel, 0.1, patches, 3, "scan")
    best = held_out_log_probability(fitted.offset, fitted.extra_variance, mu, var, y)
    grid = max(held_out_log_probability(b / a, 1 / a**2, mu, var, y)
               for a in np.linspace(0.05, 10, 60) for b in np.linspace(-3, 3, 61))
    assert best >= grid - 1e-6


def test_one_scan_patch_cannot_be_held_out():
    from gpocc.gp.classify import leave_one_scan_out
    from gpocc.gp.local import LocalProblem

    samples = _scan_case(5, n=30, scans=1)
    patch = LocalProblem(centre=np.zeros(2), samples=samples, index=np.arange(30))
    _, _, mask = leave_one_scan_out(NeuralNetworkKernel(1.0, 1.0, (2.0, 2.0)), 0.1, patch, 2)
    assert not mask.any()


def test_model_files_without_the_new_keys_load_with_the_settings_they_were_trained_with(
        tmp_path):
    """A file written before ``patch_centres``, ``free_clearance_m``, ``label_weights``,
    ``classifier_offset_range``, ``classifier_targets``, ``isotropic``,
    ``covariance_precision`` and ``patch_offset_m`` existed was trained with all-sample
    patches, no clearance, unweighted labels, the wide offset range, hard targets, one
    weight variance per axis and patches centred as drawn, and mapped in double
    precision; a new file keeps what it states."""

    from gpocc.config import Config
    from gpocc.gp.model import GPModel, load_model, save_model

    samples = _correlated_problem()
    model = GPModel(kernel=NeuralNetworkKernel(), noise_variance=0.1,
                    classifier=PlattClassifier(),
                    samples=dataclasses.replace(samples, noise_factors=np.ones(len(samples))),
                    config=Config(), input_noise=True)
    path = tmp_path / "m.npz"
    save_model(model, path)

    def settings(config):
        return (config.model.training.patch_centres, config.samples.free_clearance_m,
                config.samples.label_weights, config.model.training.classifier_offset_range,
                config.model.training.classifier_targets, config.model.training.isotropic,
                config.model.covariance_precision, config.model.training.patch_offset_m)

    assert settings(load_model(path).config) == ("hits", 0.05, "count", "latent", "platt",
                                                 True, "single", None)
    arrays, meta = read_model_file(path)
    del meta["config"]["model"]["training"]["patch_centres"]
    del meta["config"]["samples"]["free_clearance_m"]
    del meta["config"]["samples"]["label_weights"]
    del meta["config"]["model"]["training"]["classifier_offset_range"]
    del meta["config"]["model"]["training"]["classifier_targets"]
    del meta["config"]["model"]["training"]["isotropic"]
    del meta["config"]["model"]["covariance_precision"]
    del meta["config"]["model"]["training"]["patch_offset_m"]
    del arrays["noise_factors"]
    # Learned per axis from unequal initial values, which the isotropic default refuses:
    # the file still loads, as it was trained.
    meta["config"]["model"]["hyperparameters"]["weight_variance"] = [20.0, 40.0]
    write_model_file(path, arrays, meta)
    assert settings(load_model(path).config) == ("samples", 0.0, "none", "wide", "hard",
                                                 False, "double", 0.0)


def test_isotropic_learning_ties_each_axis_pair_at_a_stationary_point_of_the_tie():
    """With ``isotropic`` the two length scales end equal, and the likelihood's slope
    along the tie (both moving together; central differences of the plain likelihood)
    vanishes there, while data drawn anisotropic leave a slope along one axis alone."""
    samples = _se_draw(11, (0.5, 1.2))
    config = TrainingConfig(patches=4, patch_size=60, anneal_maxfun=10, lbfgs_maxiter=200,
                            min_noise_variance=0.01, isotropic=True)
    start = SquaredExponentialKernel(1.0, (1.0, 1.0))
    result = learn_hyperparameters(start, 0.2, samples, 1, config, seed=0, workers=1)
    x, y = axis_pairs(start)[0]
    learned = np.append(result.kernel.theta, math.log(result.noise_variance))
    assert learned[x] == learned[y]
    patches = make_patches(samples, config, 0)
    step = 1e-4

    def slope(direction: np.ndarray) -> float:
        up = negative_log_likelihood(learned + step * direction, start, patches, 1,
                                     with_gradient=False)[0]
        down = negative_log_likelihood(learned - step * direction, start, patches, 1,
                                       with_gradient=False)[0]
        return (up - down) / (2 * step)

    for i in range(len(learned)):
        direction = np.zeros(len(learned))
        direction[i] = 1.0
        if i == y:
            continue
        if i == x:
            direction[y] = 1.0
        assert abs(slope(direction)) < 0.05, i
    alone = np.zeros(len(learned))
    alone[x] = 1.0
    assert abs(slope(alone)) > 0.5


def test_isotropic_needs_equal_initial_pairs_held_together(tmp_path):
    text = ("model:\n  kernel: se\n  training:\n    isotropic: true\n"
            "  hyperparameters:\n    lengthscale_m: [0.5, 0.8]\n")
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(GpoccError, match="initial values differ"):
        load_config(path)
    path.write_text("model:\n  kernel: se\n  training:\n    isotropic: true\n"
                    "    fixed: [lengthscale_x]\n")
    with pytest.raises(GpoccError, match="holds only one of them"):
        load_config(path)
    path.write_text("model:\n  kernel: nn\n  training:\n    isotropic: true\n"
                    "    fixed: [weight_variance_x, weight_variance_y]\n")
    assert load_config(path).model.training.isotropic
    # Isotropic is the default: unequal initial values name the way to one per axis.
    path.write_text("model:\n  hyperparameters:\n    weight_variance: [20, 40]\n")
    with pytest.raises(GpoccError, match="isotropic: false to learn one per axis"):
        load_config(path)
    path.write_text("model:\n  hyperparameters:\n    weight_variance: [20, 40]\n"
                    "  training:\n    isotropic: false\n")
    assert load_config(path).model.hyperparameters.weight_variance == (20.0, 40.0)
