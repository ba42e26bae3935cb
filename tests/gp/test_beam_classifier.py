"""The classifier offset fitted on held-out beams (`model.training.classifier_offset`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.special import ndtr

from gpocc.config import Config, ModelConfig, SamplesConfig, TrainingConfig, load_config
from gpocc.errors import GpoccError
from gpocc.gp.classify import (
    C_BOUND,
    beam_holdout_predictions,
    cell_groups,
    fit_offset,
    fit_offset_and_temperature,
    held_out_log_probability,
    offset_bound,
    unique_cells,
)
from gpocc.gp.kernels import NeuralNetworkKernel
from gpocc.gp.local import centred_problem, predict_local
from gpocc.gp.model import build_model
from gpocc.samples.beams import build_samples
from gpocc.samples.heldout import (
    CalibrationPoints,
    beam_points,
    calibration_points,
    labelled_points,
    position_std,
    subset_batch,
)
from tests.evaluation.test_split import SENSOR, room_batch

CONFIG = Config(sensors=(SENSOR,), seed=3)
#: Held-out hits and free points along their beams only (no near-wall free points).
ALONG_BEAM = dataclasses.replace(CONFIG, model=ModelConfig(
    training=TrainingConfig(calibration_near_wall=0)))


def test_calibration_points_are_the_heldout_scans_numbered_like_the_samples():
    first, second = room_batch(n_scans=23, seed=1), room_batch(n_scans=17, seed=2)
    calib = calibration_points([first, second], ALONG_BEAM, every=5)
    # Scans 4, 9, 14, 19 of the first batch, then 4, 9, 14 of the second after its 23.
    np.testing.assert_array_equal(calib.scan_ids, [4, 9, 14, 19, 27, 32, 37])
    samples = build_samples([first, second], CONFIG)
    assert set(calib.scan_ids) <= set(samples.scan_ids.tolist())
    # The points are those of the held-out scans alone, drawn with the config's seed and
    # the batch's first scan id (so that a batch added later draws the same points).
    a = labelled_points(subset_batch(first, np.array([4, 9, 14, 19])), SENSOR, 3,
                        np.random.default_rng([CONFIG.seed, 0]))
    b = labelled_points(subset_batch(second, np.array([4, 9, 14])), SENSOR, 3,
                        np.random.default_rng([CONFIG.seed, 23]))
    np.testing.assert_array_equal(calib.points, np.concatenate([a[0], b[0]]))
    np.testing.assert_array_equal(calib.labels, np.where(np.concatenate([a[1], b[1]]) > 0,
                                                         1.0, -1.0))
    assert calib.usable
    assert not CalibrationPoints(calib.points[:2], np.ones(2), calib.scan_ids).usable
    # The second batch alone, added after the first's 23 scans, gives the same points.
    later = calibration_points([second], ALONG_BEAM, every=5, scan_offset=23)
    np.testing.assert_array_equal(later.scan_ids, [27, 32, 37])
    np.testing.assert_array_equal(later.points, b[0])


def test_calibration_near_wall_adds_free_points_in_front_of_the_hits():
    """``calibration_near_wall`` keeps the other points as drawn and adds free points
    0.05-0.3 m in front of each held-out hit, along its beam (checked against the hits'
    own geometry: on the segment from the laser, its beam's point at range 0, to the
    hit)."""
    batch = room_batch(n_scans=23, seed=1)
    plain = calibration_points([batch], ALONG_BEAM, every=5)
    config = dataclasses.replace(CONFIG, model=ModelConfig(
        training=TrainingConfig(calibration_near_wall=1)))
    both = calibration_points([batch], config, every=5)
    n = len(plain.labels)
    np.testing.assert_array_equal(both.points[:n], plain.points)
    np.testing.assert_array_equal(both.labels[:n], plain.labels)
    near = both.points[n:]
    assert len(near) > 0 and np.all(both.labels[n:] == -1.0)
    held = subset_batch(batch, np.array([4, 9, 14, 19]))
    hits = np.isfinite(held.ranges) & (held.ranges < held.range_max)
    assert len(near) == int(hits.sum())
    # Each near-wall point lies on the beam of its hit, 0.05-0.3 m short of it.
    lasers = beam_points(held.poses, held.angles, np.zeros(held.ranges.shape + (1,)),
                         SENSOR)[hits].reshape(-1, 2)
    ends = labelled_points(held, SENSOR, 0, np.random.default_rng(0))[0]
    to_hit = np.linalg.norm(ends - lasers, axis=1)
    to_near = np.linalg.norm(near - lasers, axis=1)
    gap = to_hit - to_near
    assert np.all(gap >= 0.05 - 1e-9) and np.all(gap <= 0.3 + 1e-9)
    cross = ((ends - lasers)[:, 0] * (near - lasers)[:, 1]
             - (ends - lasers)[:, 1] * (near - lasers)[:, 0])
    np.testing.assert_allclose(cross / to_hit, 0.0, atol=1e-9)


def test_heldout_predictions_equal_the_gp_of_the_other_scans():
    """With every remaining sample in each local problem, each block's predictions are the
    GP of the samples of the other scans (brute force, centred at the block's centre as
    every local problem is), and no held-out scan's sample is used."""
    batch = room_batch(n_scans=8, n_beams=8, seed=4)
    config = dataclasses.replace(CONFIG, samples=SamplesConfig(free_spacing_m=1.5,
                                                               thin_cell_m=0.6))
    samples = build_samples([batch], config)
    calib = calibration_points([batch], config, every=4)
    kernel = NeuralNetworkKernel(2.0, 20.0, (30.0, 30.0))
    mean, var, labels = beam_holdout_predictions(
        kernel, 0.1, samples, calib, 2, neighbours=len(samples), block_size_m=1.0,
        max_blocks=1000, rng=np.random.default_rng(0))
    rest = samples.subset(np.flatnonzero(~np.isin(samples.scan_ids, calib.scan_ids)))
    assert 0 < len(rest) < len(samples)
    keys = np.floor(calib.points).astype(int)
    want_mean, want_var, want_labels = [], [], []
    for key in np.unique(keys, axis=0):  # blocks in the function's order
        rows = np.flatnonzero((keys == key).all(axis=1))
        problem = centred_problem(rest, np.arange(len(rest)), key + 0.5)
        pred = predict_local(kernel, 0.1, problem, calib.points[rows], 2)
        want_mean.append(pred.mean)
        want_var.append(pred.variance)
        want_labels.append(calib.labels[rows])
    np.testing.assert_array_equal(labels, np.concatenate(want_labels))
    np.testing.assert_allclose(mean, np.concatenate(want_mean), rtol=0, atol=1e-9)
    np.testing.assert_allclose(var, np.concatenate(want_var), rtol=0, atol=1e-9)


