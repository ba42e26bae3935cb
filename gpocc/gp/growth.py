"""What a model keeps so that new logs can be added to it (``gpocc update``).

A model predicts from its training samples, which are the end of a chain: thinning, then
the label votes of ``samples.min_label_share``, then ``free_clearance_m``, then the
learned input-noise scale. New logs change every link after thinning (a door seen open
in one recording and closed in the next: the votes of both decide), so the model keeps
the chain's state after thinning (:class:`~gpocc.samples.beams.SamplePool`: thinned
samples as built, label votes, scans read), the held-out calibration points of
``classifier_offset: beams`` and ``classifier_temperature: beams``, and a record of each
input. Adding logs to that state gives the state that training on all logs at once
builds.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from gpocc.io.records import InputRecord
from gpocc.samples.beams import LabelVotes, SamplePool
from gpocc.samples.heldout import CalibrationPoints
from gpocc.samples.sampleset import SampleSet


@dataclass(frozen=True)
class Growth:
    """A model's state for updates.

    Attributes:
        pool: thinned samples (unscaled), label votes and scans read so far.
        records: one per input, in the order they were added.
        calibration: held-out points of ``classifier_offset: beams`` or
            ``classifier_temperature: beams`` (None: not used).
    """

    pool: SamplePool
    records: tuple[InputRecord, ...]
    calibration: CalibrationPoints | None = None


def growth_of_older_model(samples: SampleSet, input_noise_scale: float, input_noise: bool,
                          inputs: tuple[str, ...], thin_cell_m: float,
                          min_label_share: float) -> tuple[Growth, list[str]]:
    """The best stand-in for the growth state of a model file that kept none (format 2
    and older), and what it cannot keep, as notes for the user.

    Its samples (already filtered by the label votes and the clearance) become the pool,
    unscaled by the learned input-noise scale; each counts as one label vote; scan ids
    continue after the largest.
    """
    notes = []
    if input_noise:
        scale = input_noise_scale
        samples = dataclasses.replace(samples, covariances=samples.covariances / scale,
                                      pose_factors=samples.pose_factors / math.sqrt(scale))
    else:
        notes.append("its samples' input covariances (the model was trained without input "
                     "noise), so thinning prefers its samples over the new logs'")
    vote_keys = vote_counts = np.zeros(0, np.int64)
    if thin_cell_m > 0 and min_label_share > 0:
        votes = LabelVotes(thin_cell_m)
        votes.add(samples)
        vote_keys, vote_counts = votes.table()
        notes.append("the label votes of its logs (each of its samples counts as one vote), "
                     "nor the samples min_label_share and free_clearance_m dropped")
    else:
        notes.append("the samples free_clearance_m dropped")
    pool = SamplePool(samples, vote_keys, vote_counts,
                      int(samples.scan_ids.max()) + 1 if len(samples) else 0)
    notes.append("a record (content hash, scans, time span) of its inputs, so an input "
                 "already in it cannot be recognised")
    return Growth(pool, tuple(InputRecord(path=p) for p in inputs)), notes


def join_calibration(first: CalibrationPoints | None, second: CalibrationPoints | None
                     ) -> CalibrationPoints | None:
    """Both sets of held-out points, ``first``'s first (None: neither)."""
    parts = [c for c in (first, second) if c is not None]
    if not parts:
        return None
    return CalibrationPoints(np.concatenate([c.points for c in parts]),
                             np.concatenate([c.labels for c in parts]),
                             np.concatenate([c.scan_ids for c in parts]))


def input_listing(growth: Growth | None, inputs: tuple[str, ...]) -> list[dict]:
    """Every input of a model as plain data (path, content hash, scans, time span,
    sensors, transform; only the path for files that kept no records)."""
    if growth is None or len(growth.records) != len(inputs):
        return [{"path": p} for p in inputs]
    # Records without a content hash stand for inputs of older files: only their path
    # is known.
    return [r.as_dict() if r.sha256 else {"path": r.path} for r in growth.records]
