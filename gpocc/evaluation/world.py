"""Ground-truth 2-D worlds for the simulator: walls and boxes as segments, round obstacles.

A :class:`World` is a set of line segments (walls, box sides) and circles (pillars,
bins) with exact, vectorised ray casting, plus two routes through its free space: a slow
explorer's and a fast traverser's (see :mod:`gpocc.evaluation.simulate`). Named worlds:

* ``default``: a 40 x 25 m building: outer walls, a corridor with rooms on both sides
  (inner walls with doors), boxes and round pillars. Route 1 explores the west half,
  route 2 runs the whole corridor and the east rooms, which route 1 never enters.
* ``office``: a 24 x 14 m office floor: a corridor, small offices with desks and bins.
* ``warehouse``: a 30 x 20 m hall with rows of shelves, pillars and a corner office.
* ``grown-<seed>`` (e.g. ``grown-7``): a building grown from the seed by
  :func:`grow_world`: a corridor of random width and position with rooms of random
  widths and depths on both sides, doors, boxes and pillars, optionally turned
  north-south and mirrored. The explorer visits the rooms of the west (or south) part,
  the traverser runs the whole corridor and visits the others.
* ``offices-<seed>``, ``hall-<seed>``, ``clutter-<seed>``: the families of a second,
  different generator with planned routes (:mod:`gpocc.evaluation.families`).

Coordinates are metres in the map frame, x east, y north.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from gpocc.errors import GpoccError

#: Rays start this far (metres) past their origin, so a ray never hits the surface it
#: starts on through rounding.
_T_MIN = 1e-9
#: Rays are cast in chunks of this many, bounding the rays x segments temporaries.
_RAY_CHUNK = 20_000


@dataclass(frozen=True, eq=False)
class World:
    """Obstacles and the two robots' routes.

    Attributes:
        name: the world's name.
        segments: (K, 2, 2) wall / box-side segments ``[[x0, y0], [x1, y1]]``, metres.
        circles: (C, 3) round obstacles ``(cx, cy, radius)``, metres.
        routes: waypoints (n_i, 2) metres of each route: ``routes[0]`` the slow explorer
            (platform I), ``routes[1]`` the fast traverser (platform II).
        description: one line for logs and metadata.
    """

    name: str
    segments: np.ndarray
    circles: np.ndarray
    routes: tuple[np.ndarray, ...]
    description: str = ""

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of all obstacles, metres."""
        pts = [self.segments.reshape(-1, 2)]
        if len(self.circles):
            c, r = self.circles[:, :2], self.circles[:, 2:3]
            pts += [c - r, c + r]
        allp = np.concatenate(pts)
        lo, hi = allp.min(axis=0), allp.max(axis=0)
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    def cast(
        self, origins: np.ndarray, angles: np.ndarray, max_range: float = np.inf
    ) -> np.ndarray:
        """Distance along each ray to the first obstacle; ``+inf`` beyond ``max_range``.

        Args:
            origins: (N, 2) ray origins, metres.
            angles: (N,) ray directions, radians counter-clockwise from +x.
            max_range: metres; hits farther than this are reported as ``+inf``.

        Returns:
            (N,) metres.
        """
        return cast_rays(self.segments, self.circles, origins, angles, max_range)

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """(N,) distance (metres) from each (N, 2) point to the nearest obstacle surface."""
        p = np.asarray(points, dtype=float).reshape(-1, 2)
        a = self.segments[:, 0]
        e = self.segments[:, 1] - a
        w = p[:, None, :] - a[None, :, :]
        s = np.clip(np.einsum("nkd,kd->nk", w, e) / np.einsum("kd,kd->k", e, e), 0.0, 1.0)
        d = np.linalg.norm(w - s[..., None] * e[None], axis=2).min(axis=1)
        if len(self.circles):
            dc = np.abs(
                np.linalg.norm(p[:, None, :] - self.circles[None, :, :2], axis=2)
                - self.circles[None, :, 2]
            ).min(axis=1)
            d = np.minimum(d, dc)
        return d

    def boundary_segments(self, sides: int = 256) -> np.ndarray:
        """(K', 2, 2) all obstacle outlines as segments; circles as regular ``sides``-gons.

        The polygon lies within ``r (1 - cos(pi / sides))`` of the circle (1.5e-5 r for
        256 sides): for rasterising outlines, not for ray casting.
        """
        if not len(self.circles):
            return self.segments
        phi = np.linspace(0.0, 2.0 * np.pi, sides + 1)
        ring = np.stack((np.cos(phi), np.sin(phi)), axis=1)  # (sides + 1, 2)
        pts = self.circles[:, None, :2] + self.circles[:, None, 2:3] * ring[None]
        polys = np.stack((pts[:, :-1], pts[:, 1:]), axis=2).reshape(-1, 2, 2)
        return np.concatenate((self.segments, polys))


