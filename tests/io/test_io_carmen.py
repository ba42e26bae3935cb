"""CARMEN log reader: inline logs with known geometry, corrupt lines, the real Intel log."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from gpocc.config import SensorConfig
from gpocc.errors import GpoccError
from gpocc.io.carmen import describe_carmen, read_carmen

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "carmen"

SENSOR = SensorConfig(name="lab", pose_covariance=((0.01, 0, 0), (0, 0.02, 0), (0, 0, 0.003)))


def _flaser(ranges: list[float], pose: tuple[float, float, float], stamp: float) -> str:
    values = " ".join(str(r) for r in ranges)
    x, y, th = pose
    return (f"FLASER {len(ranges)} {values} {x} {y} {th} {x + 5} {y - 5} {th + 1} "
            f"{stamp} pippo {stamp}")


def _write(tmp_path: Path, lines: list[str], name: str = "lab.log") -> Path:
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def test_inline_flaser(tmp_path: Path) -> None:
    # Four beams at -90, -45, 0 and 45 degrees (the README's -pi/2 + i*pi/N); the robot at
    # (1, 2) facing +y, so the beams point +x, diagonally, +y and diagonally.
    lines = [
        "# message formats defined: PARAM SYNC ODOM FLASER",
        "PARAM robot_use_laser on 0.1 host 0.1",
        "ODOM 0 0 0 0 0 0 0.2 pippo 0.2",
        _flaser([1.0, 2.0, 3.0, 81.83], (1.0, 2.0, math.pi / 2), 10.5),
        "NEFF 12.3",
        _flaser([4.0, 81.9, 5.0, 0.5], (-1.0, 0.5, 0.0), 11.25),
    ]
    batch = read_carmen(_write(tmp_path, lines), SENSOR)
    assert (batch.n_scans, batch.n_beams, batch.sensor) == (2, 4, "lab")
    np.testing.assert_allclose(np.degrees(batch.angles), [-90, -45, 0, 45])
    np.testing.assert_array_equal(batch.ranges, [[1, 2, 3, np.inf], [4, np.inf, 5, 0.5]])
    np.testing.assert_allclose(batch.poses, [[1, 2, math.pi / 2], [-1, 0.5, 0]])
    np.testing.assert_allclose(batch.stamps, [10.5, 11.25])  # monotonic logger stamps
    assert batch.range_max == pytest.approx(81.8) and batch.range_min == 0.0
    assert not batch.has_pose_covariance
    np.testing.assert_allclose(batch.pose_covariances, [SENSOR.pose_covariance_matrix] * 2)
    # Endpoints by the README's formula: first scan, beam 0 hits (2, 2), beam 2 (1, 5).
    p, r, a = batch.poses[0], batch.ranges[0], batch.angles
    ends = p[:2] + r[:3, None] * np.column_stack([np.cos(p[2] + a[:3]), np.sin(p[2] + a[:3])])
    np.testing.assert_allclose(ends[[0, 2]], [[2, 2], [1, 5]], atol=1e-12)

    contents = describe_carmen(tmp_path / "lab.log")
    assert contents.counts == {"PARAM": 1, "ODOM": 1, "FLASER": 2, "NEFF": 1}
    assert (contents.start_s, contents.end_s) == (10.5, 11.25)


def test_stamps_fall_back_to_line_order(tmp_path: Path) -> None:
    lines = [_flaser([1.0] * 6, (0, 0, 0), t) for t in (5.0, 4.0, 6.0)]
    batch = read_carmen(_write(tmp_path, lines), SENSOR)
    np.testing.assert_array_equal(batch.stamps, [0.0, 1.0, 2.0])


def test_describe_says_when_the_scans_are_timed_by_line_order(tmp_path: Path) -> None:
    """`gpocc info` printed the logger stamps' span while every command timed the scans
    by line order; a FLASER and a ROBOTLASER1 line of one scan (equal stamps) are not
    out of order."""
    lines = [_flaser([1.0] * 6, (0, 0, 0), t) for t in (5.0, 4.0, 6.0)]
    assert describe_carmen(_write(tmp_path, lines)).out_of_order == 1
    robot = ("ROBOTLASER1 0 -1.0 2.0 1.0 20.0 0.01 0 3 1.5 25.0 2.5 2 0.1 0.2 "
             "3.0 4.0 0.5 2.9 4.0 0.5 0 0 0 0 0 {t} host {t}")
    both = [line for t in (1.0, 2.0, 3.0)
            for line in (_flaser([1.0] * 6, (0, 0, 0), t), robot.format(t=t))]
    assert describe_carmen(_write(tmp_path, both, "both.log")).out_of_order == 0
    # The reader reads FLASER lines where there are any: their order decides.
    mixed = [line for t, u in ((1.0, 1.0), (3.0, 2.0), (2.0, 3.0))
             for line in (_flaser([1.0] * 6, (0, 0, 0), t), robot.format(t=u))]
    assert describe_carmen(_write(tmp_path, mixed, "mixed.log")).out_of_order == 1
    from typer.testing import CliRunner

    from gpocc.cli import app

    shown = CliRunner().invoke(app, ["info", str(tmp_path / "lab.log")])
    assert "1 logger stamp does not increase, so scans are timed by line order" in shown.output


def test_config_range_limits_and_odd_beam_count(tmp_path: Path) -> None:
    sensor = SensorConfig(range_min_m=0.2, range_max_m=30.0)
    batch = read_carmen(_write(tmp_path, [_flaser([1.0] * 181, (0, 0, 0), 1.0)]), sensor)
    assert (batch.range_min, batch.range_max) == (0.2, 30.0)
    # 181 beams cover both ends of the 180 degree fan, one degree apart.
    np.testing.assert_allclose(np.degrees(batch.angles[[0, 90, 180]]), [-90, 0, 90])


def _robotlaser(start: float, res: float, ranges: list[float], stamp: float) -> str:
    """A ROBOTLASER1 line of ``ranges`` from ``start`` every ``res`` rad, at the origin."""
    values = " ".join(str(r) for r in ranges)
    # ... n ranges, m = 0 remissions, laser pose, robot pose, tv rv fwd side turn, stamps
    return (f"ROBOTLASER1 0 {start} {res * (len(ranges) - 1)} {res} 20.0 0.01 0 "
            f"{len(ranges)} {values} 0 0 0 0 0 0 0 0 0 0 0 0 {stamp} host {stamp}")


def test_flaser_beam_counts_that_change_share_one_layout(tmp_path: Path, capfd) -> None:
    """181 beams a degree apart and 360 half a degree apart (both fans from -90 degrees):
    one layout of 361 bearings half a degree apart, each beam on its own bearing exactly,
    so the bearing variance is unchanged; a note says so."""
    first, second = 1.0 + 0.01 * np.arange(181), 5.0 + 0.01 * np.arange(360)
    lines = [_flaser(list(first), (0, 0, 0), 1.0), _flaser(list(second), (0, 0, 0), 2.0)]
    batch = read_carmen(_write(tmp_path, lines), SENSOR)
    np.testing.assert_allclose(batch.angles, np.radians(-90.0 + 0.5 * np.arange(361)),
                               atol=1e-12)
    np.testing.assert_array_equal(batch.ranges[0, ::2], first)
    assert np.isnan(batch.ranges[0, 1::2]).all()
    np.testing.assert_array_equal(batch.ranges[1, :360], second)
    assert np.isnan(batch.ranges[1, 360])
    assert batch.sensor_config.bearing_variance_deg2 == pytest.approx(
        SENSOR.bearing_variance_deg2, abs=1e-20)
    assert "(181-360 beams): beams placed on one layout of 361 bearings 0.5 deg apart, each " \
        "on its own bearing\n" in capfd.readouterr().err


def test_robotlaser1_fans_that_change_share_one_layout(tmp_path: Path, capfd) -> None:
    """Resolutions 0.5 and 0.3 rad from -1 rad: the finer step, each beam on the nearest
    bearing (brute force), and the shifts' mean square added to the bearing variance."""
    lines = [_robotlaser(-1.0, 0.5, [1.0, 2.0, 3.0, 4.0, 5.0], 1.0),
             _robotlaser(-1.0, 0.3, [6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0], 2.0)]
    batch = read_carmen(_write(tmp_path, lines, "fans.clf"), SENSOR)
    np.testing.assert_allclose(np.diff(batch.angles), 0.3)
    shifts = []
    for row, (start, res, values) in enumerate([(-1.0, 0.5, [1.0, 2.0, 3.0, 4.0, 5.0]),
                                                (-1.0, 0.3, [6.0 + k for k in range(7)])]):
        bearings = start + res * np.arange(len(values))
        nearest = np.abs(bearings[:, None] - batch.angles[None, :]).argmin(axis=1)
        np.testing.assert_array_equal(batch.ranges[row, nearest], values)
        assert np.count_nonzero(~np.isnan(batch.ranges[row])) == len(values)
        shifts.append(bearings - batch.angles[nearest])
    grown = SENSOR.bearing_variance_deg2 + np.degrees(1.0) ** 2 * np.mean(
        np.concatenate(shifts) ** 2)
    assert batch.sensor_config.bearing_variance_deg2 == pytest.approx(grown)
    assert "fans.clf: the beam layout varies from scan to scan (5-7 beams)" in (
        capfd.readouterr().err)


