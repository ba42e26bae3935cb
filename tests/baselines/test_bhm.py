"""The Bayesian Hilbert map baseline and `gpocc bhm`, against quadrature and brute force."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
from typer.testing import CliRunner

from gpocc.baselines import bhm
from gpocc.cli import app
from gpocc.config import BHMConfig, Config, SamplesConfig, SensorConfig
from gpocc.errors import GpoccError
from gpocc.io.scans import ScanBatch
from tests.baselines.test_grid import room_ranges

ROOM = (-3.02, -2.47, 3.13, 2.58)  # x_min, y_min, x_max, y_max metres


# --------------------------------------------------------------------------- helpers


def exact_posterior(phi: np.ndarray, labels: np.ndarray, weights: np.ndarray, p0: float,
                    half_width: float = 12.0, n: int = 81):
    """Log evidence, posterior mean and variances of logistic regression with prior
    N(0, I / p0), by brute-force quadrature on a regular grid of the (few) weights."""
    d = phi.shape[1]
    axis = np.linspace(-half_width, half_width, n)
    w = np.stack(np.meshgrid(*([axis] * d), indexing="ij"), axis=-1).reshape(-1, d)
    a = w @ phi.T  # (G, N) logits
    log_lik = -(weights * np.logaddexp(0.0, -labels * a)).sum(axis=1)
    log_prior = -0.5 * p0 * (w**2).sum(axis=1) + 0.5 * d * math.log(p0 / (2 * math.pi))
    log_joint = log_lik + log_prior
    top = log_joint.max()
    mass = np.exp(log_joint - top)
    cell = (axis[1] - axis[0]) ** d
    log_z = top + math.log(mass.sum() * cell)
    prob = mass / mass.sum()
    mean = prob @ w
    var = prob @ (w - mean) ** 2
    return log_z, mean, var


def room_batch(seed: int, n_scans: int = 12, n_beams: int = 120, corrupt: bool = False,
               range_max: float = 8.0) -> ScanBatch:
    rng = np.random.default_rng(seed)
    poses = np.column_stack((rng.uniform(-1.8, 1.8, (n_scans, 2)),
                             rng.uniform(-np.pi, np.pi, n_scans)))
    angles = -np.pi + np.arange(n_beams) * 2 * np.pi / n_beams
    ranges = room_ranges(poses, angles, ROOM)
    if corrupt:
        kinds = rng.integers(0, 10, ranges.shape)
        ranges[kinds == 0] = np.nan
        ranges[kinds == 1] = -np.inf
        ranges[kinds == 2] = 0.01  # below range_min
        ranges[kinds == 3] = np.inf  # no return
    return ScanBatch(sensor="scan", source="room.test", stamps=np.arange(n_scans) * 0.5,
                     angles=angles, ranges=ranges, poses=poses,
                     pose_covariances=np.zeros((n_scans, 3, 3)), range_min=0.05,
                     range_max=range_max, has_pose_covariance=False)


# --------------------------------------------------------------------------- learning


def test_variational_posterior_of_one_weight_is_close_to_the_exact_posterior():
    rng = np.random.default_rng(3)
    x = rng.uniform(0.1, 1.0, 25)
    labels = np.where(rng.uniform(size=25) < 0.7, 1.0, -1.0)
    weights = rng.integers(1, 4, 25).astype(float)
    p0 = 2.0
    post = bhm.variational_em(sp.csr_matrix(x[:, None]), labels, weights, p0, 40)
    log_z, mean, var = exact_posterior(x[:, None], labels, weights, p0, 15.0, 30001)
    # Jaakkola-Jordan's Gaussian sits within a tenth of a posterior standard deviation of
    # the exact mean and, like every such bound, is narrower than the posterior.
    assert abs(post.mean[0] - mean[0]) < 0.1 * math.sqrt(var[0])
    assert 0.6 * var[0] < post.variance[0] <= var[0]
    assert post.bounds[-1] <= log_z
    assert post.bounds[-1] > log_z - 0.5  # a tight bound for one weight
    # With one weight the paper's diagonal update is the exact one.
    diag = bhm.variational_em(sp.csr_matrix(x[:, None]), labels, weights, p0, 40,
                              coupled=False)
    np.testing.assert_allclose(diag.mean, post.mean, rtol=10 * bhm.CG_RTOL)
    np.testing.assert_allclose(diag.variance, post.variance, rtol=10 * bhm.CG_RTOL)


def test_em_raises_a_lower_bound_of_the_exact_evidence_with_overlapping_features():
    # Three weights (two overlapping kernels and the bias) on 1-D data along x.
    rng = np.random.default_rng(5)
    xs = rng.uniform(-0.4, 1.4, 40)
    pts = np.column_stack((xs, np.zeros_like(xs)))
    grid = bhm.InducingGrid(x0=0.0, y0=0.0, spacing=1.0, nx=2, ny=1)
    phi = bhm.features(pts, grid, gamma=1.5)
    assert phi.shape == (40, 3)
    np.testing.assert_allclose(phi.toarray()[:, :2], np.exp(
        -1.5 * (xs[:, None] - np.array([0.0, 1.0])) ** 2), rtol=1e-12)
    labels = np.where(rng.uniform(size=40) < 1.0 / (1.0 + np.exp(-3.0 * (xs - 0.5))), 1.0,
                      -1.0)
    weights = np.ones(40)
    p0 = 0.5
    post = bhm.variational_em(phi, labels, weights, p0, 15)
    log_z, mean, _ = exact_posterior(phi.toarray(), labels, weights, p0, 10.0, 61)
    assert np.all(post.bounds <= log_z)
    assert np.all(np.diff(post.bounds) >= -1e-7)  # EM never lowers the bound
    assert post.bounds[-1] - post.bounds[0] > 1e-3  # and EM did move it
    # The bound at any other xi is lower than at the M-step's xi.
    phi2 = phi.multiply(phi).tocsr()
    best = bhm.evidence_bound(phi, phi2, labels, weights, post.mean, post.variance,
                              bhm.m_step(phi, phi2, post.mean, post.variance), p0)
    for scale in (0.5, 0.9, 1.1, 2.0):
        xi = scale * bhm.m_step(phi, phi2, post.mean, post.variance)
        assert bhm.evidence_bound(phi, phi2, labels, weights, post.mean, post.variance, xi,
                                  p0) <= best + 1e-9
    # The latent mean follows the exact posterior mean's logits.
    a_vb, a_exact = phi @ post.mean, phi.toarray() @ mean
    assert np.corrcoef(a_vb, a_exact)[0, 1] > 0.99


def test_jj_lambda_and_bound_against_the_logistic():
    xi = np.array([0.0, 1e-6, 0.3, 2.0, 40.0])
    lam = bhm.jj_lambda(xi)
    np.testing.assert_allclose(lam[2:], (1 / (1 + np.exp(-xi[2:])) - 0.5) / (2 * xi[2:]))
    assert lam[0] == pytest.approx(0.125) and lam[1] == pytest.approx(0.125)
    a = np.linspace(-60, 60, 2401)

    def jj(a, x):
        return -np.logaddexp(0, -x) + (a - x) / 2 - bhm.jj_lambda(x) * (a**2 - x**2)

    for x in xi:
        assert np.all(jj(a, x) <= -np.logaddexp(0, -a) + 1e-12)
        for at in (x, -x):  # tight at a = +-xi
            assert jj(at, x) == pytest.approx(-np.logaddexp(0, -at), abs=1e-9)


# --------------------------------------------------------------------------- data


def test_training_points_follow_the_beam_rules_per_beam():
    batch = room_batch(7, n_scans=3, n_beams=36, corrupt=True, range_max=3.0)
    cfg = Config(bhm=BHMConfig(free_spacing_m=0.3, hit_gap_m=0.1, sample_cell_m=0.0),
                 sensors=(SensorConfig(name="scan", no_return_free_m=2.0),))
    got = bhm.training_points([batch], cfg)
    hits, free = [], []
    for s in range(batch.n_scans):
        x, y, th = batch.poses[s]
        for b, r in enumerate(batch.ranges[s]):
            if np.isnan(r) or r < batch.range_min:
                continue
            u = np.array([math.cos(th + batch.angles[b]), math.sin(th + batch.angles[b])])
            if np.isfinite(r) and r < batch.range_max:
                hits.append((x, y) + r * u)
                end = r - 0.1
            else:
                end = min(2.0, batch.range_max)
            k = 1
            while k * 0.3 <= end + 1e-12:
                free.append((x, y) + k * 0.3 * u)
                k += 1
    want = np.concatenate((hits, free))
    labels = np.concatenate((np.ones(len(hits)), -np.ones(len(free))))
    order = lambda p, lab: np.lexsort((p[:, 1].round(9), p[:, 0].round(9), lab))  # noqa: E731
    i, j = order(got.points, got.labels), order(want, labels)
    np.testing.assert_allclose(got.points[i], want[j], atol=1e-9)
    np.testing.assert_array_equal(got.labels[i], labels[j])
    assert np.all(got.weights == 1)

    counted = bhm.training_points([batch], dataclasses.replace(
        cfg, bhm=dataclasses.replace(cfg.bhm, sample_cell_m=0.5)))
    assert len(counted) < len(got)
    for lab in (1.0, -1.0):
        sel, raw = counted.labels == lab, got.labels == lab
        assert counted.weights[sel].sum() == raw.sum()
        # Counting keeps each label's centre of mass.
        np.testing.assert_allclose(counted.weights[sel] @ counted.points[sel] / raw.sum(),
                                   got.points[raw].mean(axis=0), atol=1e-9)


def test_fit_is_deterministic_and_a_room_has_walls_and_free_space():
    batch = room_batch(11)
    cfg = Config(samples=SamplesConfig())
    runs = []
    for _ in range(2):
        model = bhm.fit_bhm(bhm.training_points([batch], cfg), cfg.bhm)
        runs.append(model)
    np.testing.assert_array_equal(runs[0].posterior.mean, runs[1].posterior.mean)
    np.testing.assert_array_equal(runs[0].posterior.variance, runs[1].posterior.variance)
    x0, y0, x1, y1 = ROOM
    t = np.linspace(0.1, 0.9, 25)
    walls = np.concatenate([np.column_stack((x0 + t * (x1 - x0), np.full(25, y0))),
                            np.column_stack((np.full(25, x1), y0 + t * (y1 - y0)))])
    inside = np.column_stack((np.linspace(-1.5, 1.5, 25), np.linspace(-1.2, 1.4, 25)))
    p_wall, v_wall = bhm.predict(runs[0], walls)
    p_free, _ = bhm.predict(runs[0], inside)
    assert np.all(p_wall > 0.5) and np.all(p_free < 0.5)
    # Far outside the data the logit's variance goes back to the prior's (bias included).
    _, v_far = bhm.predict(runs[0], np.array([[40.0, 40.0]]))
    assert v_far[0] == pytest.approx(runs[0].posterior.variance[-1])
    assert np.all(v_wall < 1.0 / cfg.bhm.prior_precision)


# --------------------------------------------------------------------------- CLI


def _write_room_bag(tmp_path: Path) -> Path:
    from gpocc.io.bags import write_bag

    bag = tmp_path / "room.mcap"
    write_bag(bag, [room_batch(13, n_scans=10, n_beams=180)], [("/scan", "/pose")], "mcap")
    return bag


def test_bhm_command_maps_a_room_that_evaluate_scores(tmp_path: Path):
    rasterio = pytest.importorskip("rasterio")
    bag = _write_room_bag(tmp_path)
    out = tmp_path / "bhm"
    runner = CliRunner()
    result = runner.invoke(app, ["bhm", str(bag), "--resolution", "0.1", "--out", str(out)])
    assert result.exit_code == 0, result.output
    for name in ("probability.tif", "variance.tif", "class.tif", "map.yaml", "map.pgm",
                 "preview.png", "metadata.json"):
        assert (out / name).is_file(), name
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["method"] == "bhm"
    assert meta["bhm"]["gamma"] == BHMConfig().gamma
    assert np.all(np.diff(meta["bhm"]["lower_bounds"]) >= -1e-6 * abs(
        meta["bhm"]["lower_bounds"][0]))

    # Truth: points on the walls (occupied) and inside the room (free).
    x0, y0, x1, y1 = ROOM
    rng = np.random.default_rng(1)
    t = rng.uniform(0.05, 0.95, 200)
    side = rng.integers(0, 4, 200)
    wall = np.where(side[:, None] == 0, np.column_stack((x0 + t * (x1 - x0), np.full(200, y0))),
           np.where(side[:, None] == 1, np.column_stack((x0 + t * (x1 - x0), np.full(200, y1))),
           np.where(side[:, None] == 2, np.column_stack((np.full(200, x0), y0 + t * (y1 - y0))),
                    np.column_stack((np.full(200, x1), y0 + t * (y1 - y0))))))
    free = np.column_stack((rng.uniform(x0 + 0.5, x1 - 0.5, 400),
                            rng.uniform(y0 + 0.5, y1 - 0.5, 400)))
    truth = tmp_path / "truth.csv"
    rows = [f"{x:.4f},{y:.4f},1" for x, y in wall] + [f"{x:.4f},{y:.4f},0" for x, y in free]
    truth.write_text("x,y,label\n" + "\n".join(rows) + "\n")
    ev = runner.invoke(app, ["evaluate", str(out), "--ground-truth", str(truth), "--out",
                             str(tmp_path / "eval")])
    assert ev.exit_code == 0, ev.output
    scores = json.loads((tmp_path / "eval" / "results.json").read_text())["maps"][0]
    assert scores["auc"] > 0.9

    with rasterio.open(out / "probability.tif") as ds:
        prob = ds.read(1)
        rows_w, cols_w = (np.asarray(v) for v in rasterio.transform.rowcol(
            ds.transform, wall[:, 0], wall[:, 1]))
        rows_f, cols_f = (np.asarray(v) for v in rasterio.transform.rowcol(
            ds.transform, free[:, 0], free[:, 1]))
    # The wall line may fall on either side of a cell edge: the wall is within a cell.
    near_wall = np.array([np.nanmax(prob[r - 1:r + 2, c - 1:c + 2])
                          for r, c in zip(rows_w, cols_w, strict=True)])
    assert np.mean(near_wall > 0.5) > 0.95
    assert np.all(prob[rows_f, cols_f] < 0.5)

    again = runner.invoke(app, ["bhm", str(bag), "--resolution", "0.1", "--out", str(out)])
    assert again.exit_code == 2 and "--force" in again.stderr
    wide = runner.invoke(app, ["bhm", str(bag), "--resolution", "0.2", "--out", str(out),
                               "--bounds", "-8", "-8", "8", "8", "--force"])
    assert wide.exit_code == 0, wide.output
    with rasterio.open(out / "probability.tif") as ds:
        prob = ds.read(1)
        xs, ys = rasterio.transform.xy(ds.transform, *np.indices(prob.shape), offset="center")
    xs, ys = np.asarray(xs).reshape(prob.shape), np.asarray(ys).reshape(prob.shape)
    # Beyond map.max_beam_distance_m (1.5 m) plus the coverage raster's error (0.24 m) of
    # every beam there are no data; well inside the room there are.
    gap = np.maximum.reduce([x0 - xs, xs - x1, y0 - ys, ys - y1])
    assert np.all(np.isnan(prob[gap > 1.75]))
    assert np.all(np.isfinite(prob[gap < -0.5]))


@pytest.mark.parametrize("text, match", [
    ("bhm:\n  gama: 3\n", "unknown key 'gama' under 'bhm'"),
    ("bhm:\n  gamma: -1\n", "key 'bhm.gamma' must be positive"),
    ("bhm:\n  gamma: 400\n", "key 'bhm.gamma'"),
    ("bhm:\n  gamma: 0.0001\n", "key 'bhm.gamma'"),
    ("bhm:\n  em_iterations: 0\n", "key 'bhm.em_iterations' must be positive"),
    ("bhm:\n  em_iterations: 2.5\n", "key 'bhm.em_iterations' must be an integer"),
    ("bhm:\n  mean_update: full\n", "key 'bhm.mean_update'"),
    ("bhm:\n  sample_cell_m: -0.1\n", "key 'bhm.sample_cell_m' must not be negative"),
])
def test_bad_bhm_config_is_one_line(tmp_path: Path, text: str, match: str):
    bag = tmp_path / "in.mcap"
    bag.write_bytes(b"")
    path = tmp_path / "job.yaml"
    path.write_text(text)
    out = tmp_path / "m"
    result = CliRunner().invoke(app, ["bhm", str(bag), "--config", str(path), "--out",
                                      str(out)])
    assert result.exit_code == 2
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and str(path) in lines[0] and match in lines[0], result.stderr
    assert "Traceback" not in result.output and not out.exists()


def test_the_paper_diagonal_update_is_exact_for_disjoint_features():
    # Features whose supports do not overlap (and no shared bias): the factorised
    # posterior's exact means are the paper's per-weight means.
    rng = np.random.default_rng(2)
    n = 30
    col = rng.integers(0, 3, n)
    vals = rng.uniform(0.2, 1.0, n)
    phi = sp.csr_matrix((vals, (np.arange(n), col)), shape=(n, 3))
    labels = np.where(rng.uniform(size=n) < 0.4, 1.0, -1.0)
    weights = np.ones(n)
    a = bhm.variational_em(phi, labels, weights, 1.0, 8)
    b = bhm.variational_em(phi, labels, weights, 1.0, 8, coupled=False)
    np.testing.assert_allclose(a.mean, b.mean, rtol=10 * bhm.CG_RTOL)
    np.testing.assert_allclose(a.bounds, b.bounds, rtol=1e-8)
    assert list(itertools.accumulate(b.bounds, max)) == pytest.approx(list(b.bounds))


def test_bhm_command_is_deterministic(tmp_path: Path):
    rasterio = pytest.importorskip("rasterio")
    bag = _write_room_bag(tmp_path)
    layers = []
    for name in ("a", "b"):
        result = CliRunner().invoke(app, ["bhm", str(bag), "--resolution", "0.2", "--out",
                                          str(tmp_path / name)])
        assert result.exit_code == 0, result.output
        with rasterio.open(tmp_path / name / "probability.tif") as p, \
                rasterio.open(tmp_path / name / "variance.tif") as v:
            layers.append((p.read(1), v.read(1)))
    for first, second in zip(*layers, strict=True):
        np.testing.assert_array_equal(first, second)


def test_bhm_command_bad_input_is_one_line(tmp_path: Path):
    bad = tmp_path / "broken.mcap"
    bad.write_bytes(b"\x00not a bag" * 10)
    result = CliRunner().invoke(app, ["bhm", str(bad), "--out", str(tmp_path / "b")])
    assert result.exit_code == 2
    lines = [ln for ln in result.stderr.splitlines() if ln.startswith("gpocc bhm: error")]
    assert len(lines) == 1 and "broken.mcap" in lines[0]
    assert "Traceback" not in result.output and not (tmp_path / "b").exists()


def test_no_usable_beam_is_an_error():
    batch = room_batch(3, n_scans=2, n_beams=10)
    batch = dataclasses.replace(batch, ranges=np.full_like(batch.ranges, np.nan))
    with pytest.raises(GpoccError, match="no usable beam"):
        bhm.training_points([batch], Config())
