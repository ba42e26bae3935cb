"""The Platt classifier's fit in (offset c, extra variance s): oracles, the a -> inf ridge."""

from __future__ import annotations

import numpy as np
import pytest
from modelfiles import read_model_file, write_model_file
from scipy.special import ndtr, ndtri

from gpocc.config import TrainingConfig
from gpocc.errors import GpoccError
from gpocc.gp.classify import (
    S_MIN,
    T_MAX,
    T_MIN,
    PlattClassifier,
    fit_classifier,
    fit_offset_and_temperature,
    fit_platt,
    fit_temperature,
    held_out_log_probability,
    platt_targets,
    separates,
)
from gpocc.gp.kernels import NeuralNetworkKernel
from gpocc.gp.model import load_model
from gpocc.gp.train import make_patches
from tests.mapping.test_map import room_samples


def test_published_form_and_fitted_form_give_the_same_probability():
    rng = np.random.default_rng(0)
    mean, var = rng.normal(0, 1, 50), rng.uniform(0, 2, 50)
    for a, b in ((0.3, -1.0), (2.0, 0.5), (800.0, -12.0)):
        clf = PlattClassifier.from_ab(a, b)
        assert clf.a == pytest.approx(a) and clf.b == pytest.approx(b)
        np.testing.assert_allclose(clf.probability(mean, var),
                                   ndtr((a * mean + b) / np.sqrt(1 + a**2 * var)), rtol=1e-12)


def test_fit_recovers_the_classifier_that_drew_the_labels():
    # Labels drawn from a known classifier: the maximum-likelihood fit must find it
    # (interior optimum; the truth is the oracle, to the sampling error of 40000 labels).
    rng = np.random.default_rng(1)
    n = 40000
    mean, var = rng.normal(0, 1, n), rng.uniform(0.01, 0.5, n)
    truth = PlattClassifier.from_ab(2.0, 0.5)
    labels = np.where(rng.random(n) < truth.probability(mean, var), 1.0, -1.0)
    fitted = fit_platt(mean, var, labels)
    assert fitted.a == pytest.approx(2.0, rel=0.08)
    assert fitted.b == pytest.approx(0.5, abs=0.05)


def _brute_force(mean, var, labels):
    """Best objective over a grid of (c, s), s including the bound S_MIN."""
    cs = np.linspace(-1, 1, 201)
    ss = np.concatenate([[S_MIN], np.geomspace(1e-5, 10, 120)])
    values = np.array([[held_out_log_probability(c, s, mean, var, labels) for s in ss]
                       for c in cs])
    i, j = np.unravel_index(values.argmax(), values.shape)
    return values[i, j], cs[i], ss[j]


def test_fit_is_at_least_as_good_as_brute_force_and_finds_the_ridge_bound():
    # Labels that the latent mean separates but for a few near the boundary: the
    # objective rises towards a -> infinity, so the optimum is the bound s = S_MIN.
    rng = np.random.default_rng(2)
    n = 400
    mean = rng.normal(0, 1, n)
    var = rng.uniform(0.01, 0.2, n)
    labels = np.where(mean + rng.normal(0, 0.1, n) > 0.2, 1.0, -1.0)
    fitted = fit_platt(mean, var, labels)
    best, c_best, s_best = _brute_force(mean, var, labels)
    value = held_out_log_probability(fitted.offset, fitted.extra_variance, mean, var, labels)
    assert value >= best - 1e-9
    assert s_best == S_MIN and fitted.extra_variance == S_MIN
    assert fitted.offset == pytest.approx(c_best, abs=0.01)


def test_fit_matches_brute_force_argmax_inside_the_box():
    rng = np.random.default_rng(3)
    n = 3000
    mean, var = rng.normal(0, 1, n), rng.uniform(0.01, 0.3, n)
    truth = PlattClassifier(offset=-0.3, extra_variance=0.5)
    labels = np.where(rng.random(n) < truth.probability(mean, var), 1.0, -1.0)
    fitted = fit_platt(mean, var, labels)
    best, c_best, s_best = _brute_force(mean, var, labels)
    value = held_out_log_probability(fitted.offset, fitted.extra_variance, mean, var, labels)
    assert value >= best - 1e-9
    assert fitted.offset == pytest.approx(c_best, abs=0.01)  # grid step 0.01
    assert fitted.extra_variance == pytest.approx(s_best, rel=0.1)  # grid ratio 1.1