def test_robotlaser1(tmp_path: Path) -> None:
    # type start fov res max_range accuracy remission_mode n ranges m remissions
    # laser pose, robot pose, tv rv fwd side turn, ipc_ts host logger_ts
    line = ("ROBOTLASER1 0 -1.0 2.0 1.0 20.0 0.01 0 3 1.5 25.0 2.5 2 0.1 0.2 "
            "3.0 4.0 0.5 2.9 4.0 0.5 0 0 0 0 0 7.0 host 7.0")
    batch = read_carmen(_write(tmp_path, [line], "robot.clf"), SENSOR)
    np.testing.assert_allclose(batch.angles, [-1.0, 0.0, 1.0])
    np.testing.assert_array_equal(batch.ranges, [[1.5, np.inf, 2.5]])  # 25 >= max range 20
    np.testing.assert_allclose(batch.poses, [[3.0, 4.0, 0.5]])  # the laser pose
    assert batch.range_max == 20.0


@pytest.mark.parametrize(
    ("bad", "why"),
    [
        ("FLASER 4 1 2 3 0 0 0 0 0 0 1.0 pippo 1.0", "needs 15 tokens, got 14 .truncated"),
        ("FLASER 4 1 2 3 4 5 0 0 0 0 0 0 1.0 pippo 1.0", "needs 15 tokens, got 16 .extra"),
        ("FLASER 4 1 2 3 x 0 0 0 0 0 0 1.0 pippo 1.0", "non-numeric value 'x'"),
        ("FLASER four 1 2 3 4 0 0 0 0 0 0 1.0 pippo 1.0", "beam count"),
        # 11 tokens, as many as 0 beams need: said "needs 11 tokens, got 11" before
        ("FLASER 0 0 0 0 0 0 0 1.0 pippo 1.0", "at least one beam"),
        ("FLASER 4 1 2 3 4 nan 0 0 0 0 0 1.0 pippo 1.0", "pose is not finite"),
        # finite, but its beams' samples would overflow (found by make fuzz)
        ("FLASER 4 1 2 3 4 0 1.8e188 0 0 0 0 1.0 pippo 1.0", "coordinate beyond 1e\\+08 m"),
    ],
)
def test_corrupt_line_names_file_and_line(tmp_path: Path, bad: str, why: str) -> None:
    lines = [_flaser([1.0] * 4, (0, 0, 0), 0.5), "ODOM 0 0 0 0 0 0 0.6 pippo 0.6", bad]
    path = _write(tmp_path, lines, "broken.log")
    with pytest.raises(GpoccError, match=rf"broken\.log: line 3: .*{why}"):
        read_carmen(path, SENSOR)


