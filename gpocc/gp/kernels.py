"""Covariance functions over 2-D positions (metres), with analytic log-parameter gradients.

Two kernels share one small protocol (:class:`Kernel`): the neural-network (arcsin) kernel
of Williams (1998), whose non-stationarity suits occupancy edges, and the squared
exponential with a length scale per axis. Hyperparameters are optimised in log space, so
``theta`` is the vector of their logarithms and ``gradient`` differentiates with respect to
it. Kernels are frozen dataclasses: ``with_theta`` returns a new one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from gpocc.config import HyperparametersConfig
from gpocc.errors import GpoccError

_TWO_OVER_PI = 2.0 / math.pi


class Kernel(Protocol):
    """What the expected-kernel quadrature and the GP solver need from a kernel.

    Points are (N, 2) arrays of metres. ``P`` is the number of hyperparameters. ``theta[0]``
    is always ``log(signal_variance)``, a pure scale, so ``gradient(a, b)[0] == k(a, b)``:
    callers that need both take the value from the gradient instead of evaluating twice.
    """

    @property
    def theta(self) -> np.ndarray: ...

    @property
    def parameter_names(self) -> tuple[str, ...]: ...

    def with_theta(self, theta: np.ndarray) -> Kernel: ...

    def __call__(self, a: np.ndarray, b: np.ndarray | None = None) -> np.ndarray: ...

    def diag(self, a: np.ndarray) -> np.ndarray: ...

    def pairwise(self, a: np.ndarray, b: np.ndarray) -> np.ndarray: ...

    def gradient(self, a: np.ndarray, b: np.ndarray | None = None) -> np.ndarray: ...

    def pairwise_gradient(self, a: np.ndarray, b: np.ndarray) -> np.ndarray: ...

    def to_hyperparameters(self, base: HyperparametersConfig) -> HyperparametersConfig: ...


def _points(x: np.ndarray, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2), got {x.shape}")
    return x


def _pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b = _points(a, "a"), _points(b, "b")
    if a.shape != b.shape:
        raise ValueError(f"pairwise inputs must have equal shapes, got {a.shape} and {b.shape}")
    return a, b


def _positive(value: float, key: str) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0.0):
        raise GpoccError(
            f"kernel hyperparameter 'model.hyperparameters.{key}' must be a positive finite "
            f"number, got {value!r}; fix it in the config"
        )
    return value


def _positive_pair(values: tuple[float, float], key: str) -> tuple[float, float]:
    """Per-axis (x, y) hyperparameters, each checked by :func:`_positive`."""
    pair = tuple(values)
    if len(pair) != 2:
        raise GpoccError(
            f"kernel hyperparameter 'model.hyperparameters.{key}' needs two entries (x, y), "
            f"got {values!r}"
        )
    return tuple(_positive(v, f"{key}[{i}]") for i, v in enumerate(pair))


def _theta(theta: np.ndarray, size: int) -> np.ndarray:
    theta = np.asarray(theta, dtype=np.float64).reshape(-1)
    if theta.shape != (size,):
        raise ValueError(f"theta must have {size} entries, got {theta.shape}")
    return theta


# --------------------------------------------------------------------------- neural network


@dataclass(frozen=True)
class NeuralNetworkKernel:
    """Williams' arcsin (neural-network) kernel on augmented inputs (1, x, y).

    ``k(x, x') = s * (2/pi) * arcsin(2 x~' S x~ / sqrt((1 + 2 x~' S x~)(1 + 2 x~'' S x~')))``
    with ``S = diag(bias_variance, wx, wy)``. Weight variances are in 1/m^2, so that
    ``1/sqrt(w)`` is roughly the length over which the kernel changes.

    Attributes:
        signal_variance: s, in label units squared (labels are +-1).
        bias_variance: variance of the bias weight (dimensionless).
        weight_variance: (wx, wy) in 1/m^2.
    """

    signal_variance: float = 1.0
    bias_variance: float = 1.0
    weight_variance: tuple[float, float] = (4.0, 4.0)

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "signal_variance", _positive(self.signal_variance, "signal_variance")
        )
        object.__setattr__(self, "bias_variance", _positive(self.bias_variance, "bias_variance"))
        object.__setattr__(
            self, "weight_variance", _positive_pair(self.weight_variance, "weight_variance")
        )

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return ("signal_variance", "bias_variance", "weight_variance_x", "weight_variance_y")

    @property
    def theta(self) -> np.ndarray:
        """(4,) log of (signal_variance, bias_variance, wx, wy)."""
        return np.log([self.signal_variance, self.bias_variance, *self.weight_variance])

    def with_theta(self, theta: np.ndarray) -> NeuralNetworkKernel:
        p = np.exp(_theta(theta, 4))
        return NeuralNetworkKernel(float(p[0]), float(p[1]), (float(p[2]), float(p[3])))

    def _scaled(self, x: np.ndarray) -> np.ndarray:
        """(N, 3) u = x~ sqrt(2 S) / sqrt(1 + 2 x~' S x~), so that z = u @ v.T.

        Normalising each side once keeps |u| < 1, hence |z| < 1 (Cauchy-Schwarz), and turns
        the whole Gram matrix into one BLAS product. Built column by column in a (3, N)
        buffer (returned transposed): row-wise work on (N, 3) arrays is several times slower.
        """
        root = self.root_two_s
        ut = np.empty((3, x.shape[0]))
        np.multiply(x[:, 0], root[1], out=ut[1])
        np.multiply(x[:, 1], root[2], out=ut[2])
        inv = ut[1] * ut[1]
        inv += ut[2] * ut[2]
        inv += 1.0 + root[0] * root[0]
        np.sqrt(inv, out=inv)
        np.divide(1.0, inv, out=inv)
        np.multiply(inv, root[0], out=ut[0])
        ut[1] *= inv
        ut[2] *= inv
        return ut.T

    def scaled_columns(self, x: np.ndarray) -> np.ndarray:
        """(3, N) C-contiguous u' with ``k(a, b) = arcsin_scale * arcsin(u_a . u_b)``."""
        return np.ascontiguousarray(self._scaled(_points(x, "x")).T)

    @property
    def root_two_s(self) -> np.ndarray:
        """(3,) ``sqrt(2 S)``: the per-coordinate factors of :meth:`scaled_inputs`."""
        return np.sqrt(2.0 * np.array([self.bias_variance, *self.weight_variance]))

    @property
    def arcsin_scale(self) -> float:
        """``signal_variance * 2 / pi``: the factor in front of the arcsin."""
        return self.signal_variance * _TWO_OVER_PI

    def _arcsin(self, z: np.ndarray) -> np.ndarray:
        """k from z, in place (z is always a fresh temporary)."""
        np.clip(z, -1.0, 1.0, out=z)  # rounding only; |z| < 1 exactly
        np.arcsin(z, out=z)
        z *= self.signal_variance * _TWO_OVER_PI
        return z

    def __call__(self, a: np.ndarray, b: np.ndarray | None = None) -> np.ndarray:
        """(N, M) k(a_i, b_j) for a (N, 2) and b (M, 2) metres (b defaults to a)."""
        u = self._scaled(_points(a, "a"))
        v = u if b is None else self._scaled(_points(b, "b"))
        return self._arcsin(u @ v.T)

    def diag(self, a: np.ndarray) -> np.ndarray:
        """(N,) k(a_i, a_i)."""
        u = self._scaled(_points(a, "a"))
        return self._arcsin(np.einsum("ij,ij->i", u, u))

    def pairwise(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(P,) k(a_p, b_p) for equal-shape a, b (P, 2)."""
        a, b = _pair(a, b)
        return self._arcsin(np.einsum("ij,ij->i", self._scaled(a), self._scaled(b)))

    def _gradient(self, u: np.ndarray, v: np.ndarray, outer: bool) -> np.ndarray:
        # With theta_c = log S_c: dz/dtheta_c = u_c v_c - z (u_c^2 + v_c^2) / 2.
        z = u @ v.T if outer else np.einsum("ij,ij->i", u, v)
        np.clip(z, -1.0, 1.0, out=z)
        out = np.empty((4, *z.shape))
        np.arcsin(z, out=out[0])
        out[0] *= self.signal_variance * _TWO_OVER_PI
        g = 1.0 - z * z
        np.sqrt(g, out=g)
        np.divide(self.signal_variance * _TWO_OVER_PI, g, out=g)
        half_z = 0.5 * z
        for c in range(3):
            uc, vc = u[:, c], v[:, c]
            if outer:
                d = np.add.outer(uc * uc, vc * vc)
                d *= half_z
                np.subtract(np.multiply.outer(uc, vc), d, out=d)
            else:
                d = uc * vc - half_z * (uc * uc + vc * vc)
            np.multiply(d, g, out=out[c + 1])
        return out

    def gradient(self, a: np.ndarray, b: np.ndarray | None = None) -> np.ndarray:
        """(4, N, M) dk/dtheta for theta = log(signal, bias, wx, wy)."""
        u = self._scaled(_points(a, "a"))
        v = u if b is None else self._scaled(_points(b, "b"))
        return self._gradient(u, v, outer=True)

    def pairwise_gradient(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(4, P) dk(a_p, b_p)/dtheta."""
        a, b = _pair(a, b)
        return self._gradient(self._scaled(a), self._scaled(b), outer=False)

    @classmethod
    def from_hyperparameters(cls, h: HyperparametersConfig) -> NeuralNetworkKernel:
        """The kernel with the initial values of ``model.hyperparameters``."""
        return cls(h.signal_variance, h.bias_variance, tuple(h.weight_variance))

    def to_hyperparameters(self, base: HyperparametersConfig) -> HyperparametersConfig:
        """``base`` with this kernel's values (for writing learned values back)."""
        return HyperparametersConfig(
            signal_variance=self.signal_variance,
            bias_variance=self.bias_variance,
            weight_variance=self.weight_variance,
            lengthscale_m=base.lengthscale_m,
            noise_variance=base.noise_variance,
        )


# --------------------------------------------------------------------------- squared exponential


@dataclass(frozen=True)
class SquaredExponentialKernel:
    """``k(x, x') = s * exp(-1/2 sum_c (x_c - x'_c)^2 / l_c^2)``.

    Attributes:
        signal_variance: s, in label units squared.
        lengthscale: (lx, ly) metres.
    """

    signal_variance: float = 1.0
    lengthscale: tuple[float, float] = (0.5, 0.5)

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "signal_variance", _positive(self.signal_variance, "signal_variance")
        )
        object.__setattr__(
            self, "lengthscale", _positive_pair(self.lengthscale, "lengthscale_m")
        )

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return ("signal_variance", "lengthscale_x", "lengthscale_y")

    @property
    def theta(self) -> np.ndarray:
        """(3,) log of (signal_variance, lx, ly)."""
        return np.log([self.signal_variance, *self.lengthscale])

    def with_theta(self, theta: np.ndarray) -> SquaredExponentialKernel:
        p = np.exp(_theta(theta, 3))
        return SquaredExponentialKernel(float(p[0]), (float(p[1]), float(p[2])))

    def _sq_diffs(self, a: np.ndarray, b: np.ndarray, outer: bool) -> list[np.ndarray]:
        """Per-axis squared differences in length-scale units (no cancellation at r=0)."""
        out = []
        for c in range(2):
            ac, bc = a[:, c] / self.lengthscale[c], b[:, c] / self.lengthscale[c]
            d = np.subtract.outer(ac, bc) if outer else ac - bc
            d *= d
            out.append(d)
        return out

    def _value(self, d2: list[np.ndarray]) -> np.ndarray:
        k = d2[0] + d2[1]
        k *= -0.5
        np.exp(k, out=k)
        k *= self.signal_variance
        return k

    def __call__(self, a: np.ndarray, b: np.ndarray | None = None) -> np.ndarray:
        """(N, M) k(a_i, b_j) for a (N, 2) and b (M, 2) metres (b defaults to a)."""
        a = _points(a, "a")
        b = a if b is None else _points(b, "b")
        return self._value(self._sq_diffs(a, b, outer=True))

    def diag(self, a: np.ndarray) -> np.ndarray:
        """(N,) k(a_i, a_i) = signal_variance."""
        return np.full(_points(a, "a").shape[0], self.signal_variance)

    def pairwise(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(P,) k(a_p, b_p) for equal-shape a, b (P, 2)."""
        a, b = _pair(a, b)
        return self._value(self._sq_diffs(a, b, outer=False))

    def _gradient(self, a: np.ndarray, b: np.ndarray, outer: bool) -> np.ndarray:
        # dk/dlog s = k; dk/dlog l_c = k (x_c - x'_c)^2 / l_c^2.
        d2 = self._sq_diffs(a, b, outer)
        out = np.empty((3, *d2[0].shape))
        out[0] = self._value(d2)
        np.multiply(out[0], d2[0], out=out[1])
        np.multiply(out[0], d2[1], out=out[2])
        return out

    def gradient(self, a: np.ndarray, b: np.ndarray | None = None) -> np.ndarray:
        """(3, N, M) dk/dtheta for theta = log(signal, lx, ly)."""
        a = _points(a, "a")
        b = a if b is None else _points(b, "b")
        return self._gradient(a, b, outer=True)

    def pairwise_gradient(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(3, P) dk(a_p, b_p)/dtheta."""
        a, b = _pair(a, b)
        return self._gradient(a, b, outer=False)

    @classmethod
    def from_hyperparameters(cls, h: HyperparametersConfig) -> SquaredExponentialKernel:
        """The kernel with the initial values of ``model.hyperparameters``."""
        return cls(h.signal_variance, tuple(h.lengthscale_m))

    def to_hyperparameters(self, base: HyperparametersConfig) -> HyperparametersConfig:
        """``base`` with this kernel's values (for writing learned values back)."""
        return HyperparametersConfig(
            signal_variance=self.signal_variance,
            bias_variance=base.bias_variance,
            weight_variance=base.weight_variance,
            lengthscale_m=self.lengthscale,
            noise_variance=base.noise_variance,
        )


#: Every kernel, by its name in ``model.kernel`` and in model files: the one list that
#: config validation, :func:`make_kernel` and :mod:`gpocc.gp.modelfile` read. A new
#: kernel is a class (the :class:`Kernel` protocol plus ``from_hyperparameters`` and
#: ``to_hyperparameters``) and one entry here.
KERNELS: dict[str, type] = {
    "nn": NeuralNetworkKernel,
    "se": SquaredExponentialKernel,
}


def kernel_names_text() -> str:
    """``'nn' or 'se'``: the kernel names for an error message."""
    names = [repr(name) for name in KERNELS]
    return " or ".join([", ".join(names[:-1]), names[-1]] if len(names) > 1 else names)


def learned_names(kernel: Kernel) -> tuple[str, ...]:
    """The names of the values learning searches, in the optimiser's order (before the
    input-noise scale): the kernel's parameters, then ``noise_variance``;
    ``model.training.fixed`` names some of them."""
    return (*kernel.parameter_names, "noise_variance")


def axis_pairs(kernel: Kernel) -> tuple[tuple[int, int], ...]:
    """Index pairs ``(x, y)`` into ``kernel.parameter_names`` (and ``theta``) of the
    parameters it has once per map axis (names ending ``_x`` and ``_y``), which
    ``model.training.isotropic`` learns as one value."""
    names = kernel.parameter_names
    return tuple((i, names.index(n[:-2] + "_y")) for i, n in enumerate(names)
                 if n.endswith("_x") and n[:-2] + "_y" in names)


def make_kernel(name: str, hyperparameters: HyperparametersConfig) -> Kernel:
    """The kernel named by ``model.kernel`` (a key of :data:`KERNELS`) with its initial
    values."""
    cls = KERNELS.get(name)
    if cls is None:
        raise GpoccError(
            f"config key 'model.kernel' must be {kernel_names_text()}, got {name!r}")
    return cls.from_hyperparameters(hyperparameters)
