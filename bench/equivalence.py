"""Behaviour check for refactors: the Freiburg samples and log-odds grid of one source tree.

Run with a gpocc tree on PYTHONPATH and compare the saved arrays of two trees, e.g.::

    git worktree add --detach /tmp/before <REV>
    PYTHONPATH=/tmp/before .venv/bin/python bench/equivalence.py /tmp/before before.npz
    PYTHONPATH=. .venv/bin/python bench/equivalence.py . after.npz
    .venv/bin/python bench/equivalence.py --compare before.npz after.npz
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

CARMEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "carmen"
LOG = CARMEN / "freiburg-079-corrected.log"


def build(root: Path, out: Path) -> None:
    from gpocc.config import load_config
    from gpocc.io.inputs import read_inputs
    from gpocc.samples.beams import build_samples

    try:
        from gpocc.baselines.grid import default_grid_spec, occupancy_grid
    except ImportError:  # trees before the grid baseline moved
        from gpocc.evaluation.grid import default_grid_spec, occupancy_grid

    cfg = load_config(root / "configs" / "carmen_freiburg.yaml")
    started = time.perf_counter()
    batches = read_inputs([LOG], cfg)
    samples = build_samples(batches, cfg)
    spec = default_grid_spec(batches, cfg, 0.1)
    grid = occupancy_grid(batches, cfg, spec)
    np.savez(out, means=samples.means, covariances=samples.covariances, labels=samples.labels,
             scan_ids=samples.scan_ids, pose_factors=samples.pose_factors,
             log_odds=grid.log_odds, bounds=np.array(spec.bounds))
    print(f"{out}: {len(samples)} samples, grid {spec.width} x {spec.height}, "
          f"{time.perf_counter() - started:.1f} s")


def compare(a_path: Path, b_path: Path) -> None:
    a, b = np.load(a_path), np.load(b_path)
    for key in a.files:
        x, y = a[key], b[key]
        same = x.shape == y.shape and np.array_equal(x, y, equal_nan=True)
        print(f"{key:14s} {str(x.shape):16s} {'bit-identical' if same else 'DIFFERENT'}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", nargs=2, type=Path, help="TREE OUT.npz, or A.npz B.npz")
    parser.add_argument("--compare", action="store_true")
    args = parser.parse_args()
    if args.compare:
        compare(*args.paths)
    else:
        build(*args.paths)


if __name__ == "__main__":
    main()