def test_unusable_files(tmp_path: Path) -> None:
    cases = {
        "empty.log": b"",
        "blank.log": b"\n  \n",
        "binary.log": bytes(range(256)),
        "odom_only.log": b"ODOM 0 0 0 0 0 0 0.1 pippo 0.1\n",
        # A second laser's fan 2 rad on, with a finer resolution: no common layout.
        "two_lasers.clf": (_robotlaser(-1.0, 0.5, [1.0] * 5, 1) + "\n"
                           + _robotlaser(2.0, 0.25, [1.0] * 5, 2) + "\n").encode(),
    }
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(GpoccError, match=name.replace(".", r"\.")):
            read_carmen(tmp_path / name, SENSOR)


def _endpoint_extent(batch) -> tuple[float, float]:
    """Spread of the hit endpoints between their 0.5 and 99.5 percentiles, metres.

    The README's extents are of this robust kind: a few stray long readings lie outside.
    """
    hit = np.isfinite(batch.ranges)
    phi = batch.poses[:, 2:3] + batch.angles[None, :]
    x = batch.poses[:, 0:1] + batch.ranges * np.cos(phi)
    y = batch.poses[:, 1:2] + batch.ranges * np.sin(phi)
    lo, hi = np.percentile(np.column_stack([x[hit], y[hit]]), [0.5, 99.5], axis=0)
    return float(hi[0] - lo[0]), float(hi[1] - lo[1])