def test_blocks_and_points_per_block_are_capped():
    batch = room_batch(n_scans=40, n_beams=90, seed=5)
    samples = build_samples([batch], CONFIG)
    calib = calibration_points([batch], CONFIG, every=2)
    kernel = NeuralNetworkKernel(2.0, 20.0, (30.0, 30.0))
    _, _, few = beam_holdout_predictions(kernel, 0.1, samples, calib, 2, 64, 1.0, 3,
                                         np.random.default_rng(0))
    _, _, all_blocks = beam_holdout_predictions(kernel, 0.1, samples, calib, 2, 64, 1.0,
                                                10_000, np.random.default_rng(0))
    from gpocc.gp.classify import POINTS_PER_BLOCK
    assert 0 < few.size <= 3 * POINTS_PER_BLOCK
    assert few.size < all_blocks.size <= calib.labels.size


def _training(offset: str) -> Config:
    return dataclasses.replace(CONFIG, model=ModelConfig(
        neighbours=64, block_size_m=1.0,
        training=TrainingConfig(patches=2, patch_size=60, anneal_maxfun=4, lbfgs_maxiter=3,
                                classifier_offset=offset, calibration_blocks=20,
                                classifier_temperature="none")))


def test_offset_maximises_the_heldout_log_probability():
    rng = np.random.default_rng(8)
    mean, var = rng.normal(0.2, 1.0, 400), rng.uniform(0.01, 0.2, 400)
    labels = np.where(rng.random(400) < ndtr((mean - 0.3) / np.sqrt(0.05 + var)), 1.0, -1.0)
    fit = fit_offset(mean, var, labels, 0.05)
    assert fit.extra_variance == 0.05
    grid = np.linspace(-2, 2, 4001)
    scores = [held_out_log_probability(c, 0.05, mean, var, labels) for c in grid]
    assert fit.offset == pytest.approx(grid[int(np.argmax(scores))], abs=2e-3)
    assert held_out_log_probability(fit.offset, 0.05, mean, var, labels) >= max(scores) - 1e-9