def cast_rays(
    segments: np.ndarray,
    circles: np.ndarray,
    origins: np.ndarray,
    angles: np.ndarray,
    max_range: float = np.inf,
) -> np.ndarray:
    """Exact first-hit distance of rays against segments and circles, vectorised.

    Ray ``o + t d`` (unit ``d``) meets segment ``p + s e`` where ``t = (w x e) / (d x e)``
    and ``s = (w x d) / (d x e)``, ``w = p - o``, ``x`` the 2-D cross product; a hit needs
    ``t > 0`` and ``0 <= s <= 1``. Parallel rays (``d x e = 0``) never hit a segment (a
    ray grazing along a wall sees its end instead). A circle is hit at the smaller
    positive root of ``|o + t d - c|^2 = r^2`` (the larger one from inside).

    Args:
        segments: (K, 2, 2) metres.
        circles: (C, 3) ``(cx, cy, r)`` metres.
        origins: (N, 2) metres.
        angles: (N,) radians.
        max_range: hits beyond this many metres count as no hit.

    Returns:
        (N,) distances, metres; ``+inf`` where nothing is hit within ``max_range``.
    """
    origins = np.asarray(origins, dtype=float).reshape(-1, 2)
    angles = np.broadcast_to(np.asarray(angles, dtype=float), origins.shape[:1])
    segments = np.asarray(segments, dtype=float).reshape(-1, 2, 2)
    circles = np.asarray(circles, dtype=float).reshape(-1, 3)
    out = np.full(origins.shape[0], np.inf)
    p = segments[:, 0]
    e = segments[:, 1] - p
    for i0 in range(0, origins.shape[0], _RAY_CHUNK):
        sl = slice(i0, i0 + _RAY_CHUNK)
        o = origins[sl]
        dx, dy = np.cos(angles[sl]), np.sin(angles[sl])
        best = np.full(o.shape[0], np.inf)
        if len(p):
            wx = p[None, :, 0] - o[:, 0, None]
            wy = p[None, :, 1] - o[:, 1, None]
            denom = dx[:, None] * e[None, :, 1] - dy[:, None] * e[None, :, 0]
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (wx * e[None, :, 1] - wy * e[None, :, 0]) / denom
                s = (wx * dy[:, None] - wy * dx[:, None]) / denom
            ok = (denom != 0.0) & (t > _T_MIN) & (s >= 0.0) & (s <= 1.0)
            best = np.where(ok, t, np.inf).min(axis=1)
        if len(circles):
            ocx = o[:, 0, None] - circles[None, :, 0]
            ocy = o[:, 1, None] - circles[None, :, 1]
            b = dx[:, None] * ocx + dy[:, None] * ocy
            c = ocx * ocx + ocy * ocy - circles[None, :, 2] ** 2
            disc = b * b - c
            root = np.sqrt(np.maximum(disc, 0.0))
            near, far = -b - root, -b + root
            t = np.where(near > _T_MIN, near, far)
            ok = (disc >= 0.0) & (t > _T_MIN)
            best = np.minimum(best, np.where(ok, t, np.inf).min(axis=1))
        out[sl] = best
    out[out > max_range] = np.inf
    return out