@pytest.mark.parametrize(
    ("name", "scans", "beams", "extent"),
    [
        ("intel.gfs.log", 910, 180, (28.7, 28.6)),
        ("freiburg-079-corrected.log", 4791, 360, (37.5, 15.6)),
    ],
)
def test_real_logs(name: str, scans: int, beams: int, extent: tuple[float, float]) -> None:
    path = DATA / name
    if not path.is_file():
        pytest.skip(f"real data absent: {path}")
    batch = read_carmen(path, SensorConfig(name="real"))
    assert (batch.n_scans, batch.n_beams) == (scans, beams)
    assert np.all(np.diff(batch.stamps) > 0)
    assert np.isfinite(batch.poses).all()
    # No-return readings became +inf and nothing else is at or above 81.8 m.
    assert np.isposinf(batch.ranges).any()
    assert np.nanmax(batch.ranges[np.isfinite(batch.ranges)]) < 81.8
    # The README's extent of the endpoints (computed independently of this reader); a
    # wrong bearing convention (clockwise, or a quarter turn off) changes it by metres.
    np.testing.assert_allclose(_endpoint_extent(batch), extent, atol=0.15)


def test_an_upside_down_mount_mirrors_the_bearings(tmp_path: Path) -> None:
    """Four beams at -90, -45, 0, 45 degrees from a laser at the origin facing +x: upside
    down, the first beam points to +y, not -y (its endpoint is where samples put it)."""
    from dataclasses import replace

    from gpocc.config import MountConfig
    from gpocc.samples.beam_rules import beam_points, laser_poses, mount_vector

    log = _write(tmp_path, [_flaser([2.0] * 4, (0, 0, 0), 1.0)])
    level = read_carmen(log, SENSOR)
    sensor = replace(SENSOR, mount=MountConfig(upside_down=True))
    flipped = read_carmen(log, sensor)
    np.testing.assert_allclose(np.degrees(flipped.angles), [90, 45, 0, -45])
    np.testing.assert_array_equal(flipped.angles, -level.angles)
    lasers = laser_poses(flipped.poses, mount_vector(sensor))
    ends = beam_points(lasers[:, None, :], flipped.angles[None, :], flipped.ranges)
    root = math.sqrt(2.0)
    np.testing.assert_allclose(ends[0], [[0, 2], [root, root], [2, 0], [root, -root]],
                               atol=1e-12)


