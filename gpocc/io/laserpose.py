"""The laser pose and its covariance at each scan stamp of a bag, from the best source.

Position: when TF reaches the scan's ``header.frame_id`` from ``map_frame`` (default
``map``, also tried under the sensor's namespace, e.g. ``robot1/map``), the laser pose is
that chain at the scan stamp (see :mod:`gpocc.io.tf`), the static mount included, so the
sensor's ``mount`` in the config must stay zero. Without ``map`` the chain starts at
``odom`` with a warning that the map will drift. Without a TF chain, the pose topic's
poses are interpolated to the scans (the config's ``mount`` then applies).

A pose topic in the map frame (AMCL, SLAM, robot_localization's global Odometry) is the
robot base's pose: when TF reaches the laser only from ``odom`` (which drifts) or not at
all, the base pose comes from that topic and the static base -> laser mount from TF
(:func:`mount_chain`), the covariance carried through the mount's lever arm.

Without TF, a PoseWithCovarianceStamped ``pose_topic`` (AMCL at its motion-triggered
cadence) anchors the robot's odometry topic in its namespace when there is one
(:func:`anchored_poses`), so a slow robot keeps its scans.

Covariance: from ``pose_topic`` when it carries one (PoseWithCovarianceStamped from AMCL
or SLAM, else Odometry), held or interpolated to each scan up to ``max_covariance_age_s``
(:func:`gpocc.io.poses.covariance_at`); unknown entries and stale scans use the config's
``pose_covariance``. With TF, the covariance is rotated from the message frame into the
map frame and carried from the robot body to the laser through the mount's lever arm.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gpocc.config import MountConfig, SensorConfig
from gpocc.errors import GpoccError
from gpocc.io.layouts import common_layout
from gpocc.io.poses import (
    COVARIANCE_DIGITS,
    PoseSeries,
    check_covariances,
    covariance_at,
    move_covariances,
    nonfinite_warning,
    rotate_covariances,
)
from gpocc.io.scans import Provenance, ScanBatch
from gpocc.io.stamps import HEADER, Stamps, choose_stamps
from gpocc.io.tf import Chain, TfBuffer
from gpocc.io.timeline import blend_poses, brackets
from gpocc.progress import log

_ROUNDED = "PSD only within the rounding"
#: A sensor losing more than this share of its scans gets a warning.
SKIP_WARNING_SHARE = 0.10


@dataclass
class ScanTopic:
    """One LaserScan topic's messages, as read (validated in gpocc.io.bags)."""

    stamps: list[float] = field(default_factory=list)  # header stamps, 0.0 when zero
    ranges: list[np.ndarray] = field(default_factory=list)
    log_times: list[float] = field(default_factory=list)  # empty: time by ``stamps``
    geometry: tuple[int, float, float] | None = None  # the first scan's layout
    # Every scan's (n, angle_min, angle_increment) once one differs from ``geometry``;
    # None while all share it.
    layouts: list[tuple[int, float, float]] | None = None
    range_limits: tuple[float, float] | None = None
    frame_id: str = ""  # the first non-empty header.frame_id
    # The first change of a non-empty frame_id: (time s, from, to), None if it never does.
    frame_change: tuple[float, str, str] | None = None
    # Scans already on the level ground plane (a 3-D lidar's projected clouds,
    # gpocc.io.cloudread): their frame may tilt with the base; the TF tilt check is moot.
    levelled: bool = False


def namespace(topic: str) -> str:
    """``/robot1/front/scan`` -> ``robot1/front``; ``/scan`` -> ``""``."""
    return topic.strip("/").rpartition("/")[0]


def _frame_candidates(frame: str, ns: str) -> list[str]:
    """``frame`` as given, then under each namespace prefix (``robot1/front/map``, ...)."""
    parts = ns.split("/") if ns else []
    out = [frame] + ["/".join(parts[:k] + [frame]) for k in range(len(parts), 0, -1)]
    return list(dict.fromkeys(out))


