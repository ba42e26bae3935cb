"""``samples.label_weights``: a thinned sample's label noise grows as its label's share of
its cell falls (``share``), and shrinks as its label's count there grows (``count``), so a
kept sample stands for the labels counted there."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from samplesets import samples_from
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.config import Config, SamplesConfig, load_config
from gpocc.errors import GpoccError
from gpocc.gp.kernels import NeuralNetworkKernel
from gpocc.gp.local import predict_full
from gpocc.gp.model import load_model
from gpocc.io.rasters import read_raster
from gpocc.samples.beams import LabelVotes, SamplePool, finish_samples
from gpocc.samples.sampleset import SampleSet

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "data" / "sample" / "intel_sample.mcap"
SAMPLE_CONFIG = ROOT / "data" / "sample" / "sample.yaml"


def test_a_weighted_pair_predicts_as_every_counted_label_would():
    """Oracle: the dense GP on the raw labels, n_hit copies of +1 and n_free of -1 at each
    site, each with noise sigma^2 N (N the site's count), solved with plain numpy. Two
    samples per site with noise sigma^2 / share carry the same sufficient statistics, so
    the predictions are equal."""
    rng = np.random.default_rng(3)
    sites = rng.uniform(-2, 2, (12, 2))
    hits, frees = rng.integers(1, 9, 12), rng.integers(1, 30, 12)
    kernel = NeuralNetworkKernel(2.0, 1.5, (4.0, 6.0))
    noise = 0.2
    raw_means = np.repeat(np.vstack([sites, sites]), np.concatenate([hits, frees]), axis=0)
    raw_labels = np.repeat(np.r_[np.ones(12), -np.ones(12)], np.concatenate([hits, frees]))
    raw_noise = noise * np.repeat(np.tile(hits + frees, 2), np.concatenate([hits, frees]))
    queries = rng.uniform(-2.5, 2.5, (30, 2))
    k = kernel(raw_means) + np.diag(raw_noise)
    cross = kernel(queries, raw_means)
    mean = cross @ np.linalg.solve(k, raw_labels)
    variance = kernel.diag(queries) - np.einsum("qi,iq->q", cross, np.linalg.solve(k, cross.T))

    total = np.tile(hits + frees, 2)
    pair = samples_from(np.vstack([sites, sites]), np.r_[np.ones(12), -np.ones(12)],
                    noise_factors=total / np.concatenate([hits, frees]))
    pred = predict_full(kernel, noise, pair, queries, level=1)
    np.testing.assert_allclose(pred.mean, mean, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(pred.variance, variance, rtol=1e-5, atol=1e-8)


def test_factors_of_one_are_the_unweighted_model():
    rng = np.random.default_rng(0)
    means = rng.uniform(-2, 2, (40, 2))
    labels = np.where(rng.random(40) < 0.4, 1.0, -1.0)
    kernel = NeuralNetworkKernel(1.0, 1.0, (3.0, 3.0))
    queries = rng.uniform(-2, 2, (10, 2))
    plain = predict_full(kernel, 0.1, samples_from(means, labels), queries, level=1)
    ones = predict_full(kernel, 0.1, samples_from(means, labels, noise_factors=np.ones(40)),
                        queries, level=1)
    np.testing.assert_allclose(ones.mean, plain.mean, rtol=1e-12)
    np.testing.assert_allclose(ones.variance, plain.variance, rtol=1e-12)


def _pool(cell: float) -> tuple[SamplePool, SampleSet]:
    """Raw samples of three cells: 1 hit among 9 free, 6 hits with 2 free, 4 free alone;
    the pool keeps one sample per label and cell and counts the rest."""
    centre = np.array([[0.05, 0.05], [0.35, 0.05], [0.65, 0.05]])
    counts = [(1, 9), (6, 2), (0, 4)]
    means, labels = [], []
    for c, (h, f) in zip(centre, counts, strict=True):
        means += [c] * (h + f)
        labels += [1.0] * h + [-1.0] * f
    raw = samples_from(np.array(means), labels)
    votes = LabelVotes(cell)
    votes.add(raw)
    first = np.unique(np.c_[np.floor(raw.means / cell), raw.labels], axis=0,
                      return_index=True)[1]
    kept = raw.subset(np.sort(first))
    return SamplePool(kept, *votes.table(), n_scans=len(raw)), kept


def test_finish_samples_weights_each_label_by_its_share():
    pool, kept = _pool(0.25)
    config = Config(samples=SamplesConfig(thin_cell_m=0.25, free_clearance_m=0.0,
                                          label_weights="share"))
    samples = finish_samples(pool, config)
    by_cell = {(round(m[0], 2), int(lab)): f for m, lab, f in
               zip(samples.means, samples.labels, samples.noise_factors, strict=True)}
    assert by_cell == pytest.approx({(0.05, 1): 10.0, (0.05, -1): 10 / 9, (0.35, 1): 8 / 6,
                                     (0.35, -1): 4.0, (0.65, -1): 1.0})
    plain = finish_samples(pool, Config(samples=SamplesConfig(
        thin_cell_m=0.25, free_clearance_m=0.0, label_weights="none")))
    assert plain.noise_factors is None and len(plain) == len(kept)
    # With min_label_share the rare label goes first; the rest keep their factors.
    both = finish_samples(pool, Config(samples=SamplesConfig(
        thin_cell_m=0.25, free_clearance_m=0.0, label_weights="share", min_label_share=0.2)))
    assert len(both) == len(kept) - 1 and both.noise_factors.max() == pytest.approx(4.0)


@pytest.mark.parametrize("power", [0.5, 1.0])
def test_finish_samples_weights_each_label_by_its_share_and_count(power):
    """Oracle: the counts of each (cell, label) as :func:`_pool` made its raw samples; a
    kept sample's factor is 1 / share * count^-power."""
    pool, kept = _pool(0.25)
    votes = LabelVotes(0.25)
    votes.add_counts(pool.vote_keys, pool.vote_counts)
    counts = {(0, 1): 1, (0, -1): 9, (1, 1): 6, (1, -1): 2, (2, -1): 4}  # as _pool made them
    config = Config(samples=SamplesConfig(thin_cell_m=0.25, free_clearance_m=0.0,
                                          label_weights="count", label_count_power=power))
    samples = finish_samples(pool, config)
    np.testing.assert_array_equal(votes.count(samples),
                                  [counts[(int(m[0] // 0.25), int(lab))] for m, lab in
                                   zip(samples.means, samples.labels, strict=True)])
    for m, lab, factor in zip(samples.means, samples.labels, samples.noise_factors,
                              strict=True):
        cell = int(m[0] // 0.25)
        own, other = counts[(cell, int(lab))], counts.get((cell, -int(lab)), 0)
        assert factor == pytest.approx((own + other) / own * own ** -power)
    assert samples.noise_factors.min() < 1.0  # the free cell counted four times


def test_count_weights_at_power_one_predict_as_every_counted_sample():
    """Oracle: the dense GP of c_i copies of each site's one label, each copy with the
    same noise, solved with plain numpy. At power 1, one kept sample per site with the
    noise divided by its count carries the same sufficient statistics (cells hold one
    label each, so their share is 1), through the pool's counts and finish_samples."""
    rng = np.random.default_rng(5)
    cell = 0.5
    sites = (rng.choice(64, 14, replace=False)[:, None] // [8, 1] % 8 + 0.5) * cell - 2.0
    labels = np.where(rng.random(14) < 0.4, 1.0, -1.0)
    copies = rng.integers(1, 12, 14)
    raw = samples_from(np.repeat(sites, copies, axis=0), np.repeat(labels, copies))
    votes = LabelVotes(cell)
    votes.add(raw)
    first = np.r_[0, np.cumsum(copies)[:-1]]
    pool = SamplePool(raw.subset(first), *votes.table(), n_scans=len(raw))
    config = Config(samples=SamplesConfig(thin_cell_m=cell, free_clearance_m=0.0,
                                          label_weights="count", label_count_power=1.0))
    kept = finish_samples(pool, config)
    np.testing.assert_allclose(kept.noise_factors, 1.0 / copies)
    kernel = NeuralNetworkKernel(2.0, 1.5, (4.0, 6.0))
    noise = 0.3
    queries = rng.uniform(-2.5, 2.5, (25, 2))
    k = kernel(raw.means) + noise * np.eye(len(raw))
    cross = kernel(queries, raw.means)
    mean = cross @ np.linalg.solve(k, raw.labels)
    variance = kernel.diag(queries) - np.einsum("qi,iq->q", cross, np.linalg.solve(k, cross.T))
    pred = predict_full(kernel, noise, kept, queries, level=1)
    # The copies make the raw system nearly singular: round-off of a few 1e-8.
    np.testing.assert_allclose(pred.mean, mean, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(pred.variance, variance, rtol=1e-5, atol=1e-6)


def test_a_bad_label_weights_value_is_one_clear_error(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("samples:\n  label_weights: counts\n")
    with pytest.raises(GpoccError,
                       match="samples.label_weights' must be 'none', 'share' or 'count'"):
        load_config(path)


@pytest.mark.parametrize("power", [-0.5, 1.5])
def test_a_label_count_power_out_of_range_is_one_clear_error(tmp_path, power):
    path = tmp_path / "bad.yaml"
    path.write_text(f"samples:\n  label_weights: count\n  label_count_power: {power}\n")
    with pytest.raises(GpoccError, match="samples.label_count_power' must be between 0 and 1"):
        load_config(path)


def _train(tmp_path: Path, weights: str, name: str) -> Path:
    config = yaml.safe_load(SAMPLE_CONFIG.read_text()) or {}
    config.setdefault("samples", {})["label_weights"] = weights
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(config))
    model = tmp_path / f"{name}.npz"
    result = CliRunner().invoke(app, ["train", str(SAMPLE), "--config", str(path), "--out",
                                      str(model)])
    assert result.exit_code == 0, result.output
    return model


def test_cli_train_and_map_with_label_weights(tmp_path):
    plain = load_model(_train(tmp_path, "none", "plain"))
    path = _train(tmp_path, "share", "weighted")
    weighted = load_model(path)
    assert plain.samples.noise_factors is None
    factors = weighted.samples.noise_factors
    np.testing.assert_array_equal(weighted.samples.means, plain.samples.means)
    assert factors.shape == (len(weighted.samples),) and factors.min() == 1.0
    assert factors.max() > 1.0  # the sample log has cells seen both free and occupied
    runner = CliRunner()
    maps = []
    for out in ("map-a", "map-b"):
        result = runner.invoke(app, ["map", str(path), "--out", str(tmp_path / out),
                                     "--resolution", "0.2", "--workers", "1"])
        assert result.exit_code == 0, result.output
        maps.append(read_raster(tmp_path / out / "probability.tif")[0])
    np.testing.assert_array_equal(maps[0], maps[1])
    result = runner.invoke(app, ["info", str(path)])
    assert result.exit_code == 0 and f"to {factors.max():.3g})" in result.output
    # A damaged, out-of-range or missing factor array is refused with one line naming
    # the file (a model that weighs labels never loads unweighted).
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    for damage in (lambda f: f * 1e-6, lambda f: f * 1e300, lambda f: f.astype(np.float32),
                   None):
        changed = dict(arrays)
        if damage is None:
            del changed["noise_factors"]
        else:
            changed["noise_factors"] = damage(arrays["noise_factors"])
        broken = tmp_path / "broken.npz"
        np.savez(broken, **changed)
        result = runner.invoke(app, ["info", str(broken)])
        if damage is not None and changed["noise_factors"].dtype == np.float32:
            assert result.exit_code == 0, result.output  # a narrower float is still numbers
            continue
        assert result.exit_code != 0 and "noise_factors" in result.output, result.output
        assert "Traceback" not in result.output
        assert len(result.output.strip().splitlines()) == 1


def test_cli_train_map_and_info_with_count_weights(tmp_path):
    """``count``: factors below 1 (cells counted many times) are saved, loaded and mapped;
    the same samples as unweighted, and ``gpocc info`` counts both kinds of factor."""
    plain = load_model(_train(tmp_path, "none", "plain"))
    path = _train(tmp_path, "count", "counted")
    counted = load_model(path)
    np.testing.assert_array_equal(counted.samples.means, plain.samples.means)
    factors = counted.samples.noise_factors
    assert factors.min() < 1.0 < factors.max()
    runner = CliRunner()
    result = runner.invoke(app, ["map", str(path), "--out", str(tmp_path / "map"),
                                 "--resolution", "0.2", "--workers", "1"])
    assert result.exit_code == 0, result.output
    assert np.isfinite(read_raster(tmp_path / "map" / "probability.tif")[0]).any()
    result = runner.invoke(app, ["info", str(path)])
    assert result.exit_code == 0, result.output
    assert f"{int((factors < 1).sum())} with less" in result.output