def test_numpy_and_compiled_kernels_give_the_same_classifier():
    # The room model's classifier lies on the ridge (steep walls); before the (c, s)
    # parametrisation the two kernel paths, agreeing to 1e-14, gave different (a, b).
    samples = room_samples()
    patches = make_patches(samples, TrainingConfig(patches=3, patch_size=120), seed=1)
    kernel = NeuralNetworkKernel(2.0, 1.0, (3.0, 3.0))
    fits = {}
    for fused in (False, True):
        fits[fused] = fit_classifier(kernel, 0.02, patches, 3,
                                     backend="compiled" if fused else "numpy")
    assert fits[True].offset == pytest.approx(fits[False].offset, abs=1e-6)
    assert fits[True].extra_variance == pytest.approx(fits[False].extra_variance,
                                                      rel=1e-6, abs=1e-12)


def _saved_model(tmp_path, classifier: PlattClassifier):
    from gpocc.config import Config, SamplesConfig
    from gpocc.gp.model import GPModel, save_model

    model = GPModel(kernel=NeuralNetworkKernel(2.0, 1.0, (3.0, 3.0)), noise_variance=0.02,
                    classifier=classifier, samples=room_samples(),
                    config=Config(samples=SamplesConfig(label_weights="none")),
                    input_noise=True)
    path = tmp_path / "model.npz"
    save_model(model, path)
    return (path, *read_model_file(path))


def test_format_1_model_files_with_a_and_b_still_load(tmp_path):
    path, arrays, meta = _saved_model(tmp_path, PlattClassifier())
    meta["format_version"] = 1
    meta["classifier"] = {"a": 527.0, "b": -28.1}
    write_model_file(path, arrays, meta)
    loaded = load_model(path).classifier
    mean, var = np.linspace(-1, 1, 11), np.linspace(0.001, 0.1, 11)
    np.testing.assert_allclose(loaded.probability(mean, var),
                               ndtr((527.0 * mean - 28.1) / np.sqrt(1 + 527.0**2 * var)),
                               rtol=1e-12)


@pytest.mark.parametrize("version, record", [
    (1, {"offset": 0.1, "extra_variance": 1e-3}),  # today's keys in an old file
    (2, {"a": 2.0, "b": 0.1}),                      # old keys in a new file
    (2, {"offset": 0.1, "extra_variance": 0.0}),    # a = infinity
    (4, {"offset": 0.1, "extra_variance": 1e-3}),   # format 4 without its temperature
    (4, {"offset": 0.1, "extra_variance": 1e-3, "temperature": 0.0}),
])
def test_classifier_record_of_the_wrong_form_is_a_clear_error(tmp_path, version, record):
    path, arrays, meta = _saved_model(tmp_path, PlattClassifier())
    meta["format_version"] = version
    meta["classifier"] = record
    write_model_file(path, arrays, meta)
    with pytest.raises(GpoccError, match="classifier.*gpocc train"):
        load_model(path)


def test_saved_classifier_round_trips_exactly(tmp_path):
    clf = PlattClassifier(offset=-0.0184823, extra_variance=S_MIN, temperature=3.25)
    path, _, meta = _saved_model(tmp_path, clf)
    assert meta["format_version"] >= 4  # the temperature since format 4
    assert load_model(path).classifier == clf


def test_format_3_model_files_load_with_temperature_one(tmp_path):
    path, arrays, meta = _saved_model(tmp_path, PlattClassifier(offset=0.2, extra_variance=0.5))
    meta["format_version"] = 3
    meta["classifier"] = {"offset": 0.2, "extra_variance": 0.5}
    write_model_file(path, arrays, meta)
    assert load_model(path).classifier == PlattClassifier(offset=0.2, extra_variance=0.5)