def find_chain(tf: TfBuffer, sensor: SensorConfig, laser_frame: str) -> tuple[Chain | None, str]:
    """The chain map_frame -> laser, or odom -> laser with a drift note, or (None, why)."""
    ns = namespace(sensor.scan_topic or "")
    for frame in _frame_candidates(sensor.map_frame, ns):
        chain = tf.chain(frame, laser_frame)
        if chain is not None:
            return chain, ""
    if sensor.map_frame != "odom":
        for frame in _frame_candidates("odom", ns):
            chain = tf.chain(frame, laser_frame)
            if chain is not None:
                return chain, (
                    f"TF has no frame '{sensor.map_frame}' connected to '{laser_frame}'; "
                    f"mapping in '{frame}', which drifts with odometry: the map will drift "
                    "(set sensors[].map_frame, or record the localisation's TF)")
    why = [f"no TF chain from '{sensor.map_frame}' to the scan frame '{laser_frame}'"]
    if laser_frame not in tf.frames():
        why.append(f"TF has no frame '{laser_frame}'")
    bad = [f"{c} (parents {p})" for c, p in tf.conflicts.items()]
    if bad:
        why.append("frames with two parents: " + "; ".join(bad))
    return None, "; ".join(why)


def _no_pose_fix(chain: Chain | None, skipped: list[tuple[str, str, int]]) -> str:
    """For the error of a sensor whose scans all lack a pose: a dynamic TF edge of the
    chain with one message (interpolation needs two: one published once belongs on
    /tf_static), else the commonest skip reason, with what to change."""
    fix = chain.published_once_fix("a transform") if chain is not None else None
    if fix is not None:
        return fix
    mostly = f"mostly for {max(skipped, key=lambda r: r[2])[0]}; " if skipped else ""
    return f"{mostly}check the topics' stamps or raise sensors[].max_pose_gap_s"


def _tf_fix(tf: TfBuffer, laser_frame: str) -> str:
    """What to change when TF in a bag does not reach ``laser_frame`` from the map: the
    cause on the laser's own path up TF (a frame of two parents, a cycle), else the root
    it hangs from, else the missing frame."""
    if not laser_frame:
        return "fix the driver's header.frame_id"
    if laser_frame not in tf.frames():
        return "record /tf_static (the robot's static transforms)"
    path = [laser_frame, *tf.parents(laser_frame)]
    torn = next((frame for frame in path if frame in tf.conflicts), None)
    if torn is not None:
        return (f"filter the bag to one publisher of '{torn}' (it has two parents: "
                f"{tf.conflicts[torn]})")
    last = tf.edges.get(path[-1])
    if last is not None:  # the walk stopped where a parent repeats
        return (f"remove the TF cycle through '{last.parent}' (a transform published the "
                "wrong way round)")
    return f"set sensors[].map_frame to '{path[-1]}' (the root of the laser's TF tree)"


def in_map_frame(frame: str, sensor: SensorConfig) -> bool:
    """Whether ``frame`` is the sensor's map frame (as given, or under its namespace)."""
    ns = namespace(sensor.scan_topic or "")
    return bool(frame) and frame in _frame_candidates(sensor.map_frame, ns)


def mount_chain(tf: TfBuffer, series: PoseSeries, laser_frame: str) -> Chain | None:
    """The static TF chain from the frame a pose topic gives the pose of to the laser.

    That frame is the pose's ``child_frame_id`` (Odometry) when TF knows it, else the top
    of the laser's static subtree (``base_footprint`` for ``base_footprint -> base_link
    -> laser``): AMCL and SLAM poses are the robot base's. None when there is no such
    chain, or it is not all static (not a mount).
    """
    body = series.child_frame_id
    if not body or body not in tf.frames():
        body = laser_frame
        edge = tf.edges.get(body)
        while edge is not None and edge.static:
            body = edge.parent
            edge = tf.edges.get(body)
    if body == laser_frame:
        return None
    chain = tf.chain(body, laser_frame)
    if chain is None or not chain.steps or not all(e.static for e, _ in chain.steps):
        return None
    return chain


def _skip_reasons(valid: np.ndarray, missing: np.ndarray) -> list[tuple[str, str, int]]:
    out = []
    for label in sorted({str(m) for m in missing[~valid]}):
        n = int(np.count_nonzero((~valid) & (missing == label)))
        out.append((f"no TF {label} within max_pose_gap_s of the scan",
                    "sensors[].max_pose_gap_s", n))
    return out