def test_model_refits_its_offset_on_the_heldout_beams():
    batch = room_batch(n_scans=30, n_beams=40, seed=6)
    config = _training("beams")
    samples = build_samples([batch], config)
    calib = calibration_points([batch], config, config.model.training.calibration_every)
    model = build_model(samples, config, calibration=calib)
    plain = build_model(samples, _training("holdout"))
    assert model.training["classifier_offset"] == "beams"
    assert plain.training["classifier_offset"] == "holdout"
    assert model.kernel == plain.kernel  # the same GP; only the offset differs
    mean, var, labels = beam_holdout_predictions(
        model.kernel, model.noise_variance, model.samples, calib, model.level, 64, 1.0, 20,
        np.random.default_rng(config.seed + 2), backend=model.backend)
    assert model.training["classifier_points"] == labels.size > 0
    bound = offset_bound(mean, config.model.training.classifier_offset_range)
    assert model.classifier == fit_offset(mean, var, labels, plain.classifier.extra_variance,
                                          bound=bound,
                                          targets=config.model.training.classifier_targets)
    assert model.training["classifier_offset_bound"] == bound < C_BOUND
    assert plain.training["classifier_offset_bound"] == C_BOUND
    assert model.classifier.offset != plain.classifier.offset


@pytest.mark.parametrize("calibration", [None, "one class"])
def test_without_usable_heldout_beams_the_offset_is_the_holdouts(calibration):
    batch = room_batch(n_scans=30, n_beams=40, seed=6)
    samples = build_samples([batch], _training("beams"))
    calib = None
    if calibration == "one class":
        full = calibration_points([batch], CONFIG, 10)
        calib = CalibrationPoints(full.points[full.labels > 0], full.labels[full.labels > 0],
                                  full.scan_ids)
    beams = build_model(samples, _training("beams"), calibration=calib)
    plain = build_model(samples, _training("holdout"))
    assert beams.training["classifier_offset"] == "holdout"
    assert beams.classifier == plain.classifier


def test_points_placed_by_uncertain_poses_are_left_out():
    """A robot whose pose is known to 0.3 m gives no calibration points at a 0.075 m
    limit; one known to 1 mm gives all of them."""
    sharp = room_batch(n_scans=20, seed=9)
    sharp = dataclasses.replace(sharp, pose_covariances=np.broadcast_to(
        np.diag([1e-6, 1e-6, 1e-8]), (20, 3, 3)).copy(), has_pose_covariance=True)
    blurred = dataclasses.replace(sharp, pose_covariances=np.broadcast_to(
        np.diag([0.09, 0.09, 1e-4]), (20, 3, 3)).copy())
    quiet = dataclasses.replace(CONFIG, sensors=(dataclasses.replace(
        SENSOR, range_variance_m2=0.0, bearing_variance_deg2=0.0),))
    everything = calibration_points([sharp], quiet, 4)
    assert len(calibration_points([sharp], quiet, 4, max_position_std_m=0.075).points) == \
        len(everything.points) > 0
    assert len(calibration_points([blurred], quiet, 4, max_position_std_m=0.075).points) == 0
    # Per point: the heading error grows with range; the limit keeps the near points.
    std = position_std(blurred, quiet.sensors[0], np.array([0, 0]), np.array([0.0, 10.0]))
    np.testing.assert_allclose(std, np.sqrt([0.09, 0.09 + 0.5 * 100 * 1e-4]))


