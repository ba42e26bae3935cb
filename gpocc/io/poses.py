"""Pose messages of a bag as validated time series, and their covariances at scan stamps.

Pose topics carry ``geometry_msgs/msg/PoseWithCovarianceStamped`` (AMCL, SLAM),
``nav_msgs/msg/Odometry`` or ``geometry_msgs/msg/PoseStamped`` (no covariance). Each
message is checked as it is read (issue 13, class 4):

* a non-finite position is an error; an all-zero or non-finite orientation quaternion is
  an error; a quaternion whose norm is not 1 is normalised and counted;
* two messages with one stamp and different poses (more than 1 mm or 1 mrad apart) are an
  error naming both: which one is right cannot be told (two publishers on one topic, or a
  replayed segment); identical repeats are dropped;
* the covariance's x, y, yaw block: an entry of magnitude ``>= covariance_sentinel`` (ROS
  drivers fill unused entries with 1e3..1e6; this includes a huge negative entry, which
  no measured covariance has), or an all-zero block, means "unknown" and the sensor
  config's ``pose_covariance`` is used instead; a NaN or infinite entry means "unknown"
  too, with a warning naming the topic and the count (:func:`nonfinite_warning`);
* a block that is positive semi-definite *within rounding* (:func:`psd_shortfall`:
  recorders store covariances with a few significant digits, and rounding a PSD matrix
  can make its smallest eigenvalue slightly negative) is clipped to PSD and counted;
  beyond that tolerance a negative variance or a block that is not positive
  semi-definite is an error naming file, topic, stamp and field, or with
  ``repair_pose_covariance: true`` its negative eigenvalues are set to zero and counted
  (a repair whose entries then reach the sentinel counts as "unknown" instead).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gpocc.errors import GpoccError
from gpocc.io.scans import MAX_POSITION_M, position_in_range
from gpocc.io.stamps import choose_stamps
from gpocc.io.tf import checked_quaternion, frame_name
from gpocc.progress import log

#: Pose message types, and whether each carries a covariance.
POSE_TYPES = {
    "geometry_msgs/msg/PoseWithCovarianceStamped": True,
    "nav_msgs/msg/Odometry": True,
    "geometry_msgs/msg/PoseStamped": False,
}

# x, y, yaw rows/columns of a 6x6 (x, y, z, roll, pitch, yaw) ROS covariance.
XY_YAW = np.array([0, 1, 5])

#: Same-stamp messages further apart than this are a conflict, metres / radians.
DUPLICATE_TOLERANCE = 1e-3


def header_stamp(msg: Any) -> float:
    """Header stamp in seconds (0.0 when zero: :mod:`gpocc.io.stamps` decides the clock)."""
    stamp = msg.header.stamp
    return stamp.sec + stamp.nanosec * 1e-9


@dataclass(frozen=True)
class PoseSeries:
    """One pose topic, sorted by stamp, validated.

    Attributes:
        stamps: (P,) seconds, strictly increasing.
        poses: (P, 3) x m, y m, yaw rad in ``frame_id``.
        covariances: (P, 3, 3) raw x, y, yaw block as recorded (NaN where the type has
            none); see :func:`covariance_at` for how it is used.
        frame_id: the frame the poses are given in (``map``, ``odom``).
        child_frame_id: the frame whose pose it is (Odometry's child; else empty).
        normalised_quaternions: how many orientations were normalised.
        stamps_from: which clock ``stamps`` are on (:mod:`gpocc.io.stamps`), e.g.
            ``/amcl_pose: header stamps``.
    """

    topic: str
    msgtype: str
    stamps: np.ndarray
    poses: np.ndarray
    covariances: np.ndarray
    frame_id: str
    child_frame_id: str
    normalised_quaternions: int = 0
    stamps_from: str = ""

    @property
    def has_covariance(self) -> bool:
        return POSE_TYPES[self.msgtype]


@dataclass
class PoseCollector:
    """Accumulates one pose topic's messages while a bag is read."""

    path: Path
    topic: str
    msgtype: str
    stamps: list[float] = field(default_factory=list)
    poses: list[tuple[float, float, float]] = field(default_factory=list)
    covariances: list[np.ndarray] = field(default_factory=list)
    frame_id: str = ""
    child_frame_id: str = ""
    normalised: int = 0
    log_times: list[float] = field(default_factory=list)

    def add(self, msg: Any, record_ns: int) -> None:
        has_cov = POSE_TYPES[self.msgtype]
        pose = msg.pose.pose if has_cov else msg.pose
        header = header_stamp(msg)
        t = header or record_ns * 1e-9
        where = f"{self.path}: topic {self.topic} at t={t:.6f} s"
        xy = (float(pose.position.x), float(pose.position.y))
        if not position_in_range(*xy):
            raise GpoccError(f"{where}: field pose.position is {xy}, not finite or beyond "
                             f"{MAX_POSITION_M:g} m; fix the publisher or drop these messages")
        o = pose.orientation
        q, repaired = checked_quaternion((o.x, o.y, o.z, o.w), f"{where}, field pose.orientation")
        self.normalised += int(repaired)
        if not self.stamps:
            self.frame_id = frame_name(msg.header.frame_id)
            self.child_frame_id = frame_name(getattr(msg, "child_frame_id", "") or "")
        self.stamps.append(header)
        self.log_times.append(record_ns * 1e-9)
        x, y, z, w = (float(v) for v in q)
        # math.atan2, not numpy's: bit-identical yaws to earlier gpocc versions.
        yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
        self.poses.append((xy[0], xy[1], yaw))
        if has_cov:
            cov = np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)
            self.covariances.append(cov[np.ix_(XY_YAW, XY_YAW)])

    def build(self) -> PoseSeries:
        chosen = choose_stamps(np.asarray(self.stamps, dtype=float),
                               np.asarray(self.log_times, dtype=float), repeats_allowed=True)
        if chosen.reason:
            log(f"warning: {self.path}: {chosen.warning(self.topic)}")
        stamps = chosen.times
        poses = np.asarray(self.poses, dtype=float).reshape(-1, 3)
        covs = (np.asarray(self.covariances, dtype=float).reshape(-1, 3, 3)
                if self.covariances else np.full((len(stamps), 3, 3), np.nan))
        if chosen.keep is not None:
            stamps, poses, covs = stamps[chosen.keep], poses[chosen.keep], covs[chosen.keep]
        order = np.argsort(stamps, kind="stable")
        stamps, poses, covs = stamps[order], poses[order], covs[order]
        same = np.flatnonzero(np.diff(stamps) == 0)
        for i in same:
            d = poses[i + 1] - poses[i]
            dyaw = abs(math.remainder(d[2], 2 * math.pi))
            if math.hypot(d[0], d[1]) > DUPLICATE_TOLERANCE or dyaw > DUPLICATE_TOLERANCE:
                raise GpoccError(
                    f"{self.path}: topic {self.topic} has two messages at t={stamps[i]:.6f} s "
                    f"with different poses ({poses[i, 0]:.3f}, {poses[i, 1]:.3f}) and "
                    f"({poses[i + 1, 0]:.3f}, {poses[i + 1, 1]:.3f}), field header.stamp; "
                    "two publishers on one topic? filter the bag to one, or pick another "
                    "pose_topic"
                )
        keep = np.ones(len(stamps), bool)
        keep[same + 1] = False
        return PoseSeries(self.topic, self.msgtype, stamps[keep], poses[keep], covs[keep],
                          self.frame_id, self.child_frame_id, self.normalised,
                          chosen.describe(self.topic))


