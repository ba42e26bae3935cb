"""Expected kernels: quadrature against closed forms, Monte Carlo and brute force."""

from __future__ import annotations

import numpy as np
import pytest

from gpocc.gp import expected as ex
from gpocc.gp.backends.c_loops import _node_major
from gpocc.gp.expected import (
    expected_kernel_cross,
    expected_kernel_diag,
    expected_kernel_matrix,
    expected_se_closed_form,
    expected_se_closed_form_pairs,
    gauss_hermite,
    gaussian_nodes,
)
from gpocc.gp.kernels import NeuralNetworkKernel, SquaredExponentialKernel

NN = NeuralNetworkKernel(signal_variance=1.0, bias_variance=1.0, weight_variance=(4.0, 4.0))
SE = SquaredExponentialKernel(signal_variance=1.0, lengthscale=(0.5, 0.5))
MC_DRAWS = 100_000


def _covariances(rng: np.random.Generator, n: int, std: float) -> np.ndarray:
    """Random full-rank (N, 2, 2) covariances with roughly ``std`` metres per axis."""
    b = rng.normal(size=(n, 2, 2)) * (std / np.sqrt(2))
    return b @ b.transpose(0, 2, 1) + (0.2 * std) ** 2 * np.eye(2)


def _scan_problem(seed: int, n: int = 12, pose_std: float = 0.15, noise_std: float = 0.05):
    """Samples of three scans: x_i = u_i + A_i e_scan + B_i n_i, with S_i = A A' + B B'."""
    rng = np.random.default_rng(seed)
    means = rng.uniform(-1.0, 1.0, (n, 2))
    scan_ids = np.arange(n) % 3
    factors = rng.normal(size=(n, 2, 3)) * pose_std / np.sqrt(3)
    noise = rng.normal(size=(n, 2, 2)) * noise_std / np.sqrt(2)
    covs = factors @ factors.transpose(0, 2, 1) + noise @ noise.transpose(0, 2, 1)
    return means, covs, scan_ids, factors, noise


def _scan_runs_problem():
    """:func:`_scan_problem` (36 points) with each scan's points consecutive, as in a map's
    problems, one scan split in two runs, and two points inside runs whose pose share is
    too small for the correlated rule."""
    means, covs, _, factors, _ = _scan_problem(41, n=36)
    scan_ids = np.repeat([0, 1, 2, 3, 0], [9, 10, 4, 8, 5])
    factors[[3, 14]] *= 1e-3
    covs[[3, 14]] = factors[[3, 14]] @ factors[[3, 14]].transpose(0, 2, 1) + 1e-4 * np.eye(2)
    return means, covs, scan_ids, factors


def _mc(values: np.ndarray) -> tuple[float, float]:
    return float(values.mean()), float(values.std() / np.sqrt(len(values)))


def _brute_independent(kernel, means, covs, level):
    """Product rule written the obvious way: full (N, L2, N, L2) tensor, every point L2 nodes."""
    nodes, w = gaussian_nodes(means, covs, level)
    n, l2, _ = nodes.shape
    flat = nodes.reshape(-1, 2)
    kk = kernel(flat, flat).reshape(n, l2, n, l2)
    return np.einsum("iajb,a,b->ij", kk, w, w)


# --------------------------------------------------------------------------- rules and nodes


@pytest.mark.parametrize("dim", [1, 2, 4])
def test_gauss_hermite_integrates_normal_moments(dim):
    nodes, w = gauss_hermite(4, dim)
    assert nodes.shape == (4**dim, dim) and w.shape == (4**dim,)
    assert np.all(w > 0)
    np.testing.assert_allclose(w.sum(), 1.0, rtol=1e-14)
    np.testing.assert_allclose(w @ nodes, 0.0, atol=1e-14)
    np.testing.assert_allclose((nodes * w[:, None]).T @ nodes, np.eye(dim), atol=1e-13)
    # E[x^6] = 15 needs degree 6 <= 2 level - 1 = 7.
    np.testing.assert_allclose(w @ nodes[:, 0] ** 6, 15.0, rtol=1e-12)
    with pytest.raises(ValueError):
        gauss_hermite(0, dim)


def test_gaussian_nodes_reproduce_moments_and_handle_singular():
    rng = np.random.default_rng(0)
    means = rng.normal(size=(4, 2))
    covs = _covariances(rng, 4, 0.3)
    covs[1] = 0.0  # zero: all nodes at the mean
    v = np.array([0.6, 0.8])
    covs[2] = 0.09 * np.outer(v, v)  # rank one: nodes on a line through the mean
    covs[3, 0, 1] = covs[3, 1, 0] = np.sqrt(covs[3, 0, 0] * covs[3, 1, 1])  # singular, rounded
    nodes, w = gaussian_nodes(means, covs, 5)
    assert np.all(np.isfinite(nodes))
    np.testing.assert_allclose(np.einsum("a,nai->ni", w, nodes), means, atol=1e-13)
    d = nodes - means[:, None, :]
    np.testing.assert_allclose(np.einsum("a,nai,naj->nij", w, d, d), covs, atol=1e-13)
    assert np.all(nodes[1] == means[1])
    cross = d[2, :, 0] * v[1] - d[2, :, 1] * v[0]
    np.testing.assert_allclose(cross, 0.0, atol=1e-14)


