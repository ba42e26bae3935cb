"""The held-out-scan protocol: train on some scans, label points from the others.

Of each sensor's scans, the ones whose index ``i`` (0-based, in recorded order) satisfies
``i % every == every - 1`` are held out (so the first scan always trains, and ``every``
scans hold out ``n // every`` of ``n``). The remaining scans, optionally thinned (every
``keep_every``-th scan, every ``beam_every``-th beam: the sparse regime), are the
training set. The held-out scans become labelled points of three kinds
(:func:`gpocc.samples.heldout.protocol_points`): each valid hit is an occupied point at
its endpoint (``hit``), each beam adds ``free_per_beam`` free points at uniformly random
distances along the beam, short of the hit (``free``), and each hit adds
``near_wall_per_beam`` free points uniform in the band 0.05-0.3 m in front of it
(``near-wall``).
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass

import numpy as np

from gpocc.config import Config, SensorConfig
from gpocc.errors import GpoccError
from gpocc.io.scans import ScanBatch
from gpocc.samples import beam_rules
from gpocc.samples.heldout import heldout_mask, protocol_points, subset_batch
from gpocc.samples.heldout import labelled_points as labelled_points  # re-exported


@dataclass(frozen=True)
class SplitResult:
    """One sensor's split.

    Attributes:
        train: the training scans (thinned), with pose covariances filled in.
        points: (N, 2) metres, labelled points from the held-out scans.
        labels: (N,) int8, 1 occupied, 0 free.
        n_heldout: number of held-out scans.
        kinds: (N,) str, each point's kind (``hit``, ``free`` or ``near-wall``).
    """

    train: ScanBatch
    points: np.ndarray
    labels: np.ndarray
    n_heldout: int
    kinds: np.ndarray


def with_pose_covariances(batch: ScanBatch, sensor: SensorConfig) -> ScanBatch:
    """The batch with the pose covariances that apply to it (:mod:`gpocc.samples.beam_rules`).

    Written into a bag, the covariances then travel with the scans, so the bag needs no
    config to say how uncertain its poses are.
    """
    if beam_rules.uses_input_covariance(batch, sensor):
        return batch
    cov = np.broadcast_to(sensor.pose_covariance_matrix, (batch.n_scans, 3, 3)).copy()
    return dataclasses.replace(batch, pose_covariances=cov, has_pose_covariance=True)


def split_batch(
    batch: ScanBatch,
    sensor: SensorConfig,
    *,
    every: int,
    keep_every: int = 1,
    beam_every: int = 1,
    free_per_beam: int = 3,
    near_wall_per_beam: int = 1,
    rng: np.random.Generator,
) -> SplitResult:
    """Split one sensor's scans into training scans and held-out labelled points.

    The held-out scans keep all their beams (the truth stays dense whatever the training
    regime); ``keep_every`` and ``beam_every`` thin only the training scans.
    """
    if keep_every < 1 or beam_every < 1:
        raise GpoccError(f"the training scan and beam steps must be at least 1, got "
                         f"{keep_every} and {beam_every}")
    if free_per_beam < 0 or near_wall_per_beam < 0:
        raise GpoccError(f"the free and near-wall points per beam must not be negative, got "
                         f"{free_per_beam} and {near_wall_per_beam}")
    held = heldout_mask(batch.n_scans, every)
    train_idx = np.flatnonzero(~held)[::keep_every]
    train = with_pose_covariances(subset_batch(batch, train_idx, beam_every), sensor)
    points, labels, kinds = protocol_points(
        subset_batch(batch, np.flatnonzero(held)), sensor, free_per_beam, near_wall_per_beam,
        rng,
    )
    return SplitResult(train=train, points=points, labels=labels, n_heldout=int(held.sum()),
                       kinds=kinds)


def topic_prefix(sensor_name: str) -> str:
    """A valid ROS name from a sensor name (``intel.gfs`` -> ``intel_gfs``)."""
    name = re.sub(r"[^A-Za-z0-9_]", "_", sensor_name) or "sensor"
    return name if name[0].isalpha() else f"s_{name}"


def train_config(config: Config, sensors: list[tuple[SensorConfig, str, str]]) -> Config:
    """The input config with ``sensors`` pointing at the training bag's topics.

    Args:
        config: the input job's config; everything but the sensors is kept.
        sensors: (sensor config, scan topic, pose topic) per written sensor; the noise
            settings are kept, the input globs dropped (the bag is the only input).
    """
    # The bag holds the scans as read: an upside-down laser's bearings already mirrored
    # (mount.upside_down acts when reading), so reading it must not mirror them again.
    entries = tuple(
        dataclasses.replace(s, inputs=(), scan_topic=scan, pose_topic=pose,
                            mount=dataclasses.replace(s.mount, upside_down=False))
        for s, scan, pose in sensors
    )
    # The bag's poses are in the job's map frame already (the inputs' transforms applied
    # when reading): its config must not move them again.
    return dataclasses.replace(config, sensors=entries, inputs=())


def merge_by_sensor(batches: list[ScanBatch]) -> list[ScanBatch]:
    """One batch per sensor, joining same-sensor batches in time order.

    The written bag has one scan topic per sensor, so batches that share a sensor must
    share their beam layout.
    """
    merged: dict[str, ScanBatch] = {}
    for b in batches:
        if b.sensor not in merged:
            merged[b.sensor] = b
            continue
        a = merged[b.sensor]
        if a.angles.shape != b.angles.shape or not np.allclose(a.angles, b.angles):
            raise GpoccError(
                f"{b.source}: sensor '{b.sensor}' has a different beam layout than in "
                f"{a.source}; give them different sensor names in the config"
            )
        joined = {
            f: np.concatenate([getattr(a, f), getattr(b, f)])
            for f in ("stamps", "ranges", "poses", "pose_covariances")
        }
        order = np.argsort(joined["stamps"], kind="stable")
        merged[b.sensor] = dataclasses.replace(
            a,
            **{k: v[order] for k, v in joined.items()},
            has_pose_covariance=a.has_pose_covariance and b.has_pose_covariance,
            skipped_scans=a.skipped_scans + b.skipped_scans,
        )
    return list(merged.values())