# --------------------------------------------------------------------------- builders


def _wall(x0: float, y0: float, x1: float, y1: float,
          doors: tuple[tuple[float, float], ...] = ()) -> list[list[list[float]]]:
    """An axis-parallel wall with door gaps ``(from, to)`` along its length."""
    horizontal = y0 == y1
    lo, hi = (min(x0, x1), max(x0, x1)) if horizontal else (min(y0, y1), max(y0, y1))
    cuts = [lo]
    for a, b in sorted(doors):
        cuts += [a, b]
    cuts.append(hi)
    out = []
    for a, b in zip(cuts[::2], cuts[1::2], strict=True):
        if b > a:
            out.append([[a, y0], [b, y0]] if horizontal else [[x0, a], [x0, b]])
    return out


def _box(x0: float, y0: float, x1: float, y1: float) -> list[list[list[float]]]:
    return [[[x0, y0], [x1, y0]], [[x1, y0], [x1, y1]], [[x1, y1], [x0, y1]],
            [[x0, y1], [x0, y0]]]


def _make(name: str, description: str, parts: list[list[list[list[float]]]],
          circles: list[tuple[float, float, float]], routes: list[list[tuple[float, float]]]
          ) -> World:
    segments = np.array([seg for part in parts for seg in part], dtype=float)
    return World(
        name=name,
        segments=segments,
        circles=np.array(circles, dtype=float).reshape(-1, 3),
        routes=tuple(np.array(r, dtype=float) for r in routes),
        description=description,
    )


def _default() -> World:
    parts = [
        _box(0, 0, 40, 25),
        # Corridor 11 < y < 14 with doors into the rooms south and north of it.
        _wall(0, 11, 40, 11, ((4.5, 6.0), (14.5, 16.0), (24.5, 26.0), (34.0, 35.5))),
        _wall(0, 14, 40, 14, ((7.0, 8.5), (19.0, 20.5), (31.0, 32.5))),
        # South rooms, two of them joined by side doors.
        _wall(10, 0, 10, 11, ((3.0, 4.5),)),
        _wall(20, 0, 20, 11),
        _wall(30, 0, 30, 11, ((6.0, 7.5),)),
        # North rooms.
        _wall(13, 14, 13, 25, ((20.0, 21.5),)),
        _wall(26, 14, 26, 25),
        # Boxes.
        _box(2.0, 1.5, 3.5, 3.0),
        _box(16.0, 6.0, 18.0, 8.0),
        _box(36.0, 1.0, 38.0, 2.5),
        _box(22.0, 21.0, 24.5, 23.0),
        _box(34.0, 17.0, 36.0, 18.5),
    ]
    circles = [(6.0, 19.0, 0.4), (9.5, 23.0, 0.3), (17.0, 17.5, 0.35), (27.0, 4.5, 0.5),
               (33.5, 21.5, 0.45), (3.0, 8.5, 0.3)]
    explorer = [(1.5, 12.5), (5.25, 12.5), (5.25, 8.0), (8.0, 8.0), (8.0, 3.75), (12.0, 3.75),
                (12.0, 9.0), (15.25, 9.0), (15.25, 12.5), (7.75, 12.5), (7.75, 17.0),
                (3.0, 17.0), (3.0, 23.0), (7.5, 21.5), (11.0, 20.75), (16.0, 20.75),
                (16.0, 15.5), (19.0, 15.5)]
    traverser = [(1.5, 12.8), (34.75, 12.8), (34.75, 6.0), (32.0, 4.0), (32.0, 6.75),
                 (28.5, 6.75), (25.25, 8.0), (25.25, 12.5), (31.75, 12.5), (31.75, 17.0),
                 (29.0, 17.0), (29.0, 23.0), (38.0, 23.5), (38.0, 16.0), (31.75, 15.5),
                 (31.75, 12.5), (2.0, 12.5)]
    return _make("default", "40 x 25 m building: corridor, rooms with doors, boxes, pillars",
                 parts, circles, [explorer, traverser])