def _level_scans(path: str | Path, sensor: SensorConfig, scans: ScanTopic, via: str,
                 valid: np.ndarray, tilt_rad: np.ndarray
                 ) -> tuple[np.ndarray, list[tuple[str, str, int]]]:
    """``valid`` (S,) without the scans whose laser plane TF tilts (``tilt_rad`` (S,))
    more than ``sensors[].max_tilt_deg`` from level, and their skip reason; all of
    ``valid`` for scans already levelled (projected 3-D clouds).

    Raises:
        GpoccError: every scan with a pose is tilted (``via``: the TF chain, for the
            message).
    """
    if scans.levelled:
        return valid, []
    frame = scans.frame_id
    tilted = valid & (tilt_rad > math.radians(sensor.max_tilt_deg))
    count = int(np.count_nonzero(tilted))
    if count == 0:
        return valid, []
    if count == int(np.count_nonzero(valid)):
        raise GpoccError(
            f"{path}: sensor '{sensor.name}': TF ({via}) tilts the laser frame '{frame}' "
            f"{math.degrees(float(np.median(tilt_rad[tilted]))):.1f} degrees from level, more "
            f"than sensors[].max_tilt_deg ({sensor.max_tilt_deg:g}): its beams would meet "
            "floors or ceilings that a planar map draws as walls; check the mount's "
            "rotation in TF, give a 3-D lidar as a PointCloud2 topic, or raise max_tilt_deg")
    return valid & ~tilted, [(f"the laser frame '{frame}' tilted more than "
                              "max_tilt_deg from level", "sensors[].max_tilt_deg", count)]


def _lever(tf: TfBuffer, chain: Chain, body: str, laser_frame: str, stamps: np.ndarray,
           laser_yaw: np.ndarray, max_gap_s: float) -> np.ndarray:
    """(S, 2) laser position minus body position in the map frame, metres (0 if unknown)."""
    inner = tf.chain(body, laser_frame)
    if inner is None or not inner.steps:
        return np.zeros((stamps.size, 2))
    rel = tf.lookup(inner, stamps, max_gap_s)
    yaw_body = laser_yaw - rel.poses[:, 2]
    c, s = np.cos(yaw_body), np.sin(yaw_body)
    x, y = rel.poses[:, 0], rel.poses[:, 1]
    lever = np.column_stack([c * x - s * y, s * x + c * y])
    return np.where(rel.valid[:, None], lever, 0.0)


@dataclass(frozen=True)
class _Covariance:
    covariances: np.ndarray  # (S, 3, 3) in the map frame, at the pose's body
    from_input: np.ndarray   # (S,) bool
    source: str
    notes: tuple[str, ...]


def _covariances(path: Path, sensor: SensorConfig, series: PoseSeries | None,
                 stamps: np.ndarray, tf: TfBuffer | None, map_frame: str | None,
                 max_age_s: float, age_key: str, used: np.ndarray) -> _Covariance:
    """Covariances at ``stamps`` (S,), held up to ``max_age_s`` (the config key
    ``age_key``); ``used`` (S,) marks the scans that have a pose: only those are counted
    as stale."""
    fallback = sensor.pose_covariance_matrix
    n = stamps.size
    config_only = _Covariance(np.broadcast_to(fallback, (n, 3, 3)).copy(), np.zeros(n, bool),
                              "config (sensors[].pose_covariance)", ())
    if series is None:
        return config_only
    if sensor.override_pose_covariance:
        return _Covariance(config_only.covariances, config_only.from_input,
                           "config (override_pose_covariance)", ())
    check = check_covariances(series, path, sensor.covariance_sentinel,
                              sensor.repair_pose_covariance, "sensors[]")
    notes = []
    if check.rounded:
        notes.append(f"{check.rounded} covariances on {series.topic} {_ROUNDED} of "
                     f"{COVARIANCE_DIGITS} significant digits: clipped to PSD")
    if check.nonfinite:
        log(f"warning: {path}: sensor '{sensor.name}': {nonfinite_warning(series.topic, check)}")
    if check.repaired:
        notes.append(f"{check.repaired} non-PSD covariances on {series.topic} repaired "
                     "(negative eigenvalues set to 0)")
    if not check.known.any():
        why = check.unknown_reason
        source = f"config (sensors[].pose_covariance): {series.topic} {why}"
        if series.has_covariance and why:
            notes.append(f"{series.topic}: covariance unknown ({why}); the config's "
                         "pose_covariance is used")
        return _Covariance(config_only.covariances, config_only.from_input, source,
                           tuple(notes))
    cov = check.covariances
    if tf is not None and map_frame and series.frame_id and series.frame_id != map_frame:
        # Odometry covariance is given in the odom frame: turn it into the map frame.
        link = tf.chain(map_frame, series.frame_id)
        if link is not None:
            rot = tf.lookup(link, series.stamps, max_age_s)
            cov = rotate_covariances(cov, np.where(rot.valid, rot.poses[:, 2], 0.0))
    check = dataclasses.replace(check, covariances=cov)
    at = covariance_at(stamps, series.stamps, check, fallback, max_age_s)
    source = f"{series.topic} (held or interpolated up to {age_key}={max_age_s:g} s)"
    unknown = int(np.count_nonzero(~check.known))
    if unknown:
        notes.append(f"{series.topic}: {unknown} of {check.known.size} covariances unknown "
                     f"({check.unknown_reason}); the config's pose_covariance stands in")
    # Scans without a pose are dropped (and counted as skipped): not stale as well.
    stale = int(np.count_nonzero(used & ~at.from_input))
    if stale:
        notes.append(f"{stale} scans more than {age_key}={max_age_s:g} s from a "
                     f"known covariance on {series.topic} use the config's pose_covariance")
    return _Covariance(at.covariances, at.from_input, source, tuple(notes))


