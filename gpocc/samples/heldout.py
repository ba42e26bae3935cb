"""Labelled points from held-out scans: occupied at each hit, free along each beam,
and free just in front of each hit (the near-wall band).

The points a user checks a map against: ``gpocc split`` makes them the ground truth of
held-out scans (:mod:`gpocc.evaluation.split`), and with ``model.training.
classifier_offset: beams`` ``gpocc train`` re-fits the classifier's offset on them
(:mod:`gpocc.gp.classify`), so that it is calibrated at points where beams end rather
than on thinned training samples. Of a batch's scans, those with index
``i % every == every - 1`` are held out.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from gpocc.config import Config, SensorConfig
from gpocc.errors import GpoccError
from gpocc.io.scans import ScanBatch
from gpocc.samples import beam_rules
from gpocc.samples.sampleset import has_both_labels

#: Free points start this far from the laser and stop this far short of a hit, metres.
FREE_MARGIN_M = 0.1
#: Near-wall free points lie this far in front of a hit, metres: uniform in
#: ``[r - NEAR_WALL_BAND_M[1], r - NEAR_WALL_BAND_M[0]]`` for a hit at range ``r``. Free
#: points along the whole beam rarely fall there, so only these test whether a map
#: paints the space just in front of a wall occupied (a thick wall).
NEAR_WALL_BAND_M = (0.05, 0.3)
#: The kinds of labelled points, as written in ``heldout.csv``'s ``kind`` column.
HIT, FREE, NEAR_WALL = "hit", "free", "near-wall"


def heldout_mask(n_scans: int, every: int) -> np.ndarray:
    """(n_scans,) bool: True for the held-out scans, index % every == every - 1."""
    if every < 2:
        raise GpoccError(f"the hold-out period must be at least 2 (every scan would be held "
                         f"out), got {every}")
    # A period beyond the scans holds none out, as n_scans + 1 does (and fits an int64).
    period = min(every, n_scans + 1)
    return np.arange(n_scans) % period == period - 1


def subset_batch(batch: ScanBatch, scans: np.ndarray, beam_every: int = 1) -> ScanBatch:
    """The scans at integer indices ``scans``, keeping every ``beam_every``-th beam."""
    return dataclasses.replace(
        batch,
        stamps=batch.stamps[scans],
        angles=batch.angles[::beam_every],
        ranges=batch.ranges[scans][:, ::beam_every],
        poses=batch.poses[scans],
        pose_covariances=batch.pose_covariances[scans],
    )


def beam_points(
    poses: np.ndarray, angles: np.ndarray, distances: np.ndarray, sensor: SensorConfig
) -> np.ndarray:
    """Points at ``distances`` along beams, in the map frame (:mod:`gpocc.samples.beam_rules`).

    Args:
        poses: (S, 3) base poses (x m, y m, yaw rad).
        angles: (B,) beam bearings in the laser frame, radians.
        distances: (S, B, F) metres along each beam.
        sensor: gives the mount.

    Returns:
        (S, B, F, 2) metres.
    """
    lasers = beam_rules.laser_poses(poses, beam_rules.mount_vector(sensor))
    return beam_rules.beam_points(lasers[:, None, None, :], np.asarray(angles)[None, :, None],
                            distances)


def labelled_points(
    batch: ScanBatch, sensor: SensorConfig, free_per_beam: int, rng: np.random.Generator,
    geometry: bool = False,
) -> tuple[np.ndarray, ...]:
    """Occupied and free points from scans, with the poses as recorded.

    Ranges follow REP 117 (see :class:`ScanBatch`): a finite ``range_min <= r <
    range_max`` is a hit, labelled 1 at its endpoint, with ``free_per_beam`` free points
    at distances uniform in ``[0.1, r - 0.1)`` m; ``+inf`` or ``r >= range_max`` (no
    return) gives free points uniform in ``[0.1, min(no_return_free_m, range_max))``;
    NaN, ``-inf`` and ``r < range_min`` give nothing. A beam too short for the interval
    gives no free points.

    Returns:
        ``(points, labels)``: (N, 2) metres and (N,) int8 (1 occupied, 0 free); hits first.
        With ``geometry``, also (N,) the scan index of each point and (N,) its distance
        from the laser, metres.
    """
    r = batch.ranges
    classes = beam_rules.classify_beams(r, batch.range_min, batch.range_max)
    hit, no_return = classes.hit, classes.no_return
    hit_r = np.where(hit, r, 0.0)
    hits = beam_points(batch.poses, batch.angles, hit_r[:, :, None], sensor)[hit]

    no_return_end = beam_rules.no_return_free_m(sensor, batch.range_max)
    end = np.where(hit, hit_r - FREE_MARGIN_M, np.where(no_return, no_return_end, 0.0))
    ok = end > FREE_MARGIN_M
    u = rng.random((batch.n_scans, batch.n_beams, free_per_beam))
    free_d = FREE_MARGIN_M + u * (end - FREE_MARGIN_M)[:, :, None]
    keep = np.broadcast_to(ok[:, :, None], free_d.shape)
    free = beam_points(batch.poses, batch.angles, np.where(keep, free_d, 0.0), sensor)[keep]

    points = np.concatenate([hits.reshape(-1, 2), free.reshape(-1, 2)])
    labels = np.concatenate(
        [np.ones(len(hits), dtype=np.int8), np.zeros(len(free), dtype=np.int8)]
    )
    if not geometry:
        return points, labels
    scans = np.concatenate([np.nonzero(hit)[0], np.nonzero(keep)[0]])
    distances = np.concatenate([hit_r[hit], free_d[keep]])
    return points, labels, scans, distances


def near_wall_points(
    batch: ScanBatch, sensor: SensorConfig, per_beam: int, rng: np.random.Generator,
    band: tuple[float, float] = NEAR_WALL_BAND_M, geometry: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Free points just in front of each hit: ``per_beam`` per hit beam, at distances
    uniform in ``[r - band[1], r - band[0]]`` (``r`` its range), the interval clipped to
    start at least :data:`FREE_MARGIN_M` from the laser; a hit too close for the clipped
    interval gives none. No-return and invalid beams give none (they have no wall).

    Returns:
        (N, 2) metres, map frame, in scan, beam, draw order. With ``geometry``, also (N,)
        the scan index of each point and (N,) its distance from the laser, metres.
    """
    near, far = band
    if not 0.0 <= near < far:
        raise GpoccError(f"the near-wall band must satisfy 0 <= near < far, got {band}")
    r = batch.ranges
    hit = beam_rules.classify_beams(r, batch.range_min, batch.range_max).hit
    hit_r = np.where(hit, r, 0.0)
    start = np.maximum(hit_r - far, FREE_MARGIN_M)
    end = hit_r - near
    ok = hit & (end > start)
    u = rng.random((batch.n_scans, batch.n_beams, per_beam))
    d = start[:, :, None] + u * (end - start)[:, :, None]
    keep = np.broadcast_to(ok[:, :, None], d.shape)
    points = beam_points(batch.poses, batch.angles, np.where(keep, d, 0.0), sensor)[keep]
    if not geometry:
        return points.reshape(-1, 2)
    return points.reshape(-1, 2), np.nonzero(keep)[0], d[keep]