def _flatter_predictions() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Held-out predictions with labels drawn from a flatter classifier than the latent
    one: T about 2, c = -0.3."""
    rng = np.random.default_rng(9)
    mean, var = rng.normal(0.2, 1.0, 400), rng.uniform(0.01, 0.2, 400)
    labels = np.where(rng.random(400) < ndtr((mean - 0.3) / (2.0 * np.sqrt(0.05 + var))),
                      1.0, -1.0)
    return mean, var, labels


def test_offset_and_temperature_maximise_the_heldout_log_probability_together():
    mean, var, labels = _flatter_predictions()
    fit = fit_offset_and_temperature(mean, var, labels, 0.05)
    assert fit.extra_variance == 0.05
    offsets, log_t = np.linspace(-1.5, 1.0, 251), np.linspace(-1.0, 2.0, 301)
    scores = np.array([[held_out_log_probability(c, 0.05, mean, var, labels, np.exp(lt))
                        for lt in log_t] for c in offsets])
    i, j = np.unravel_index(np.argmax(scores), scores.shape)
    assert fit.offset == pytest.approx(offsets[i], abs=0.02)
    assert np.log(fit.temperature) == pytest.approx(log_t[j], abs=0.02)
    assert held_out_log_probability(fit.offset, 0.05, mean, var, labels,
                                    fit.temperature) >= scores.max() - 1e-6


@pytest.mark.parametrize("offset_range", ["wide", "latent"])
def test_with_a_beam_temperature_the_offset_is_fitted_with_it(offset_range):
    """... within the configured range (``classifier_offset_range``)."""
    batch = room_batch(n_scans=30, n_beams=40, seed=6)
    config = dataclasses.replace(_training("beams"), model=dataclasses.replace(
        _training("beams").model, training=dataclasses.replace(
            _training("beams").model.training, classifier_temperature="beams",
            classifier_offset_range=offset_range)))
    samples = build_samples([batch], config)
    calib = calibration_points([batch], config, config.model.training.calibration_every)
    model = build_model(samples, config, calibration=calib)
    plain = build_model(samples, _training("holdout"))
    mean, var, labels = beam_holdout_predictions(
        model.kernel, model.noise_variance, model.samples, calib, model.level, 64, 1.0, 20,
        np.random.default_rng(config.seed + 2), backend=model.backend)
    assert model.training["classifier_offset"] == "beams"
    bound = 100.0 if offset_range == "wide" else float(np.max(np.abs(mean)))
    assert model.classifier == fit_offset_and_temperature(
        mean, var, labels, plain.classifier.extra_variance, bound,
        config.model.training.classifier_targets)


def _uninformative_means(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Held-out predictions whose means barely separate the labels while their variances
    do: free points where the map is sure, occupied ones where it is not."""
    rng = np.random.default_rng(seed)
    var = rng.uniform(0.001, 0.3, 600)
    labels = np.where(rng.random(600) < var / 0.3, 1.0, -1.0)
    mean = rng.normal(0.0, 0.5, 600) + 0.01 * labels
    return mean, var, labels


