"""TF: ``/tf`` and ``/tf_static`` as a time-indexed buffer of 3-D transforms.

Each TF edge ``parent -> child`` holds the pose of ``child`` in ``parent`` over time
(``tf2_msgs/msg/TFMessage`` in ROS 2 and MCAP, ``tf2_msgs/TFMessage`` or the older
``tf/tfMessage`` in ROS 1). :meth:`TfBuffer.lookup` chains the edges between two frames
at given stamps as tf2 does: each dynamic edge is interpolated between its two samples
bracketing the stamp (translation linear, rotation by slerp), static edges hold for all
time, and the 3-D transforms are composed before the result is projected to SE(2)
(x, y, yaw of the child's x axis).

Message repairs and rules (issue 13, class 4), counted in :class:`TfBuffer`:

* a quaternion whose norm is not 1 is normalised (a common rounding or hand-written
  static transform); an all-zero or non-finite one, or a non-finite translation, is an
  error naming the file, topic, stamp and field;
* a repeated stamp on one edge keeps the first transform and counts the rest, which is
  what tf2 does (``TF_REPEATED_DATA``);
* a frame given two different parents (e.g. two robots publishing an un-prefixed
  ``odom -> base_link`` on one ``/tf``) is unusable: chains through it are not served
  and the pose falls back to the pose topic.

Frame names lose a leading ``/`` (ROS 1 tf used ``/base_link``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gpocc.errors import GpoccError
from gpocc.io.scans import MAX_POSITION_M, position_in_range
from gpocc.io.timeline import brackets

TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")

#: Quaternions whose norm differs from 1 by more than this are counted as repaired.
QUATERNION_TOLERANCE = 1e-6


def frame_name(frame: str) -> str:
    """A frame id without the leading slash of ROS 1 tf."""
    return frame.lstrip("/")


def is_static_topic(topic: str) -> bool:
    return topic.rstrip("/").endswith("tf_static")


# --------------------------------------------------------------------------- quaternions


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) quaternions stored (x, y, z, w)."""
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ], axis=-1)


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(..., 3) vectors ``v`` rotated by unit quaternions ``q`` (..., 4)."""
    u, w = q[..., :3], q[..., 3:4]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


def quat_slerp(q0: np.ndarray, q1: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Spherical interpolation of (S, 4) unit quaternions at weights ``w`` (S,) in [0, 1]."""
    dot = np.sum(q0 * q1, axis=-1)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    dot = np.clip(np.abs(dot), -1.0, 1.0)
    theta = np.arccos(dot)
    small = theta < 1e-9
    sin = np.where(small, 1.0, np.sin(theta))
    a = np.where(small, 1.0 - w, np.sin((1.0 - w) * theta) / sin)
    b = np.where(small, w, np.sin(w * theta) / sin)
    q = a[:, None] * q0 + b[:, None] * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def yaw_of(q: np.ndarray) -> np.ndarray:
    """Heading (rad) of the rotated x axis projected on the ground plane, for (..., 4)."""
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def checked_quaternion(q: tuple[float, float, float, float], where: str) -> tuple[np.ndarray, bool]:
    """The unit quaternion (x, y, z, w) and whether it had to be normalised.

    Raises:
        GpoccError: a non-finite or all-zero quaternion (``where`` names file, topic,
            stamp and field).
    """
    arr = np.asarray(q, dtype=float)
    norm = float(np.linalg.norm(arr))
    if not np.isfinite(arr).all() or norm < 1e-9:
        raise GpoccError(
            f"{where}: the orientation quaternion {tuple(float(v) for v in arr)} is "
            f"{'not finite' if not np.isfinite(arr).all() else 'all zero'}, so it gives no "
            "rotation; fix the publisher or drop these messages (ros2 bag filter / rosbag filter)"
        )
    if abs(norm - 1.0) <= QUATERNION_TOLERANCE:
        return arr, False  # unit to rounding: kept bit for bit, as recorded
    return arr / norm, True


# --------------------------------------------------------------------------- buffer


