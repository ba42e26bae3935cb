"""Sites of many buildings built from the real CARMEN logs: rotated and offset copies of
``intel.gfs.log`` and ``freiburg-079-corrected.log`` placed side by side.

``write_campus(folder)`` writes the campus: 4 Intel copies and 1 of Freiburg 079 as CARMEN
logs (FLASER lines only) on a 150 x 150 m site, plus a config with one sensor entry per
source log. 4 x 910 + 4791 = 8431 scans, five buildings. ``grid_layout`` places N x N
buildings on a square grid (the city of ``bench/city.py``) and ``write_site`` writes any
layout, optionally of a subset of each log's scans. The copies share nothing but the site
frame: each is its own input file, so scan ids, timestamps and sensors stay per building.

Run ``.venv/bin/python -m bench.campus OUT_DIR`` to write the campus for a manual run.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
import yaml

from .paths import FREIBURG, FREIBURG_CONFIG, INTEL, INTEL_CONFIG


@dataclass(frozen=True)
class Building:
    """One copy of a source log: its poses rotated by ``yaw`` (rad) about the map origin,
    then moved by (``dx``, ``dy``) metres, written to ``name``."""

    source: Path
    name: str
    yaw: float
    dx: float
    dy: float

    def apply(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) points of the source log's frame in the site frame."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        x, y = points[:, 0], points[:, 1]
        return np.column_stack([c * x - s * y + self.dx, s * x + c * y + self.dy])


# Intel's poses span about x -9..17, y -22..4 and Freiburg's x -24..12, y -8..7 (endpoints
# reach ~10 m further), so these centres keep the buildings apart and the site a little
# over 150 m on each side.
LAYOUT = (
    Building(INTEL, "intel_sw.log", 0.0, 0.0, 0.0),
    Building(INTEL, "intel_se.log", 0.5 * math.pi, 120.0, 0.0),
    Building(INTEL, "intel_nw.log", math.pi, 0.0, 120.0),
    Building(INTEL, "intel_ne.log", 1.5 * math.pi, 120.0, 120.0),
    Building(FREIBURG, "freiburg_centre.log", 0.0, 60.0, 60.0),
)

#: Centres of the source logs' beam endpoints (metres): a grid building turns about it.
#: Intel's endpoints lie within 20 m of it (x -19.9..18.8, y -23.2..12.8) and Freiburg's
#: within 23 m (x -24.6..20.1, y -8.2..8.1).
CENTRES = {INTEL.name: (-0.5, -5.0), FREIBURG.name: (-2.2, 0.0)}


def grid_layout(side: int, spacing_m: float) -> list[Building]:
    """``side`` x ``side`` buildings ``spacing_m`` apart (centre to centre), the grid's
    south-west building centred on the origin. Every fourth is Freiburg 079 (the others
    Intel), so one building is Intel and four hold one Freiburg; each is turned by a
    multiple of 90 degrees (so its cells stay aligned with the map's) about its centre.
    Both buildings' endpoints lie within 23 m of their centre: at 62.5 m (8 x 8 on 500 m)
    neighbours stay at least 16 m apart."""
    out = []
    for k in range(side * side):
        row, col = divmod(k, side)
        source = FREIBURG if k % 4 == 3 else INTEL
        yaw = 0.5 * math.pi * ((row + 2 * col) % 4)
        cx, cy = CENTRES[source.name]
        c, s = math.cos(yaw), math.sin(yaw)
        gx, gy = col * spacing_m, row * spacing_m
        out.append(Building(source, f"b{k:03d}_{source.name.split('-')[0].split('.')[0]}.log",
                            yaw, gx - (c * cx - s * cy), gy - (s * cx + c * cy)))
    return out


@cache
def flaser_lines(source: Path) -> tuple[tuple[str, ...], ...]:
    """The tokens of each ``FLASER`` line of ``source``, in order (the reader's scans)."""
    with source.open() as src:
        return tuple(tuple(line.split()) for line in src if line.startswith("FLASER "))


def transform_lines(lines: Sequence[Sequence[str]], yaw: float, dx: float,
                    dy: float) -> list[str]:
    """FLASER lines (tokens) with poses (laser and odometry) moved by the rigid transform
    (yaw rad, then dx, dy metres), as text lines."""
    c, s = math.cos(yaw), math.sin(yaw)
    out = []
    for tokens in lines:
        tokens = list(tokens)
        n = int(tokens[1])
        for at in (n + 2, n + 5):  # laser pose, then odometry pose
            x, y, th = (float(t) for t in tokens[at : at + 3])
            tokens[at] = f"{c * x - s * y + dx:.6f}"
            tokens[at + 1] = f"{s * x + c * y + dy:.6f}"
            tokens[at + 2] = f"{math.remainder(th + yaw, 2.0 * math.pi):.6f}"
        out.append(" ".join(tokens) + "\n")
    return out


def transform_log(source: Path, target: Path, yaw: float, dx: float, dy: float) -> int:
    """Write ``source``'s FLASER lines with poses moved by the rigid transform (yaw rad,
    then dx, dy metres). Returns the number of scans."""
    lines = transform_lines(flaser_lines(source), yaw, dx, dy)
    target.write_text("".join(lines))
    return len(lines)


def write_site(folder: Path, layout: Sequence[Building],
               scans: dict[str, np.ndarray] | None = None) -> tuple[list[Path], int]:
    """Each building of ``layout`` as a CARMEN log in ``folder``: (log paths, total scans).
    ``scans`` maps a source log's file name to the indices of its FLASER lines to keep
    (default: all)."""
    folder.mkdir(parents=True, exist_ok=True)
    logs, total = [], 0
    for b in layout:
        lines = flaser_lines(b.source)
        if scans is not None:
            lines = [lines[i] for i in scans[b.source.name]]
        text = transform_lines(lines, b.yaw, b.dx, b.dy)
        path = folder / b.name
        path.write_text("".join(text))
        logs.append(path)
        total += len(text)
    return logs, total


def write_campus(folder: Path) -> tuple[list[Path], Path, int]:
    """The campus logs and config in ``folder``: (log paths, config path, total scans)."""
    logs, total = write_site(folder, LAYOUT)
    config = {}
    for base, name in ((INTEL_CONFIG, "intel"), (FREIBURG_CONFIG, "freiburg")):
        data = yaml.safe_load(base.read_text())
        sensor = data["sensors"][0]
        sensor["name"] = name
        sensor["inputs"] = [f"{name}_*.log"]
        config.setdefault("sensors", []).append(sensor)
        config.setdefault("seed", data.get("seed", 0))
        config.setdefault("samples", data.get("samples", {}))
        config.setdefault("map", data.get("map", {}))
    # Label votes are counted per cell; the buildings do not overlap, so each keeps its own.
    path = folder / "campus.yaml"
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return logs, path, total


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python -m bench.campus OUT_DIR")
    logs, cfg, scans = write_campus(Path(sys.argv[1]))
    print(f"{scans} scans in {len(logs)} logs; config {cfg}")