# --------------------------------------------------------------------------- covariance


#: Significant digits a recorded covariance is assumed to keep, at the least: GMapping's
#: particle covariance, AMCL and many recorders and log converters print 2 or 3.
COVARIANCE_DIGITS = 2


def psd_shortfall(cov: np.ndarray, digits: int = COVARIANCE_DIGITS) -> np.ndarray:
    """How far a stored block is from PSD, in units of what rounding can explain.

    A covariance ``C`` (positive semi-definite) stored with ``digits`` significant digits
    reads back as ``C~ = C + E`` with ``|E_ij| <= u |C_ij| <= u' |C~_ij|``, where
    ``u = 0.5 * 10**(1 - digits)`` (round to nearest) and ``u' = u / (1 - u)``. Rounding
    is relative per entry, so the test is made on the correlation matrix ``R~ = D C~ D``,
    ``D = diag(C~_ii)**-1/2`` (a congruence: PSD-ness and the relative errors are kept,
    and metres and radians no longer mix): ``D C D`` is PSD and the perturbation ``D E D``
    is entrywise at most ``u' |R~|``, so by Weyl's inequality and the monotonicity of the
    spectral norm on non-negative matrices

        lambda_min(R~) >= -u' * lambda_max(|R~|).

    A smallest eigenvalue below that is no rounding of a PSD matrix. For two variables
    this allows a correlation up to ``(1 + u') / (1 - u')`` (1.11 for 2 digits), the
    largest that rounding 2 digits can produce (1.105). Rounding never makes a variance
    negative, nor a positive one zero.

    Args:
        cov: (..., 3, 3) symmetric blocks as stored.
        digits: significant digits kept by the recorder.

    Returns:
        (...) ``-lambda_min(R~) / (u' lambda_max(|R~|))``: <= 0 PSD, in (0, 1] PSD within
        rounding, > 1 beyond it (inf: a zero variance with a non-zero covariance).
    """
    u = 0.5 * 10.0 ** (1 - digits)
    u1 = u / (1.0 - u)
    cov = np.asarray(cov, dtype=float)
    d = np.diagonal(cov, axis1=-2, axis2=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(d > 0, 1.0 / np.sqrt(np.where(d > 0, d, 1.0)), 0.0)
    r = cov * scale[..., :, None] * scale[..., None, :]
    lam_min = np.linalg.eigvalsh(r)[..., 0]
    lam_abs = np.linalg.eigvalsh(np.abs(r))[..., -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(lam_abs > 0, -lam_min / (u1 * np.where(lam_abs > 0, lam_abs, 1.0)), 0.0)
    # A zero variance whose row is not zero: no rounding gives it.
    off = np.abs(cov).sum(axis=-1) - np.abs(d)
    return np.where(((d <= 0) & (off > 0)).any(axis=-1), np.inf, out)


def _clip_psd(cov: np.ndarray) -> np.ndarray:
    """(N, 3, 3) the nearest PSD matrices (negative eigenvalues set to zero; Higham 1988)."""
    w, v = np.linalg.eigh(cov)
    return (v * np.maximum(w, 0.0)[:, None, :]) @ np.swapaxes(v, 1, 2)


@dataclass(frozen=True)
class CovarianceCheck:
    """Which covariances are known, after validation and (optional) repair.

    Attributes:
        covariances: (P, 3, 3) symmetric PSD where ``known``.
        known: (P,) bool.
        unknown_reason: why some are unknown ("" if none are).
        repaired: how many were not PSD and had negative eigenvalues clipped.
        rounded: how many were PSD only within rounding (:func:`psd_shortfall`) and
            were clipped to PSD.
        nonfinite: how many had a NaN or infinite entry (unknown).
    """

    covariances: np.ndarray
    known: np.ndarray
    unknown_reason: str
    repaired: int
    rounded: int = 0
    nonfinite: int = 0


def nonfinite_warning(topic: str, check: CovarianceCheck) -> str:
    """The warning for NaN / inf covariances on ``topic`` ("" when there are none)."""
    if not check.nonfinite:
        return ""
    return (f"{topic}: {check.nonfinite} of {check.known.size} covariances have NaN or "
            "infinite entries and are taken as unknown: the config's pose_covariance "
            "stands in (set sensors[].pose_covariance to what the pose source's error is)")


def check_covariances(series: PoseSeries, path: Path, sentinel: float, repair: bool,
                      key: str) -> CovarianceCheck:
    """Validate a series' covariances (see the module docs for the rules).

    Args:
        key: config key prefix for messages (``sensors[0]``).

    Raises:
        GpoccError: a negative variance, or a covariance not PSD even within rounding
            (:func:`psd_shortfall`), unless ``repair``.
    """
    cov = np.array(series.covariances, dtype=float)
    p = cov.shape[0]
    if not series.has_covariance:
        return CovarianceCheck(cov, np.zeros(p, bool), f"{series.msgtype} has no covariance", 0)
    nan = np.any(~np.isfinite(cov), axis=(1, 2))
    with np.errstate(invalid="ignore"):
        # Magnitude: a PSD matrix cannot have |c_ij| >= sentinel without a diagonal entry
        # >= sentinel, so a huge off-diagonal entry is as unknown as a huge variance.
        sentinel_hit = ~nan & np.any(np.abs(cov) >= sentinel, axis=(1, 2))
    zero = ~nan & np.all(cov == 0, axis=(1, 2))
    known = ~(sentinel_hit | nan | zero)
    sym = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    sym[~known] = 0.0
    eig = np.linalg.eigvalsh(sym)
    diag = np.diagonal(sym, axis1=1, axis2=2)
    below = known & (eig.min(axis=1) < 0)
    bad = below & ((diag < 0).any(axis=1) | (psd_shortfall(sym) > 1.0))
    rounded = below & ~bad
    if rounded.any():
        sym[rounded] = _clip_psd(sym[rounded])
    repaired = 0
    if bad.any():
        if not repair:
            i = int(np.flatnonzero(bad)[0])
            what = ("has a negative variance" if (diag[i] < 0).any()
                    else f"is not positive semi-definite (smallest eigenvalue "
                         f"{eig[i].min():.3g}, beyond the rounding of "
                         f"{COVARIANCE_DIGITS} significant digits)")
            raise GpoccError(
                f"{path}: topic {series.topic} at t={series.stamps[i]:.6f} s: field "
                f"pose.covariance (x, y, yaw block {np.round(sym[i], 9).tolist()}) {what} "
                f"({int(bad.sum())} such messages); fix the publisher, or set "
                f"{key}.repair_pose_covariance: true to clip its negative eigenvalues"
            )
        sym[bad] = _clip_psd(sym[bad])
        repaired = int(bad.sum())
        # Clipping can lift a variance past the sentinel (e.g. a zero diagonal with a
        # large off-diagonal entry): such a repair is no measurement either.
        lifted = bad & np.any(np.abs(sym) >= sentinel, axis=(1, 2))
        sym[lifted] = 0.0
        known &= ~lifted
        sentinel_hit |= lifted
        repaired -= int(lifted.sum())  # counted once, as unknown
    reasons = []
    if sentinel_hit.any():
        reasons.append(f"{int(sentinel_hit.sum())} with entries >= {key}.covariance_sentinel="
                       f"{sentinel:g}")
    if nan.any():
        reasons.append(f"{int(nan.sum())} with NaN or infinite entries")
    if zero.any():
        reasons.append(f"{int(zero.sum())} all zero")
    return CovarianceCheck(sym, known, "; ".join(reasons), repaired, int(rounded.sum()),
                           int(nan.sum()))


@dataclass(frozen=True)
class CovarianceAtScans:
    """Covariances at scan stamps: (S, 3, 3), and which came from the input (S,) bool."""

    covariances: np.ndarray
    from_input: np.ndarray
    stale: int


def covariance_at(stamps: np.ndarray, cov_stamps: np.ndarray, check: CovarianceCheck,
                  fallback: np.ndarray, max_age_s: float) -> CovarianceAtScans:
    """Known covariances at ``stamps``: interpolated, or held, else ``fallback``.

    A stamp between two known covariances at most ``max_age_s`` apart gets the linear
    interpolation; otherwise the nearest known one (before or after) if it is at most
    ``max_age_s`` away: AMCL publishes only after the robot has moved 0.25 m or turned
    0.2 rad, so a slow or stopped robot's last covariance is still its current one.
    Beyond that the config's ``fallback`` (3, 3) is used and counted as stale.

    Args:
        stamps: (S,) seconds.
        cov_stamps: (P,) seconds, increasing.
        fallback: (3, 3).
    """
    s = stamps.shape[0]
    out = np.broadcast_to(fallback, (s, 3, 3)).copy()
    t = cov_stamps[check.known]
    c = check.covariances[check.known]
    if t.size == 0:
        return CovarianceAtScans(out, np.zeros(s, bool), 0)
    n = t.size
    right = np.searchsorted(t, stamps, side="right")
    i0 = np.clip(right - 1, 0, n - 1)
    i1 = np.clip(right, 0, n - 1)
    before = right > 0
    after = right < n
    age0 = np.where(before, stamps - t[i0], np.inf)
    age1 = np.where(after, t[i1] - stamps, np.inf)
    gap = t[i1] - t[i0]
    interp = before & after & (gap <= max_age_s) & (gap > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(interp, (stamps - t[i0]) / np.where(gap > 0, gap, 1.0), 0.0)
    held = np.where(age0 <= age1, i0, i1)
    near = np.minimum(age0, age1) <= max_age_s
    use = interp | near
    cov = np.where(interp[:, None, None],
                   (1 - w)[:, None, None] * c[i0] + w[:, None, None] * c[i1], c[held])
    out[use] = cov[use]
    return CovarianceAtScans(out, use, int(np.count_nonzero(~use)))


def rotate_covariances(cov: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """(S, 3, 3) x, y, yaw covariances expressed in a frame rotated by ``angle`` (S,) rad."""
    c, s = np.cos(angle), np.sin(angle)
    j = np.zeros(cov.shape)
    j[:, 0, 0], j[:, 0, 1], j[:, 1, 0], j[:, 1, 1] = c, -s, s, c
    j[:, 2, 2] = 1.0
    return j @ cov @ np.swapaxes(j, 1, 2)


def move_covariances(cov: np.ndarray, lever: np.ndarray) -> np.ndarray:
    """Body (x, y, yaw) covariances (S, 3, 3) carried to a laser mounted on the body.

    The laser sits at ``p_l = p_b + R(yaw_b) m`` with the mount ``m`` in the body frame;
    ``lever`` (S, 2) is ``R(yaw_b) m``, the laser position minus the body position in the
    map frame, metres. To first order its covariance is ``J P J^T`` with
    ``J = [[1, 0, -lever_y], [0, 1, lever_x], [0, 0, 1]]``: the laser also moves when the
    body turns.
    """
    j = np.zeros(cov.shape)
    j[:, 0, 0] = j[:, 1, 1] = j[:, 2, 2] = 1.0
    j[:, 0, 2] = -lever[:, 1]
    j[:, 1, 2] = lever[:, 0]
    return j @ cov @ np.swapaxes(j, 1, 2)
