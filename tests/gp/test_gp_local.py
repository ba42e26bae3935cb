"""Local GP inference against the full GP, and the uncertain-input 1-D case (paper Fig. 1)."""

from __future__ import annotations

import numpy as np
import pytest

from gpocc.gp.kernels import NeuralNetworkKernel, SquaredExponentialKernel
from gpocc.gp.local import (
    NeighbourIndex,
    leave_one_out,
    predict_full,
    predict_local,
    training_covariance,
)
from gpocc.samples.sampleset import SampleSet


def make_samples(means, covariances, labels, scan_ids=None) -> SampleSet:
    n = len(means)
    return SampleSet(
        means=np.asarray(means, float),
        covariances=np.asarray(covariances, float),
        labels=np.asarray(labels, float),
        scan_ids=np.arange(n) if scan_ids is None else np.asarray(scan_ids),
        pose_factors=np.zeros((n, 2, 3)),
        sensor_ids=np.zeros(n, dtype=np.int16),
    )


def room_samples(rng: np.random.Generator, n: int = 400) -> SampleSet:
    """Random points in a 6 x 6 m square: occupied near the walls, free inside."""
    pts = rng.uniform(-3, 3, size=(n, 2))
    near_wall = np.max(np.abs(pts), axis=1) > 2.6
    labels = np.where(near_wall, 1.0, -1.0)
    covs = np.einsum("n,ij->nij", rng.uniform(0.0005, 0.01, n), np.eye(2))
    return make_samples(pts, covs, labels)


def test_full_neighbourhood_equals_full_gp():
    rng = np.random.default_rng(0)
    samples = room_samples(rng, 120)
    kernel = NeuralNetworkKernel(1.0, 1.0, (2.0, 2.0))
    queries = rng.uniform(-3, 3, size=(50, 2))
    full = predict_full(kernel, 0.1, samples, queries, 3)
    problem = NeighbourIndex(samples).problem(np.zeros(2), len(samples))
    local = predict_local(kernel, 0.1, problem, queries, 3)
    np.testing.assert_allclose(local.mean, full.mean, atol=1e-8)
    np.testing.assert_allclose(local.variance, full.variance, atol=1e-8)


def test_local_approximation_converges_to_full_gp():
    # With a short-range kernel, distant samples carry little weight: local problems must
    # reproduce the brute-force full GP closely, and more neighbours must bring them closer.
    rng = np.random.default_rng(1)
    samples = room_samples(rng, 500)
    kernel = SquaredExponentialKernel(1.0, (0.4, 0.4))
    index = NeighbourIndex(samples)
    queries = rng.uniform(-2.5, 2.5, size=(40, 2))
    full = predict_full(kernel, 0.1, samples, queries, 3)

    def local_error(neighbours: int) -> tuple[float, float]:
        preds = [predict_local(kernel, 0.1, index.problem(q, neighbours), q[None, :], 3)
                 for q in queries]
        mean = np.array([p.mean[0] for p in preds])
        var = np.array([p.variance[0] for p in preds])
        return np.max(np.abs(mean - full.mean)), np.max(np.abs(var - full.variance))

    coarse = local_error(100)
    fine = local_error(250)
    assert fine[0] < 0.02 and fine[1] < 0.02
    assert fine[0] < coarse[0] and fine[1] <= coarse[1]


def test_local_problem_is_centred_and_translation_consistent_for_nn_kernel():
    # The NN kernel is not translation invariant: shifting all data and queries must give
    # the same local prediction, because every local problem is centred at the origin.
    rng = np.random.default_rng(2)
    samples = room_samples(rng, 200)
    kernel = NeuralNetworkKernel(1.0, 1.0, (3.0, 3.0))
    shift = np.array([250.0, -140.0])
    shifted = make_samples(samples.means + shift, samples.covariances, samples.labels)
    q = rng.uniform(-1, 1, size=(10, 2))
    centre = np.array([0.2, -0.3])
    a = predict_local(kernel, 0.1, NeighbourIndex(samples).problem(centre, 80), q, 3)
    b = predict_local(kernel, 0.1, NeighbourIndex(shifted).problem(centre + shift, 80),
                      q + shift, 3)
    np.testing.assert_allclose(a.mean, b.mean, atol=1e-9)
    np.testing.assert_allclose(a.variance, b.variance, atol=1e-9)


