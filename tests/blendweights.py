"""The blend weight of a map anchor, written from its definition (gpocc.mapping.blocks),
for the tests that check the lattice and the maps against it."""

from __future__ import annotations


def trapezoid(distance_blocks: float, overlap: float) -> float:
    """The weight of an anchor ``distance_blocks`` away along one axis: 1 up to
    (1 - o) / 2, 0 from (1 + o) / 2, linear between (o = 1: the bilinear tent)."""
    inner, outer = (1 - overlap) / 2, (1 + overlap) / 2
    if distance_blocks <= inner:
        return 1.0
    if distance_blocks >= outer:
        return 0.0
    return (outer - distance_blocks) / overlap