def test_closed_form_root_gives_the_eigh_node_sets():
    """The 2 x 2 closed form against LAPACK's eigenvectors (the 3 x 3 path of the same
    function, on the matrix padded with a zero row and column): every point's node set is
    the same set, and R R' = S; the cases where the angle is degenerate or flips."""
    rng = np.random.default_rng(5)
    covs = np.concatenate([_covariances(rng, 20, 0.2), np.array([
        np.zeros((2, 2)), np.diag([0.04, 0.04]), np.diag([0.01, 0.09]), np.diag([0.09, 0.01]),
        [[0.04, -0.02], [-0.02, 0.01]], [[1e-30, 0.0], [0.0, 0.04]],
        [[-1e-20, 0.0], [0.0, -2e-20]]])])  # rounding below zero: a zero root, as eigh's
    root = ex.sqrt_psd(covs)
    assert np.isfinite(root).all()
    np.testing.assert_allclose(root @ np.swapaxes(root, 1, 2), covs, rtol=0, atol=1e-16)
    padded = np.zeros((len(covs), 3, 3))
    padded[:, :2, :2] = covs
    lapack = ex.sqrt_psd(padded)[:, :2, :]
    unit, _ = ex.gauss_hermite(3, 2)
    for r2, r3 in zip(root, lapack, strict=True):
        # the padded root's extra column is zero; keep the two live ones
        live = r3[:, np.sort(np.argsort(-np.abs(r3).sum(axis=0))[:2])]

        def node_set(r):
            nodes = np.round(unit @ r.T, 12) + 0.0  # + 0.0: no -0.0 in the sort
            return nodes[np.lexsort(nodes.T[::-1])]

        np.testing.assert_allclose(node_set(r2), node_set(live), rtol=0, atol=1e-11)