def test_uncertain_input_does_not_drag_the_mean():
    """1-D case like the method paper's Figure 1, on the line y = 0.

    Accurate samples follow f(x) = sin(x); one sample far off the curve has a large input
    variance. With input noise modelled, the mean near it stays close to f; ignoring input
    noise, the one bad sample pulls the mean towards itself.
    """
    x = np.linspace(-4, 4, 41)
    y = np.sin(x)
    cov = np.zeros((len(x), 2, 2))
    bad = 20  # x = 0
    x_bad = x.copy()
    x_bad[bad] = 1.2  # recorded at the wrong place: its true input was x = 0
    y_bad = y.copy()
    y_bad[bad] = np.sin(0.0)
    cov[bad] = np.diag([1.5**2, 1e-6])
    means = np.column_stack([x_bad, np.zeros_like(x)])
    kernel = SquaredExponentialKernel(1.0, (0.8, 5.0))
    noisy = make_samples(means, cov, y_bad)
    queries = np.column_stack([np.linspace(0.8, 1.6, 9), np.zeros(9)])
    truth = np.sin(queries[:, 0])
    with_noise = predict_full(kernel, 0.01, noisy, queries, 8)
    without = predict_full(kernel, 0.01, noisy.without_input_noise(), queries, 8)
    err_with = np.max(np.abs(with_noise.mean - truth))
    err_without = np.max(np.abs(without.mean - truth))
    assert err_without > 0.15
    assert err_with < 0.1 * err_without


@pytest.mark.parametrize("kernel", [NeuralNetworkKernel(1.0, 1.0, (2.0, 2.0)),
                                    SquaredExponentialKernel(1.0, (0.7, 0.7))])
def test_leave_one_out_matches_refitting(kernel):
    rng = np.random.default_rng(3)
    samples = room_samples(rng, 40)
    k = training_covariance(kernel, 0.1, samples, 3)
    mu, var = leave_one_out(np.linalg.cholesky(k), samples.labels)
    for i in (0, 7, 23):
        keep = np.arange(len(samples)) != i
        kk = k[np.ix_(keep, keep)]
        ks = k[i, keep]
        alpha = np.linalg.solve(kk, samples.labels[keep])
        assert mu[i] == pytest.approx(ks @ alpha, rel=1e-6, abs=1e-9)
        assert var[i] == pytest.approx(k[i, i] - ks @ np.linalg.solve(kk, ks), rel=1e-6)


def test_failed_cholesky_is_rejected_for_learning_and_jittered_for_prediction():
    from gpocc.gp.local import try_cholesky

    # Rank-deficient by rounding: a Gram matrix of 3 vectors in 2-D, slightly indefinite.
    v = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    gram = v @ v.T - 1e-12 * np.eye(3)
    assert np.linalg.eigvalsh(gram).min() < 0
    assert try_cholesky(gram, jitter=False) is None
    chol = try_cholesky(gram, jitter=True)
    assert chol is not None
    # The jitter is tiny next to the matrix: the factor reproduces it to 1e-4 of its scale.
    np.testing.assert_allclose(chol @ chol.T, gram, atol=1e-4 * np.mean(np.diag(gram)))
    # A positive definite matrix is factored exactly, whatever the policy.
    pd = gram + 0.1 * np.eye(3)
    np.testing.assert_allclose(try_cholesky(pd, jitter=False), np.linalg.cholesky(pd))
    # Far from positive definite: even jitter fails, and the caller decides.
    assert try_cholesky(-np.eye(3), jitter=True) is None
    # LAPACK factors a NaN matrix "successfully" into NaN; it must be refused like an
    # indefinite one, not reach a likelihood or a map.
    broken = pd.copy()
    broken[2, 1] = broken[1, 2] = np.nan
    assert try_cholesky(broken, jitter=False) is None
    assert try_cholesky(broken, jitter=True) is None


