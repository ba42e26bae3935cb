"""Uncertain training samples: Gaussian input positions with +-1 labels."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Largest label-noise factor (``SampleSet.noise_factors``, ``samples.label_weights``): a
#: label seen in under 0.1% of its cell's samples. The smallest is its inverse (``count``).
MAX_NOISE_FACTOR = 1000.0


def has_both_labels(labels: np.ndarray) -> bool:
    """Whether ``labels`` (+1 occupied, -1 free) hold both classes: what fitting a
    classifier on them needs."""
    return bool(np.any(labels > 0) and np.any(labels < 0))


@dataclass(frozen=True)
class SampleSet:
    """Training samples x_i ~ N(means[i], covariances[i]) with label labels[i].

    Samples of one scan share that scan's pose error, so their positions are correlated:
    ``Cov(x_i, x_j) = pose_factors[i] @ pose_factors[j].T`` when ``scan_ids[i] ==
    scan_ids[j]`` (i != j), and zero otherwise. ``pose_factors[i]`` is G_i L where G_i
    (2x3) is the unscented (statistically linearised) sensitivity of the sample to the
    pose and L L^T the scan's pose covariance.

    Attributes:
        means: (N, 2) metres, map frame.
        covariances: (N, 2, 2) m^2.
        labels: (N,) +1.0 occupied, -1.0 free.
        scan_ids: (N,) int64, unique per scan across all sensors of a job.
        pose_factors: (N, 2, 3) metres.
        sensor_ids: (N,) int16 index into ``sensor_names``.
        sensor_names: the job's sensor names, in ``sensor_ids`` order (empty when not
            known, e.g. a local problem's copy).
        noise_factors: (N,) in [1 / MAX_NOISE_FACTOR, MAX_NOISE_FACTOR] or None (all 1):
            each label's noise variance is the learned label noise times its factor
            (``samples.label_weights``).
    """

    means: np.ndarray
    covariances: np.ndarray
    labels: np.ndarray
    scan_ids: np.ndarray
    pose_factors: np.ndarray
    sensor_ids: np.ndarray
    sensor_names: tuple[str, ...] = ()
    noise_factors: np.ndarray | None = None

    def label_noise(self, noise_variance: float) -> float | np.ndarray:
        """The label-noise variance of each sample: ``noise_variance`` (a scalar) when
        every factor is 1, else (N,) ``noise_variance * noise_factors``."""
        if self.noise_factors is None:
            return noise_variance
        return noise_variance * self.noise_factors

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def subset(self, index: np.ndarray) -> SampleSet:
        """The samples at ``index`` (boolean mask or integer indices)."""
        return SampleSet(
            means=self.means[index],
            covariances=self.covariances[index],
            labels=self.labels[index],
            scan_ids=self.scan_ids[index],
            pose_factors=self.pose_factors[index],
            sensor_ids=self.sensor_ids[index],
            sensor_names=self.sensor_names,
            noise_factors=None if self.noise_factors is None else self.noise_factors[index],
        )

    def without_input_noise(self) -> SampleSet:
        """The same samples with every covariance zero (the no-input-noise baseline)."""
        return SampleSet(
            means=self.means,
            covariances=np.zeros_like(self.covariances),
            labels=self.labels,
            scan_ids=self.scan_ids,
            pose_factors=np.zeros_like(self.pose_factors),
            sensor_ids=self.sensor_ids,
            sensor_names=self.sensor_names,
            noise_factors=self.noise_factors,
        )

    @staticmethod
    def concatenate(parts: list[SampleSet]) -> SampleSet:
        """The parts one after the other; they index one sensor list, whose longest
        ``sensor_names`` is kept."""
        if not parts:
            return SampleSet(
                means=np.zeros((0, 2)),
                covariances=np.zeros((0, 2, 2)),
                labels=np.zeros(0),
                scan_ids=np.zeros(0, dtype=np.int64),
                pose_factors=np.zeros((0, 2, 3)),
                sensor_ids=np.zeros(0, dtype=np.int16),
            )
        return SampleSet(
            means=np.concatenate([p.means for p in parts]),
            covariances=np.concatenate([p.covariances for p in parts]),
            labels=np.concatenate([p.labels for p in parts]),
            scan_ids=np.concatenate([p.scan_ids for p in parts]),
            pose_factors=np.concatenate([p.pose_factors for p in parts]),
            sensor_ids=np.concatenate([p.sensor_ids for p in parts]),
            sensor_names=max((p.sensor_names for p in parts), key=len),
            noise_factors=(None if all(p.noise_factors is None for p in parts) else
                           np.concatenate([np.ones(len(p)) if p.noise_factors is None
                                           else p.noise_factors for p in parts])),
        )