def test_temperature_divides_the_argument_and_keeps_the_order():
    rng = np.random.default_rng(3)
    mean, var = rng.normal(0, 1, 200), rng.uniform(0, 0.3, 200)
    plain = PlattClassifier(offset=0.1, extra_variance=0.02)
    warm = PlattClassifier(offset=0.1, extra_variance=0.02, temperature=4.0)
    np.testing.assert_allclose(warm.probability(mean, var),
                               ndtr((mean + 0.1) / (4.0 * np.sqrt(0.02 + var))), rtol=1e-12)
    assert not np.allclose(warm.probability(mean, var), plain.probability(mean, var))


def _drawn_at_temperature_3() -> tuple[PlattClassifier, np.ndarray, np.ndarray, np.ndarray]:
    """40000 labels drawn from Phi(z / 3) for a known (c, s), and that (c, s) at T = 1."""
    rng = np.random.default_rng(4)
    n = 40000
    mean, var = rng.normal(0, 1, n), rng.uniform(0.0, 0.2, n)
    given = PlattClassifier(offset=-0.05, extra_variance=0.01)
    truth = PlattClassifier(offset=-0.05, extra_variance=0.01, temperature=3.0)
    labels = np.where(rng.random(n) < truth.probability(mean, var), 1.0, -1.0)
    return given, mean, var, labels


def test_fitted_temperature_recovers_the_one_that_drew_the_labels():
    # The maximum-likelihood temperature must be 3 to the sampling error of 40000 labels;
    # (c, s) are kept as given.
    given, mean, var, labels = _drawn_at_temperature_3()
    fitted = fit_temperature(given, mean, var, labels)
    assert fitted.temperature == pytest.approx(3.0, rel=0.05)
    assert (fitted.offset, fitted.extra_variance) == (given.offset, given.extra_variance)
    # ... and no temperature on a grid of them does better (brute force).
    grid = np.geomspace(0.5, 20, 400)
    best = max(held_out_log_probability(-0.05, 0.01, mean, var, labels, t) for t in grid)
    assert held_out_log_probability(-0.05, 0.01, mean, var, labels,
                                    fitted.temperature) >= best - 1e-6


def test_temperature_of_one_label_only_is_left_alone():
    given = PlattClassifier(offset=0.3, extra_variance=0.1)
    assert fit_temperature(given, np.ones(5), np.ones(5), np.ones(5)) == given


def test_no_temperature_is_fitted_when_the_classifier_separates_the_points():
    # Every point on its label's side: the log probability rises as T falls (checked on a
    # grid), so no T maximises it and the classifier is returned as it was, not one
    # anywhere on that slope.
    rng = np.random.default_rng(6)
    given = PlattClassifier(offset=0.05, extra_variance=1e-6)
    labels = np.where(rng.random(300) < 0.1, 1.0, -1.0)
    mean = labels * rng.uniform(0.2, 2.0, 300) - given.offset
    var = rng.uniform(0.01, 0.1, 300)
    assert separates(given, mean, labels)
    values = [held_out_log_probability(given.offset, given.extra_variance, mean, var, labels,
                                       t) for t in np.geomspace(T_MAX, T_MIN, 50)]
    assert np.all(np.diff(values) >= 0) and values[-1] > values[0]
    assert fit_temperature(given, mean, var, labels) == given
    # One point on the wrong side: the probability has a maximum, and the fit finds it.
    mean[0] = -labels[0] * 0.05 - given.offset
    assert not separates(given, mean, labels)
    fitted = fit_temperature(given, mean, var, labels)
    grid = np.geomspace(T_MIN, T_MAX, 4000)
    best = max(held_out_log_probability(given.offset, given.extra_variance, mean, var,
                                        labels, t) for t in grid)
    assert held_out_log_probability(given.offset, given.extra_variance, mean, var, labels,
                                    fitted.temperature) >= best - 1e-6
    assert T_MIN < fitted.temperature < 1.0


def test_platt_targets_count_each_label():
    labels = np.array([1.0, -1.0, -1.0, 1.0, -1.0, -1.0, -1.0])
    # 2 occupied points: (2 + 1) / (2 + 2); 5 free: (5 + 1) / (5 + 2), brute force.
    expected = [3 / 4 if y > 0 else 6 / 7 for y in labels]
    np.testing.assert_allclose(platt_targets(labels), expected, rtol=0, atol=0)