def interpolate_poses(
    pose_stamps: np.ndarray,
    poses: np.ndarray,
    stamps: np.ndarray,
    max_gap_s: float,
    tolerance_s: float = 1e-6,
) -> tuple[np.ndarray, np.ndarray]:
    """Poses at ``stamps``: x, y linear in time, yaw along the shorter arc.

    A stamp is served when it lies between two poses at most ``max_gap_s`` apart, or
    within ``tolerance_s`` of a pose (it takes that pose). Returns
    ``(poses (S, 3), valid (S,) bool)``.
    """
    at = brackets(pose_stamps, stamps, max_gap_s, tolerance_s)
    return blend_poses(poses, at), at.served


def _compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SE(2) ``a (+) b`` row by row, (N, 3)."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack([a[:, 0] + c * b[:, 0] - s * b[:, 1],
                            a[:, 1] + s * b[:, 0] + c * b[:, 1],
                            np.angle(np.exp(1j * (a[:, 2] + b[:, 2])))])


def _inverse(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.column_stack([-c * a[:, 0] - s * a[:, 1], s * a[:, 0] - c * a[:, 1], -a[:, 2]])


def anchored_poses(fixes: PoseSeries, odom: PoseSeries, stamps: np.ndarray, max_gap_s: float,
                   max_age_s: float, tolerance_s: float = 1e-6,
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Odometry anchored to sparse localisation fixes, as AMCL's ``map -> odom`` TF does.

    At each fix ``A_k`` (AMCL publishes only after 0.25 m or 0.2 rad of motion) the
    correction ``C_k = A_k (-) O(t_k)`` is computed with the odometry ``O`` interpolated to
    the fix; a scan at ``t`` gets ``C (+) O(t)`` with the latest correction at or before
    ``t`` (the first one before the first fix), if that fix is at most ``max_age_s`` away.

    Returns:
        ``(poses (S, 3), valid (S,), stale (S,))``, ``stale`` marking scans too far from a
        fix; None when no fix falls within the odometry.
    """
    o_fix, ok = interpolate_poses(odom.stamps, odom.poses, fixes.stamps, max_gap_s, tolerance_s)
    if not ok.any():
        return None
    t_fix = fixes.stamps[ok]
    correction = _compose(fixes.poses[ok], _inverse(o_fix[ok]))
    o_scan, valid = interpolate_poses(odom.stamps, odom.poses, stamps, max_gap_s, tolerance_s)
    i = np.clip(np.searchsorted(t_fix, stamps, side="right") - 1, 0, t_fix.size - 1)
    stale = np.abs(stamps - t_fix[i]) > max_age_s
    return _compose(correction[i], o_scan), valid & ~stale, stale


def assemble(path: Path, sensor: SensorConfig, scans: ScanTopic, tf: TfBuffer | None,
             series: PoseSeries | None, odometry: PoseSeries | None = None) -> ScanBatch:
    """One sensor's batch: scans sorted by stamp, each with its laser pose and covariance.

    Raises:
        GpoccError: no scans, no pose source, a config mount on top of a TF mount, TF in
            the bag that does not place the laser (its mount unknown), a frame_id that
            changes when TF poses the scans, a laser tilted in every scan, no scan with a
            pose, or unusable range limits.
    """
    scan_topic = sensor.scan_topic
    if not scans.stamps:
        raise GpoccError(f"{path}: topic {scan_topic} has no messages; pick another scan_topic")
    assert scans.geometry is not None and scans.range_limits is not None
    timing = (choose_stamps(np.asarray(scans.stamps), np.asarray(scans.log_times), False)
              if len(scans.log_times) == len(scans.stamps) else
              Stamps(np.asarray(scans.stamps, dtype=float), HEADER))
    if timing.reason:
        log(f"warning: {path}: {timing.warning(scan_topic)}")
    kept = (np.arange(len(scans.stamps)) if timing.keep is None
            else np.flatnonzero(timing.keep))
    stamps = timing.times[kept]
    order = kept[np.argsort(stamps, kind="stable")]
    stamps = timing.times[order]
    if scans.layouts is None:
        ranges = np.stack(scans.ranges)[order]
        n, angle_min, increment = scans.geometry
        angles = angle_min + np.arange(n) * increment
        layout_note = ""
    else:
        common = common_layout(f"{path}: topic {scan_topic}", scans.ranges, scans.layouts)
        ranges, angles = common.ranges[order], common.angles
        layout_note = common.describe()
        sensor = common.widened(sensor)

    chain, why = (find_chain(tf, sensor, scans.frame_id)
                  if tf and sensor.position_from_tf and scans.frame_id else (None, ""))
    notes: list[str] = [layout_note] if layout_note else []
    warned: set[str] = set()  # notes already on stderr as warnings
    mount_tf = None
    if (tf and sensor.position_from_tf and scans.frame_id and series is not None
            and (chain is None and not scans.levelled
                 or (chain is None or why) and in_map_frame(series.frame_id, sensor))):
        # A map-frame pose topic (AMCL, robot_localization's global Odometry) beats TF
        # from odom, which drifts; TF still gives the base -> laser mount. Without any TF
        # chain to the laser (a bag of /odom and /tf_static), TF's mount is still the one.
        mount_tf = mount_chain(tf, series, scans.frame_id)
        if mount_tf is not None and chain is not None:
            notes.append(f"TF reaches '{scans.frame_id}' only from '{chain.target}', which "
                         f"drifts: poses from {series.topic} (frame '{series.frame_id}') "
                         "with the mount from TF instead")
            chain, why = None, ""
    if scans.frame_change is not None and (chain is not None or mount_tf is not None):
        # TF poses the topic by one frame's mount: a second laser's scans would take it.
        t_change, before, after = scans.frame_change
        raise GpoccError(
            f"{path}: topic {scan_topic} changes its header.frame_id from '{before}' to "
            f"'{after}' at t={t_change:.3f} s; TF poses a laser topic by one frame: fix the "
            "driver's frame_id, or split the bag at that time")
    skipped: list[tuple[str, str, int]] = []
    chain_text = ""
    if chain is not None:
        mount = sensor.mount
        if mount != MountConfig():
            raise GpoccError(
                f"{path}: sensor '{sensor.name}': TF already gives the laser's mount "
                f"({chain.describe()}), and the config sets sensors[].mount too; remove mount "
                "from that entry (or set position_from_tf: false to use the pose topic)")
        if why:
            log(f"warning: {path}: sensor '{sensor.name}': {why}")
            notes.append(why)
            warned.add(why)
        look = tf.lookup(chain, stamps, sensor.max_pose_gap_s)
        valid, tilt_skips = _level_scans(path, sensor, scans, chain.describe(), look.valid,
                                         look.tilt_rad)
        poses = look.poses
        if valid.any():
            flipped = look.upside_down[valid]
            if flipped.all():
                angles = -angles  # an upside-down laser scans clockwise in the map
                notes.append(f"laser frame '{scans.frame_id}' is upside down: bearings mirrored")
            elif flipped.any():
                raise GpoccError(
                    f"{path}: sensor '{sensor.name}': the laser frame '{scans.frame_id}' turns "
                    "upside down during the log; check the TF of its mount")
        skipped = _skip_reasons(look.valid, look.missing) + tilt_skips
        chain_text = chain.describe()
        pose_source = f"TF {chain.target} -> {chain.source}"
        body = (series.child_frame_id if series is not None and series.child_frame_id
                and series.child_frame_id in tf.frames() else chain.body_frame())
        cov = _covariances(path, sensor, series, stamps, tf, chain.target,
                           sensor.max_covariance_age_s, "max_covariance_age_s", valid)
        lever = _lever(tf, chain, body, scans.frame_id, stamps, poses[:, 2],
                       sensor.max_pose_gap_s)
        covariances = move_covariances(cov.covariances, lever)
        has_cov = not sensor.override_pose_covariance
    else:
        if series is None:
            raise GpoccError(
                f"{path}: sensor '{sensor.name}' has no pose: {why or 'the bag has no TF'}, "
                f"and no pose topic; set sensors[].pose_topic to a pose topic, or "
                "sensors[].map_frame to a frame TF connects to the laser")
        if not series.stamps.size:
            raise GpoccError(f"{path}: topic {series.topic} has no messages; pick another "
                             "pose_topic")
        if (tf and sensor.position_from_tf and mount_tf is None and not scans.levelled
                and sensor.mount == MountConfig()
                and not (scans.frame_id and series.child_frame_id == scans.frame_id)):
            # The bag has TF, but not to this laser: where the laser sits on the pose's
            # frame is unknown, and a zero mount draws the map shifted (or, for a laser
            # facing backwards, turned 180 degrees). A missing /tf_static is the usual
            # cause. (A pose topic whose child frame is the scan's poses the laser itself;
            # a 3-D lidar's projection brings its own mount.)
            frame = f"the scan frame '{scans.frame_id}'" if scans.frame_id else (
                "the scans, which have no frame_id,")
            raise GpoccError(
                f"{path}: sensor '{sensor.name}': the bag has TF, but it does not place "
                f"{frame} ({why or 'no chain'}), so the laser's mount on {series.topic}'s "
                f"frame is unknown; {_tf_fix(tf, scans.frame_id)}, set sensors[].mount to "
                "where the laser sits, or set position_from_tf: false if "
                f"{series.topic} gives the laser's own pose")
        if why and tf:
            notes.append(f"poses from {series.topic}: {why}")
        if sensor.mount.upside_down:
            angles = -angles  # as for an upside-down laser found in TF
            notes.append("sensors[].mount.upside_down: bearings mirrored")
        fused = None
        if odometry is not None and odometry.stamps.size and odometry.topic != series.topic:
            fused = anchored_poses(series, odometry, stamps, sensor.max_pose_gap_s,
                                   sensor.max_covariance_age_s, sensor.stamp_tolerance_s)
        if fused is not None:
            poses, valid, stale = fused
            gap = ~valid & ~stale
            skipped = [r for r in (
                (f"no odometry on {odometry.topic} within max_pose_gap_s of the scan",
                 "sensors[].max_pose_gap_s", int(np.count_nonzero(gap))),
                (f"no fix on {series.topic} within max_covariance_age_s of the scan",
                 "sensors[].max_covariance_age_s", int(np.count_nonzero(stale)))) if r[2]]
            pose_source = f"topic {series.topic} anchoring odometry {odometry.topic}"
            cov_age, age_key = sensor.max_covariance_age_s, "max_covariance_age_s"
        else:
            poses, valid = interpolate_poses(series.stamps, series.poses, stamps,
                                             sensor.max_pose_gap_s, sensor.stamp_tolerance_s)
            if not valid.all():
                skipped = [(f"no pose on {series.topic} within stamp_tolerance_s of the "
                            "scan, nor two poses around it within max_pose_gap_s",
                            "sensors[].max_pose_gap_s", int(np.count_nonzero(~valid)))]
            pose_source = f"topic {series.topic} ({series.msgtype.rsplit('/', 1)[-1]})"
            # The pose and its covariance come from the same messages: one time bound.
            cov_age, age_key = sensor.max_pose_gap_s, "max_pose_gap_s"
        cov = _covariances(path, sensor, series, stamps, None, None, cov_age, age_key, valid)
        covariances = cov.covariances
        has_cov = bool(cov.from_input[valid].any())
        if mount_tf is not None:
            if sensor.mount != MountConfig():
                raise GpoccError(
                    f"{path}: sensor '{sensor.name}': TF already gives the laser's mount "
                    f"({mount_tf.describe()}), and the config sets sensors[].mount too; "
                    "remove mount from that entry (or set position_from_tf: false)")
            rel = tf.lookup(mount_tf, stamps, sensor.max_pose_gap_s)
            valid, tilt_skips = _level_scans(path, sensor, scans, mount_tf.describe(), valid,
                                             rel.tilt_rad)
            skipped += tilt_skips
            laser = _compose(poses, rel.poses)
            # The base's covariance carried to the laser through the mount's lever arm.
            covariances = move_covariances(covariances, laser[:, :2] - poses[:, :2])
            poses = laser
            if rel.upside_down.any():
                angles = -angles
                notes.append(f"laser frame '{scans.frame_id}' is upside down: bearings "
                             "mirrored")
            chain_text = mount_tf.describe()
            pose_source += f" with the mount TF {mount_tf.target} -> {mount_tf.source}"
    notes.extend(cov.notes)
    if series is not None and series.normalised_quaternions:
        notes.append(f"{series.normalised_quaternions} non-unit quaternions on {series.topic} "
                     "normalised")
    if tf is not None and tf.normalised_quaternions and chain is not None:
        notes.append(f"{tf.normalised_quaternions} non-unit TF quaternions normalised")
    if tf is not None and tf.repeated_stamps and chain is not None:
        notes.append(f"{tf.repeated_stamps} repeated TF stamps ignored (first kept, as tf2)")

    if not valid.any():
        source = pose_source if chain is None else f"TF ({chain.describe()})"
        raise GpoccError(
            f"{path}: none of the {stamps.size} scans on {scan_topic} "
            f"({stamps[0]:.3f}..{stamps[-1]:.3f} s) has a pose from {source} within "
            f"max_pose_gap_s={sensor.max_pose_gap_s} s; {_no_pose_fix(chain, skipped)}")
    msg_min, msg_max = scans.range_limits
    range_min = sensor.range_min_m if sensor.range_min_m is not None else msg_min
    range_max = sensor.range_max_m if sensor.range_max_m is not None else msg_max
    if not (math.isfinite(range_min) and math.isfinite(range_max) and
            0.0 <= range_min < range_max):
        raise GpoccError(
            f"{path}: topic {scan_topic} gives range_min={range_min:.7g} and "
            f"range_max={range_max:.7g}, "
            "which are unusable; set sensors[].range_min_m and range_max_m in the config"
        )
    n_skipped = int(np.count_nonzero(~valid))
    for note in notes:
        if _ROUNDED in note or note in warned:
            continue  # rounding is no fault of the log: counted in `gpocc info` only
        log(f"note: {path}: sensor '{sensor.name}': {note}")
    if n_skipped > SKIP_WARNING_SHARE * stamps.size:
        reason, key, count = max(skipped, key=lambda r: r[2])
        log(f"warning: {path}: sensor '{sensor.name}': {n_skipped} of {stamps.size} scans "
            f"({100 * n_skipped / stamps.size:.0f}%) skipped, mostly ({count}) for {reason}; "
            f"raise {key} if the pose source is just slow")
    elif n_skipped:  # never a scan lost without a word
        for reason, key, count in skipped:
            log(f"note: {path}: sensor '{sensor.name}': {count} of {stamps.size} scans "
                f"skipped for {reason} (config key {key})")
    clocks = [timing.describe(scan_topic)] + [
        p.stamps_from for p in (series, odometry if chain is None else None)
        if p is not None and p.stamps_from]
    provenance = Provenance(pose_source=pose_source, frame_chain=chain_text,
                            covariance_source=cov.source, skipped=tuple(skipped),
                            notes=tuple(notes), stamps="; ".join(dict.fromkeys(clocks)))
    return ScanBatch(
        sensor=sensor.name,
        source=str(path),
        stamps=stamps[valid],
        angles=angles,
        ranges=ranges[valid],
        poses=poses[valid],
        pose_covariances=np.array(covariances[valid]),
        range_min=float(range_min),
        range_max=float(range_max),
        has_pose_covariance=has_cov,
        skipped_scans=n_skipped,
        provenance=provenance,
        # The bearing variance grown by the layouts' rounding (None: the entry as given).
        sensor_config=sensor if scans.layouts is not None else None,
    )
