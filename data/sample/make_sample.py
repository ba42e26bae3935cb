"""Cut scans 240-289 of the Intel Research Lab CARMEN log into data/sample/intel_sample.mcap.

Run from the repository root, with the shared data beside it:

    .venv/bin/python data/sample/make_sample.py [--log ../shared/data/carmen/intel.gfs.log]

The poses get the covariance of the ``intel`` sensor in data/sample/sample.yaml; stamps are
the CARMEN reader's (line order: scan k of the log at k seconds).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from gpocc.config import load_config
from gpocc.io.bags import write_bag
from gpocc.io.carmen import read_carmen

HERE = Path(__file__).resolve().parent
FIRST, LAST = 240, 289  # inclusive scan indices (0-based FLASER line order)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default_log = HERE.parents[2] / "shared" / "data" / "carmen" / "intel.gfs.log"
    parser.add_argument("--log", type=Path, default=default_log)
    parser.add_argument("--out", type=Path, default=HERE / "intel_sample.mcap")
    args = parser.parse_args()

    sensor = load_config(HERE / "sample.yaml").sensors[0]
    batch = read_carmen(args.log, sensor)
    cut = slice(FIRST, LAST + 1)
    sample = replace(
        batch,
        source=str(args.out),
        stamps=batch.stamps[cut],
        ranges=batch.ranges[cut],
        poses=batch.poses[cut],
        pose_covariances=batch.pose_covariances[cut],
    )
    write_bag(args.out, [sample], [(sensor.scan_topic, sensor.pose_topic)], "mcap", force=True)
    print(f"wrote {args.out}: scans {FIRST}..{LAST} ({sample.n_scans} x {sample.n_beams} beams)")


if __name__ == "__main__":
    main()