def test_describe_counts_first_tokens_and_stamps_as_whole_line_splitting_does(tmp_path):
    # describe_carmen looks at each line's first and last tokens only. Oracle: the
    # whole-line split, on odd whitespace, comments, short and malformed lines.
    lines = ["FLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 12.5 host 10.25",
             "  \tFLASER 1 1.0 0 0 0 0 0 0 11.0 host 9.5  \t",
             "ODOM 0 0 0 0 0 0 7.0 host 8.0",
             "# FLASER 1 1 0 0 0 0 0 0 1 host 1.0",
             "#comment",
             "",
             "   ",
             "FLASER",
             "ROBOTLASER1 0 0 0 0 0 0 0 host 11.75\r",
             "FLASER 1 1 0 0 0 0 0 0 1 host notanumber",
             "PARAM robot_front_laser_max 50.0",
             "\tODOM\t1\t2\t3\t0\t0\t0\t7.0\thost\t3.5"]
    path = tmp_path / "odd.log"
    path.write_text("\n".join(lines) + "\n")
    counts: dict[str, int] = {}
    stamps = []
    for line in lines:
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        counts[tokens[0]] = counts.get(tokens[0], 0) + 1
        if tokens[0] in ("FLASER", "ROBOTLASER1"):
            try:
                stamps.append(float(tokens[-1]))
            except ValueError:
                pass
    contents = describe_carmen(path)
    assert contents.counts == counts
    assert (contents.start_s, contents.end_s) == (min(stamps), max(stamps))


# Tokens float() reads, in the spellings logs use: what the compiled reader must turn into
# the very same doubles.
_TOKENS = ["0", "-0.0", "1", "+2.5", ".5", "5.", "1e3", "1E-3", "-7.25e+02", "81.83",
           "3.141592653589793238462643", "1e-310", "1.7976931348623157e308", "inf", "-inf",
           "Infinity", "nan", "0.1000000000000000055511151231257827"]