@dataclass(frozen=True)
class Edge:
    """One TF edge: the pose of ``child`` in ``parent``.

    Attributes:
        stamps: (N,) seconds, strictly increasing (one row for a static edge).
        translations: (N, 3) metres.
        quaternions: (N, 4) unit (x, y, z, w).
    """

    parent: str
    child: str
    static: bool
    topic: str
    stamps: np.ndarray
    translations: np.ndarray
    quaternions: np.ndarray

    def label(self) -> str:
        return f"{self.parent}->{self.child}"

    def at(self, stamps: np.ndarray, max_gap_s: float) -> tuple[np.ndarray, np.ndarray,
                                                                  np.ndarray]:
        """Translations (S, 3), quaternions (S, 4) and served (S,) bool at ``stamps``.

        A dynamic edge serves a stamp equal to one of its samples, or between two samples
        at most ``max_gap_s`` apart.
        """
        s = stamps.shape[0]
        if self.static:
            return (np.broadcast_to(self.translations[0], (s, 3)).copy(),
                    np.broadcast_to(self.quaternions[0], (s, 4)).copy(), np.ones(s, bool))
        at = brackets(self.stamps, stamps, max_gap_s)
        t0, t1 = self.translations[at.before], self.translations[at.after]
        trans = t0 + at.weight[:, None] * (t1 - t0)
        quats = quat_slerp(self.quaternions[at.before], self.quaternions[at.after], at.weight)
        return trans, quats, at.served


@dataclass(frozen=True)
class Chain:
    """The edges from ``target`` to ``source``: (edge, upward) pairs, in order.

    ``upward`` edges are walked child to parent (their inverse is applied).
    """

    target: str
    source: str
    steps: tuple[tuple[Edge, bool], ...]

    def describe(self) -> str:
        """``map -> odom -> base_link -> laser (static)``-style text for ``gpocc info``."""
        parts = [self.target]
        for edge, upward in self.steps:
            nxt = edge.parent if upward else edge.child
            kind = "static" if edge.static else edge.topic
            parts.append(f"{nxt} ({kind}{', inverted' if upward else ''})")
        return " -> ".join(parts)

    def static_tail(self) -> int:
        """Index of the first step of the static run that ends the chain."""
        k = len(self.steps)
        while k > 0 and self.steps[k - 1][0].static and not self.steps[k - 1][1]:
            k -= 1
        return k

    def published_once(self) -> Edge | None:
        """The first dynamic edge with fewer than two messages: it serves no stamp but
        its own (interpolation needs two), where a transform that never changes belongs
        on /tf_static; None if there is none."""
        return next((e for e, _ in self.steps if not e.static and e.stamps.size < 2), None)

    def published_once_fix(self, what: str) -> str | None:
        """The fix for :meth:`published_once`'s edge, ``what`` naming the transform
        (``a mount``), or None if there is no such edge."""
        once = self.published_once()
        if once is None:
            return None
        return (f"TF {once.label()} on {once.topic} has {once.stamps.size} message: publish "
                f"{what} that never changes on /tf_static")

    def body_frame(self) -> str:
        """The frame the last dynamic edge moves (``base_link``): where the mount starts."""
        k = self.static_tail()
        if k == 0:
            return self.target
        edge, upward = self.steps[k - 1]
        return edge.parent if upward else edge.child


@dataclass(frozen=True)
class Lookup:
    """A chain evaluated at stamps: SE(2) poses (S, 3), served (S,), and the failing edge.

    ``missing`` (S,) holds, for unserved stamps, the label of the first dynamic edge
    without data there (empty string where served). ``upside_down`` (S,): the source's
    z axis points down. ``tilt_rad`` (S,): the angle between the source's x-y plane and
    the target's, 0..pi/2 (0 for a level frame, upside down or not).
    """

    poses: np.ndarray
    valid: np.ndarray
    missing: np.ndarray
    upside_down: np.ndarray
    tilt_rad: np.ndarray