def _office() -> World:
    parts = [
        _box(0, 0, 24, 14),
        _wall(0, 6, 24, 6, ((2.5, 3.5), (8.5, 9.5), (14.5, 15.5), (20.5, 21.5))),
        _wall(0, 8, 24, 8, ((3.5, 4.5), (11.5, 12.5), (19.5, 20.5))),
        _wall(6, 0, 6, 6), _wall(12, 0, 12, 6), _wall(18, 0, 18, 6),
        _wall(8, 8, 8, 14), _wall(16, 8, 16, 14),
        # Desks.
        _box(0.5, 0.5, 2.5, 1.5), _box(8.5, 0.5, 11.0, 1.5), _box(13.0, 3.5, 14.0, 5.0),
        _box(20.0, 1.0, 23.0, 2.0), _box(1.0, 12.0, 3.5, 13.2), _box(12.5, 12.0, 15.0, 13.0),
        _box(20.0, 11.5, 22.5, 12.5),
    ]
    circles = [(4.5, 1.0, 0.25), (6.5, 11.0, 0.3), (10.5, 11.0, 0.25), (17.0, 4.5, 0.3),
               (22.5, 9.5, 0.25)]
    explorer = [(1.0, 7.0), (3.0, 7.0), (3.0, 3.5), (4.0, 3.0), (3.0, 2.5), (3.0, 7.0),
                (9.0, 7.0), (9.0, 3.5), (10.5, 3.0), (9.0, 3.0), (9.0, 7.0), (4.0, 7.0),
                (4.0, 10.5), (2.0, 10.5), (5.5, 11.5), (4.0, 10.0), (4.0, 7.0), (11.0, 7.0)]
    traverser = [(1.0, 7.2), (23.0, 7.2), (21.0, 7.2), (21.0, 3.5), (19.5, 4.0), (21.0, 4.5),
                 (21.0, 7.0), (15.0, 7.0), (15.0, 2.5), (16.5, 2.0), (15.0, 2.5), (15.0, 7.0),
                 (20.0, 7.0), (20.0, 10.0), (18.5, 10.5), (23.0, 10.5), (20.0, 10.0),
                 (20.0, 7.0), (12.0, 7.0), (12.0, 10.0), (14.0, 10.5), (12.0, 10.0),
                 (12.0, 7.0), (1.0, 6.8)]
    return _make("office", "24 x 14 m office floor: corridor, offices with desks and bins",
                 parts, circles, [explorer, traverser])


def _warehouse() -> World:
    parts = [_box(0, 0, 30, 20)]
    for y in (4.0, 8.0, 12.0):
        parts += [_box(4.0, y, 12.0, y + 1.0), _box(16.0, y, 22.5, y + 1.0)]
    # Corner office with a door.
    parts += [_wall(24, 14, 30, 14, ((26.0, 27.5),)), _wall(24, 14, 24, 20),
              _box(27.5, 17.5, 29.5, 19.0)]
    circles = [(14.0, 2.5, 0.4), (14.0, 10.5, 0.4), (14.0, 17.0, 0.4), (26.0, 6.0, 0.35),
               (8.0, 16.5, 0.3), (2.0, 17.5, 0.3)]
    explorer = [(1.5, 1.5), (1.5, 15.0), (12.0, 15.0), (2.0, 15.0), (2.0, 10.5),
                (12.5, 10.5), (12.5, 6.5), (2.0, 6.5), (2.0, 2.5), (12.0, 2.5)]
    traverser = [(1.0, 1.2), (24.0, 1.2), (24.0, 6.5), (15.0, 6.5), (15.0, 10.5),
                 (24.5, 10.5), (24.5, 13.0), (26.75, 13.0), (26.75, 16.0), (25.5, 18.5),
                 (26.75, 16.0), (26.75, 12.5), (28.5, 12.5), (28.5, 1.5)]
    return _make("warehouse", "30 x 20 m hall: shelf rows, pillars, a corner office",
                 parts, circles, [explorer, traverser])


