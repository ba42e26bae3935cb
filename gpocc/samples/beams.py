"""Laser beams to uncertain training samples: hits (+1) and free space along beams (-1).

Each sample is a point at a distance along one beam of one scan. Its position is a
nonlinear function (:func:`gpocc.samples.beam_rules.beam_endpoint`) of five uncertain
inputs: the range or distance, the beam bearing and the robot pose (x, y, yaw). The
unscented transform turns the Gaussian of those inputs into the Gaussian of the position,
and its cross-covariance gives each sample's sensitivity to its scan's pose, so that samples
of one scan keep their shared pose error (see :class:`~gpocc.samples.sampleset.SampleSet`).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from gpocc import compiled
from gpocc.config import Config, SamplesConfig, SensorConfig
from gpocc.errors import GpoccError
from gpocc.io.scans import ScanBatch
from gpocc.limits import MAX_SAMPLES_PER_SCAN
from gpocc.parallel import default_workers, thread_map
from gpocc.samples import beam_rules
from gpocc.samples.beam_unscented import beam_unscented
from gpocc.samples.sampleset import MAX_NOISE_FACTOR, SampleSet, has_both_labels
from gpocc.samples.unscented import matrix_sqrt

#: Upper bound (approximately: whole scans are never split) on the samples pushed through
#: one unscented-transform call; bounds peak memory to a few hundred MB.
CHUNK_SAMPLES = 100_000

#: Threads computing chunks at once (each holds one chunk, ~15 MB a 100,000 samples):
#: the caller merging their results in order gains little from more.
MAX_CHUNK_THREADS = 4

# Free-sample counts are floor(limit / spacing); this slack keeps a sample that lies
# exactly on the limit when the division rounds down (e.g. 2.0 / 0.4 = 4.999...).
_COUNT_SLACK = 1e-9


def build_samples(batches: list[ScanBatch], config: Config) -> SampleSet:
    """Training samples from all scans of all sensors.

    Beam classes follow REP 117 (``r`` the raw range, ``[range_min, range_max)`` the
    batch's valid interval):

    * NaN (invalid), ``-inf`` (too close) or ``r < range_min``: nothing.
    * finite ``range_min <= r < range_max``: a hit (+1) at ``r`` and free samples (-1) at
      ``d = k * free_spacing_m`` (k = 1, 2, ...) while ``d <= r - gap``, with
      ``gap = max(hit_gap_m, hit_gap_sigmas * sqrt(range_variance_m2))``.
    * ``+inf`` or ``r >= range_max`` (no return): no hit; free samples at the same spacing
      up to ``min(no_return_free_m, range_max)``.

    Only every ``scan_stride``-th scan and ``beam_stride``-th beam is used.

    Input noise: a sample's inputs are (range or distance, bearing, x, y, yaw) with
    covariance ``blockdiag(diag(var_r, var_b), P)``, ``P`` the scan's pose covariance.
    Hits have ``var_r = range_variance_m2`` (the range is measured). Free samples have
    ``var_r = 0``: their distance along the beam is chosen by us, not measured, so it
    carries no error; a noisy range only moves where free space ends, which the gap
    absorbs: with a noisy range the true surface may lie up to a few standard deviations
    before the measured hit, and a "free" sample there would be a wrong label. Their position
    error comes from the bearing and the pose alone. ``var_b`` is
    ``bearing_variance_rad2`` for both. With ``samples.free_range_variance`` the free
    samples of a beam that hit get ``var_r = range_variance_m2`` as well: where free
    space ends along that beam is as uncertain as its reading, and a noisy sensor's hits
    would otherwise lose kernel amplitude to their input noise while its free samples,
    exact-looking, keep theirs and erode its obstacles.

    Sensor settings and pose covariance: :func:`gpocc.samples.beam_rules.sensor_config` and
    :func:`gpocc.samples.beam_rules.pose_covariances` (the batch's per-scan covariances when it
    has them and the sensor's ``override_pose_covariance`` is off; the sensor's
    ``pose_covariance`` otherwise).

    Pose factors: ``A_i = G_i L`` with ``G_i = C_i^T pinv(P)`` (2x3), ``C_i`` the (3, 2)
    pose block of the unscented cross-covariance (statistical linear regression of the
    position on the pose) and ``L L^T = P``. For the symmetric sigma points used here
    ``A_i`` is the central difference of the position along the columns of ``L``, so
    ``covariances[i] - A_i A_i^T`` is the (PSD, for ``wc[0] >= 0``) part of the error not
    shared with other beams of the scan.

    Thinning (``samples.thin_cell_m > 0``): see :func:`thin_samples`; applied as the
    chunks arrive, which gives the same result as thinning the whole set at the end
    (``tests/samples/test_beams.py`` checks it). Chunks (their unscented transform, thinning and
    label counts) are computed on one thread per core and consumed in order, so the
    result does not depend on the number of cores. Then ``samples.min_label_share`` (see
    ``SamplesConfig``) and ``samples.free_clearance_m`` (:func:`clear_free_near_hits`)
    drop samples of the whole set.

    Args:
        batches: the readers' output, one per sensor and source.
        config: the job configuration (``sensors`` and ``samples`` are used).

    Returns:
        The samples, ordered by batch, then by chunks of consecutive scans; within a chunk
        hits come first, then free samples, each in (scan, beam, distance) order.
        ``scan_ids`` are the scan's index in its batch plus the number of scans of all
        earlier batches (unique across batches); ``sensor_ids`` index the sensors in the
        order their names first appear in ``batches``, and ``sensor_names`` names them.

    Raises:
        GpoccError: no batches, non-finite poses or pose covariances, or a batch that
            gives no sample at all (no valid beam).
    """
    return finish_samples(build_pool(batches, config), config)


@dataclass(frozen=True)
class SamplePool:
    """Thinned training samples before the whole-set rules (``min_label_share``,
    ``free_clearance_m``): what a model keeps so that new logs can be added later.

    Attributes:
        samples: thinned samples (one per label and ``thin_cell_m`` cell, in build
            order), covariances as built (not scaled by a learned input-noise scale).
        vote_keys, vote_counts: (K,) int64 label votes (:class:`LabelVotes`) of every
            sample before thinning; empty when ``min_label_share`` is off.
        n_scans: scans read so far (used or not): the next input's first scan id.
    """

    samples: SampleSet
    vote_keys: np.ndarray
    vote_counts: np.ndarray
    n_scans: int


def build_pool(batches: list[ScanBatch], config: Config, scan_offset: int = 0,
               sensor_names: tuple[str, ...] = ()) -> SamplePool:
    """The thinned samples and label votes of ``batches`` (:func:`build_samples` before
    its whole-set rules). ``scan_offset``: the first batch's first scan id;
    ``sensor_names``: sensors already numbered (a model's), new ones are appended."""
    if not batches:
        raise GpoccError("no scans to build training samples from; check the input files")
    sensor_index: dict[str, int] = {name: i for i, name in enumerate(sensor_names)}
    thin_cell = float(config.samples.thin_cell_m)
    parts: list[_ThinnedPart] = []
    # Thinning keeps a per-cell minimum, so thinning each chunk and thinning their union
    # again equals thinning everything at the end; the union is re-thinned only when the
    # thinned chunks have grown to twice what it held, which keeps the work linear.
    thinned_size, pending = 0, 0
    votes = LabelVotes(thin_cell) if config.samples.counts_labels else None

    def chunk(job: Callable[[], SampleSet]
              ) -> tuple[_ThinnedPart, np.ndarray | None, np.ndarray | None]:
        # On a helper thread: the unscented transform (compiled, GIL-free), then the
        # chunk's thinning and label counts (a hash table of its keys).
        part = job()
        if thin_cell <= 0:
            return _ThinnedPart(part, None, None), None, None
        return _thinned_part(part, thin_cell)

    def jobs() -> Iterator[Callable[[], SampleSet]]:
        # One stream over every batch's chunks: the threads never wait for a batch's last
        # chunk before the next batch starts. Drawn ahead of the results, so a batch's
        # error is a job that raises it: it reaches the caller after the earlier chunks'
        # results (and errors), as if the batches were read one after another.
        offset = scan_offset
        for batch in batches:
            try:
                sensor = beam_rules.sensor_config(batch, config)
                sensor_id = sensor_index.setdefault(batch.sensor, len(sensor_index))
                made = 0
                for job in _batch_chunks(batch, sensor, config.samples, offset, sensor_id):
                    made += 1
                    yield job
                if made == 0:
                    raise _no_samples(batch)
            except Exception as error:  # raised in order, by the job
                yield functools.partial(_raise, error)
                return
            offset += batch.n_scans

    with thread_map(chunk, jobs(), min(default_workers(), MAX_CHUNK_THREADS)) as chunks:
        for part, keys, counts in chunks:
            if votes is not None:
                votes.add_counts(keys, counts)
            if len(part.samples) == 0:
                continue
            parts.append(part)
            if thin_cell > 0:
                pending += len(part.samples)
                if pending > max(thinned_size, CHUNK_SAMPLES):
                    parts = _thin_parts(parts, thin_cell)
                    thinned_size, pending = sum(len(p.samples) for p in parts), 0
    if thin_cell > 0:
        parts = _thin_parts(parts, thin_cell)
    result = dataclasses.replace(SampleSet.concatenate([p.samples for p in parts]),
                                 sensor_names=tuple(sensor_index))
    n_scans = scan_offset + sum(b.n_scans for b in batches)
    if votes is None:
        return SamplePool(result, np.zeros(0, np.int64), np.zeros(0, np.int64), n_scans)
    return SamplePool(result, *votes.table(), n_scans)


def _raise(error: Exception) -> SampleSet:
    raise error


def _no_samples(batch: ScanBatch) -> GpoccError:
    """The error of a batch none of whose beams gives a training sample."""
    return GpoccError(
        f"{batch.source}: sensor '{batch.sensor}' gave no training samples: none of "
        f"its {batch.n_scans} scans x {batch.n_beams} beams has a usable range in "
        f"[{batch.range_min:g}, {batch.range_max:g}) m (NaN, -inf and ranges below "
        f"range_min are skipped); check the sensor's range_min_m / range_max_m, "
        f"no_return_free_m and that the ranges are in metres"
    )


@dataclass(frozen=True)
class _ThinnedPart:
    """Samples of one chunk (thinned, unless thinning is off) with what thinning their
    union needs of them: (N,) int64 (cell, label) keys and (N,) float32 covariance traces
    (:func:`_thin_keys`); both None when thinning is off, the keys also for cells past
    2**30."""

    samples: SampleSet
    keys: np.ndarray | None
    trace: np.ndarray | None


def _thinned_part(part: SampleSet, cell_m: float
                  ) -> tuple[_ThinnedPart, np.ndarray | None, np.ndarray | None]:
    """``part`` thinned (:func:`thin_samples`) with its kept samples' keys and traces,
    and the (cell, label) groups' keys and counts of :func:`_thinned`."""
    if len(part) == 0:
        empty = np.zeros(0, np.int64)
        return _ThinnedPart(part, empty, np.zeros(0, np.float32)), empty, empty
    cells, keys, trace = _thin_keys(part, cell_m)
    kept, group_keys, counts = _thinned_from(cells, keys, trace, part.labels)
    return (_ThinnedPart(part.subset(kept), None if keys is None else keys[kept],
                         trace[kept]), group_keys, counts)


def _thin_parts(parts: list[_ThinnedPart], cell_m: float) -> list[_ThinnedPart]:
    """:func:`thin_samples` of the parts' concatenation, as parts: each part's samples
    that thinning the whole keeps (a part that keeps all is not copied). Decided on the
    parts' keys and traces alone, without concatenating their samples, except for cells
    past 2**30 or non-finite traces (one part, thinned as :func:`thin_samples` does)."""
    if not parts:
        return parts
    keyed = all(p.keys is not None and p.trace is not None for p in parts)
    trace = np.concatenate([p.trace for p in parts]) if keyed else None
    if trace is None or not np.isfinite(trace).all():  # NaN never equals a minimum
        return [_thinned_part(SampleSet.concatenate([p.samples for p in parts]),
                              cell_m)[0]]
    keys = np.concatenate([p.keys for p in parts])
    keep = np.zeros(len(keys), dtype=bool)
    keep[compiled.thin_groups(keys, trace)[2]] = True
    out, start = [], 0
    for part in parts:
        mine = keep[start:start + len(part.samples)]
        start += len(part.samples)
        if mine.all():
            out.append(part)
        elif mine.any():
            out.append(_ThinnedPart(part.samples.subset(mine), part.keys[mine],
                                    part.trace[mine]))
    return out


def label_noise_factors(share: np.ndarray, counts: np.ndarray | None,
                        power: float) -> np.ndarray:
    """(N,) label-noise factors of kept samples (``samples.label_weights``): 1 / ``share``
    (their label's share of their cell's counted samples, NaN for a cell never counted:
    factor 1), times ``counts ** -power`` (their label's count in the cell; None: not
    weighed by count), within [1 / MAX_NOISE_FACTOR, MAX_NOISE_FACTOR]."""
    factors = 1.0 / np.clip(np.nan_to_num(share, nan=1.0), 1.0 / MAX_NOISE_FACTOR, 1.0)
    if counts is not None:
        factors = factors * np.maximum(counts, 1).astype(float) ** -power
    return np.clip(factors, 1.0 / MAX_NOISE_FACTOR, MAX_NOISE_FACTOR)


def finish_samples(pool: SamplePool, config: Config) -> SampleSet:
    """The training samples of ``pool``: ``samples.min_label_share`` (by the pool's
    votes), then ``samples.free_clearance_m`` (:func:`clear_free_near_hits`)."""
    samples = pool.samples
    kept: np.ndarray | None = None  # None: every sample
    factors = None
    min_share = float(config.samples.min_label_share)
    if config.samples.counts_labels and pool.vote_keys.size:
        votes = LabelVotes(float(config.samples.thin_cell_m))
        votes.add_counts(pool.vote_keys, pool.vote_counts)
        share, counts = votes.share_and_count(samples)
        if min_share > 0:
            kept = np.flatnonzero(share >= min_share)
        if config.samples.weighs_labels:
            factors = label_noise_factors(
                share, counts if config.samples.label_weights == "count" else None,
                config.samples.label_count_power)
    means, labels = ((samples.means, samples.labels) if kept is None
                     else (samples.means[kept], samples.labels[kept]))
    cleared = _free_near_hits(means, labels, float(config.samples.free_clearance_m))
    if cleared is not None and cleared.any():
        kept = np.flatnonzero(~cleared) if kept is None else kept[~cleared]
    # The rules' choices are applied in one copy of the samples (a copy of a city's
    # samples took a second).
    result = samples if kept is None else samples.subset(kept)
    if factors is not None:
        result = dataclasses.replace(
            result, noise_factors=factors if kept is None else factors[kept])
    return result


def merge_pools(first: SamplePool, second: SamplePool, config: Config) -> SamplePool:
    """One pool of two, ``first``'s samples first: the pool :func:`build_pool` gives for
    both pools' batches in that order (thinning keeps a per-cell minimum, earliest on
    ties; votes add). ``second`` must number sensors and scans after ``first``."""
    names = max((first.samples.sensor_names, second.samples.sensor_names), key=len)
    samples = thin_samples(SampleSet.concatenate([first.samples, second.samples]),
                           float(config.samples.thin_cell_m))
    votes = LabelVotes(float(config.samples.thin_cell_m))
    for pool in (first, second):
        if pool.vote_keys.size:
            votes.add_counts(pool.vote_keys, pool.vote_counts)
    return SamplePool(dataclasses.replace(samples, sensor_names=names), *votes.table(),
                      max(first.n_scans, second.n_scans))


def clear_free_near_hits(samples: SampleSet, radius_m: float) -> SampleSet:
    """Drop free samples whose mean lies within ``radius_m`` of an occupied sample's mean.

    A beam that grazes a wall leaves free samples a few centimetres from that wall's
    hits, closer than the map resolves. With both labels that close, the latent mean
    crosses zero on the wall surface itself and hits seen later come out free (measured
    on held-out scans of real logs; commit 3198d15). It runs on the thinned
    set (the measured setting, and the cheap one: thinning happens as chunks stream in),
    so it compares against the hits thinning kept. With ``classifier_offset: beams`` the
    calibration scans' hits have cleared free samples of other scans too, which makes
    those held-out hits look a little more occupied than an unseen scan's would.
    ``radius_m <= 0`` returns the samples unchanged.

    Args:
        samples: any sample set.
        radius_m: clearance, metres.
    """
    cleared = _free_near_hits(samples.means, samples.labels, radius_m)
    return samples if cleared is None else samples.subset(~cleared)


def _free_near_hits(means: np.ndarray, labels: np.ndarray, radius_m: float
                    ) -> np.ndarray | None:
    """(N,) bool: the free samples (``labels`` (N,)) whose ``means`` (N, 2) metres lie
    within ``radius_m`` of an occupied sample's; None when none can (``radius_m <= 0``
    or one label only)."""
    if radius_m <= 0 or not has_both_labels(labels):
        return None
    occupied = labels > 0
    free = np.flatnonzero(~occupied)
    distance, _ = cKDTree(means[occupied]).query(means[free], distance_upper_bound=radius_m)
    cleared = np.zeros(len(labels), dtype=bool)
    cleared[free[distance < radius_m]] = True
    return cleared


def packed_cells(cells: np.ndarray) -> np.ndarray:
    """(N,) int64, one key per (N, 2) integer cell, the first index in the high half:
    distinct for indices within 32 bits."""
    return (cells[:, 0] << 32) + (cells[:, 1] & 0xFFFFFFFF)


def _cells(samples: SampleSet, cell_m: float) -> np.ndarray:
    """(N, 2) int64 square cells of side ``cell_m`` of the samples' means."""
    return np.floor(samples.means / cell_m).astype(np.int64)


def _cell_label_keys(cells: np.ndarray, labels: np.ndarray) -> np.ndarray | None:
    """(N,) int64, one key per (cell, label): the packed cell shifted left by one bit, the
    label (occupied) in the lowest bit; None for cells past 2**30, where the shift would
    overflow."""
    if cells.size and np.abs(cells).max() >= 2**30:
        return None
    return (packed_cells(cells) << 1) | (labels > 0)


class LabelVotes:
    """Running counts of samples per label and square cell of side ``cell_m``.

    Thinning keeps one sample per label and cell, which forgets how often a cell was seen
    free or occupied; these counts remember it, so that a label seen in only a small share
    of a cell's samples (a person walking through a corridor, a beam grazing a wall
    through pose error) can be dropped. Counts are kept per (cell, label) key
    (:func:`_cell_label_keys`; the other label of a key is the key with its lowest bit
    flipped).
    """

    def __init__(self, cell_m: float) -> None:
        self.cell_m = cell_m
        self.keys = np.zeros(0, dtype=np.int64)
        self.counts = np.zeros(0, dtype=np.int64)
        # Counted chunks not merged yet: merging every chunk into the whole table would
        # sort the table once per chunk; it is merged when they outgrow it.
        self._pending: list[tuple[np.ndarray, np.ndarray]] = []
        self._pending_size = 0

    def _too_far(self) -> GpoccError:
        return GpoccError(
            f"training samples lie more than {2**30 * self.cell_m:.3g} m from the map "
            f"origin; check the poses' units or raise samples.thin_cell_m")

    def _keys(self, samples: SampleSet) -> np.ndarray:
        keys = _cell_label_keys(_cells(samples, self.cell_m), samples.labels)
        if keys is None:
            raise self._too_far()
        return keys

    @staticmethod
    def _reduce(keys: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if keys.size == 0:
            return keys, counts
        order, sorted_keys, starts = _sorted_runs(keys)
        return sorted_keys[starts], np.add.reduceat(counts[order], starts)

    def add(self, samples: SampleSet) -> None:
        """Count a chunk of samples."""
        if len(samples) == 0:
            return
        self.add_counts(*self._reduce(self._keys(samples), np.ones(len(samples), np.int64)))

    def add_counts(self, keys: np.ndarray | None, counts: np.ndarray | None) -> None:
        """Add ``counts`` samples of each (cell, label) key (:func:`_thinned`'s groups;
        None: cells past 2**30, which have no keys)."""
        if keys is None or counts is None:
            raise self._too_far()
        self._pending.append((keys, counts))
        self._pending_size += len(keys)
        if self._pending_size > max(len(self.keys), 1 << 16):
            self._merge()

    def _merge(self) -> None:
        if self._pending:
            keys = np.concatenate([self.keys, *(k for k, _ in self._pending)])
            counts = np.concatenate([self.counts, *(c for _, c in self._pending)])
            self.keys, self.counts = self._reduce(keys, counts)
            self._pending, self._pending_size = [], 0

    def _count(self, keys: np.ndarray) -> np.ndarray:
        if self.keys.size == 0:
            return np.zeros(keys.shape, dtype=np.int64)
        index = np.minimum(np.searchsorted(self.keys, keys), self.keys.size - 1)
        return np.where(self.keys[index] == keys, self.counts[index], 0)

    def table(self) -> tuple[np.ndarray, np.ndarray]:
        """The (cell, label) keys, ascending, and their counts: (K,) int64 each."""
        self._merge()
        return self.keys, self.counts

    def share_and_count(self, samples: SampleSet) -> tuple[np.ndarray, np.ndarray]:
        """(N,) fraction of its cell's counted samples that carry each sample's label
        (NaN for a cell never counted), and (N,) int64 how many they are (0 there)."""
        self._merge()
        keys = self._keys(samples)
        own = self._count(keys)
        with np.errstate(invalid="ignore"):
            return own / (own + self._count(keys ^ 1)), own

    def count(self, samples: SampleSet) -> np.ndarray:
        """(N,) int64 counted samples of each sample's label in its cell (0 for a cell
        never counted)."""
        return self.share_and_count(samples)[1]

    def share(self, samples: SampleSet) -> np.ndarray:
        """(N,) fraction of its cell's counted samples that carry each sample's label
        (NaN for a cell never counted)."""
        return self.share_and_count(samples)[0]


def thin_samples(samples: SampleSet, cell_m: float) -> SampleSet:
    """Keep, per label and per square cell of side ``cell_m``, the most certain sample.

    Cells are ``floor(mean / cell_m)`` in the map frame. "Most certain" is the smallest
    covariance trace (to 7 significant digits); ties keep the earliest sample. The kept
    samples stay in their original order. ``cell_m <= 0`` returns the samples unchanged.

    Args:
        samples: any sample set.
        cell_m: cell side, metres.
    """
    if cell_m <= 0 or len(samples) == 0:
        return samples
    return samples.subset(_thinned(samples, cell_m)[0])


def _thinned(samples: SampleSet, cell_m: float
             ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """:func:`thin_samples`' kept indices (ascending), with the (cell, label) keys of the
    groups (:func:`_cell_label_keys`, ascending) and their sample counts; the keys and
    counts are None for cells past 2**30."""
    if len(samples) == 0:
        return np.zeros(0, dtype=np.intp), np.zeros(0, np.int64), np.zeros(0, np.int64)
    return _thinned_from(*_thin_keys(samples, cell_m), samples.labels)


def _thin_keys(samples: SampleSet, cell_m: float
               ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """What thinning decides on: the (N, 2) cells, the (N,) (cell, label) keys (None for
    cells past 2**30) and the (N,) float32 covariance traces."""
    cells = _cells(samples, cell_m)
    # Traces are compared in single precision (7 significant digits): samples of one scan
    # at the same distance along different beams have mathematically equal traces, and
    # round-off (which differs between code paths and BLAS builds) must not decide which
    # of them is kept.
    trace = (samples.covariances[:, 0, 0] + samples.covariances[:, 1, 1]).astype(np.float32)
    return cells, _cell_label_keys(cells, samples.labels), trace


def _thinned_from(cells: np.ndarray, keys: np.ndarray | None, trace: np.ndarray,
                  labels: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """:func:`_thinned` of samples with these (non-empty) :func:`_thin_keys` and labels."""
    if keys is None:
        return _thin_by_lexsort(cells, trace, labels), None, None
    if not np.isfinite(trace).all():  # NaN never equals a group's minimum
        groups, counts = np.unique(keys, return_counts=True)
        return _thin_by_lexsort(cells, trace, labels), groups, counts
    # One pass over a hash table of the (cell, label) keys (compiled): each group's
    # smallest trace and, among the samples that have it, the smallest index; then only
    # the groups are sorted, a few thousand for a chunk of 100,000 samples.
    group_keys, counts, earliest = compiled.thin_groups(keys, trace)
    order = np.argsort(group_keys)
    return np.sort(earliest), group_keys[order], counts[order]


def _sorted_runs(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An order sorting the non-empty ``keys`` (N,) (numpy's SIMD sort, not stable), the
    sorted keys, and the start of each run of equal keys in them."""
    order = np.argsort(keys)
    sorted_keys = keys[order]
    starts = np.flatnonzero(np.concatenate(([True], sorted_keys[1:] != sorted_keys[:-1])))
    return order, sorted_keys, starts


def _thin_by_lexsort(cells: np.ndarray, trace: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """:func:`thin_samples`' kept indices for any cells and traces (NaN included)."""
    keys = (trace, cells[:, 1], cells[:, 0], labels)
    # lexsort is stable, so within one (label, cell) and trace the earliest sample leads.
    order = np.lexsort(keys)
    first = np.zeros(len(order), dtype=bool)
    first[0] = True
    for key in keys[1:]:
        sorted_key = key[order]
        first[1:] |= sorted_key[1:] != sorted_key[:-1]
    return np.sort(order[first])


def _check_scan_sizes(batch: ScanBatch, per_scan: np.ndarray, hits: np.ndarray,
                      spacing: float) -> None:
    """Refuse scans that would give more than MAX_SAMPLES_PER_SCAN samples (absurd ranges)."""
    if per_scan.size == 0 or per_scan.max() <= MAX_SAMPLES_PER_SCAN:
        return
    worst = int(np.argmax(per_scan))
    longest = float(hits.max()) if hits.size else float(batch.range_max)
    raise GpoccError(
        f"{batch.source}: sensor '{batch.sensor}' scan {worst} would give "
        f"{per_scan[worst]:.3g} training samples (ranges up to {longest:.3g} m, range_max "
        f"{batch.range_max:.3g} m, a free sample every {spacing:g} m), more than "
        f"{MAX_SAMPLES_PER_SCAN:.0e}; set range_max_m for this sensor in the config to the "
        f"laser's real maximum range (check that ranges are in metres)"
    )


def _batch_chunks(
    batch: ScanBatch,
    sensor: SensorConfig,
    cfg: SamplesConfig,
    scan_offset: int,
    sensor_id: int,
) -> Iterator[Callable[[], SampleSet]]:
    """The samples of one batch, in chunks of whole scans (about CHUNK_SAMPLES each):
    each item computes its chunk when called (the unscented transform, on any thread)."""
    scans = np.arange(0, batch.n_scans, cfg.scan_stride)
    beams = np.arange(0, batch.n_beams, cfg.beam_stride)
    ranges = np.asarray(batch.ranges, dtype=float)[np.ix_(scans, beams)]
    angles = np.asarray(batch.angles, dtype=float)[beams]
    poses = beam_rules.checked_poses(batch, scans)
    pose_cov = beam_rules.pose_covariances(batch, sensor, scans)
    pose_root = matrix_sqrt(pose_cov) if len(scans) else np.zeros((0, 3, 3))
    # A_i = C_i^T pinv(P) L: the scan-level factor pinv(P) L is shared by all its samples.
    pose_map = np.linalg.pinv(pose_cov, hermitian=True) @ pose_root if len(scans) else pose_root

    classes = beam_rules.classify_beams(ranges, float(batch.range_min), float(batch.range_max))
    is_hit, no_return = classes.hit, classes.no_return
    no_return_limit = beam_rules.no_return_free_m(sensor, batch.range_max)
    gap = max(cfg.hit_gap_m, cfg.hit_gap_sigmas * float(np.sqrt(sensor.range_variance_m2)))
    limit = np.where(is_hit, ranges - gap, np.where(no_return, no_return_limit, 0.0))
    limit = np.where(np.isfinite(limit), limit, 0.0)
    # Counted in floats first: a range of 1e20 m would overflow an integer count.
    n_free_f = np.floor(np.maximum(limit, 0.0) / cfg.free_spacing_m + _COUNT_SLACK)
    per_scan_f = is_hit.sum(axis=1) + n_free_f.sum(axis=1)
    _check_scan_sizes(batch, per_scan_f, ranges[is_hit], cfg.free_spacing_m)
    n_free = n_free_f.astype(np.int64)

    per_scan = is_hit.sum(axis=1) + n_free.sum(axis=1)
    if per_scan.sum() == 0:
        return
    chunk_of_scan = (np.cumsum(per_scan) - per_scan) // CHUNK_SAMPLES
    bounds = np.concatenate(([0], np.flatnonzero(np.diff(chunk_of_scan)) + 1, [len(scans)]))

    plan = _BatchPlan(
        scan_index=scans, ranges=ranges, angles=angles, poses=poses, pose_root=pose_root,
        pose_map=pose_map, is_hit=is_hit, n_free=n_free, mount=beam_rules.mount_vector(sensor),
        var_r_hit=float(sensor.range_variance_m2), var_b=float(sensor.bearing_variance_rad2),
        cfg=cfg, scan_offset=scan_offset, sensor_id=sensor_id)
    for s0, s1 in zip(bounds[:-1], bounds[1:], strict=True):
        yield functools.partial(_chunk_samples, plan, int(s0), int(s1))


@dataclass(frozen=True)
class _BatchPlan:
    """What every chunk of one batch reads (:func:`_batch_chunks`); shared, never written.

    scan_index (S,): the batch's scans used; ranges (S, B) metres and angles (B,) rad of
    the beams used; poses (S, 3); pose_root and pose_map (S, 3, 3); is_hit (S, B);
    n_free (S, B) free samples per beam; mount (3,); var_r_hit m^2, var_b rad^2.
    """

    scan_index: np.ndarray
    ranges: np.ndarray
    angles: np.ndarray
    poses: np.ndarray
    pose_root: np.ndarray
    pose_map: np.ndarray
    is_hit: np.ndarray
    n_free: np.ndarray
    mount: np.ndarray
    var_r_hit: float
    var_b: float
    cfg: SamplesConfig
    scan_offset: int
    sensor_id: int


def _chunk_samples(plan: _BatchPlan, s0: int, s1: int) -> SampleSet:
    """The samples of scans ``s0:s1`` of ``plan`` (hits first, then free samples, each in
    (scan, beam, distance) order); on any thread."""
    cfg = plan.cfg
    hit_scan, hit_beam = np.nonzero(plan.is_hit[s0:s1])
    counts = plan.n_free[s0:s1].ravel()
    flat = np.repeat(np.arange(counts.size), counts)
    first = np.cumsum(counts) - counts
    k = np.arange(flat.size) - np.repeat(first, counts) + 1
    free_scan, free_beam = np.divmod(flat, plan.angles.size)
    n_hit = hit_scan.size
    n = n_hit + flat.size
    scan_local = np.concatenate((hit_scan, free_scan)) + s0
    beam_local = np.concatenate((hit_beam, free_beam))
    dist = np.concatenate((plan.ranges[hit_scan + s0, hit_beam], k * cfg.free_spacing_m))
    var_r = np.zeros(n)
    var_r[:n_hit] = plan.var_r_hit
    if cfg.free_range_variance:
        # Free samples of beams that hit carry the beam's range variance too.
        beam_hit = plan.is_hit[free_scan + s0, free_beam]
        var_r[n_hit:] = np.where(beam_hit, plan.var_r_hit, 0.0)
    labels = np.full(n, -1.0)
    labels[:n_hit] = 1.0
    ut = cfg.unscented
    # The compiled transform uses the block-diagonal root (range, bearing, then the
    # pose's L) directly, which keeps the pose sigma points along the columns of L
    # (the A_i identity in build_samples' docstring).
    y_mean, y_cov, factors = beam_unscented(
        dist, plan.angles[beam_local], var_r, plan.var_b, scan_local, plan.poses,
        plan.pose_root, plan.pose_map, plan.mount, ut.alpha, ut.beta, ut.kappa,
    )
    return SampleSet(
        means=y_mean,
        covariances=y_cov,
        labels=labels,
        scan_ids=(plan.scan_index[scan_local] + plan.scan_offset).astype(np.int64),
        pose_factors=factors,
        sensor_ids=np.full(n, plan.sensor_id, dtype=np.int16),
    )
