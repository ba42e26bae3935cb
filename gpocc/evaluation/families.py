"""A second world generator: three families of buildings, drawn from a seed.

:func:`gpocc.evaluation.world.grow_world` grows one kind of building (a corridor with
rooms on both sides). The families here are built differently, so that a result that
holds on them is not a property of one generator:

* ``offices-<seed>``: an office floor with two parallel corridors joined by cross
  corridors, offices on three bands, doors that are open or closed, desks along the
  walls, round tables and cabinets.
* ``hall-<seed>``: an open hall with a grid of square and round pillars, free-standing
  partitions and crates: long free beams, few walls.
* ``clutter-<seed>``: a cluttered warehouse: blocks of shelf rows running east-west or
  north-south with narrow aisles, pallets left in the aisles, pillars.

The robots' routes are planned, not drawn by hand: a grid of the cells at least
:data:`ROUTE_CLEARANCE_M` from every obstacle, spread-out targets in the largest
connected free region, shortest grid paths between them (8-connected), pulled tight
where the straight line stays clear. The explorer (platform I) visits the targets west
of a split line; the traverser (platform II) crosses the whole building from the
explorer's start and visits the targets east of it, which the explorer never sees.

Deterministic for a name. Coordinates are metres, x east, y north.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from gpocc.errors import GpoccError
from gpocc.evaluation.world import World, _box, _route_clear, _wall

#: Family names; a world is ``<family>-<seed>``.
FAMILIES: tuple[str, ...] = ("offices", "hall", "clutter")

#: Distance (metres) routes keep from every obstacle; the final check asks for 0.45 m,
#: the rule of the grown worlds.
ROUTE_CLEARANCE_M = 0.55
_CHECK_CLEARANCE_M = 0.45
_GRID_M = 0.2


def family_seed(name: str) -> tuple[str, int] | None:
    """``(family, seed)`` of a family world's name, or None for any other name."""
    family, _, tail = name.partition("-")
    if family in FAMILIES and tail.isdigit():
        return family, int(tail)
    return None


def family_world(name: str) -> World:
    """The world ``<family>-<seed>`` (see the module docstring).

    Raises:
        GpoccError: not a family world's name, or no world with clear routes could be
            drawn from the seed (not seen for seeds 0-199).
    """
    parsed = family_seed(name)
    if parsed is None:
        raise GpoccError(f"unknown world {name!r}: a family world is "
                         f"<{'|'.join(FAMILIES)}>-<seed>")
    family, seed = parsed
    rng = np.random.default_rng([seed, FAMILIES.index(family)])
    for _ in range(50):
        segments, circles, description = _DRAW[family](rng)
        world = World(name=name, segments=segments, circles=circles, routes=(),
                      description=f"{family} from seed {seed}: {description}")
        routes = plan_routes(world, rng)
        if routes is not None:
            return World(name=name, segments=segments, circles=circles, routes=routes,
                         description=world.description)
    raise GpoccError(f"could not draw the world {name} with clear routes")  # pragma: no cover


# --------------------------------------------------------------------------- obstacles


def _segments(parts: list[list[list[list[float]]]]) -> np.ndarray:
    return np.array([seg for part in parts for seg in part], dtype=float).reshape(-1, 2, 2)


def _circles(circles: list[tuple[float, float, float]]) -> np.ndarray:
    return np.array(circles, dtype=float).reshape(-1, 3)


def _door(rng: np.random.Generator, lo: float, hi: float, open_share: float = 0.8
          ) -> list[tuple[float, float]]:
    """A door gap 1.3-1.7 m wide somewhere in [lo, hi], or none when it is closed."""
    width = float(rng.uniform(1.3, 1.7))
    if hi - lo < width + 0.6 or rng.random() > open_share:
        return []
    start = float(rng.uniform(lo + 0.3, hi - 0.3 - width))
    return [(start, start + width)]