def protocol_points(
    batch: ScanBatch, sensor: SensorConfig, free_per_beam: int, near_wall_per_beam: int,
    rng: np.random.Generator, geometry: bool = False,
) -> tuple[np.ndarray, ...]:
    """The three kinds of held-out points of ``batch``'s scans: hits and free points along
    the beams (:func:`labelled_points`, drawn first, so their draws do not depend on
    ``near_wall_per_beam``), then near-wall free points (:func:`near_wall_points`).

    Returns:
        ``(points, labels, kinds)``: (N, 2) metres, (N,) int8 (1 occupied, 0 free) and
        (N,) str (:data:`HIT`, :data:`FREE` or :data:`NEAR_WALL`). With ``geometry``, also
        (N,) the scan index of each point and (N,) its distance from the laser, metres.
    """
    points, labels, scans, distances = labelled_points(batch, sensor, free_per_beam, rng,
                                                       geometry=True)
    near, near_scans, near_distances = near_wall_points(batch, sensor, near_wall_per_beam,
                                                        rng, geometry=True)
    kinds = np.concatenate([np.where(labels == 1, HIT, FREE), np.full(len(near), NEAR_WALL)])
    joined = (np.concatenate([points, near]),
              np.concatenate([labels, np.zeros(len(near), dtype=np.int8)]), kinds)
    if not geometry:
        return joined
    return (*joined, np.concatenate([scans, near_scans]),
            np.concatenate([distances, near_distances]))


