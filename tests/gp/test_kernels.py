"""Kernels: values against independent formulas, gradients against finite differences."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import erf
from sklearn.gaussian_process.kernels import RBF

from gpocc.config import HyperparametersConfig
from gpocc.errors import GpoccError
from gpocc.gp.kernels import NeuralNetworkKernel, SquaredExponentialKernel, make_kernel

NN = NeuralNetworkKernel(signal_variance=0.8, bias_variance=1.7, weight_variance=(3.0, 6.5))
SE = SquaredExponentialKernel(signal_variance=1.3, lengthscale=(0.4, 0.9))
KERNELS = [NN, SE]


def _points(seed: int, n: int, scale: float = 1.5) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-scale, scale, (n, 2))


def _nn_formula(k: NeuralNetworkKernel, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The arcsin kernel written literally from Williams (1998), with matrix Sigma."""
    sigma = np.diag([k.bias_variance, *k.weight_variance])
    at = np.column_stack([np.ones(len(a)), a])
    bt = np.column_stack([np.ones(len(b)), b])
    num = 2.0 * at @ sigma @ bt.T
    na = 1.0 + 2.0 * np.einsum("ij,jk,ik->i", at, sigma, at)
    nb = 1.0 + 2.0 * np.einsum("ij,jk,ik->i", bt, sigma, bt)
    return k.signal_variance * 2.0 / np.pi * np.arcsin(num / np.sqrt(np.outer(na, nb)))


def test_nn_matches_formula():
    a, b = _points(0, 7), _points(1, 5, scale=4.0)
    np.testing.assert_allclose(NN(a, b), _nn_formula(NN, a, b), rtol=1e-12, atol=1e-14)


def test_nn_is_erf_network_covariance():
    # Williams: k(x, x') / s = E_w[erf(w . x~) erf(w . x~')] with w ~ N(0, Sigma); check
    # that definition by Monte Carlo over the weights.
    rng = np.random.default_rng(2)
    a = np.array([[0.3, -0.7], [1.2, 0.4]])
    b = np.array([[-0.5, 0.2], [1.0, 0.9]])
    sd = np.sqrt([NN.bias_variance, *NN.weight_variance])
    w = rng.normal(size=(200_000, 3)) * sd
    ha = erf(w[:, :1] + w[:, 1:] @ a.T)  # (draws, 2)
    hb = erf(w[:, :1] + w[:, 1:] @ b.T)
    prod = ha[:, :, None] * hb[:, None, :]
    mc = prod.mean(axis=0)
    se = prod.std(axis=0) / np.sqrt(len(w))
    got = NN(a, b) / NN.signal_variance
    assert np.all(np.abs(got - mc) < 5 * se + 1e-12)