def _offices(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, str]:
    width = float(rng.uniform(28.0, 44.0))
    band = rng.uniform(4.0, 6.0, 3)  # south offices, middle block, north offices
    corridor = rng.uniform(1.8, 2.6, 2)
    ys = np.cumsum([0.0, band[0], corridor[0], band[1], corridor[1], band[2]])
    height = float(ys[-1])
    parts = [_box(0, 0, width, height)]
    circles: list[tuple[float, float, float]] = []
    cross = sorted(rng.choice([0, 1, 2], size=int(rng.integers(1, 3)), replace=False))
    cross_x = {0: (0.0, 2.2), 1: (0.5 * width - 1.1, 0.5 * width + 1.1),
               2: (width - 2.2, width)}
    # The middle block is cut by cross corridors (at the west end, middle or east end).
    # The corridor walls' door gaps, by the wall's index in ys.
    walls_of: dict[int, list[tuple[float, float]]] = {1: [], 2: [], 3: [], 4: []}
    for b, (y_lo, y_hi) in enumerate(((ys[0], ys[1]), (ys[2], ys[3]), (ys[4], ys[5]))):
        x = 0.0
        cells = []
        while width - x > 3.0:
            w = float(min(rng.uniform(3.0, 6.5), width - x))
            if width - (x + w) < 3.0:
                w = width - x
            cells.append((x, x + w))
            x += w
        for i, (x0, x1) in enumerate(cells):
            if b == 1 and any(c0 < x1 and x0 < c1 for c0, c1 in (cross_x[c] for c in cross)):
                continue  # a cross corridor: no office here
            if i > 0:
                parts.append(_wall(x0, y_lo, x0, y_hi, tuple(_door(rng, y_lo, y_hi, 0.25))))
            if x1 < width:
                parts.append(_wall(x1, y_lo, x1, y_hi))
            # Doors onto the corridor(s): south band opens north, north band south,
            # the middle block either way.
            sides = {0: [1], 1: [2, 3] if rng.random() < 0.5 else [2], 2: [4]}[b]
            for wall_index in sides:
                walls_of[wall_index] += _door(rng, x0, x1)
            # Furniture: desks along the back wall, a round table, a cabinet.
            for _ in range(int(rng.integers(0, 3))):
                dw, dd = float(rng.uniform(1.2, 1.8)), float(rng.uniform(0.6, 0.8))
                if x1 - x0 < dw + 0.6:
                    continue
                dx = float(rng.uniform(x0 + 0.3, x1 - 0.3 - dw))
                back = y_lo if b == 0 else y_hi
                dy = back + (0.25 if b == 0 else -0.25 - dd)
                parts.append(_box(dx, dy, dx + dw, dy + dd))
            if rng.random() < 0.5 and x1 - x0 > 3.5:
                r = float(rng.uniform(0.35, 0.6))
                circles.append((float(rng.uniform(x0 + 1.2, x1 - 1.2)),
                                0.5 * (y_lo + y_hi), r))
    for wall_index in (1, 2, 3, 4):
        y = float(ys[wall_index])
        gaps = list(walls_of[wall_index])
        if wall_index in (2, 3):
            gaps += [cross_x[c] for c in cross]
        parts.append(_wall(0, y, width, y, tuple(_merge(gaps))))
    names = ", ".join(("west", "middle", "east")[c] for c in cross)
    return (_segments(parts), _circles(circles),
            f"{width:.0f} x {height:.0f} m office floor, two corridors joined {names}")


