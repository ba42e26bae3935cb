"""The rules of a laser beam, in one place.

The GP's training samples (:mod:`gpocc.samples.beams`), the log-odds grid baseline
(:mod:`gpocc.baselines.grid`), the held-out truth of ``gpocc split`` and the simulator all
turn the same scans into the same beams; they compare fairly only because they agree on:

* which sensor config a scan batch follows (:func:`sensor_config`): the entry the reader
  resolved and attached to the batch, else the config entry of that name, else defaults;
* what a range means (:func:`classify_beams`, REP 117);
* where the laser is (:func:`laser_poses`, :func:`laser_pose_covariances`) and where a
  point along a beam lies (:func:`beam_points`, :func:`beam_endpoint`);
* which pose covariance applies (:func:`uses_input_covariance`, :func:`pose_covariances`).

Poses are (x m, y m, yaw rad) in the map frame; bearings are radians, counter-clockwise,
in the laser frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gpocc.config import Config, SensorConfig
from gpocc.errors import GpoccError
from gpocc.io.poses import move_covariances
from gpocc.io.scans import ScanBatch


def sensor_config(batch: ScanBatch, config: Config) -> SensorConfig:
    """The sensor settings ``batch`` follows.

    The reader resolves each batch's config entry once and attaches it
    (``batch.sensor_config``); a batch built another way (the simulator, tests) is matched
    to the config entry of its sensor name, or gets :class:`SensorConfig` defaults.
    """
    if batch.sensor_config is not None:
        return batch.sensor_config
    return next((s for s in config.sensors if s.name == batch.sensor),
                SensorConfig(name=batch.sensor))


def mount_vector(sensor: SensorConfig) -> np.ndarray:
    """(3,) the laser's mount on the robot base: (x m, y m, yaw rad)."""
    m = sensor.mount
    return np.array([m.x_m, m.y_m, math.radians(m.yaw_deg)])


@dataclass(frozen=True, eq=False)
class BeamClasses:
    """What each raw range means (REP 117), per beam.

    Attributes:
        hit: finite ``range_min <= r < range_max``: the beam hit something at ``r``.
        no_return: ``+inf`` or ``r >= range_max``: nothing within range; free space along
            the beam, no hit.
        invalid: everything else (NaN, ``-inf`` too close, ``r < range_min``): no
            information.
    """

    hit: np.ndarray
    no_return: np.ndarray

    @property
    def invalid(self) -> np.ndarray:
        return ~(self.hit | self.no_return)


def classify_beams(ranges: np.ndarray, range_min: float, range_max: float) -> BeamClasses:
    """Classify raw ranges (any shape, metres) against ``[range_min, range_max)``."""
    r = np.asarray(ranges, dtype=float)
    with np.errstate(invalid="ignore"):
        hit = np.isfinite(r) & (r >= range_min) & (r < range_max)
        no_return = (r >= range_max) | (r == np.inf)
    return BeamClasses(hit=hit, no_return=no_return)


def no_return_free_m(sensor: SensorConfig, range_max: float) -> float:
    """Metres of free space a no-return beam vouches for: ``min(no_return_free_m, range_max)``."""
    return min(float(sensor.no_return_free_m), float(range_max))


def checked_poses(batch: ScanBatch, scans: np.ndarray | slice = slice(None)) -> np.ndarray:
    """(S', 3) the batch's base poses at ``scans``, float.

    Raises:
        GpoccError: a non-finite pose.
    """
    poses = np.asarray(batch.poses, dtype=float)[scans]
    if not np.isfinite(poses).all():
        raise GpoccError(
            f"{batch.source}: sensor '{batch.sensor}' has non-finite poses; check the pose "
            f"source of this input"
        )
    return poses


def laser_poses(poses: np.ndarray, mount: np.ndarray) -> np.ndarray:
    """(..., 3) laser poses: base poses (..., 3) composed with the mount (3,)."""
    poses = np.asarray(poses, dtype=float)
    x, y, th = poses[..., 0], poses[..., 1], poses[..., 2]
    mx, my, myaw = (float(v) for v in np.asarray(mount, dtype=float))
    c, s = np.cos(th), np.sin(th)
    return np.stack((x + c * mx - s * my, y + s * mx + c * my, th + myaw), axis=-1)


