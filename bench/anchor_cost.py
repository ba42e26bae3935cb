"""CPU time of one map anchor (one local problem and its footprint's queries), in one
process with single-threaded BLAS: the unit the map's predict stage is made of.

Loads a model, lays out the anchors of a map at ``--resolution`` as ``gpocc map`` does
(support mask included), and predicts ``--anchors`` of them (every k-th, so the sample
spans the map) after one warm-up call. Prints the CPU milliseconds per anchor and the
product with the number of anchors; with ``--profile``, the cProfile functions that
took the most time of their own. Usage::

    .venv/bin/python bench/anchor_cost.py MODEL.npz [--anchors 200] [--profile]

Wall time of whole commands belongs to ``bench/run_bench.py``; this script is for
comparing two versions of the per-anchor code on a machine whose speed drifts
(interleave the runs).
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time

from gpocc.blas import single_threaded_blas
from gpocc.gp.local import NeighbourIndex
from gpocc.gp.model import load_model
from gpocc.mapping.blend import supported_anchors
from gpocc.mapping.blocks import Anchor, AnchorLattice, predict_anchor
from gpocc.mapping.mapper import default_spec
from gpocc.mapping.support import model_support


def map_anchors(model, resolution: float) -> tuple[AnchorLattice, list[Anchor]]:
    """The map's anchor lattice and its anchors with at least one supported cell."""
    spec = default_spec(model, resolution, model.config.map.margin_m)
    lattice = AnchorLattice.of_model(spec, model.config.model)
    rows, cols = lattice.shape
    every = [Anchor(r, c) for r in range(rows) for c in range(cols)]
    mask = model_support(model).mask(spec, lattice.cells)
    anchors, _ = supported_anchors(lattice, every, mask)
    return lattice, anchors


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("--resolution", type=float, default=0.1)
    parser.add_argument("--anchors", type=int, default=200)
    parser.add_argument("--profile", action="store_true")
    args = parser.parse_args()
    single_threaded_blas()
    model = load_model(args.model)
    lattice, anchors = map_anchors(model, args.resolution)
    index = NeighbourIndex(model.samples)
    chosen = anchors[:: max(1, len(anchors) // args.anchors)][: args.anchors]
    predict_anchor(model, index, lattice, chosen[0])  # compiled loops and caches warm
    profiler = cProfile.Profile() if args.profile else None
    if profiler is not None:
        profiler.enable()
    start = time.process_time()
    for anchor in chosen:
        predict_anchor(model, index, lattice, anchor)
    per_anchor = (time.process_time() - start) / len(chosen)
    if profiler is not None:
        profiler.disable()
        pstats.Stats(profiler).sort_stats("tottime").print_stats(15)
    print(f"{len(anchors)} anchors with support; {len(chosen)} timed: "
          f"{per_anchor * 1e3:.1f} ms CPU per anchor, x {len(anchors)} = "
          f"{per_anchor * len(anchors):.1f} s CPU")


if __name__ == "__main__":
    main()