def _merge(gaps: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Overlapping gaps as one."""
    out: list[tuple[float, float]] = []
    for a, b in sorted(gaps):
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


def _hall(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, str]:
    width, height = float(rng.uniform(30.0, 50.0)), float(rng.uniform(20.0, 32.0))
    parts = [_box(0, 0, width, height)]
    circles: list[tuple[float, float, float]] = []
    spacing = float(rng.uniform(5.0, 8.0))
    square = rng.random() < 0.5
    for px in np.arange(spacing, width - 2.0, spacing):
        for py in np.arange(spacing, height - 2.0, spacing):
            if square:
                s = float(rng.uniform(0.25, 0.4))
                parts.append(_box(px - s, py - s, px + s, py + s))
            else:
                circles.append((float(px), float(py), float(rng.uniform(0.2, 0.4))))
    for _ in range(int(rng.integers(2, 6))):  # free-standing partitions
        length = float(rng.uniform(2.0, 6.0))
        x, y = float(rng.uniform(2.0, width - 2.0 - length)), float(rng.uniform(2.0, height - 2.0))
        if rng.random() < 0.5:
            parts.append(_wall(x, y, x + length, y))
        else:
            y = float(rng.uniform(2.0, height - 2.0 - length))
            parts.append(_wall(x, y, x, y + length))
    for _ in range(int(rng.integers(3, 9))):  # crates
        w, h = rng.uniform(0.6, 1.6, 2)
        x, y = rng.uniform(1.0, width - 1.0 - w), rng.uniform(1.0, height - 1.0 - h)
        parts.append(_box(float(x), float(y), float(x + w), float(y + h)))
    kind = "square" if square else "round"
    return (_segments(parts), _circles(circles),
            f"{width:.0f} x {height:.0f} m hall, {kind} pillars every {spacing:.1f} m")


def _clutter(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, str]:
    width, height = float(rng.uniform(25.0, 40.0)), float(rng.uniform(18.0, 28.0))
    parts = [_box(0, 0, width, height)]
    circles: list[tuple[float, float, float]] = []
    # Two or three blocks of shelf rows side by side, each east-west or north-south.
    n_blocks = int(rng.integers(2, 4))
    edges = np.linspace(0.0, width, n_blocks + 1)
    for x_lo, x_hi in zip(edges[:-1], edges[1:], strict=True):
        x_lo, x_hi = x_lo + 2.0, x_hi - 1.0
        depth, aisle = float(rng.uniform(0.8, 1.2)), float(rng.uniform(1.7, 2.5))
        if rng.random() < 0.5:  # rows east-west
            y = 2.5
            while y + depth < height - 2.5:
                parts.append(_box(x_lo, y, x_hi, y + depth))
                y += depth + aisle
        else:  # rows north-south
            x = x_lo
            while x + depth < x_hi:
                parts.append(_box(x, 2.5, x + depth, height - 2.5))
                x += depth + aisle
    for _ in range(int(rng.integers(4, 12))):  # pallets left about
        s = float(rng.uniform(0.6, 1.1))
        x, y = float(rng.uniform(1.0, width - 1.0 - s)), float(rng.uniform(1.0, height - 1.0 - s))
        parts.append(_box(x, y, x + s, y + s))
    for _ in range(int(rng.integers(2, 6))):
        circles.append((float(rng.uniform(1.0, width - 1.0)),
                        float(rng.uniform(1.0, height - 1.0)), float(rng.uniform(0.2, 0.35))))
    return (_segments(parts), _circles(circles),
            f"{width:.0f} x {height:.0f} m warehouse, {n_blocks} blocks of shelf rows")


_DRAW: dict[str, Callable[[np.random.Generator], tuple[np.ndarray, np.ndarray, str]]] = {
    "offices": _offices, "hall": _hall, "clutter": _clutter,
}


# --------------------------------------------------------------------------- routes


def plan_routes(world: World, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray] | None:
    """(explorer, traverser) waypoint routes (n, 2) through ``world``'s free space, or
    None when its free space is too small or broken up for two routes."""
    from scipy import ndimage
    from scipy.sparse import coo_matrix

    from gpocc.gp.train import farthest_point_indices
    x0, y0, x1, y1 = world.bounds
    xs = np.arange(x0 + 0.5 * _GRID_M, x1, _GRID_M)
    ys = np.arange(y0 + 0.5 * _GRID_M, y1, _GRID_M)
    gx, gy = np.meshgrid(xs, ys)
    centres = np.column_stack((gx.ravel(), gy.ravel()))
    clearance = np.concatenate([world.clearance(c) for c in np.array_split(
        centres, max(1, len(centres) // 4000))]).reshape(gx.shape)
    free = clearance >= ROUTE_CLEARANCE_M
    labels, count = ndimage.label(free, structure=np.ones((3, 3)))
    if count == 0:
        return None
    sizes = np.bincount(labels.ravel())[1:]
    region = labels == 1 + int(np.argmax(sizes))
    if region.sum() * _GRID_M**2 < 60.0:
        return None
    cells = np.flatnonzero(region.ravel())
    node = np.full(region.size, -1)
    node[cells] = np.arange(cells.size)
    rows, cols = np.unravel_index(cells, region.shape)
    edges_from, edges_to, weights = [], [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        r2, c2 = rows + dr, cols + dc
        ok = (r2 >= 0) & (r2 < region.shape[0]) & (c2 >= 0) & (c2 < region.shape[1])
        ok[ok] &= region[r2[ok], c2[ok]]
        edges_from.append(np.arange(cells.size)[ok])
        edges_to.append(node[r2[ok] * region.shape[1] + c2[ok]])
        weights.append(np.full(int(ok.sum()), np.hypot(dr, dc)))
    graph = coo_matrix((np.concatenate(weights), (np.concatenate(edges_from),
                                                  np.concatenate(edges_to))),
                       shape=(cells.size, cells.size)).tocsr()
    points = centres[cells]
    targets = farthest_point_indices(points, max(8, int(region.sum() * _GRID_M**2 / 45.0)), rng)
    split = float(np.quantile(points[:, 0], rng.uniform(0.4, 0.6)))
    west = [t for t in targets if points[t, 0] < split]
    east = [t for t in targets if points[t, 0] >= split]
    if len(west) < 2 or not east:
        return None
    start = int(np.argmin(points[:, 0]))  # the westmost free cell
    explorer = _tour(graph, points, start, west, region, (xs[0], ys[0]))
    far = int(np.argmax(points[:, 0]))
    traverser = _tour(graph, points, start, [far, *east, start], region, (xs[0], ys[0]),
                      ordered_first=True)
    if explorer is None or traverser is None:
        return None
    if not all(_route_clear(world, r, _CHECK_CLEARANCE_M) for r in (explorer, traverser)):
        return None
    return explorer, traverser


def _tour(graph, points: np.ndarray, start: int, targets: list[int], region: np.ndarray,
          origin: tuple[float, float], ordered_first: bool = False
          ) -> np.ndarray | None:
    """Waypoints from ``start`` through ``targets`` (nearest unvisited next by path
    length; with ``ordered_first`` the first target is visited first), as grid paths
    pulled tight."""
    from scipy.sparse.csgraph import dijkstra

    path = [start]
    remaining = list(targets)
    here = start
    while remaining:
        dist, pred = dijkstra(graph, directed=False, indices=here, return_predecessors=True)
        if ordered_first:
            nxt, ordered_first = remaining[0], False
        else:
            nxt = min(remaining, key=lambda t: dist[t])
        remaining.remove(nxt)
        if not np.isfinite(dist[nxt]):
            return None
        leg = [nxt]
        while leg[-1] != here:
            leg.append(int(pred[leg[-1]]))
        path += leg[::-1][1:]
        here = nxt
    if len(path) < 2:
        return None
    return _pull_tight(points[path], region, origin)


def _pull_tight(path: np.ndarray, region: np.ndarray, origin: tuple[float, float]
                ) -> np.ndarray:
    """Keep only the corners of a grid path: from each kept point, the farthest later
    point whose straight line stays on free cells."""

    def clear(a: np.ndarray, b: np.ndarray) -> bool:
        n = max(2, int(np.ceil(np.linalg.norm(b - a) / (0.5 * _GRID_M))) + 1)
        pts = a + (b - a) * np.linspace(0.0, 1.0, n)[:, None]
        c = np.rint((pts[:, 0] - origin[0]) / _GRID_M).astype(int)
        r = np.rint((pts[:, 1] - origin[1]) / _GRID_M).astype(int)
        ok = (r >= 0) & (r < region.shape[0]) & (c >= 0) & (c < region.shape[1])
        return bool(ok.all() and region[r, c].all())

    kept = [path[0]]
    i = 0
    while i < len(path) - 1:
        j = i + 1
        while j + 1 < len(path) and clear(path[i], path[j + 1]):
            j += 1
        kept.append(path[j])
        i = j
    out = np.array(kept)
    keep = np.ones(len(out), bool)
    keep[1:] = np.linalg.norm(np.diff(out, axis=0), axis=1) > 1e-9
    return out[keep]