def test_cholesky_solve_matches_a_dense_solve():
    from gpocc.gp.local import cholesky_solve, try_cholesky

    rng = np.random.default_rng(4)
    a = rng.normal(size=(30, 30))
    matrix = a @ a.T + 0.5 * np.eye(30)
    chol = try_cholesky(matrix, jitter=False)
    for rhs in (rng.normal(size=30), rng.normal(size=(30, 4))):
        np.testing.assert_allclose(cholesky_solve(chol, rhs), np.linalg.solve(matrix, rhs),
                                   rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("case", ["factor fails once", "mixed zero covariances"])
def test_prediction_paths_agree_with_the_separate_calls(case, monkeypatch):
    """predict_local's one-call covariances, and its fallbacks (a failed factor of the
    one-call matrix; mixed zero and non-zero covariances, which the one call declines),
    against the separate calls of the numpy reference."""
    import gpocc.gp.local as local

    rng = np.random.default_rng(5)
    samples = room_samples(rng, 150)
    scan_ids = np.arange(150) // 10
    factors = rng.normal(0.0, 0.03, (150, 2, 3))
    covs = samples.covariances + factors @ np.swapaxes(factors, 1, 2)
    if case == "mixed zero covariances":
        covs[::6] = 0.0
        factors[::6] = 0.0
    samples = SampleSet(samples.means, covs, samples.labels, scan_ids, factors,
                        samples.sensor_ids)
    kernel = NeuralNetworkKernel(2.0, 5.0, (3.0, 4.0))
    queries = rng.uniform(-3, 3, size=(40, 2))
    problem = NeighbourIndex(samples).problem(np.array([0.3, -0.2]), 120)
    calls = {"system": 0, "factors": 0}
    systems, factor = local._local_systems, local.try_cholesky

    def counted_systems(*args, **kwargs):
        result = systems(*args, **kwargs)
        calls["system"] += sum(system is not None for system in result)
        return result

    def failing_once(matrix, jitter=True):
        calls["factors"] += 1
        return None if calls["factors"] == 1 else factor(matrix, jitter)

    monkeypatch.setattr(local, "_local_systems", counted_systems)
    if case == "factor fails once":
        monkeypatch.setattr(local, "try_cholesky", failing_once)
    got = predict_local(kernel, 0.05, problem, queries, 2)
    assert calls["system"] == (1 if case == "factor fails once" else 0)
    monkeypatch.setattr(local, "_local_systems",
                        lambda kernel, backend, batch, *a: [None] * len(batch))
    monkeypatch.setattr(local, "try_cholesky", factor)
    want = predict_local(kernel, 0.05, problem, queries, 2, backend="numpy")
    np.testing.assert_allclose(got.mean, want.mean, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got.variance, want.variance, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got.prior_variance, want.prior_variance, rtol=0, atol=1e-12)


@pytest.mark.parametrize("neighbours", [1, 7, 400, 1000])
def test_problems_of_many_centres_are_the_brute_force_neighbourhoods(neighbours):
    # Oracle: the nearest samples by sorted brute-force distances (no ties: random
    # points), centred at each centre; one look-up for all centres must give each one's.
    rng = np.random.default_rng(5)
    samples = room_samples(rng)
    samples = SampleSet(
        means=samples.means, covariances=samples.covariances, labels=samples.labels,
        scan_ids=rng.integers(0, 30, len(samples)), pose_factors=rng.normal(size=(400, 2, 3)),
        sensor_ids=rng.integers(0, 3, len(samples)).astype(np.int16), sensor_names=("a", "b", "c"))
    centres = rng.uniform(-3, 3, size=(9, 2))
    index = NeighbourIndex(samples)
    problems = index.problems(centres, neighbours)
    assert len(problems) == len(centres)
    k = min(neighbours, len(samples))
    for centre, problem in zip(centres, problems, strict=True):
        nearest = np.sort(np.argsort(np.linalg.norm(samples.means - centre, axis=1))[:k])
        np.testing.assert_array_equal(problem.index, nearest)
        np.testing.assert_array_equal(problem.centre, centre)
        local = problem.samples
        np.testing.assert_array_equal(local.means, samples.means[nearest] - centre)
        for name in ("covariances", "labels", "scan_ids", "pose_factors", "sensor_ids"):
            np.testing.assert_array_equal(getattr(local, name), getattr(samples, name)[nearest])
        assert local.sensor_names == ()
        single = index.problem(centre, neighbours)
        np.testing.assert_array_equal(single.index, problem.index)
    assert index.problems(np.empty((0, 2)), neighbours) == []


def test_a_backend_gets_a_whole_batch_of_local_problems():
    """A backend is an object with the Backend protocol: here the compiled one with its
    NN loops' batch method observed. predict_locals hands it every problem of the batch
    in one call (the empty one excluded), and each prediction equals predict_local's of
    its problem alone and, to round-off, the numpy reference's."""
    from gpocc.gp import backends
    from gpocc.gp.backends.c_loops import CompiledBackend, NeuralNetworkLoops
    from gpocc.gp.local import predict_locals

    batches = []

    class ObservedLoops(NeuralNetworkLoops):
        def local_systems(self, kernel, batch, level, diagonal):
            batches.append(len(batch))
            return super().local_systems(kernel, batch, level, diagonal)

    class ObservedBackend(CompiledBackend):
        name = "observed"

        def __init__(self) -> None:
            super().__init__()
            self.served = {NeuralNetworkKernel: ObservedLoops()}

    rng = np.random.default_rng(8)
    samples = room_samples(rng, 300)
    index = NeighbourIndex(samples)
    kernel = NeuralNetworkKernel(2.0, 5.0, (3.0, 4.0))
    centres = rng.uniform(-2, 2, (4, 2))
    problems = index.problems(centres, 60)
    empty = problems[0].samples.subset(np.zeros(0, dtype=np.intp))
    problems.append(type(problems[0])(centres[0], empty, np.zeros(0, dtype=np.intp)))
    queries = [c + rng.uniform(-0.5, 0.5, (9, 2)) for c in centres] + [centres[:1]]
    got = predict_locals(kernel, 0.05, problems, queries, 2, backend=ObservedBackend())
    assert batches == [4]
    assert backends.get("compiled").loops(kernel).__class__ is NeuralNetworkLoops
    for problem, q, pred in zip(problems, queries, got, strict=True):
        alone = predict_local(kernel, 0.05, problem, q, 2)
        reference = predict_local(kernel, 0.05, problem, q, 2, backend="numpy")
        np.testing.assert_array_equal(pred.mean, alone.mean)
        np.testing.assert_array_equal(pred.variance, alone.variance)
        np.testing.assert_allclose(pred.mean, reference.mean, rtol=0, atol=1e-9)
        np.testing.assert_allclose(pred.variance, reference.variance, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(got[-1].variance, kernel.diag(centres[:1] - centres[0]))


def test_an_index_over_samples_of_the_same_means_gives_their_own_problems():
    # Oracle: a fresh index of the scaled samples. Sharing the tree must give the same
    # neighbourhoods, filled from the samples it is over (not the ones it was built on).
    rng = np.random.default_rng(8)
    samples = room_samples(rng)
    scaled = SampleSet(means=samples.means.copy(), covariances=4.0 * samples.covariances,
                       labels=samples.labels, scan_ids=samples.scan_ids,
                       pose_factors=samples.pose_factors, sensor_ids=samples.sensor_ids)
    centres = rng.uniform(-3, 3, size=(6, 2))
    shared = NeighbourIndex(samples).over(scaled).problems(centres, 50)
    fresh = NeighbourIndex(scaled).problems(centres, 50)
    for a, b in zip(shared, fresh, strict=True):
        np.testing.assert_array_equal(a.index, b.index)
        np.testing.assert_array_equal(a.samples.covariances, b.samples.covariances)
        np.testing.assert_array_equal(a.samples.means, b.samples.means)
    moved = SampleSet(means=samples.means + 0.01, covariances=samples.covariances,
                      labels=samples.labels, scan_ids=samples.scan_ids,
                      pose_factors=samples.pose_factors, sensor_ids=samples.sensor_ids)
    with pytest.raises(ValueError, match="other means"):
        NeighbourIndex(samples).over(moved)


def test_an_index_of_some_rows_gives_the_problems_of_their_subset():
    # Oracle: an index of the subset itself. The neighbourhoods hold the same samples in
    # the same order; their indices point into the full set.
    rng = np.random.default_rng(9)
    samples = room_samples(rng)
    rows = np.flatnonzero(rng.random(len(samples)) < 0.6)
    centres = rng.uniform(-3, 3, size=(5, 2))
    got = NeighbourIndex(samples, rows=rows).problems(centres, 40)
    want = NeighbourIndex(samples.subset(rows)).problems(centres, 40)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_array_equal(a.index, rows[b.index])
        for field in ("means", "covariances", "labels", "scan_ids", "pose_factors"):
            np.testing.assert_array_equal(getattr(a.samples, field), getattr(b.samples, field))
    few = NeighbourIndex(samples, rows=rows[:7]).problem(np.zeros(2), 40)
    assert sorted(few.index) == list(rows[:7])  # no more neighbours than rows


def test_a_model_maps_alike_in_single_and_double_precision():
    """The same model's predictions through predict_locals with single- and double-
    precision local systems: latent means and variances agree to 1e-5 of the prior
    variance; the numpy backend (double only) ignores the setting."""
    from gpocc.gp import backends
    from gpocc.gp.local import predict_locals

    rng = np.random.default_rng(21)
    samples = room_samples(rng, 400)
    kernel = NeuralNetworkKernel(3.0, 100.0, (200.0, 200.0))
    centres = rng.uniform(-2.0, 2.0, (6, 2))
    problems = NeighbourIndex(samples).problems(centres, 96)
    queries = [c + rng.uniform(-0.5, 0.5, (50, 2)) for c in centres]
    runs = {p: predict_locals(kernel, 0.1, problems, queries, 2,
                              backend=backends.choose("compiled", precision=p))
            for p in backends.PRECISIONS}
    for single, double in zip(runs["single"], runs["double"], strict=True):
        tolerance = 1e-5 * double.prior_variance.max()
        assert np.abs(single.mean - double.mean).max() < tolerance
        assert np.abs(single.variance - double.variance).max() < tolerance
    assert backends.get("numpy").in_precision("single") is backends.get("numpy")
