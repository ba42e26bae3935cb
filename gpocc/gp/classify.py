"""Probabilistic least-squares classification (Platt scaling of the GP regression).

``p(occupied | x) = Phi((a * mu + b) / sqrt(1 + a^2 * var))`` squashes the latent GP
mean ``mu`` and variance ``var`` into a probability (Rasmussen and Williams, section
6.5). It is fitted and stored as ``Phi((mu + c) / sqrt(s + var))`` with the offset
``c = b / a`` (latent units) and the extra variance ``s = 1 / a^2`` (latent units
squared): the same family, but as ``a`` grows the objective tends to that of
``Phi((mu + c) / sqrt(var))``, a ridge towards ``a -> infinity`` along which the fitted
``a`` depended on round-off. In ``(c, s)`` that ridge is the finite
boundary ``s = S_MIN`` (``a = 1000``, the old bound), which a bounded optimiser reaches
exactly. ``c`` and ``s`` maximise the predictive log probability of training labels that
the predicting GP did not see, in one of two ways (``model.training.
classifier_holdout``):

* ``sample`` (default): the method as published, closed-form leave-one-sample-out of
  the training labels (predictive variance including the label noise).
* ``scan``: leave one *scan* out. Each sample of a local problem is predicted, as a map
  cell would be (an exact point at its mean, latent mean and variance), from the
  problem's samples of all *other* scans, so that samples of one scan (which share its
  pose error) cannot vouch for each other. It gives a much flatter classifier (a of
  1.3-1.6 instead of 260-530), which measured *worse* calibrated on held-out scans and
  simulated truth (docs/results.md, 'Summary' and 'Protocol `cells`', made with
  ``python -m bench.experiment --variant scan-cv`` against ``--variant published``): free
  space came out grey (p 0.2-0.3). A likely
  reason, not yet verified: held-out training samples are not distributed like map
  queries (thinning keeps boundary cells over-represented, and map cells lie between
  samples), so a classifier fitted on them is too timid for open space.

``model.training.classifier_offset: beams`` then re-fits the offset ``c`` (``s`` kept;
with ``classifier_temperature: beams``, together with the temperature) on labelled points
of held-out *scans* (every ``calibration_every``-th scan; an
occupied point at each hit, three free points at uniform distances along each beam, only
points whose position is known to ``calibration_max_position_std_m``:
:mod:`gpocc.samples.heldout`), predicted as map cells are from the samples of all other
scans, in up to ``calibration_blocks`` randomly chosen map blocks. Held-out hits lie on
wall surfaces, where the latent mean crosses zero, so this offset makes the probability
mean what it says at points where beams end, while the leave-one-out offset is
calibrated for the training samples (``make experiment``'s variant ``offset-holdout``
measures both).

``model.training.classifier_temperature`` then divides the classifier's argument by a
temperature ``T`` fitted on the same held-out predictions, their variances taken as a map
cell's are (of the latent function: with ``sample``, the leave-one-out variance of the
label minus the label noise). The fit of ``c`` and ``s`` uses the label's variance, as
published, but a map cell has only the latent one: without ``T`` the map divides by a
smaller variance than the fit did and comes out overconfident (p of 0 or 1 within a
cell of walls). ``Phi(z / T)`` is increasing in ``z``, so the map's ranking, its AUC and
FPR at any TPR, stay as they were; only the probabilities move, except where they reach
0 or 1 in float32, whose cells then tie.

The offset and temperature fits aim at ``model.training.classifier_targets``. With
``hard`` targets (each label as 0 or 1), where every held-out point lies on its label's
side (:func:`separates`) the log probability rises without limit as ``T`` falls, so the
data do not choose one; no ``T`` is fitted then, but where all but a few points lie so,
the fit still runs ``T`` to its lower bound, and the map's probabilities are 0 or 1
everywhere but at the walls: stored as float32, most cells tie and the ranking is lost.
``platt`` targets (default; Platt 1999) give a point of a label that N points carry the
target ``(N + 1) / (N + 2)`` instead of 1 (:func:`platt_targets`): the log probability
then has a maximum at a finite ``T`` on any points, and where the labels overlap the fit
moves by about 1 / N.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.special import log_ndtr, ndtr

from gpocc.config import CLASSIFIER_TARGETS
from gpocc.constants import FREE, NO_DATA, OCCUPIED, UNSURE
from gpocc.gp.expected import expected_kernel_cross
from gpocc.gp.kernels import Kernel
from gpocc.gp.local import (
    LocalProblem,
    NeighbourIndex,
    cholesky_solve,
    factor_training_covariance,
    leave_one_out,
    predict_local,
)
from gpocc.samples.beams import packed_cells
from gpocc.samples.heldout import CalibrationPoints
from gpocc.samples.sampleset import SampleSet, has_both_labels

#: ``map(fn, items)``: the results of ``fn`` over ``items``, in order.
MapFunction = Callable[[Callable[[Any], Any], Iterable[Any]], Iterable[Any]]

#: Ways to hold labels out when fitting the classifier (see the module docstring).
HOLDOUTS = ("scan", "sample")



#: Most held-out points predicted per block for the beam offset (Freiburg's busiest blocks hold
#: thousands; a random share keeps the fit's cost bounded by the number of blocks).
POINTS_PER_BLOCK = 256

#: Bounds of the fit: extra variance s = 1/a^2 (a in [1e-3, 1e3]) and offset c = b/a.
S_MIN, S_MAX = 1e-6, 1e6
C_BOUND = 1e2
#: Bounds of the fitted temperature (``model.training.classifier_temperature``).
T_MIN, T_MAX = 1e-2, 1e3


@dataclass(frozen=True)
class PlattClassifier:
    """p = Phi((mu + offset) / (temperature * sqrt(extra_variance + var))).

    ``offset`` is c = b / a and ``extra_variance`` s = 1 / a^2 > 0 of the published form
    Phi((a mu + b) / sqrt(1 + a^2 var)); ``a`` and ``b`` are derived for display.
    ``temperature`` T > 0 (1: the published form) rescales the argument; see the module
    docstring.
    """

    offset: float = 0.0
    extra_variance: float = 1.0
    temperature: float = 1.0

    @classmethod
    def from_ab(cls, a: float, b: float) -> PlattClassifier:
        """The classifier Phi((a mu + b) / sqrt(1 + a^2 var)) for a > 0."""
        return cls(offset=b / a, extra_variance=1.0 / a**2)

    @property
    def a(self) -> float:
        return float(1.0 / np.sqrt(self.extra_variance))

    @property
    def b(self) -> float:
        return float(self.offset / np.sqrt(self.extra_variance))

    def summary(self) -> str:
        """``a=.. b=.. (offset .., extra variance ..[, temperature ..]``, without the
        closing parenthesis (a command adds what the classifier was fitted on)."""
        return (f"a={self.a:.4g} b={self.b:.4g} (offset {self.offset:.4g}, extra variance "
                f"{self.extra_variance:.3g}"
                + (f", temperature {self.temperature:.4g}" if self.temperature != 1.0 else ""))

    def probability(self, mean: np.ndarray, variance: np.ndarray) -> np.ndarray:
        """p(occupied) for latent means and variances of any (matching) shape."""
        return ndtr((mean + self.offset)
                    / (self.temperature * np.sqrt(self.extra_variance + variance)))


def platt_targets(labels: np.ndarray) -> np.ndarray:
    """(N,) the probability each point's target gives its own label (labels +-1, (N,)):
    Platt's out-of-sample targets, ``(N_y + 1) / (N_y + 2)`` for a point of a label that
    N_y points carry (Platt 1999, "Probabilistic outputs for support vector machines",
    section 2.2). A 0/1 target makes a fit on separable points run to the steepest
    squashing its box allows; these keep a finite optimum there, and move the fit by
    about 1 / N where the labels overlap."""
    occupied = labels > 0
    n_occupied = float(np.count_nonzero(occupied))
    n_free = float(labels.size) - n_occupied
    return np.where(occupied, (n_occupied + 1.0) / (n_occupied + 2.0),
                    (n_free + 1.0) / (n_free + 2.0))


def held_out_log_probability(offset: float, extra_variance: float, mean: np.ndarray,
                             variance: np.ndarray, labels: np.ndarray,
                             temperature: float = 1.0,
                             targets: np.ndarray | None = None) -> float:
    """Sum over held-out predictions (N,) of ``t_i log Phi(z_i) + (1 - t_i) log
    Phi(-z_i)``, ``z_i = y_i (mu_i + c) / (T sqrt(s + var_i))``: the log probability of
    their labels under targets ``t`` (N,; the probability each target gives the point's
    own label, :func:`platt_targets`; None: 1, the labels themselves)."""
    z = labels * (mean + offset) / (temperature * np.sqrt(extra_variance + variance))
    if targets is None:
        return float(log_ndtr(z).sum())
    return float((targets * log_ndtr(z) + (1.0 - targets) * log_ndtr(-z)).sum())


def target_probabilities(labels: np.ndarray, kind: str) -> np.ndarray | None:
    """The targets of ``model.training.classifier_targets`` ``kind`` for ``labels`` (N,):
    :func:`platt_targets` for ``platt``, None (the labels) for ``hard``."""
    if kind not in CLASSIFIER_TARGETS:
        raise ValueError(f"unknown classifier targets {kind!r}")
    return platt_targets(labels) if kind == "platt" else None


def _negative_log_probability(params: np.ndarray, mean: np.ndarray, variance: np.ndarray,
                              labels: np.ndarray) -> tuple[float, np.ndarray]:
    """-held_out_log_probability and its gradient in (c, s)."""
    c, s = params
    root = np.sqrt(s + variance)
    z = labels * (mean + c) / root
    log_cdf = log_ndtr(z)
    # d log Phi(z) / dz = phi(z) / Phi(z), evaluated in logs (stable for z << 0).
    ratio = np.exp(-0.5 * z**2 - 0.5 * np.log(2 * np.pi) - log_cdf)
    grad_c = -np.sum(ratio * labels / root)
    grad_s = np.sum(ratio * z / (2.0 * root**2))
    return float(-log_cdf.sum()), np.array([grad_c, grad_s])


def leave_one_scan_out(kernel: Kernel, noise_variance: float, patch: LocalProblem,
                       level: int, backend: str = "auto",
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Latent predictions at each sample of ``patch`` from the patch's other scans.

    Sample ``i`` of scan ``s`` is treated as a query at its mean (exact, like a map
    cell) and predicted by the GP on the patch's samples of every scan but ``s``:
    ``mu_i = k_i,R K_RR^-1 y_R`` and ``var_i = k(x_i, x_i) - k_i,R K_RR^-1 k_R,i``. One
    factorisation serves all scans: ``K_RR^-1`` is the Schur complement of the held-out
    block ``G`` in ``K^-1``, ``(K^-1)_RR - (K^-1)_RG ((K^-1)_GG)^-1 (K^-1)_GR``.

    Returns:
        ``(mean, variance, mask)``, each (M,): predictions, and True where the sample could
        be predicted (its scan is not the patch's only scan).
    """
    s = patch.samples
    m = len(s)
    chol = factor_training_covariance(kernel, noise_variance, s, level, backend)
    inverse = cholesky_solve(chol, np.eye(m))
    alpha = inverse @ s.labels
    cross = expected_kernel_cross(kernel, s.means, s.means, s.covariances, level,
                                  backend=backend)
    prior = kernel.diag(s.means)
    mean, variance = np.zeros(m), np.zeros(m)
    mask = np.zeros(m, dtype=bool)
    for scan in np.unique(s.scan_ids):
        held = np.flatnonzero(s.scan_ids == scan)
        rest = np.flatnonzero(s.scan_ids != scan)
        if rest.size == 0:
            continue
        # K_RR^-1 y_R = alpha_R - (K^-1)_RG (K^-1)_GG^-1 alpha_G (block inverse identity).
        g_inv = inverse[np.ix_(held, held)]
        rg = inverse[np.ix_(rest, held)]
        weights_y = alpha[rest] - rg @ np.linalg.solve(g_inv, alpha[held])
        k_gr = cross[np.ix_(held, rest)]
        mean[held] = k_gr @ weights_y
        rr_inv_k = inverse[np.ix_(rest, rest)] @ k_gr.T - rg @ np.linalg.solve(g_inv, rg.T @ k_gr.T)
        variance[held] = np.maximum(prior[held] - np.einsum("gr,rg->g", k_gr, rr_inv_k), 0.0)
        mask[held] = True
    return mean, variance, mask


def patch_holdout_predictions(kernel: Kernel, noise_variance: float, patch: LocalProblem,
                              level: int, holdout: str = "sample", backend: str = "auto",
                              latent: bool = False,
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Held-out latent means, variances and labels of one patch's samples (``holdout``:
    scan or sample; with ``scan``, only the samples another scan of the patch can
    predict). ``latent`` (with ``sample``): the variance of the latent function, the
    leave-one-out variance of the label minus the label noise (``y_i = f_i + e_i`` with
    ``e_i`` independent of the other labels), as a map cell's variance is; ``scan``'s
    are latent already."""
    if holdout == "scan":
        mu, var, mask = leave_one_scan_out(kernel, noise_variance, patch, level, backend)
        return mu[mask], var[mask], patch.samples.labels[mask]
    chol = factor_training_covariance(kernel, noise_variance, patch.samples, level, backend)
    mu, var = leave_one_out(chol, patch.samples.labels)
    factors = patch.samples.noise_factors
    if latent:
        var = latent_variance(var, patch.samples.label_noise(noise_variance))
    elif factors is not None:
        # The variance of one new label there: a weighted sample's own noise stands for
        # its cell's count, a new label has the base noise.
        var = np.maximum(var - noise_variance * (factors - 1.0), noise_variance)
    return mu, var, patch.samples.labels


def latent_variance(label_variance: np.ndarray, noise_variance: float | np.ndarray
                    ) -> np.ndarray:
    """The latent function's leave-one-out variances (N,) from the label's (N,): minus
    the label noise (``y_i = f_i + e_i``, ``e_i`` independent of the other labels)."""
    # 1/[K^-1]_ii >= noise_variance in exact arithmetic; round-off may cross it.
    return np.maximum(label_variance - noise_variance, 0.0)


def holdout_predictions(kernel: Kernel, noise_variance: float, patches: list[LocalProblem],
                        level: int, holdout: str = "sample", backend: str = "auto",
                        map_fn: MapFunction = map, latent: bool = False,
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Held-out latent means, variances and labels (concatenated over ``patches``);
    ``backend``: ``model.backend`` (:mod:`gpocc.gp.backends`), as everywhere here.

    ``map_fn(fn, items)``: how the patches are computed, in order (the built-in ``map``
    here; :func:`gpocc.parallel.cluster_map` on a Dask cluster)."""
    if holdout not in HOLDOUTS:
        raise ValueError(f"holdout must be one of {HOLDOUTS}, got {holdout!r}")
    one = functools.partial(patch_holdout_predictions, kernel, noise_variance,
                            level=level, holdout=holdout, backend=backend, latent=latent)
    means, variances, labels = zip(*map_fn(one, patches), strict=True)
    return np.concatenate(means), np.concatenate(variances), np.concatenate(labels)


def fit_platt(mean: np.ndarray, variance: np.ndarray, labels: np.ndarray) -> PlattClassifier:
    """c and s maximising :func:`held_out_log_probability` of held-out predictions (N,).

    Bounded L-BFGS-B in (c, s) with the analytic gradient: where the objective keeps
    rising towards a -> infinity, s stops at the bound :data:`S_MIN` exactly.
    """
    if not has_both_labels(labels):
        # Nothing to calibrate against: keep the identity squashing.
        return PlattClassifier()
    from scipy.optimize import minimize  # here: `gpocc map` never fits, and the import is slow

    result = minimize(_negative_log_probability, np.array([0.0, 1.0]),
                      args=(mean, variance, labels), jac=True, method="L-BFGS-B",
                      bounds=[(-C_BOUND, C_BOUND), (S_MIN, S_MAX)])
    return PlattClassifier(offset=float(result.x[0]), extra_variance=float(result.x[1]))


def beam_holdout_predictions(
    kernel: Kernel, noise_variance: float, samples: SampleSet, calibration: CalibrationPoints,
    level: int, neighbours: int, block_size_m: float, max_blocks: int,
    rng: np.random.Generator, backend: str = "auto", map_fn: MapFunction = map,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Latent predictions at held-out beam points from the samples of the other scans.

    The points are grouped into square blocks of ``block_size_m``; up to ``max_blocks``
    blocks (chosen with ``rng``) are predicted, each from the ``neighbours`` samples
    nearest its centre among those whose scan is not held out, like a map block, at up
    to :data:`POINTS_PER_BLOCK` of its points. ``map_fn``: as in
    :func:`holdout_predictions`, over the blocks.

    Returns:
        ``(mean, variance, labels)``, each (M,), M <= len(calibration.points).
    """
    keep = np.flatnonzero(~np.isin(samples.scan_ids, calibration.scan_ids))
    if keep.size == 0 or calibration.points.shape[0] == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    index = NeighbourIndex(samples, rows=keep)
    blocks, order, bounds = cell_groups(
        np.floor(calibration.points / block_size_m).astype(np.int64))
    chosen = np.sort(rng.permutation(len(blocks))[:max_blocks])
    problems, points, labels = [], [], []
    for b in chosen:
        rows = order[bounds[b]:bounds[b + 1]]
        if rows.size > POINTS_PER_BLOCK:  # a block many scans crossed: a random share
            rows = np.sort(rng.choice(rows, POINTS_PER_BLOCK, replace=False))
        problems.append(index.problem((blocks[b] + 0.5) * block_size_m, neighbours))
        points.append(calibration.points[rows])
        labels.append(calibration.labels[rows])
    one = functools.partial(_predict_block, kernel, noise_variance, level=level,
                            backend=backend)
    means, variances = zip(*map_fn(one, zip(problems, points, strict=True)), strict=True)
    return np.concatenate(means), np.concatenate(variances), np.concatenate(labels)


def unique_cells(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(cells, axis=0, return_inverse=True)`` of integer cells (N, 2), the
    inverse flat (N,): the distinct cells in lexicographic order and each row's index
    among them, from :func:`cell_groups`."""
    unique, order, bounds = cell_groups(cells)
    inverse = np.empty(len(cells), dtype=np.intp)
    inverse[order] = np.repeat(np.arange(len(unique)), np.diff(bounds))
    return unique, inverse


def cell_groups(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rows of integer ``cells`` (N, 2) grouped by cell: the distinct cells (G, 2) in
    lexicographic order, an order (N,) of the rows, cell by cell and stable within a
    cell, and (G + 1,) bounds: cell g's rows are ``order[bounds[g]:bounds[g + 1]]``.

    Each row is one key (:func:`gpocc.samples.beams.packed_cells` of the cells from their
    minimum, so the keys sort as the rows do) for one stable 1-D sort: ``np.unique`` with
    ``axis=0`` sorts rows as structured records, many times slower on the 3 million
    held-out points of a city."""
    if len(cells) == 0:
        return np.zeros((0, 2), dtype=cells.dtype), np.zeros(0, np.intp), np.zeros(1, np.intp)
    low = np.array([cells[:, 0].min(), cells[:, 1].min()])  # column by column: faster
    shifted = cells - low
    if shifted.max() >= 2**31:  # past one packed key: rows as records
        unique, member = np.unique(cells, axis=0, return_inverse=True)
        order = np.argsort(member.ravel(), kind="stable")
        return unique, order, np.searchsorted(member.ravel()[order],
                                              np.arange(len(unique) + 1))
    keys = packed_cells(shifted)
    order = np.argsort(keys, kind="stable")
    ordered = keys[order]
    starts = np.flatnonzero(np.concatenate(([True], ordered[1:] != ordered[:-1])))
    distinct = ordered[starts]
    unique = np.column_stack([(distinct >> 32) + low[0], (distinct & 0xFFFFFFFF) + low[1]])
    return unique, order, np.append(starts, len(cells))


def _predict_block(kernel: Kernel, noise_variance: float,
                   block: tuple[LocalProblem, np.ndarray], level: int, backend: str,
                   ) -> tuple[np.ndarray, np.ndarray]:
    pred = predict_local(kernel, noise_variance, block[0], block[1], level, backend)
    return pred.mean, pred.variance


def offset_bound(mean: np.ndarray, offset_range: str = "wide") -> float:
    """The largest |c| an offset fitted on held-out predictions (N,) may take
    (``model.training.classifier_offset_range``): :data:`C_BOUND` for ``wide``; for
    ``latent`` the largest |mean| (at most C_BOUND, at least 1e-6)."""
    if offset_range == "wide" or mean.size == 0:
        return C_BOUND
    return float(np.clip(np.max(np.abs(mean)), 1e-6, C_BOUND))


def fit_offset(mean: np.ndarray, variance: np.ndarray, labels: np.ndarray,
               extra_variance: float, temperature: float = 1.0,
               bound: float = C_BOUND, targets: str = "hard") -> PlattClassifier:
    """The offset c maximising :func:`held_out_log_probability` of held-out predictions
    (N,) with the extra variance s and temperature T fixed (bounded Brent search in
    [-bound, bound]; :func:`offset_bound`), under ``targets``
    (:func:`target_probabilities`)."""
    from scipy.optimize import minimize_scalar  # here: `gpocc map` never fits

    t = target_probabilities(labels, targets)
    best = minimize_scalar(
        lambda c: -held_out_log_probability(c, extra_variance, mean, variance, labels,
                                            temperature, t),
        bounds=(-bound, bound), method="bounded", options={"xatol": 1e-6})
    return PlattClassifier(offset=float(best.x), extra_variance=extra_variance,
                           temperature=temperature)


def fit_offset_and_temperature(mean: np.ndarray, variance: np.ndarray, labels: np.ndarray,
                               extra_variance: float, bound: float = C_BOUND,
                               targets: str = "hard") -> PlattClassifier:
    """The offset c and temperature T maximising :func:`held_out_log_probability` of
    held-out predictions (N,) together, the extra variance s fixed (L-BFGS-B on (c, log T)
    within [-bound, bound] (:func:`offset_bound`) and [T_MIN, T_MAX], from c = 0, T = 1).

    As c and T grow together with c / T fixed, p tends to Phi(c / (T sqrt(s + var))): a
    function of the latent variance alone. Where the means barely separate the labels
    that limit can beat every c among the means, and a wide box lets the fit run to it;
    ``bound`` at the largest |mean| keeps the decision among the means.

    Fitted one after the other (c at T = 1, then T), c is chosen for probabilities far
    sharper than the map's: on points few of which lie near the decision it runs toward
    one label (on some simulated worlds, toward occupied). Points that one label holds
    entirely give no temperature: c alone is fitted then, at T = 1. ``targets``: as in
    :func:`fit_offset`."""
    if not has_both_labels(labels):
        return fit_offset(mean, variance, labels, extra_variance, bound=bound,
                          targets=targets)
    from scipy.optimize import minimize  # here: `gpocc map` never fits

    t = target_probabilities(labels, targets)

    def negative(params: np.ndarray) -> float:
        return -held_out_log_probability(params[0], extra_variance, mean, variance, labels,
                                         float(np.exp(params[1])), t)

    best = minimize(negative, np.zeros(2), method="L-BFGS-B",
                    bounds=[(-bound, bound), (np.log(T_MIN), np.log(T_MAX))])
    return PlattClassifier(offset=float(best.x[0]), extra_variance=extra_variance,
                           temperature=float(np.exp(best.x[1])))


def separates(classifier: PlattClassifier, mean: np.ndarray, labels: np.ndarray) -> bool:
    """Whether every held-out prediction (N,) is on its label's side of ``classifier``'s
    decision: mu + c > 0 for occupied (+1), < 0 for free (-1)."""
    return bool(np.all(labels * (mean + classifier.offset) > 0))


def temperature_undetermined(classifier: PlattClassifier, mean: np.ndarray,
                             labels: np.ndarray, targets: str) -> bool:
    """Whether no temperature maximises :func:`held_out_log_probability` of held-out
    predictions (N,) under ``targets``: with ``hard`` targets, where ``classifier``
    :func:`separates` them (the probability rises as T falls); Platt's always have one."""
    return targets == "hard" and separates(classifier, mean, labels)


def fit_temperature(classifier: PlattClassifier, mean: np.ndarray, variance: np.ndarray,
                    labels: np.ndarray, targets: str = "hard") -> PlattClassifier:
    """``classifier`` with the temperature T maximising :func:`held_out_log_probability`
    of held-out predictions (N,; ``variance`` of the latent function, as a map cell's)
    under ``targets`` (:func:`target_probabilities`), its offset and extra variance kept
    (bounded Brent search on log T in [log T_MIN, log T_MAX]). ``classifier`` unchanged
    when the points hold one label, or when :func:`temperature_undetermined`."""
    if not has_both_labels(labels) or temperature_undetermined(classifier, mean, labels,
                                                                targets):
        return classifier
    from scipy.optimize import minimize_scalar  # here: `gpocc map` never fits

    c, s = classifier.offset, classifier.extra_variance
    t = target_probabilities(labels, targets)
    best = minimize_scalar(
        lambda log_t: -held_out_log_probability(c, s, mean, variance, labels,
                                                float(np.exp(log_t)), t),
        bounds=(np.log(T_MIN), np.log(T_MAX)), method="bounded", options={"xatol": 1e-6})
    return PlattClassifier(offset=c, extra_variance=s, temperature=float(np.exp(best.x)))


def fit_classifier(kernel: Kernel, noise_variance: float, patches: list[LocalProblem],
                   level: int, holdout: str = "sample", backend: str = "auto",
                   map_fn: MapFunction = map, latent: bool = False,
                   temperature: bool = False, targets: str = "hard") -> PlattClassifier:
    """Fit the classifier on held-out predictions over ``patches`` (``holdout``: scan or
    sample; ``backend``, ``map_fn`` and ``latent`` as in :func:`holdout_predictions`);
    with ``temperature``, then its temperature on the same predictions with the variance
    of the latent function (:func:`fit_temperature`, under ``targets``)."""
    mu, var, y = holdout_predictions(kernel, noise_variance, patches, level, holdout, backend,
                                     map_fn, latent)
    classifier = fit_platt(mu, var, y)
    if not temperature:
        return classifier
    if holdout == "sample" and not latent:
        var = latent_variance(var, noise_variance)
    return fit_temperature(classifier, mu, var, y, targets)


def class_counts(classes: np.ndarray) -> dict[str, int]:
    """Cells per class of a ``classify`` result (no-data cells are not counted)."""
    return {"free": int(np.count_nonzero(classes == FREE)),
            "occupied": int(np.count_nonzero(classes == OCCUPIED)),
            "unsure": int(np.count_nonzero(classes == UNSURE))}


def classify(probability: np.ndarray, occupied: float, free: float,
             unsure: np.ndarray | None = None) -> np.ndarray:
    """uint8 classes: 1 occupied (p > occupied), 0 free (p < free), 2 unsure, 255 no data.

    ``unsure`` (bool, same shape) forces cells to unsure, e.g. where the predictive
    variance is too close to the prior variance for a decision.
    """
    classes = np.full(probability.shape, UNSURE, dtype=np.uint8)
    classes[probability > occupied] = OCCUPIED
    classes[probability < free] = FREE
    if unsure is not None:
        classes[unsure] = UNSURE
    classes[~np.isfinite(probability)] = NO_DATA
    return classes