@dataclass(frozen=True)
class TfBuffer:
    """All TF edges of one input, keyed by child frame; conflicting frames excluded."""

    edges: dict[str, Edge] = field(default_factory=dict)
    conflicts: dict[str, str] = field(default_factory=dict)
    normalised_quaternions: int = 0
    repeated_stamps: int = 0

    def __bool__(self) -> bool:
        return bool(self.edges)

    def frames(self) -> set[str]:
        return set(self.edges) | {e.parent for e in self.edges.values()}

    def parents(self, frame: str) -> list[str]:
        """``frame``'s parent, its parent's, ... up to a root, a frame of two parents
        (which has no edge here) or the frame before a cycle closes."""
        out: list[str] = []
        edge = self.edges.get(frame)
        while edge is not None and edge.parent != frame and edge.parent not in out:
            out.append(edge.parent)
            edge = self.edges.get(edge.parent)
        return out

    def _ancestors(self, frame: str) -> list[tuple[str, Edge | None]] | None:
        """[(frame, edge to its parent), ...] up to the root, or None through a conflict."""
        out: list[tuple[str, Edge | None]] = []
        seen = set()
        while True:
            if frame in self.conflicts:
                return None
            if frame in seen:
                return None  # a cycle: no usable chain
            seen.add(frame)
            edge = self.edges.get(frame)
            out.append((frame, edge))
            if edge is None:
                return out
            frame = edge.parent

    def chain(self, target: str, source: str) -> Chain | None:
        """The chain from ``target`` (e.g. ``map``) to ``source`` (the laser), or None."""
        target, source = frame_name(target), frame_name(source)
        if target not in self.frames() or source not in self.frames():
            return None
        up_t = self._ancestors(target)
        up_s = self._ancestors(source)
        if up_t is None or up_s is None:
            return None
        index_s = {f: i for i, (f, _) in enumerate(up_s)}
        common = next((i for i, (f, _) in enumerate(up_t) if f in index_s), None)
        if common is None:
            return None
        j = index_s[up_t[common][0]]
        steps: list[tuple[Edge, bool]] = [(e, True) for _, e in up_t[:common] if e is not None]
        steps += [(e, False) for _, e in reversed(up_s[:j]) if e is not None]
        return Chain(target, source, tuple(steps))

    def lookup(self, chain: Chain, stamps: np.ndarray, max_gap_s: float,
               start: int = 0, stop: int | None = None) -> Lookup:
        """``chain.steps[start:stop]`` composed at ``stamps`` (S,) seconds."""
        trans, quat, valid, missing = self.transforms(chain, stamps, max_gap_s, start, stop)
        poses = np.column_stack([trans[:, 0], trans[:, 1], yaw_of(quat)])
        # The rotated z axis pointing down: the scan turns clockwise in the map.
        up_z = 1.0 - 2.0 * (quat[:, 0] ** 2 + quat[:, 1] ** 2)
        return Lookup(poses, valid, missing, up_z < 0, np.arccos(np.clip(np.abs(up_z), 0, 1)))

    def transforms(self, chain: Chain, stamps: np.ndarray, max_gap_s: float,
                   start: int = 0, stop: int | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The full 3-D transforms of ``chain.steps[start:stop]`` at ``stamps`` (S,) s.

        Returns:
            ``(translations (S, 3) m, unit quaternions (S, 4) (x, y, z, w), valid (S,),
            missing (S,))``: a point ``p`` in ``chain.source`` is
            ``quat_rotate(q, p) + t`` in ``chain.target``; ``missing`` as in
            :class:`Lookup`.
        """
        s = stamps.shape[0]
        trans = np.zeros((s, 3))
        quat = np.tile([0.0, 0.0, 0.0, 1.0], (s, 1))
        valid = np.ones(s, bool)
        missing = np.full(s, "", dtype=object)
        for edge, upward in chain.steps[start:stop]:
            t, q, ok = edge.at(stamps, max_gap_s)
            if upward:  # inverse: (R^T, -R^T t)
                q = quat_conjugate(q)
                t = -quat_rotate(q, t)
            trans = trans + quat_rotate(quat, t)
            quat = quat_multiply(quat, q)
            missing = np.where(valid & ~ok, edge.label(), missing)
            valid &= ok
        quat /= np.linalg.norm(quat, axis=-1, keepdims=True)
        return trans, quat, valid, missing


@dataclass
class _EdgeAcc:
    parent: str
    topic: str
    static: bool
    stamps: list[float] = field(default_factory=list)
    translations: list[tuple[float, float, float]] = field(default_factory=list)
    quaternions: list[np.ndarray] = field(default_factory=list)


@dataclass
class TfCollector:
    """Accumulates TF messages while a bag is read; :meth:`build` gives the buffer."""

    path: Path
    edges: dict[str, _EdgeAcc] = field(default_factory=dict)
    conflicts: dict[str, str] = field(default_factory=dict)
    normalised: int = 0

    def add(self, msg: Any, topic: str, record_ns: int) -> None:
        static = is_static_topic(topic)
        for tf in msg.transforms:
            stamp = tf.header.stamp
            t = stamp.sec + stamp.nanosec * 1e-9
            if t == 0.0:
                t = record_ns * 1e-9
            parent, child = frame_name(tf.header.frame_id), frame_name(tf.child_frame_id)
            where = f"{self.path}: topic {topic} at t={t:.6f} s, transform {parent}->{child}"
            tr = tf.transform.translation
            xyz = (float(tr.x), float(tr.y), float(tr.z))
            if not position_in_range(*xyz):
                raise GpoccError(f"{where}: field transform.translation is {xyz}, not finite "
                                 f"or beyond {MAX_POSITION_M:g} m; fix the publisher or drop "
                                 "these messages")
            r = tf.transform.rotation
            q, repaired = checked_quaternion((r.x, r.y, r.z, r.w),
                                             f"{where}, field transform.rotation")
            self.normalised += int(repaired)
            acc = self.edges.get(child)
            if acc is None:
                acc = self.edges[child] = _EdgeAcc(parent, topic, static)
            elif acc.parent != parent:
                self.conflicts[child] = f"{acc.parent} ({acc.topic}) and {parent} ({topic})"
                continue
            if static:
                # A static edge is republished whole; the latest message wins.
                acc.static = True
                acc.stamps[:] = [t]
                acc.translations[:] = [xyz]
                acc.quaternions[:] = [q]
                continue
            acc.stamps.append(t)
            acc.translations.append(xyz)
            acc.quaternions.append(q)

    def build(self) -> TfBuffer:
        edges = {}
        repeated = 0
        for child, acc in self.edges.items():
            if not acc.stamps:
                continue
            stamps = np.asarray(acc.stamps)
            order = np.argsort(stamps, kind="stable")
            stamps, first = np.unique(stamps[order], return_index=True)
            keep = order[first]
            repeated += len(order) - len(keep)
            edges[child] = Edge(
                parent=acc.parent, child=child, static=acc.static, topic=acc.topic,
                stamps=stamps, translations=np.asarray(acc.translations, float)[keep],
                quaternions=np.asarray(acc.quaternions, float)[keep])
        return TfBuffer(edges, dict(self.conflicts), self.normalised, repeated)


def merge_buffers(buffers: list[TfBuffer]) -> TfBuffer:
    """One buffer from several TF topics (``/tf``, ``/tf_static``, ``/robot1/tf``, ...)."""
    edges: dict[str, Edge] = {}
    conflicts: dict[str, str] = {}
    for buf in buffers:
        conflicts.update(buf.conflicts)
        for child, edge in buf.edges.items():
            other = edges.get(child)
            if other is not None and other.parent != edge.parent:
                conflicts[child] = (f"{other.parent} ({other.topic}) and {edge.parent} "
                                    f"({edge.topic})")
            elif other is None or edge.static:
                edges[child] = edge
    return TfBuffer(edges, conflicts, sum(b.normalised_quaternions for b in buffers),
                    sum(b.repeated_stamps for b in buffers))