@dataclass(frozen=True)
class CalibrationPoints:
    """Labelled points of held-out scans, for the classifier.

    Attributes:
        points: (N, 2) metres, map frame.
        labels: (N,) +1 occupied, -1 free.
        scan_ids: (K,) the held-out scans, numbered as the samples' ``scan_ids`` (index in
            the batch plus the scans of all earlier batches, :mod:`gpocc.samples.beams`).
    """

    points: np.ndarray
    labels: np.ndarray
    scan_ids: np.ndarray

    @property
    def usable(self) -> bool:
        """Both classes present: a classifier can be fitted on them."""
        return has_both_labels(self.labels)


def position_std(batch: ScanBatch, sensor: SensorConfig, scans: np.ndarray,
                 distances: np.ndarray) -> np.ndarray:
    """(N,) metres: the standard deviation of a point at ``distances`` along a beam of
    scan ``scans`` (indices into ``batch``), from the pose covariance (position and
    heading) and the sensor's range and bearing noise, per axis (first order)."""
    cov = beam_rules.pose_covariances(batch, sensor, scans)
    position = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
    angular = cov[:, 2, 2] + sensor.bearing_variance_rad2
    return np.sqrt(position + 0.5 * (distances**2 * angular + sensor.range_variance_m2))


def calibration_points(batches: list[ScanBatch], config: Config, every: int,
                       free_per_beam: int = 3,
                       max_position_std_m: float | None = None,
                       scan_offset: int = 0) -> CalibrationPoints:
    """Every ``every``-th scan of each batch as labelled points (:func:`protocol_points`,
    free points drawn with the config's seed and the batch's first scan id), keeping only
    those whose position is known to ``max_position_std_m`` (:func:`position_std`; None
    keeps all): a hit placed by a wrong pose lies in free space and would teach the
    classifier that free space is occupied. Scan ids start at ``scan_offset`` (a model's
    scan count when logs are added to it), so that adding logs one by one draws the
    points training on all of them does. ``model.training.calibration_near_wall`` adds
    that many near-wall free points per hit (:func:`protocol_points`: drawn after the
    others, so those stay as they were)."""
    points, labels, scan_ids = [np.zeros((0, 2))], [np.zeros(0)], [np.zeros(0, np.int64)]
    offset = scan_offset
    for batch in batches:
        held = np.flatnonzero(heldout_mask(batch.n_scans, every))
        rng = np.random.default_rng([config.seed, offset])
        if held.size:
            sensor = beam_rules.sensor_config(batch, config)
            p, lab, _, scans, dist = protocol_points(
                subset_batch(batch, held), sensor, free_per_beam,
                config.model.training.calibration_near_wall, rng, geometry=True)
            if max_position_std_m is not None:
                sharp = position_std(batch, sensor, held[scans], dist) <= max_position_std_m
                p, lab = p[sharp], lab[sharp]
            points.append(p)
            labels.append(np.where(lab > 0, 1.0, -1.0))
            scan_ids.append(held.astype(np.int64) + offset)
        offset += batch.n_scans
    return CalibrationPoints(np.concatenate(points), np.concatenate(labels),
                             np.concatenate(scan_ids))