def test_a_wide_offset_runs_out_with_the_temperature_where_the_means_do_not_separate():
    """The limit the latent range rules out: c and T far out together, p a function of
    the variance alone, beats every fit with c among the means; a latent range keeps c
    within the largest |mean| and is the best fit in that box (grid oracle)."""
    mean, var, labels = _uninformative_means(4)
    wide = fit_offset_and_temperature(mean, var, labels, 1e-6)
    bound = offset_bound(mean, "latent")
    assert bound == pytest.approx(np.max(np.abs(mean)))
    assert abs(wide.offset) > 10 * bound and wide.temperature > 10
    latent = fit_offset_and_temperature(mean, var, labels, 1e-6, bound)
    assert abs(latent.offset) <= bound + 1e-12
    offsets, log_t = np.linspace(-bound, bound, 201), np.linspace(np.log(1e-2), np.log(1e3), 301)
    scores = np.array([[held_out_log_probability(c, 1e-6, mean, var, labels, np.exp(lt))
                        for lt in log_t] for c in offsets])
    assert held_out_log_probability(latent.offset, 1e-6, mean, var, labels,
                                    latent.temperature) >= scores.max() - 1e-6
    assert held_out_log_probability(wide.offset, 1e-6, mean, var, labels,
                                    wide.temperature) > scores.max()


def test_a_latent_offset_range_changes_nothing_where_the_means_separate():
    mean, var, labels = _flatter_predictions()
    wide = fit_offset_and_temperature(mean, var, labels, 0.05)
    latent = fit_offset_and_temperature(mean, var, labels, 0.05,
                                        offset_bound(mean, "latent"))
    assert abs(wide.offset) < np.max(np.abs(mean))
    assert latent.offset == pytest.approx(wide.offset, abs=1e-4)
    assert latent.temperature == pytest.approx(wide.temperature, rel=1e-3)
    assert offset_bound(mean, "wide") == offset_bound(np.zeros(0), "latent") == 100.0


def test_a_bad_classifier_targets_value_is_one_clear_error(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("model:\n  training:\n    classifier_targets: soft\n")
    with pytest.raises(GpoccError, match="classifier_targets' must be 'platt' or 'hard'"):
        load_config(path)


def test_a_bad_offset_range_is_one_clear_error(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("model:\n  training:\n    classifier_offset_range: narrow\n")
    with pytest.raises(GpoccError, match="classifier_offset_range' must be 'wide' or 'latent'"):
        load_config(path)


@pytest.mark.parametrize("spread", [3, 1000, 2**40])
def test_unique_cells_equal_numpy_unique_of_rows(spread):
    """Against ``np.unique(axis=0, return_inverse=True)``: negative cells, repeats, and
    a range too wide for one int64 key (the records fallback)."""
    rng = np.random.default_rng(spread)
    cells = rng.integers(-spread, spread, (5000, 2))
    cells[::7] = cells[3]  # many repeats of one cell
    got, inverse = unique_cells(cells)
    want, want_inverse = np.unique(cells, axis=0, return_inverse=True)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(inverse, want_inverse.ravel())
    np.testing.assert_array_equal(got[inverse], cells)
    empty, none = unique_cells(np.zeros((0, 2), dtype=np.int64))
    assert empty.shape == (0, 2) and none.size == 0


@pytest.mark.parametrize("spread", [3, 1000, 2**40])
def test_cell_groups_list_each_cells_rows_in_input_order(spread):
    """Against a dictionary of each distinct cell's rows, in order of appearance, and the
    cells sorted as rows: negative cells, repeats, a range too wide for one key."""
    rng = np.random.default_rng(spread + 1)
    cells = rng.integers(-spread, spread, (3000, 2))
    cells[::5] = cells[2]
    unique, order, bounds = cell_groups(cells)
    rows: dict[tuple[int, int], list[int]] = {}
    for i, cell in enumerate(map(tuple, cells.tolist())):
        rows.setdefault(cell, []).append(i)
    assert [tuple(c) for c in unique.tolist()] == sorted(rows)
    assert bounds[0] == 0 and bounds[-1] == len(cells) and len(bounds) == len(unique) + 1
    for g, cell in enumerate(map(tuple, unique.tolist())):
        assert order[bounds[g]:bounds[g + 1]].tolist() == rows[cell]
    empty, none, first = cell_groups(np.zeros((0, 2), dtype=np.int64))
    assert empty.shape == (0, 2) and none.size == 0 and first.tolist() == [0]