def test_se_matches_sklearn_rbf():
    a, b = _points(3, 8), _points(4, 6)
    oracle = SE.signal_variance * RBF(length_scale=np.array(SE.lengthscale))(a, b)
    np.testing.assert_allclose(SE(a, b), oracle, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("kernel", KERNELS, ids=["nn", "se"])
def test_diag_pairwise_and_default_b_agree_with_matrix(kernel):
    a, b = _points(5, 9), _points(6, 9)
    full = kernel(a, b)
    np.testing.assert_allclose(kernel.pairwise(a, b), np.diag(full), rtol=1e-13)
    np.testing.assert_allclose(kernel.diag(a), np.diag(kernel(a, a)), rtol=1e-13)
    np.testing.assert_array_equal(kernel(a), kernel(a, a))
    np.testing.assert_allclose(kernel.pairwise_gradient(a, b), np.diagonal(
        kernel.gradient(a, b), axis1=1, axis2=2), rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("kernel", KERNELS, ids=["nn", "se"])
def test_gram_matrix_is_psd(kernel):
    a = _points(7, 60, scale=3.0)
    k = kernel(a, a)
    lam = np.linalg.eigvalsh(0.5 * (k + k.T))
    assert lam.min() >= -1e-10 * lam.max()


@pytest.mark.parametrize("kernel", KERNELS, ids=["nn", "se"])
def test_gradient_matches_finite_differences(kernel):
    a, b = _points(8, 6), _points(9, 4, scale=2.5)
    theta = kernel.theta
    h = 1e-6
    grad = kernel.gradient(a, b)
    pgrad = kernel.pairwise_gradient(a, b[np.arange(6) % 4])
    assert grad.shape == (len(theta), 6, 4)
    assert pgrad.shape == (len(theta), 6)
    for p in range(len(theta)):
        step = np.zeros_like(theta)
        step[p] = h
        up, down = kernel.with_theta(theta + step), kernel.with_theta(theta - step)
        fd = (up(a, b) - down(a, b)) / (2 * h)
        np.testing.assert_allclose(grad[p], fd, rtol=1e-6, atol=1e-9)
        bb = b[np.arange(6) % 4]
        fdp = (up.pairwise(a, bb) - down.pairwise(a, bb)) / (2 * h)
        np.testing.assert_allclose(pgrad[p], fdp, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("kernel", KERNELS, ids=["nn", "se"])
def test_first_derivative_is_the_value(kernel):
    # Protocol invariant the expected-kernel code relies on: theta[0] = log(signal).
    a, b = _points(10, 5), _points(11, 3)
    np.testing.assert_allclose(kernel.gradient(a, b)[0], kernel(a, b), rtol=1e-14)
    assert kernel.parameter_names[0] == "signal_variance"


@pytest.mark.parametrize("kernel", KERNELS, ids=["nn", "se"])
def test_theta_round_trip(kernel):
    theta = kernel.theta
    assert len(kernel.parameter_names) == len(theta)
    same = kernel.with_theta(theta)
    assert type(same) is type(kernel)
    np.testing.assert_allclose(same.theta, theta, rtol=1e-14)
    np.testing.assert_allclose(np.exp(theta[0]), kernel.signal_variance)
    with pytest.raises(ValueError):
        kernel.with_theta(np.zeros(len(theta) + 1))


def test_make_kernel_and_bad_values():
    h = HyperparametersConfig(
        signal_variance=2.0, bias_variance=0.5, weight_variance=(3.0, 5.0),
        lengthscale_m=(0.2, 0.7),
    )
    nn = make_kernel("nn", h)
    assert nn == NeuralNetworkKernel(2.0, 0.5, (3.0, 5.0))
    se = make_kernel("se", h)
    assert se == SquaredExponentialKernel(2.0, (0.2, 0.7))
    assert nn.to_hyperparameters(h) == h
    assert se.to_hyperparameters(h) == h
    with pytest.raises(GpoccError, match="model.kernel"):
        make_kernel("matern", h)
    with pytest.raises(GpoccError, match="lengthscale_m"):
        SquaredExponentialKernel(1.0, (0.5, 0.0))
    with pytest.raises(GpoccError, match="bias_variance"):
        NeuralNetworkKernel(1.0, -1.0, (1.0, 1.0))


def test_kernel_table_is_the_one_list_of_names(tmp_path):
    """Config validation, make_kernel and the model file all read KERNELS: every name in
    it makes its class, and a name outside it is refused by the config loader."""
    from gpocc.config import load_config
    from gpocc.gp.kernels import KERNELS

    h = HyperparametersConfig()
    for name, cls in KERNELS.items():
        kernel = make_kernel(name, h)
        assert type(kernel) is cls
        np.testing.assert_allclose(kernel.with_theta(kernel.theta).theta, kernel.theta)
        assert kernel.to_hyperparameters(h) == h
        path = tmp_path / f"{name}.yaml"
        path.write_text(f"model:\n  kernel: {name}\n")
        assert load_config(path).model.kernel == name
    path = tmp_path / "bad.yaml"
    path.write_text("model:\n  kernel: matern\n")
    with pytest.raises(GpoccError, match="'nn' or 'se'"):
        load_config(path)