_GROWN = "grown-"


def _route_clear(world: World, route: np.ndarray, margin: float) -> bool:
    """True when every point of the polyline (every 0.1 m) is ``margin`` m from obstacles."""
    pts = [route[:1]]
    for a, b in zip(route[:-1], route[1:], strict=True):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / 0.1)))
        pts.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return bool(world.clearance(np.concatenate(pts)).min() >= margin)


def _leg_clear(segments: np.ndarray, circles: np.ndarray, leg: np.ndarray) -> bool:
    """True when a candidate obstacle keeps 0.6 m from a room's route leg."""
    probe = World("probe", segments.reshape(-1, 2, 2), circles.reshape(-1, 3), ())
    if not len(probe.segments):
        probe = World("probe", np.array([[[1e6, 1e6], [1e6, 1e6 + 1]]]), probe.circles, ())
    return _route_clear(probe, leg, 0.6)


def _rooms(rng: np.random.Generator, width: float) -> list[tuple[float, float]]:
    """Random partition of [0, width] into rooms 4.5-9 m wide, as (x0, x1)."""
    cuts = [0.0]
    while width - cuts[-1] > 9.0:
        cuts.append(cuts[-1] + float(rng.uniform(4.5, 9.0)))
    if width - cuts[-1] < 4.5 and len(cuts) > 1:
        cuts.pop()
    cuts.append(width)
    return list(zip(cuts[:-1], cuts[1:], strict=True))


def grow_world(seed: int) -> World:
    """A random corridor building grown from ``seed`` (see the module docstring).

    Deterministic for a seed. Obstacles are redrawn until both routes keep 0.45 m from
    every obstacle, so the simulated robots never drive through a wall.
    """
    rng = np.random.default_rng(seed)
    for _ in range(200):
        world = _grow_once(rng, seed)
        if world is not None:
            return world
    raise GpoccError(f"could not grow a world from seed {seed}")  # pragma: no cover