def laser_pose_covariances(poses: np.ndarray, covariances: np.ndarray,
                           mount: np.ndarray) -> np.ndarray:
    """(S, 3, 3) covariance of the laser pose, linearised: ``J P J^T``.

    ``J`` is the Jacobian of :func:`laser_poses` in the base pose: the mount offset turns
    yaw error into position error ``(-s mx - c my, c mx - s my) dtheta``.

    Args:
        poses: (S, 3) base poses.
        covariances: (S, 3, 3) base pose covariances, m^2 / rad^2.
        mount: (3,) see :func:`mount_vector`.
    """
    poses = np.asarray(poses, dtype=float)
    mx, my, _ = (float(v) for v in np.asarray(mount, dtype=float))
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    lever = np.column_stack([c * mx - s * my, s * mx + c * my])  # R(yaw) (mx, my)
    return move_covariances(np.asarray(covariances, dtype=float), lever)


def beam_points(lasers: np.ndarray, bearings: np.ndarray, distances: np.ndarray) -> np.ndarray:
    """Map-frame points at ``distances`` along beams.

    ``p = (lx, ly) + d (cos(lyaw + b), sin(lyaw + b))``; arguments broadcast against each
    other (the last axis of ``lasers`` holds the pose).

    Args:
        lasers: (..., 3) laser poses (:func:`laser_poses`).
        bearings: (...) radians.
        distances: (...) metres.

    Returns:
        (..., 2) metres.
    """
    lasers = np.asarray(lasers, dtype=float)
    phi = lasers[..., 2] + bearings
    return np.stack((lasers[..., 0] + distances * np.cos(phi),
                     lasers[..., 1] + distances * np.sin(phi)), axis=-1)


def beam_endpoint(inputs: np.ndarray, mount: np.ndarray) -> np.ndarray:
    """Map-frame position of a point at range r along a beam, vectorised (the function
    the unscented transform pushes sigma points through).

    ``p = (x, y) + R(theta) (mx, my) + r (cos(theta + myaw + b), sin(theta + myaw + b))``:
    :func:`laser_poses` then :func:`beam_points`.

    Args:
        inputs: (..., 5) of (range r m, bearing b rad, base x m, base y m, base yaw
            theta rad).
        mount: (3,) laser offset and yaw on the base.

    Returns:
        (..., 2) metres.
    """
    inputs = np.asarray(inputs, dtype=float)
    return beam_points(laser_poses(inputs[..., 2:], mount), inputs[..., 1], inputs[..., 0])


def uses_input_covariance(batch: ScanBatch, sensor: SensorConfig) -> bool:
    """Whether the batch's own pose covariances apply (else the sensor's ``pose_covariance``).

    They apply when the input had them and the config does not override them.
    """
    return batch.has_pose_covariance and not sensor.override_pose_covariance


def pose_covariances(batch: ScanBatch, sensor: SensorConfig,
                     scans: np.ndarray | slice = slice(None)) -> np.ndarray:
    """(S', 3, 3) the pose covariance of the scans at ``scans``, symmetrised.

    Raises:
        GpoccError: non-finite covariances in the input.
    """
    if uses_input_covariance(batch, sensor):
        cov = np.asarray(batch.pose_covariances, dtype=float)[scans]
        if not np.isfinite(cov).all():
            raise GpoccError(
                f"{batch.source}: sensor '{batch.sensor}' has non-finite pose covariances; "
                f"set override_pose_covariance: true and pose_covariance for it in the config"
            )
        return 0.5 * (cov + np.swapaxes(cov, -1, -2))
    n = len(np.arange(batch.n_scans)[scans])
    return np.broadcast_to(sensor.pose_covariance_matrix, (n, 3, 3)).copy()
