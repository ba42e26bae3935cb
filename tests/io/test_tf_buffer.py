"""The TF buffer alone: chains through inverted edges, interpolation, gaps, conflicts."""

from __future__ import annotations

import numpy as np
from rosbag_scenes import compose, inverse, quat

from gpocc.io.tf import Edge, TfBuffer, merge_buffers, quat_slerp


def edge(parent: str, child: str, stamps: list[float], poses: np.ndarray,
         static: bool = False) -> Edge:
    poses = np.atleast_2d(poses)
    return Edge(parent, child, static, "/tf_static" if static else "/tf", np.asarray(stamps),
                np.column_stack([poses[:, :2], np.full(len(poses), 0.3)]),
                np.array([quat(yaw=p[2]) for p in poses]))


def test_chain_through_a_common_ancestor_matches_se2_composition() -> None:
    # world -> map (static) and world -> odom -> base -> laser: map -> laser goes up to
    # world through an inverted edge, then down.
    w_map = np.array([2.0, -1.0, 0.7])
    stamps = [0.0, 1.0, 2.0]
    odom = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.4], [1.5, 1.5, 1.2]])
    base = np.array([[0.2, 0.0, 0.1], [0.3, 0.1, 0.2], [0.1, -0.2, -0.3]])
    mount = np.array([0.25, -0.05, 3.0])
    buf = TfBuffer({
        "map": edge("world", "map", [0.0], w_map, static=True),
        "odom": edge("world", "odom", stamps, odom),
        "base": edge("odom", "base", stamps, base),
        "laser": edge("base", "laser", [0.0], mount, static=True),
    })
    chain = buf.chain("map", "laser")
    assert chain.describe() == ("map -> world (static, inverted) -> odom (/tf) -> base (/tf) -> "
                                "laser (static)")
    assert chain.body_frame() == "base"
    got = buf.lookup(chain, np.array(stamps), max_gap_s=1.5)
    want = compose(compose(compose(inverse(w_map), odom), base), mount)
    assert got.valid.all()
    np.testing.assert_allclose(got.poses[:, :2], want[:, :2], atol=1e-12)
    np.testing.assert_allclose(np.angle(np.exp(1j * (got.poses[:, 2] - want[:, 2]))), 0,
                               atol=1e-12)
    # Between samples each edge is interpolated (yaw by slerp); beyond a gap, not served.
    mid = buf.lookup(chain, np.array([0.5, 2.5]), max_gap_s=1.5)
    assert mid.valid.tolist() == [True, False] and mid.missing[1] == "world->odom"
    half = lambda a: (a[0] + a[1]) / 2  # noqa: E731
    want_mid = compose(compose(compose(inverse(w_map), half(odom)[None]), half(base)[None]),
                       mount)
    np.testing.assert_allclose(mid.poses[0], want_mid[0], atol=1e-12)
    assert buf.lookup(chain, np.array([0.5]), max_gap_s=0.5).valid.tolist() == [False]


def test_conflicting_parents_break_the_chain() -> None:
    a = TfBuffer({"base": edge("odom", "base", [0.0], np.zeros(3), static=True)})
    b = TfBuffer({"base": edge("other_odom", "base", [0.0], np.zeros(3), static=True),
                  "laser": edge("base", "laser", [0.0], np.zeros(3), static=True)})
    merged = merge_buffers([a, b])
    assert "base" in merged.conflicts
    assert merged.chain("odom", "laser") is None


def test_slerp_is_uniform_in_angle() -> None:
    q0 = np.array([quat(yaw=0.2)] * 5)
    q1 = np.array([quat(yaw=2.6)] * 5)
    w = np.linspace(0, 1, 5)
    q = quat_slerp(q0, q1, w)
    yaw = 2 * np.arctan2(q[:, 2], q[:, 3])
    np.testing.assert_allclose(yaw, 0.2 + 2.4 * w, atol=1e-12)