def _grow_once(rng: np.random.Generator, seed: int) -> World | None:
    width = float(rng.uniform(24.0, 40.0))
    height = float(rng.uniform(16.0, 26.0))
    corridor_w = float(rng.uniform(2.4, 3.6))
    c0 = float(rng.uniform(0.35, 0.55) * (height - corridor_w))
    c1 = c0 + corridor_w
    mid = c0 + 0.5 * corridor_w
    parts = [_box(0, 0, width, height)]
    circles: list[tuple[float, float, float]] = []
    south_doors, north_doors = [], []
    visits: list[tuple[float, list[tuple[float, float]]]] = []
    for side, (y_lo, y_hi, wall_y) in enumerate(((0.0, c0, c0), (c1, height, c1))):
        doors = south_doors if side == 0 else north_doors
        rooms = _rooms(rng, width)
        for i, (x0, x1) in enumerate(rooms):
            if i > 0:
                gap = ()
                if rng.random() < 0.3:  # a side door into the previous room
                    d = float(rng.uniform(y_lo + 1.0, y_hi - 2.2))
                    gap = ((d, d + 1.2),)
                parts.append(_wall(x0, y_lo, x0, y_hi, gap))
            door_w = float(rng.uniform(1.1, 1.6))
            dx = float(rng.uniform(x0 + 0.9, x1 - 0.9 - door_w))
            doors.append((dx, dx + door_w))
            door_x = dx + 0.5 * door_w
            inward = -1.0 if side == 0 else 1.0
            inside = (door_x, wall_y + inward * 1.0)
            centre = (0.5 * (x0 + x1), 0.5 * (y_lo + y_hi))
            path = [(door_x, mid), inside, centre, inside, (door_x, mid)]
            visits.append((door_x, path))
            leg = np.array([(door_x, wall_y), inside, centre])
            for _ in range(int(rng.integers(0, 3))):
                bw, bh = rng.uniform(0.6, 2.2, 2)
                bx = rng.uniform(x0 + 0.4, x1 - 0.4 - bw)
                by = rng.uniform(y_lo + 0.4, y_hi - 0.4 - bh)
                box = _box(bx, by, bx + bw, by + bh)
                if _leg_clear(np.array(box, dtype=float), np.zeros((0, 3)), leg):
                    parts.append(box)
            if rng.random() < 0.6:
                r = float(rng.uniform(0.2, 0.5))
                pillar = (float(rng.uniform(x0 + 0.6, x1 - 0.6)),
                          float(rng.uniform(y_lo + 0.6, y_hi - 0.6)), r)
                if _leg_clear(np.zeros((0, 2, 2)), np.array([pillar]), leg):
                    circles.append(pillar)
    parts.append(_wall(0, c0, width, c0, tuple(south_doors)))
    parts.append(_wall(0, c1, width, c1, tuple(north_doors)))
    split = float(rng.uniform(0.4, 0.6) * width)
    west = [p for x, path in sorted(visits) if x < split for p in path]
    east = [p for x, path in sorted(visits) if x >= split for p in path]
    explorer = [(1.2, mid - 0.15), *[(x, mid - 0.15) if y == mid else (x, y) for x, y in west]]
    traverser = [(1.2, mid + 0.15), (width - 1.2, mid + 0.15),
                 *[(x, mid + 0.15) if y == mid else (x, y) for x, y in reversed(east)],
                 (1.5, mid + 0.15)]
    if len(explorer) < 2 or not east:
        return None
    segments = np.array([seg for part in parts for seg in part], dtype=float)
    circ = np.array(circles, dtype=float).reshape(-1, 3)
    routes = [np.array(explorer), np.array(traverser)]
    if rng.random() < 0.5:  # turn the building north-south
        segments, circ = segments[..., ::-1].copy(), np.column_stack((circ[:, 1::-1], circ[:, 2]))
        routes = [r[:, ::-1].copy() for r in routes]
    world = World(
        name=f"{_GROWN}{seed}", segments=segments, circles=circ, routes=tuple(routes),
        description=(f"grown from seed {seed}: {width:.0f} x {height:.0f} m, corridor "
                     f"{corridor_w:.1f} m wide, rooms both sides, boxes, pillars"),
    )
    if not all(_route_clear(world, r, 0.45) for r in world.routes):
        return None
    return world


_WORLDS: dict[str, Callable[[], World]] = {
    "default": _default,
    "office": _office,
    "warehouse": _warehouse,
}

#: Names accepted by :func:`make_world` besides ``grown-<seed>``.
WORLD_NAMES: tuple[str, ...] = tuple(_WORLDS)


def is_world_name(name: str) -> bool:
    """True for a named world, ``grown-<non-negative integer>`` or a family world
    (``offices-<seed>``, ``hall-<seed>``, ``clutter-<seed>``)."""
    from gpocc.evaluation.families import family_seed

    if name in _WORLDS or family_seed(name) is not None:
        return True
    tail = name[len(_GROWN):] if name.startswith(_GROWN) else ""
    return tail.isdigit()


def make_world(name: str = "default") -> World:
    """The named world, ``grown-<seed>`` or a family world (see the module docstring)."""
    # Imported here: families builds its worlds from this module's pieces.
    from gpocc.evaluation.families import family_seed, family_world

    if name in _WORLDS:
        return _WORLDS[name]()
    if family_seed(name) is not None:
        return family_world(name)
    if is_world_name(name):
        return grow_world(int(name[len(_GROWN):]))
    raise GpoccError(
        f"unknown world {name!r}; choose one of: {', '.join(WORLD_NAMES)}, grown-<seed>, "
        f"offices-<seed>, hall-<seed> or clutter-<seed>"
    )
