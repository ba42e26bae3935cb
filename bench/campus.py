"""A campus-sized job built from the real CARMEN logs: building copies placed side by side.

``write_campus(folder)`` writes rotated and offset copies of ``intel.gfs.log`` (4) and
``freiburg-079-corrected.log`` (1) as CARMEN logs (FLASER lines only) on a 150 x 150 m
site, plus a config with one sensor entry per source log. 4 x 910 + 4791 = 8431 scans,
five buildings. The copies share nothing but the site frame: each is its own input file,
so scan ids, timestamps and sensors stay per building.

Run ``.venv/bin/python -m bench.campus OUT_DIR`` to write the files for a manual run.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import yaml

from .paths import FREIBURG, FREIBURG_CONFIG, INTEL, INTEL_CONFIG

# (source, file name, yaw rad, dx m, dy m): Intel's poses span about x -9..17, y -22..4 and
# Freiburg's x -24..12, y -8..7 (endpoints reach ~10 m further), so these centres keep the
# buildings apart and the site a little over 150 m on each side.
LAYOUT = (
    (INTEL, "intel_sw.log", 0.0, 0.0, 0.0),
    (INTEL, "intel_se.log", 0.5 * math.pi, 120.0, 0.0),
    (INTEL, "intel_nw.log", math.pi, 0.0, 120.0),
    (INTEL, "intel_ne.log", 1.5 * math.pi, 120.0, 120.0),
    (FREIBURG, "freiburg_centre.log", 0.0, 60.0, 60.0),
)


def transform_log(source: Path, target: Path, yaw: float, dx: float, dy: float) -> int:
    """Write ``source``'s FLASER lines with poses (laser and odometry) moved by the rigid
    transform (yaw rad, then dx, dy metres). Returns the number of scans."""
    c, s = math.cos(yaw), math.sin(yaw)
    scans = 0
    with source.open() as src, target.open("w") as dst:
        for line in src:
            tokens = line.split()
            if not tokens or tokens[0] != "FLASER":
                continue
            n = int(tokens[1])
            for at in (n + 2, n + 5):  # laser pose, then odometry pose
                x, y, th = (float(t) for t in tokens[at : at + 3])
                tokens[at] = f"{c * x - s * y + dx:.6f}"
                tokens[at + 1] = f"{s * x + c * y + dy:.6f}"
                tokens[at + 2] = f"{math.remainder(th + yaw, 2.0 * math.pi):.6f}"
            dst.write(" ".join(tokens) + "\n")
            scans += 1
    return scans


def write_campus(folder: Path) -> tuple[list[Path], Path, int]:
    """The campus logs and config in ``folder``: (log paths, config path, total scans)."""
    folder.mkdir(parents=True, exist_ok=True)
    logs, total = [], 0
    for source, name, yaw, dx, dy in LAYOUT:
        path = folder / name
        total += transform_log(source, path, yaw, dx, dy)
        logs.append(path)
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