@pytest.mark.parametrize("level", [2, 3])
def test_compiled_node_sets_equal_the_numpy_ones(level):
    """The compiled expansion of points that all have a covariance against the numpy
    path (closed-form roots, tensordot): the same nodes, weights and layout."""
    rng = np.random.default_rng(11)
    covs = np.concatenate([_covariances(rng, 30, 0.2), np.array([
        np.diag([0.04, 0.04]), np.diag([0.01, 0.09]), [[0.04, -0.02], [-0.02, 0.01]],
        [[1e-30, 0.0], [0.0, 0.04]], [[0.02, 0.02], [0.02, 0.02]]])])  # singular ones
    means = rng.normal(0.0, 5.0, (len(covs), 2))
    compiled = ex._expand(means, covs, level, "compiled")
    reference = ex._expand(means, covs, level, "numpy")
    np.testing.assert_allclose(compiled.nodes, reference.nodes, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(compiled.weights, reference.weights)
    np.testing.assert_array_equal(compiled.starts, reference.starts)
    assert compiled.uniform == reference.uniform == level**2
    assert compiled.nodes.T.flags.c_contiguous and reference.nodes.T.flags.c_contiguous


# --------------------------------------------------------------------------- SE closed form


def test_quadrature_matches_girard_for_small_variances():
    rng = np.random.default_rng(1)
    means = rng.uniform(-0.8, 0.8, (10, 2))
    covs = _covariances(rng, 10, 0.05)
    quad = expected_kernel_matrix(SE, means, covs, 10)
    exact = expected_se_closed_form(SE, means, covs, means, covs)
    off = ~np.eye(10, dtype=bool)
    assert np.max(np.abs(quad - exact)[off] / exact[off]) < 1e-6
    # One point: E[k(x, x)] = s exactly for a stationary kernel.
    np.testing.assert_allclose(np.diag(quad), SE.signal_variance, rtol=1e-14)


def test_quadrature_matches_girard_for_moderate_variances():
    rng = np.random.default_rng(2)
    means = rng.uniform(-0.8, 0.8, (8, 2))
    covs = _covariances(rng, 8, 0.25)
    quad = expected_kernel_matrix(SE, means, covs, 10)
    exact = expected_se_closed_form(SE, means, covs, means, covs)
    off = ~np.eye(8, dtype=bool)
    assert np.max(np.abs(quad - exact)[off]) < 1e-3 * SE.signal_variance


def test_girard_closed_forms_match_monte_carlo():
    # The closed forms are themselves checked against sampling (independent and correlated).
    rng = np.random.default_rng(3)
    ua, ub = np.array([0.1, -0.2]), np.array([0.4, 0.3])
    sa, sb = _covariances(rng, 2, 0.3)
    lab, lb = np.linalg.cholesky(sa), np.linalg.cholesky(sb)
    xa = ua + rng.normal(size=(MC_DRAWS, 2)) @ lab.T
    xb = ub + rng.normal(size=(MC_DRAWS, 2)) @ lb.T
    mean, err = _mc(SE.pairwise(xa, xb))
    got = expected_se_closed_form(SE, ua[None], sa[None], ub[None], sb[None])[0, 0]
    assert abs(got - mean) < 4 * err
    # Correlated: a shared 3-D error e moves both points.
    fa, fb = rng.normal(size=(2, 2, 3)) * 0.2
    e = rng.normal(size=(MC_DRAWS, 3))
    ya, yb = xa + e @ fa.T, xb + e @ fb.T
    mean, err = _mc(SE.pairwise(ya, yb))
    got = expected_se_closed_form_pairs(
        SE, ua[None], (sa + fa @ fa.T)[None], ub[None], (sb + fb @ fb.T)[None],
        cross=(fa @ fb.T)[None],
    )[0]
    assert abs(got - mean) < 4 * err
    same = expected_se_closed_form_pairs(SE, ua[None], sa[None], ua[None], sa[None], sa[None])
    np.testing.assert_allclose(same, SE.signal_variance, rtol=1e-14)


def test_correlated_quadrature_matches_girard_pairs():
    means, covs, scan_ids, factors, _ = _scan_problem(4)
    i, j = np.triu_indices(len(means), 1)
    same = scan_ids[i] == scan_ids[j]
    cross = np.where(same[:, None, None], factors[i] @ factors[j].transpose(0, 2, 1), 0.0)
    exact = expected_se_closed_form_pairs(SE, means[i], covs[i], means[j], covs[j], cross)
    ignored = expected_se_closed_form_pairs(SE, means[i], covs[i], means[j], covs[j])
    effect = np.abs(exact - ignored)[same].max()
    assert effect > 0.01  # the correlation matters here
    errors = []
    for level in (3, 6, 10):
        k = expected_kernel_matrix(
            SE, means, covs, level, scan_ids=scan_ids, pose_factors=factors
        )
        errors.append(np.abs(k[i, j] - exact)[same].max())
        if level == 10:
            np.testing.assert_allclose(k[i, j][~same], exact[~same], rtol=1e-7, atol=1e-9)
    # The 4-D rule converges more slowly than the 2-D ones, but it does converge.
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 1e-3 * effect


# --------------------------------------------------------------------------- Monte Carlo


def _quad_tolerance(f, level: int) -> float:
    """Quadrature error estimate: distance to the rule two levels up."""
    return float(np.max(np.abs(f(level) - f(level + 2))))


@pytest.mark.parametrize("kernel", [NN, SE], ids=["nn", "se"])
def test_independent_pair_matches_monte_carlo(kernel):
    rng = np.random.default_rng(5)
    means = np.array([[0.3, -0.4], [0.9, 0.2]])
    covs = _covariances(rng, 2, 0.25)
    x = [means[i] + rng.normal(size=(MC_DRAWS, 2)) @ np.linalg.cholesky(covs[i]).T
         for i in range(2)]
    mean, err = _mc(kernel.pairwise(x[0], x[1]))
    level = 6
    quad = expected_kernel_matrix(kernel, means, covs, level)[0, 1]
    tol = 4 * err + _quad_tolerance(
        lambda lv: expected_kernel_matrix(kernel, means, covs, lv)[0, 1], level
    )
    assert abs(quad - mean) < tol


@pytest.mark.parametrize("kernel", [NN, SE], ids=["nn", "se"])
def test_correlated_pair_matches_monte_carlo(kernel):
    rng = np.random.default_rng(6)
    means = np.array([[0.2, 0.5], [0.6, 0.3]])
    factors = np.array([[[0.25, 0.05, -0.3], [0.0, 0.2, 0.25]],
                        [[0.2, -0.05, -0.25], [0.05, 0.25, 0.3]]])
    noise = rng.normal(size=(2, 2, 2)) * 0.03
    covs = factors @ factors.transpose(0, 2, 1) + noise @ noise.transpose(0, 2, 1)
    e = rng.normal(size=(MC_DRAWS, 3))
    x = [means[i] + e @ factors[i].T + rng.normal(size=(MC_DRAWS, 2)) @ noise[i].T
         for i in range(2)]
    mean, err = _mc(kernel.pairwise(x[0], x[1]))

    def corr(lv):
        return expected_kernel_matrix(
            kernel, means, covs, lv, scan_ids=np.array([7, 7]), pose_factors=factors
        )[0, 1]

    level = 5
    assert abs(corr(level) - mean) < 4 * err + _quad_tolerance(corr, level)
    # Ignoring the shared error would be visibly wrong (so the test above has teeth) ...
    independent = expected_kernel_matrix(kernel, means, covs, level)[0, 1]
    assert abs(independent - mean) > 10 * err
    # ... and different scans are independent.
    other = expected_kernel_matrix(
        kernel, means, covs, level, scan_ids=np.array([7, 8]), pose_factors=factors
    )[0, 1]
    assert other == pytest.approx(independent, rel=1e-12)


def test_diagonal_is_one_point_expectation():
    rng = np.random.default_rng(7)
    means = np.array([[0.8, -0.6]])
    covs = _covariances(rng, 1, 0.35)
    x = means[0] + rng.normal(size=(MC_DRAWS, 2)) @ np.linalg.cholesky(covs[0]).T
    x2 = means[0] + rng.normal(size=(MC_DRAWS, 2)) @ np.linalg.cholesky(covs[0]).T
    one, err1 = _mc(NN.diag(x))
    two, err2 = _mc(NN.pairwise(x, x2))
    level = 6

    def diag(lv):
        return expected_kernel_matrix(NN, means, covs, lv)[0, 0]

    assert abs(diag(level) - one) < 4 * err1 + _quad_tolerance(diag, level)
    # The two-point expectation is clearly different: the diagonal is not that.
    assert abs(diag(level) - two) > 10 * err2 + 10 * err1
    np.testing.assert_allclose(expected_kernel_diag(NN, means, covs, level), diag(level))


def test_cross_matches_monte_carlo_and_closed_form():
    rng = np.random.default_rng(8)
    queries = np.array([[0.0, 0.0], [0.5, -0.3], [1.2, 0.9]])
    means = np.array([[0.3, -0.2], [-0.4, 0.6]])
    covs = _covariances(rng, 2, 0.3)
    level = 6
    kx = expected_kernel_cross(NN, queries, means, covs, level)
    kx_hi = expected_kernel_cross(NN, queries, means, covs, level + 2)
    assert kx.shape == (3, 2)
    for i in range(2):
        x = means[i] + rng.normal(size=(MC_DRAWS, 2)) @ np.linalg.cholesky(covs[i]).T
        for q in range(3):
            mean, err = _mc(NN(queries[q : q + 1], x)[0])
            assert abs(kx[q, i] - mean) < 4 * err + abs(kx[q, i] - kx_hi[q, i])
    zero = np.zeros((3, 2, 2))
    small = covs / 9.0  # 0.1 m: level 10 is then exact to ~1e-7
    exact = expected_se_closed_form(SE, queries, zero, means, small)
    np.testing.assert_allclose(
        expected_kernel_cross(SE, queries, means, small, 10), exact, rtol=1e-6
    )


# --------------------------------------------------------------------------- structure


def test_error_falls_with_level():
    # Strongly nonlinear: std ~0.2 m against a 0.3 m length scale (SE, exact reference) and
    # weight variance 16 /m^2 (NN, level-14 reference).
    rng = np.random.default_rng(0)
    means = rng.uniform(-0.5, 0.5, (6, 2))
    b = rng.normal(size=(6, 2, 2)) * 0.15
    covs = b @ b.transpose(0, 2, 1) + 0.01 * np.eye(2)
    off = ~np.eye(6, dtype=bool)
    se = SquaredExponentialKernel(1.0, (0.3, 0.3))
    exact = expected_se_closed_form(se, means, covs, means, covs)
    nn = NeuralNetworkKernel(1.0, 1.0, (16.0, 16.0))
    ref = expected_kernel_matrix(nn, means, covs, 14)
    for kernel, oracle in ((se, exact), (nn, ref)):
        errors = [
            np.abs(expected_kernel_matrix(kernel, means, covs, lv) - oracle)[off].max()
            for lv in (1, 2, 3, 5)
        ]
        assert errors[0] > errors[1] > errors[2] > errors[3]
        assert errors[3] < errors[0] / 10


def test_zero_covariance_is_plain_kernel():
    rng = np.random.default_rng(9)
    means = rng.uniform(-2, 2, (30, 2))
    zero = np.zeros((30, 2, 2))
    factors = rng.normal(size=(30, 2, 3))
    for kernel in (NN, SE):
        k = expected_kernel_matrix(
            kernel, means, zero, 5, scan_ids=np.zeros(30, int), pose_factors=factors
        )
        plain = kernel(means, means)
        np.testing.assert_allclose(k, plain, rtol=1e-15, atol=1e-15)
        np.testing.assert_allclose(np.diag(k), kernel.diag(means), rtol=1e-15)
        # To rounding: the compiled NN path has its own arcsin (<= 2 ulp from numpy's).
        np.testing.assert_allclose(
            expected_kernel_cross(kernel, means[:4], means, zero, 5), plain[:4], rtol=1e-14,
            atol=1e-15,
        )


@pytest.mark.parametrize("kernel", [NN, SE], ids=["nn", "se"])
def test_matches_brute_force_with_mixed_node_counts_and_small_blocks(kernel, monkeypatch):
    rng = np.random.default_rng(10)
    means = rng.uniform(-1, 1, (25, 2))
    covs = _covariances(rng, 25, 0.2)
    covs[::4] = 0.0  # single-node points among full ones
    brute = _brute_independent(kernel, means, covs, 3)
    np.fill_diagonal(brute, expected_kernel_diag(kernel, means, covs, 3))
    default = expected_kernel_matrix(kernel, means, covs, 3)
    np.testing.assert_allclose(default, brute, rtol=1e-12, atol=1e-14)
    cross_brute = np.einsum(
        "qia,a->qi",
        kernel(means[:5], gaussian_nodes(means, covs, 3)[0].reshape(-1, 2)).reshape(5, 25, 9),
        gauss_hermite(3, 2)[1],
    )
    # Tiny blocks and chunks exercise the blocked paths (many blocks, ragged edges).
    monkeypatch.setattr(ex, "_BLOCK_NODES", 7)
    monkeypatch.setattr(ex, "_PAIR_CHUNK", 100)
    np.testing.assert_allclose(
        expected_kernel_matrix(kernel, means, covs, 3), brute, rtol=1e-12, atol=1e-14
    )
    np.testing.assert_allclose(
        expected_kernel_cross(kernel, means[:5], means, covs, 3), cross_brute, rtol=1e-12
    )


def test_blocking_does_not_change_correlated_results(monkeypatch):
    means, covs, scan_ids, factors, _ = _scan_problem(11, n=20)
    kw = dict(scan_ids=scan_ids, pose_factors=factors, with_gradient=True)
    k, dk = expected_kernel_matrix(NN, means, covs, 3, **kw)
    monkeypatch.setattr(ex, "_BLOCK_NODES", 10)
    monkeypatch.setattr(ex, "_PAIR_CHUNK", 200)
    k2, dk2 = expected_kernel_matrix(NN, means, covs, 3, **kw)
    np.testing.assert_allclose(k2, k, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(dk2, dk, rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("kernel", [NN, SE], ids=["nn", "se"])
def test_symmetric_and_positive_semidefinite(kernel):
    means, covs, scan_ids, factors, _ = _scan_problem(12, n=60, pose_std=0.2)
    covs[::7] = 0.0  # one-node points among the others
    k = expected_kernel_matrix(kernel, means, covs, 3, scan_ids=scan_ids, pose_factors=factors)
    np.testing.assert_array_equal(k, k.T)
    lam = np.linalg.eigvalsh(k)
    assert lam.min() >= -1e-10 * lam.max()
    # Exactly symmetric gradients too (the compiled path does not average transposes).
    scaled = {"input_scale": 1.7, "with_scale_gradient": True} if kernel is NN else {}
    kg, dk = expected_kernel_matrix(kernel, means, covs, 3, scan_ids=scan_ids,
                                    pose_factors=factors, with_gradient=True, **scaled)
    np.testing.assert_array_equal(kg, kg.T)
    np.testing.assert_array_equal(dk, np.swapaxes(dk, 1, 2))


@pytest.mark.parametrize("kernel", [NN, SE], ids=["nn", "se"])
def test_gradients_match_finite_differences(kernel):
    means, covs, scan_ids, factors, _ = _scan_problem(13, n=9)
    covs[4] = 0.0
    kw = dict(scan_ids=scan_ids, pose_factors=factors)
    k, dk = expected_kernel_matrix(kernel, means, covs, 3, with_gradient=True, **kw)
    queries = np.array([[0.1, 0.2], [-0.5, 0.7]])
    kx, dkx = expected_kernel_cross(kernel, queries, means, covs, 3, with_gradient=True)
    kd, dkd = expected_kernel_diag(kernel, means, covs, 3, with_gradient=True)
    np.testing.assert_allclose(k, expected_kernel_matrix(kernel, means, covs, 3, **kw))
    np.testing.assert_allclose(np.diag(k), kd)
    theta, h = kernel.theta, 1e-6
    assert dk.shape == (len(theta), 9, 9) and dkx.shape == (len(theta), 2, 9)
    for p in range(len(theta)):
        step = np.zeros_like(theta)
        step[p] = h
        up, down = kernel.with_theta(theta + step), kernel.with_theta(theta - step)
        fd = (expected_kernel_matrix(up, means, covs, 3, **kw)
              - expected_kernel_matrix(down, means, covs, 3, **kw)) / (2 * h)
        np.testing.assert_allclose(dk[p], fd, rtol=1e-6, atol=1e-9)
        fdx = (expected_kernel_cross(up, queries, means, covs, 3)
               - expected_kernel_cross(down, queries, means, covs, 3)) / (2 * h)
        np.testing.assert_allclose(dkx[p], fdx, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(dkd[p], np.diag(fd), rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("level", [2, 3])
@pytest.mark.parametrize("scale", [1.0, 2.5])
def test_input_scale_gradient_matches_finite_differences(level, scale):
    """dK/dlog g (analytic, compiled path) against central differences of K at g e^{+-h}:
    independent and same-scan pairs, a zero-covariance point, and the diagonal."""
    means, covs, scan_ids, factors, _ = _scan_problem(31, n=14)
    covs[4], factors[4] = 0.0, 0.0
    kernel = NeuralNetworkKernel(2.3, 30.0, (45.0, 70.0))
    kw = dict(scan_ids=scan_ids, pose_factors=factors)
    assert ex.same_scan_pairs(covs, scan_ids, factors)[0].shape[0] > 10
    k, dk = expected_kernel_matrix(kernel, means, covs, level, with_gradient=True,
                                   input_scale=scale, with_scale_gradient=True, **kw)
    plain, dplain = expected_kernel_matrix(kernel, means, covs, level, with_gradient=True,
                                           input_scale=scale, **kw)
    np.testing.assert_array_equal(k, plain)
    np.testing.assert_allclose(dk[:-1], dplain, rtol=0, atol=1e-13)
    h = 1e-5
    fd = (expected_kernel_matrix(kernel, means, covs, level, input_scale=scale * np.exp(h),
                                 **kw)
          - expected_kernel_matrix(kernel, means, covs, level, input_scale=scale * np.exp(-h),
                                   **kw)) / (2 * h)
    assert np.abs(fd).max() > 1e-3  # the scale matters here
    np.testing.assert_allclose(dk[-1], fd, rtol=1e-6, atol=1e-8)
    assert dk[-1][4, 4] == 0.0  # a point without spread: its own variance cannot change


def test_input_scale_gradient_needs_the_compiled_kernel():
    means, covs, scan_ids, factors, _ = _scan_problem(32, n=5)
    with pytest.raises(ValueError, match="compiled NN kernel"):
        expected_kernel_matrix(SE, means, covs, 2, with_gradient=True,
                               with_scale_gradient=True)
    assert not ex.supports_scale_gradient(SE)
    assert ex.supports_scale_gradient(NeuralNetworkKernel(1.0, 1.0, (1.0, 1.0)))


def test_bad_shapes_are_rejected():
    with pytest.raises(ValueError, match="covariances"):
        expected_kernel_matrix(NN, np.zeros((3, 2)), np.zeros((2, 2, 2)), 3)
    with pytest.raises(ValueError, match="pose_factors"):
        expected_kernel_matrix(
            NN, np.zeros((3, 2)), np.zeros((3, 2, 2)), 3,
            scan_ids=np.zeros(3), pose_factors=np.zeros((3, 2, 2)),
        )


# --------------------------------------------------------------------------- compiled NN path


def test_compiled_arcsin_matches_numpy_to_two_ulp():
    from gpocc import compiled as fused

    x = np.concatenate([np.linspace(-1.0, 1.0, 20_001), [0.5, -0.5, 0.975, 1e-300, -0.0],
                        np.random.default_rng(20).uniform(-1.0, 1.0, 20_000)])
    ref = np.arcsin(x)
    ulp = np.spacing(np.maximum(np.abs(ref), 1e-300))
    assert np.all(np.abs(fused.asin_array(x) - ref) <= 2 * ulp)


def test_compiled_root_of_joint_covariance_reproduces_it():
    """Semi-definite Cholesky roots, compiled and numpy, of joint covariances of full rank
    and of rank 3 (no per-point noise: both points move only with the shared pose)."""
    from gpocc import compiled as fused

    means, covs, scan_ids, factors, _ = _scan_problem(21, n=30)
    i, j = ex.same_scan_pairs(covs, scan_ids, factors)
    joint = np.empty((i.shape[0], 4, 4))
    joint[:, :2, :2], joint[:, 2:, 2:] = covs[i], covs[j]
    joint[:, :2, 2:] = factors[i] @ factors[j].transpose(0, 2, 1)
    joint[:, 2:, :2] = joint[:, :2, 2:].transpose(0, 2, 1)
    stacked = np.concatenate([factors[i], factors[j]], axis=1)  # (P, 4, 3)
    singular = stacked @ stacked.transpose(0, 2, 1)
    for matrices in (joint, singular):
        compiled = fused.cholesky_psd4(
            np.ascontiguousarray(matrices.transpose(1, 2, 0))).transpose(2, 0, 1)
        reference = ex.cholesky_psd(matrices)
        for root in (compiled, reference):
            scale = np.abs(matrices).max()
            np.testing.assert_allclose(root @ root.transpose(0, 2, 1), matrices,
                                       atol=1e-9 * scale)
            assert np.all(np.triu(root, 1) == 0.0) and np.all(np.isfinite(root))
            # Rank 3: the last pivot is rounding noise (or zeroed).
            last = np.abs(root[:, 3, 3]).max() / np.sqrt(scale)
            assert last < (1.0 if matrices is joint else 1e-5)
    compiled = fused.cholesky_psd4(np.ascontiguousarray(joint.transpose(1, 2, 0)))
    np.testing.assert_allclose(compiled.transpose(2, 0, 1), np.linalg.cholesky(joint),
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(ex.cholesky_psd(joint), np.linalg.cholesky(joint),
                               rtol=0, atol=1e-12)


@pytest.mark.parametrize("level", [1, 2, 3])
@pytest.mark.parametrize("mixed", [True, False], ids=["mixed", "uniform"])
def test_compiled_nn_path_matches_numpy_reference(level, mixed):
    """Compiled loops against the numpy path: values, gradients, cross, correlated pairs;
    ``mixed``: points with zero covariance (one node) among others (the point-major loops),
    else every point with the same rule (the node-major loops)."""
    means, covs, scan_ids, factors, _ = _scan_problem(22, n=40)
    if mixed:
        covs[::5] = 0.0
        factors[::5] = 0.0
    kernel = NeuralNetworkKernel(3.7, 50.0, (40.0, 60.0))
    queries = np.random.default_rng(23).uniform(-1.2, 1.2, (25, 2))

    def run(backend):
        k = expected_kernel_matrix(kernel, means, covs, level, scan_ids=scan_ids,
                                   pose_factors=factors, backend=backend)
        kg, dk = expected_kernel_matrix(kernel, means, covs, level, scan_ids=scan_ids,
                                        pose_factors=factors, with_gradient=True,
                                        backend=backend)
        return k, kg, dk, expected_kernel_cross(kernel, queries, means, covs, level,
                                                backend=backend)

    fused = run("compiled")
    reference = run("numpy")
    assert ex.same_scan_pairs(covs, scan_ids, factors)[0].shape[0] > 50
    for got, want in zip(fused, reference, strict=True):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("level", [1, 2, 3])
@pytest.mark.parametrize("n", [0, 1, 2, 37])
def test_node_major_loops_give_the_point_major_sums(level, n):
    """The uniform (node-major) matrix loop adds the same terms in the same order as the
    point-major one, so its values agree to the last bits (the compiler may fuse a
    multiply-add in one loop and not the other: 4e-16 relative was seen) and its diagonal
    is left alone; the cross loop agrees to round-off (its general path, L != 4, sums
    node by node). The rule's weights are made unequal, so that a weight given to the
    wrong node changes the sums."""
    from gpocc import compiled as fused

    rng = np.random.default_rng(47)
    kernel = NeuralNetworkKernel(2.3, 30.0, (25.0, 70.0))
    means, covs = rng.uniform(-1.5, 1.5, (n, 2)), _covariances(rng, n, 0.05)
    exp = ex._expand(means, covs, level)
    size = exp.uniform
    assert size == (level**2 if n else 1)
    rule = rng.dirichlet(np.ones(size))
    weights = np.tile(rule, n)
    u = kernel.scaled_columns(exp.nodes)
    by_node = _node_major(u, size)
    if n > 5:
        last = size - 1  # node `last` of point 5
        np.testing.assert_array_equal(by_node[:, last * n + 5], u[:, 5 * size + last])
    point_major, node_major = np.zeros((n, n)), np.full((n, n), np.nan)
    fused.nn_matrix(u, weights, exp.starts, kernel.arcsin_scale, point_major)
    fused.nn_matrix_uniform(by_node, rule, kernel.arcsin_scale, node_major)
    off = ~np.eye(n, dtype=bool)
    np.testing.assert_allclose(node_major[off], point_major[off], rtol=4e-15, atol=0)
    assert np.isnan(np.diag(node_major)).all()
    np.testing.assert_array_equal(node_major[off], node_major.T[off])
    q = kernel.scaled_columns(rng.uniform(-2, 2, (23, 2)))
    cross_point, cross_node = np.empty((23, n)), np.empty((23, n))
    fused.nn_cross(q, u, weights, exp.starts, kernel.arcsin_scale, cross_point)
    fused.nn_cross_uniform(q, by_node, rule, kernel.arcsin_scale, cross_node)
    np.testing.assert_allclose(cross_node, cross_point, rtol=1e-14, atol=1e-15)


def test_compiled_pair_listing_matches_the_numpy_rule():
    """Same pairs in the same order: unsorted scans, zero covariances, pose shares on both
    sides of POSE_SHARE_MIN, and integer scan ids of either width or byte order."""
    rng = np.random.default_rng(31)
    n = 90
    covs = _covariances(rng, n, 0.1)
    factors = rng.normal(size=(n, 2, 3)) * 0.05
    factors[::7] *= 1e-3  # pose share below the threshold
    covs[::11] = 0.0
    ids = rng.integers(0, 9, n)
    # the compiled rule converts any integer width and byte order
    for scan_ids in (ids, ids.astype(np.int32), ids.astype(">i8")):
        compiled = ex.same_scan_pairs(covs, scan_ids, factors, "compiled")
        reference = ex.same_scan_pairs(covs, scan_ids, factors, "numpy")
        assert reference[0].shape[0] > 100
        for got, want in zip(compiled, reference, strict=True):
            np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("level", [1, 2, 3])
@pytest.mark.parametrize("case", ["correlated", "scan runs", "independent", "all zero"])
def test_local_system_in_one_call_matches_the_separate_calls(level, case):
    """The one-call local system (training matrix plus diagonal term, cross-covariances,
    query priors) against the numpy reference of the three separate calls. "scan runs":
    :func:`_scan_runs_problem`, whose runs the product rule skips."""
    means, covs, scan_ids, factors, _ = _scan_problem(41, n=36)
    if case == "all zero":
        covs[:] = 0.0
        factors[:] = 0.0
    if case == "scan runs":
        means, covs, scan_ids, factors = _scan_runs_problem()
    pairs = {"scan_ids": scan_ids, "pose_factors": factors} if case != "independent" else {}
    kernel = NeuralNetworkKernel(2.3, 30.0, (25.0, 70.0))
    queries = np.random.default_rng(42).uniform(-1.3, 1.3, (30, 2))
    k, cross, prior = ex.expected_local_system(kernel, means, covs, queries, level, 0.125,
                                               **pairs)
    want = expected_kernel_matrix(kernel, means, covs, level, backend="numpy", **pairs)
    want[np.diag_indices_from(want)] += 0.125
    if case in ("correlated", "scan runs") and level > 1:
        assert ex.same_scan_pairs(covs, scan_ids, factors)[0].shape[0] > 100
        independent = expected_kernel_matrix(kernel, means, covs, level, backend="numpy")
        assert np.abs(want - 0.125 * np.eye(36) - independent).max() > 1e-3
    np.testing.assert_allclose(k, want, rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        cross, expected_kernel_cross(kernel, queries, means, covs, level, backend="numpy"),
        rtol=0, atol=1e-12)
    np.testing.assert_allclose(prior, kernel.diag(queries), rtol=0, atol=1e-12)


@pytest.mark.parametrize("single", [False, True])
@pytest.mark.parametrize("level", [2, 3])
def test_the_skipped_same_scan_runs_are_written_and_the_rest_is_bit_identical(level, single):
    """A map problem's product rule skips the runs of consecutive same-scan points, whose
    entries the 4-D rule then writes: into a NaN-filled matrix every entry is written,
    and every entry outside the same-scan pairs is bit for bit the product rule's without
    skipping (``correlated`` off), whatever the loops leave to their scalar remainders;
    in double and in single precision."""
    from gpocc import compiled as fused

    means, covs, scan_ids, factors = _scan_runs_problem()
    kernel = NeuralNetworkKernel(2.3, 30.0, (25.0, 70.0))
    unit, weights = gauss_hermite(level, 2)
    unit4, weights4 = gauss_hermite(level, 4)

    def training_matrix(correlated: bool) -> np.ndarray:
        k = np.full((36, 36), np.nan)
        fused.nn_local_system(means, covs, scan_ids, factors, np.zeros((1, 2)), unit,
                              weights, unit4, weights4, kernel.root_two_s,
                              kernel.arcsin_scale, 0.125, correlated, ex.POSE_SHARE_MIN,
                              ex.ZERO_VARIANCE_M2, single, k, np.empty((1, 36)),
                              np.empty(1))
        return k

    first, second = ex.same_scan_pairs(covs, scan_ids, factors)
    pairs = np.zeros((36, 36), dtype=bool)
    pairs[first, second] = pairs[second, first] = True
    assert pairs.sum() > 200
    correlated, independent = training_matrix(True), training_matrix(False)
    assert np.isfinite(correlated).all()
    np.testing.assert_array_equal(correlated[~pairs], independent[~pairs])
    assert np.abs(correlated[pairs] - independent[pairs]).max() > 1e-3


def test_local_system_declines_what_it_does_not_compile():
    """Mixed zero and non-zero covariances and kernels without compiled loops: None, so
    that the caller takes the separate calls."""
    means, covs, scan_ids, factors, _ = _scan_problem(43, n=10)
    queries = np.zeros((3, 2))
    assert ex.expected_local_system(NN, means, covs, queries, 2, 0.1) is not None
    covs[::4] = 0.0
    assert ex.expected_local_system(NN, means, covs, queries, 2, 0.1) is None
    assert ex.expected_local_system(SE, means, covs * 0 + np.eye(2) * 0.01, queries, 2,
                                    0.1) is None


def test_backends_serve_the_kernels_they_register():
    """``model.backend``'s names: the compiled loops serve the NN kernel, every other
    kernel (and every kernel of the numpy backend) gets the numpy quadrature, and the
    numpy backend agrees with Girard's closed form through the same entry point."""
    from gpocc.gp import backends
    from gpocc.gp.backends.quadrature import QUADRATURE

    compiled, numpy_backend = backends.get("compiled"), backends.get("numpy")
    assert backends.get("auto") is compiled
    assert backends.get(compiled) is compiled
    assert compiled.loops(NN) is not QUADRATURE
    assert compiled.loops(SE) is QUADRATURE and numpy_backend.loops(NN) is QUADRATURE
    with pytest.raises(ValueError, match="auto, numpy, compiled"):
        backends.get("gpu")
    rng = np.random.default_rng(5)
    means, covs = rng.uniform(-1, 1, (12, 2)), _covariances(rng, 12, 0.05)
    for backend in ("numpy", "compiled"):
        k = expected_kernel_matrix(SE, means, covs, 8, backend=backend)
        closed = expected_se_closed_form(SE, means, covs, means, covs)
        off = ~np.eye(12, dtype=bool)
        np.testing.assert_allclose(k[off], closed[off], rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("level", [1, 2, 3])
def test_single_precision_local_systems_are_within_a_millionth_of_the_kernel_scale(level):
    """``model.covariance_precision: single``: the product-rule part of K and the
    cross-covariances in single precision, against the double loops (themselves checked
    against Monte Carlo above). The kernel is as sharp as the learned ones (weight
    variance 500 / m^2) and the points lie centimetres apart and a few metres out, where
    arcsine arguments come within 1e-5 of 1 and a single-precision 1 - z would keep
    hardly a digit. Diagonal, same-scan pairs and priors are double, bit for bit."""
    from gpocc.gp import backends

    rng = np.random.default_rng(11 + level)
    kernel = NeuralNetworkKernel(3.0, 400.0, (500.0, 500.0))
    cluster = rng.uniform(2.0, 3.0, 2) + rng.normal(0.0, 0.03, (40, 2))
    spread = rng.uniform(-4.0, 4.0, (40, 2))
    means = np.concatenate([cluster, spread])
    covs = _covariances(rng, 80, 0.02)
    scan_ids = np.repeat(np.arange(8), 10)
    factors = rng.normal(0.0, 0.01, (80, 2, 3))
    queries = np.concatenate([cluster[:20] + rng.normal(0.0, 0.01, (20, 2)),
                              rng.uniform(-4.0, 4.0, (60, 2))])
    double = ex.expected_local_system(kernel, means, covs, queries, level, 0.1,
                                      scan_ids=scan_ids, pose_factors=factors,
                                      backend="compiled")
    single = ex.expected_local_system(
        kernel, means, covs, queries, level, 0.1, scan_ids=scan_ids, pose_factors=factors,
        backend=backends.choose("compiled", precision="single"))
    scale = kernel.arcsin_scale
    k_double, cross_double, prior_double = double
    k_single, cross_single, prior_single = single
    off = ~np.eye(80, dtype=bool)
    assert np.abs(k_single - k_double)[off].max() < 1e-6 * scale
    assert np.abs(cross_single - cross_double).max() < 1e-6 * scale
    assert (k_single != k_double)[off].any()  # single precision did run
    np.testing.assert_array_equal(np.diag(k_single), np.diag(k_double))
    np.testing.assert_array_equal(prior_single, prior_double)
    np.testing.assert_array_equal(k_single, k_single.T)
    # Some arguments come that close to 1: the case the cancellation-free gap is for.
    u = kernel.scaled_columns(queries[:20])
    v = kernel.scaled_columns(means[:40])
    assert (1.0 - (u.T @ v)).min() < 1e-4


def test_single_precision_takes_any_quadrature_level():
    """Levels up to 10 (100 nodes a point) in single precision too, as in double."""
    from gpocc.gp import backends

    rng = np.random.default_rng(4)
    means, covs = rng.uniform(-1.0, 1.0, (20, 2)), _covariances(rng, 20, 0.1)
    queries = rng.uniform(-1.0, 1.0, (5, 2))
    kernel = NeuralNetworkKernel(1.0, 10.0, (20.0, 20.0))
    for level in (9, 10):
        double = ex.expected_local_system(kernel, means, covs, queries, level, 0.1,
                                          backend="compiled")
        single = ex.expected_local_system(
            kernel, means, covs, queries, level, 0.1,
            backend=backends.choose("compiled", precision="single"))
        assert np.abs(single[1] - double[1]).max() < 1e-6 * kernel.arcsin_scale