def test_held_out_log_probability_under_targets_is_the_cross_entropy():
    rng = np.random.default_rng(11)
    mean, var = rng.normal(0, 1, 30), rng.uniform(0.01, 0.5, 30)
    labels = np.where(rng.random(30) < 0.4, 1.0, -1.0)
    t = platt_targets(labels)
    # Brute force: the probability p of occupied, and each point's target of occupied.
    p = ndtr((mean + 0.2) / (1.7 * np.sqrt(0.05 + var)))
    occupied_target = np.where(labels > 0, t, 1.0 - t)
    expected = np.sum(occupied_target * np.log(p) + (1 - occupied_target) * np.log(1 - p))
    assert held_out_log_probability(0.2, 0.05, mean, var, labels, 1.7, t) == pytest.approx(
        expected, rel=1e-12)


def _separated(seed: int, n_occupied: int, n_free: int, margin: float, var: float):
    """Held-out predictions every one of which lies ``margin`` on its label's side, all
    with latent variance ``var``."""
    labels = np.concatenate([np.ones(n_occupied), -np.ones(n_free)])
    np.random.default_rng(seed).shuffle(labels)
    return labels * margin, np.full(labels.size, var), labels


@pytest.mark.parametrize("counts", [(50, 50), (40, 360)])
def test_platt_targets_give_separated_points_the_temperature_that_meets_them(counts):
    """Analytic case: every point at distance m of the decision, variance v, s fixed.
    Under hard targets no temperature is best (the probability rises as T falls); under
    Platt's, the optimum has Phi(m / (T sqrt(s + v))) equal to the mean target, so
    T = m / (sqrt(s + v) Phi^-1(mean target))."""
    mean, var, labels = _separated(2, *counts, margin=0.3, var=0.02)
    given = PlattClassifier(offset=0.0, extra_variance=0.01)
    assert separates(given, mean, labels)
    assert fit_temperature(given, mean, var, labels, "hard") == given
    fitted = fit_temperature(given, mean, var, labels, "platt")
    target = platt_targets(labels).mean()
    expected = 0.3 / (np.sqrt(0.01 + 0.02) * ndtri(target))
    assert fitted.temperature == pytest.approx(expected, rel=1e-4)
    assert T_MIN < fitted.temperature < T_MAX
    # Offset and temperature together: the symmetric case keeps c at 0.
    if counts[0] == counts[1]:
        joint = fit_offset_and_temperature(mean, var, labels, 0.01, targets="platt")
        assert joint.offset == pytest.approx(0.0, abs=1e-4)
        assert joint.temperature == pytest.approx(expected, rel=1e-3)


def test_platt_targets_find_the_grid_maximum_where_hard_ones_run_to_the_bound():
    """The separated points of the hard-target test above: with Platt's targets the fit
    is the maximum of the same objective on a fine grid of T (brute force)."""
    rng = np.random.default_rng(6)
    given = PlattClassifier(offset=0.05, extra_variance=1e-6)
    labels = np.where(rng.random(300) < 0.1, 1.0, -1.0)
    mean = labels * rng.uniform(0.2, 2.0, 300) - given.offset
    var = rng.uniform(0.01, 0.1, 300)
    t = platt_targets(labels)
    fitted = fit_temperature(given, mean, var, labels, "platt")
    grid = np.geomspace(T_MIN, T_MAX, 4000)
    values = [held_out_log_probability(given.offset, given.extra_variance, mean, var, labels,
                                       g, t) for g in grid]
    assert fitted.temperature == pytest.approx(grid[int(np.argmax(values))], rel=0.01)
    assert T_MIN * 1.5 < fitted.temperature < T_MAX


def test_platt_targets_barely_move_a_temperature_the_labels_determine():
    """40000 labels drawn at T = 3: Platt's targets move the fit by about 1 / N."""
    given, mean, var, labels = _drawn_at_temperature_3()
    hard = fit_temperature(given, mean, var, labels, "hard")
    platt = fit_temperature(given, mean, var, labels, "platt")
    assert platt.temperature == pytest.approx(hard.temperature, rel=1e-3)
    assert platt.temperature >= hard.temperature  # softer targets, never a sharper map