def test_parse_rows_reads_what_float_reads() -> None:
    from gpocc.compiled import parse_rows

    rng = np.random.default_rng(7)
    values = np.concatenate([rng.normal(size=3000) * 10.0 ** rng.integers(-300, 300, 3000),
                             rng.uniform(0, 82, 3000)])
    tokens = [repr(float(v)) for v in values] + [f"{v:.3f}" for v in values] + _TOKENS * 10
    tokens = [tokens[i] for i in rng.permutation(len(tokens))][: len(tokens) // 6 * 6]
    rows = [tokens[i:i + 6] for i in range(0, len(tokens), 6)]
    blanks = [" ", "  ", "\t", " \t "]
    text = "\n".join(rng.choice(blanks) + rng.choice(blanks).join(r) + rng.choice(blanks)
                     for r in rows)
    got = parse_rows(text.encode(), 6, len(rows))
    want = np.array([[float(t) for t in r] for r in rows])
    assert got is not None
    assert np.array_equal(got.view(np.int64)[~np.isnan(want)], want.view(np.int64)[~np.isnan(want)])
    assert np.array_equal(np.isnan(got), np.isnan(want))


@pytest.mark.parametrize(("text", "lines"), [
    ("1 2 3\n4 5", 2),          # a line short
    ("1 2 3\n4 5 6 7", 2),      # a line long
    ("1 2 3", 2),               # a line missing
    ("1 2 3\n4 5 6\n7", 2),     # text after the last line
    ("1 2 3\x00", 1), ("1 2 3\x00 9", 1), ("1 2\x00 3", 1),  # a NUL
    ("1 2 0x10", 1), ("1 2 1e", 1), ("1 2 1,5", 1), ("1 2 nan(1)", 1), ("1 2 .", 1),
    ("1 2 1-2", 1), ("1 2 -", 1), ("1 2 infx", 1),
])
def test_parse_rows_refuses_what_it_cannot_read_as_float_does(text: str, lines: int) -> None:
    from gpocc.compiled import parse_rows

    assert parse_rows(text.encode(), 3, lines) is None
    assert parse_rows(b"1 2 3\n4 5 6\n \n", 3, 2) is not None  # trailing blank lines


def _paths_agree(path: Path) -> None:
    """The compiled path (which must be taken) and the token-by-token path (float of each
    token, the oracle) read the same scans: line numbers, ranges, bearings, poses, logger
    stamps and the no-return range, bit for bit."""
    from gpocc.io import carmen

    lines = carmen._lines(path)
    fast, slow = carmen._flaser_table(lines), carmen._scan_table(path, lines)
    assert fast is not None
    assert fast.linenos == slow.linenos and fast.no_return_m == slow.no_return_m
    for name in ("ranges", "angles", "poses", "logger_stamps"):
        a, b = getattr(fast, name), getattr(slow, name)
        assert a.shape == b.shape and np.array_equal(a.view(np.int64), b.view(np.int64)), name


def test_the_compiled_reader_gives_the_token_readers_scans(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    lines = ["# a comment", "PARAM robot_name pippo", ""]
    for k in range(50):
        ranges = [float(v) for v in rng.uniform(0.1, 90.0, 7)]
        lines.append(_flaser(ranges, tuple(rng.normal(size=3)), 0.1 * k + 1))
        lines.append(f"ODOM {k} 0 0 0 0 0 {k} pippo {k}")
    lines[10] = lines[10].replace(" ", "\t", 5).replace(" ", "   ", 3)  # other blanks
    lines[12] = lines[12] + "  \r"
    path = _write(tmp_path, lines)
    _paths_agree(path)
    batch = read_carmen(path, SENSOR)
    assert batch.n_scans == 50


@pytest.mark.parametrize("name", ["intel.gfs.log", "freiburg-079-corrected.log"])
def test_the_compiled_reader_gives_the_token_readers_scans_of_real_logs(name: str) -> None:
    path = DATA / name
    if not path.is_file():
        pytest.skip(f"real data absent: {path}")
    _paths_agree(path)


@pytest.mark.parametrize(("bad", "why"), [
    # A NUL ended C's text: the rest of the line was dropped instead of refused.
    ("FLASER 4 1 2 3 4 0 0 0 0 0 0.0\x00 7 8 9 1.0 pippo 1.0", "needs 15 tokens, got 18"),
    ("FLASER 4 1 2 3 4 0 0 0 0 0 0.0\x00 1.0 pippo 1.0", "non-numeric value"),
    # A vast beam count must not reach an allocation (the token path names the count).
    ("FLASER 1000000000000 1 2 0 0 0 0 0 0 1 pippo 1", "needs 1000000000011 tokens"),
    ("FLASER 99999999999999999999999 1 2 0 0 0 0 0 0 1 pippo 1", "needs"),
])
def test_lines_the_compiled_path_refuses_get_the_token_paths_error(tmp_path: Path, bad: str,
                                                                   why: str) -> None:
    from gpocc.io import carmen

    path = _write(tmp_path, [_flaser([1.0] * 4, (0, 0, 0), 0.5), bad], "odd.log")
    assert carmen._flaser_table(carmen._lines(path)) is None
    with pytest.raises(GpoccError, match=rf"odd\.log: line 2: .*{why}"):
        read_carmen(path, SENSOR)


def test_logs_read_without_the_compiled_loops(tmp_path: Path, monkeypatch) -> None:
    import sys

    path = _write(tmp_path, [_flaser([1.0, 2.0, 3.0], (0, 0, 0), k + 1.0) for k in range(3)])
    want = read_carmen(path, SENSOR)
    monkeypatch.setitem(sys.modules, "gpocc.compiled", None)  # importing it fails
    got = read_carmen(path, SENSOR)
    assert np.array_equal(got.ranges, want.ranges) and np.array_equal(got.poses, want.poses)
