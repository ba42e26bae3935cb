"""Recordings made in another map frame: the config's ``inputs`` transforms.

A log recorded on another day may have its own map frame; the user states the rigid
transform from it into the job's map frame (``inputs: [{path, transform: {x_m, y_m,
yaw_deg}}]``), and every pose of that input is moved before any later stage sees it, so
samples, coverage, the grid baseline and ``split`` all follow.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import math
from pathlib import Path, PurePosixPath

import numpy as np

from gpocc.config import Config, TransformConfig
from gpocc.errors import GpoccError
from gpocc.io.scans import ScanBatch

IDENTITY = TransformConfig()


def entry_matches(pattern: str, path: str | Path) -> bool:
    """Whether an ``inputs`` entry's ``pattern`` (globs allowed) names ``path``: as its
    file name, its last folders and file name (``day2/run.mcap`` names
    ``logs/day2/run.mcap``), or the whole path as given."""
    path = Path(path)
    depth = len(PurePosixPath(pattern).parts)
    tail = "/".join(path.parts[-depth:]) if depth else ""
    return any(fnmatch.fnmatchcase(text, pattern)
               for text in (path.name, tail, path.as_posix(), str(path)))


def input_transform(path: str | Path, config: Config) -> TransformConfig:
    """The transform of the config's ``inputs`` entry whose ``path`` matches ``path``
    (file name or whole path, globs allowed); the identity when none does.

    Raises:
        GpoccError: several entries match.
    """
    path = Path(path)
    matching = [entry for entry in config.inputs if entry_matches(entry.path, path)]
    if len(matching) > 1:
        raise GpoccError(
            f"{path}: several `inputs` entries of the config match this input "
            f"({', '.join(e.path for e in matching)}); make their paths match one input each")
    return matching[0].transform if matching else IDENTITY


def transform_poses(poses: np.ndarray, covariances: np.ndarray,
                    transform: TransformConfig) -> tuple[np.ndarray, np.ndarray]:
    """Poses (S, 3) (x m, y m, yaw rad) and their covariances (S, 3, 3) moved by
    ``transform``: positions rotated and shifted, yaw turned, covariances rotated
    (``J P J^T`` with ``J = blockdiag(R, 1)``)."""
    yaw = math.radians(transform.yaw_deg)
    c, s = math.cos(yaw), math.sin(yaw)
    poses = np.asarray(poses, dtype=float)
    moved = np.column_stack([
        transform.x_m + c * poses[:, 0] - s * poses[:, 1],
        transform.y_m + s * poses[:, 0] + c * poses[:, 1],
        poses[:, 2] + yaw,
    ])
    jac = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    cov = jac @ np.asarray(covariances, dtype=float) @ jac.T
    return moved, 0.5 * (cov + np.swapaxes(cov, 1, 2))


def transform_batch(batch: ScanBatch, transform: TransformConfig) -> ScanBatch:
    """``batch`` with its poses in the job's map frame (``transform`` applied); the
    batch itself for the identity."""
    if transform == IDENTITY:
        return batch
    poses, cov = transform_poses(batch.poses, batch.pose_covariances, transform)
    return dataclasses.replace(batch, poses=poses, pose_covariances=cov)
