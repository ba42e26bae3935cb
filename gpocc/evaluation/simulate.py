"""The method paper's two-robot experiment, simulated: noisy scans, honest poses, truth.

Two platforms (Table I of the method paper) drive waypoint routes through a ground-truth
:class:`~gpocc.evaluation.world.World` at constant speed, heading along the current route
leg, and scan at a fixed rate:

============  =========  ==========  =======  ==================  ==================
platform      speed      scan rate   range    range variance      bearing variance
============  =========  ==========  =======  ==================  ==================
I (robot1)    0.5 m/s    0.5 scan/s  20 m     1e-6 m^2            1e-4 deg^2
II (robot2)   4 m/s      4 scan/s    8 m      0.8 m^2             0.5 deg^2
============  =========  ==========  =======  ==================  ==================

Both carry a 180-beam laser over 180 degrees at the base (no mount offset), bearings
``-pi/2 + i pi/180`` (i = 0..179), as in the CARMEN logs. Platform I explores one part of
the world (route 0); platform II traverses all of it (route 1), including areas platform
I never sees.

Noise model, per beam: the bearing error ``db ~ N(0, var_b)`` moves the ray that is
actually cast (the reading is reported at the nominal bearing, which is what a bearing
error means); the range error ``N(0, var_r)`` is added to that ray's true distance. A
reading at or beyond the platform's range (true or noisy) is reported as ``+inf`` (no
return); readings below ``range_min`` are kept as measured (readers ignore them). The
messages' ``range_max`` is the platform's range.

Pose noise (off by default): the recorded pose is the true pose plus ``N(0, P)``, drawn
independently per scan, with ``P = diag(s_xy^2, s_xy^2, s_yaw^2)``, and ``P`` is what the
pose messages carry as their covariance (honest covariances). Without pose noise the
messages carry a tiny covariance (:data:`TINY_POSE_COVARIANCE`).

Ground truth (:func:`truth_raster`) labels only what the robots observed: cells crossed
by noiseless rays from the true poses are free, and cells holding a true hit point, or
holding an obstacle outline that some ray entered, are occupied; every other cell
(unseen, behind walls, inside obstacles) is no data, so an evaluation scores only the
observed area.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from gpocc.baselines.grid import ray_cells
from gpocc.constants import NO_DATA
from gpocc.errors import GpoccError
from gpocc.evaluation.families import FAMILIES, family_seed
from gpocc.evaluation.world import World, make_world
from gpocc.gridspec import GridSpec
from gpocc.io.scans import ScanBatch
from gpocc.samples import beam_rules

#: Pose covariance (x m^2, y m^2, yaw rad^2) recorded when no pose noise is simulated.
TINY_POSE_COVARIANCE = np.diag([1e-6, 1e-6, 1e-8])

#: Start time of the simulated logs, seconds (nonzero: some tools treat 0 as unset).
START_TIME_S = 1000.0

_RAY_CHUNK = 50_000


@dataclass(frozen=True)
class Platform:
    """A robot with its laser: motion, scan rate, range and noise variances."""

    name: str
    speed_m_s: float
    scan_rate_hz: float
    max_range_m: float
    range_variance_m2: float
    bearing_variance_deg2: float
    n_beams: int = 180
    fov_deg: float = 180.0
    range_min_m: float = 0.1

    @property
    def scan_topic(self) -> str:
        return f"/{self.name}/scan"

    @property
    def pose_topic(self) -> str:
        return f"/{self.name}/pose"

    @property
    def angles(self) -> np.ndarray:
        """(B,) beam bearings, radians: ``-fov/2 + i fov/B``."""
        fov = math.radians(self.fov_deg)
        return -0.5 * fov + np.arange(self.n_beams) * fov / self.n_beams

    @property
    def no_return_free_m(self) -> float:
        """Free-space length to assume for a no-return reading, metres.

        A no-return means nothing within range, but with range noise a wall just inside
        the range can read as no-return; two range standard deviations short of the
        range keeps such a wall out of the free space in all but ~2% of those cases.
        """
        return max(0.0, self.max_range_m - 2.0 * math.sqrt(self.range_variance_m2))


PLATFORM_I = Platform("robot1", speed_m_s=0.5, scan_rate_hz=0.5, max_range_m=20.0,
                      range_variance_m2=1e-6, bearing_variance_deg2=1e-4)
PLATFORM_II = Platform("robot2", speed_m_s=4.0, scan_rate_hz=4.0, max_range_m=8.0,
                       range_variance_m2=0.8, bearing_variance_deg2=0.5)


def platforms_for(world: World) -> tuple[Platform, Platform]:
    """Table I's platforms; for a family world (:mod:`gpocc.evaluation.families`), the
    platforms' noise drawn around Table I's from the world's seed: each variance times a
    log-uniform factor in [1/4, 2] (platform II's range variance 0.2-1.6 m^2), platform
    II's range 6-10 m and speed 3-5 m/s, so that no result rests on one noise setting."""
    parsed = family_seed(world.name)
    if parsed is None:
        return PLATFORM_I, PLATFORM_II
    rng = np.random.default_rng([parsed[1], 1 + FAMILIES.index(parsed[0]), 2])

    def factor() -> float:
        return float(np.exp(rng.uniform(math.log(0.25), math.log(2.0))))

    first = dataclasses.replace(
        PLATFORM_I, range_variance_m2=PLATFORM_I.range_variance_m2 * factor(),
        bearing_variance_deg2=PLATFORM_I.bearing_variance_deg2 * factor())
    second = dataclasses.replace(
        PLATFORM_II, range_variance_m2=PLATFORM_II.range_variance_m2 * factor(),
        bearing_variance_deg2=PLATFORM_II.bearing_variance_deg2 * factor(),
        max_range_m=float(rng.uniform(6.0, 10.0)), speed_m_s=float(rng.uniform(3.0, 5.0)))
    return first, second


@dataclass(frozen=True)
class PoseNoise:
    """Localisation error: standard deviations of x and y (metres) and yaw (degrees)."""

    sigma_xy_m: float = 0.0
    sigma_yaw_deg: float = 0.0

    def __post_init__(self) -> None:
        if not (self.sigma_xy_m >= 0 and self.sigma_yaw_deg >= 0
                and math.isfinite(self.sigma_xy_m) and math.isfinite(self.sigma_yaw_deg)):
            raise GpoccError(
                f"pose noise needs two non-negative numbers (SIGMA_XY metres, SIGMA_YAW "
                f"degrees), got {self.sigma_xy_m} {self.sigma_yaw_deg}"
            )

    @property
    def enabled(self) -> bool:
        return self.sigma_xy_m > 0 or self.sigma_yaw_deg > 0

    @property
    def covariance(self) -> np.ndarray:
        """(3, 3) covariance of (x, y, yaw) the pose messages carry."""
        if not self.enabled:
            return TINY_POSE_COVARIANCE.copy()
        s_yaw = math.radians(self.sigma_yaw_deg)
        return np.diag([self.sigma_xy_m**2, self.sigma_xy_m**2, s_yaw**2])


def route_poses(
    waypoints: np.ndarray, speed: float, rate: float, t0: float = START_TIME_S
) -> tuple[np.ndarray, np.ndarray]:
    """Poses along a waypoint route at constant speed, sampled at a fixed rate.

    The robot is at distance ``speed * k / rate`` along the polyline at scan ``k``; its
    yaw is the heading of the leg it is on (the next leg at a waypoint). Zero-length legs
    are skipped.

    Args:
        waypoints: (n, 2) metres.
        speed: metres per second.
        rate: scans per second.
        t0: time of the first scan, seconds.

    Returns:
        stamps (S,) seconds and poses (S, 3) (x m, y m, yaw rad), with
        ``S = floor(duration * rate) + 1``, ``duration = length / speed``.
    """
    pts = np.asarray(waypoints, dtype=float)
    legs = np.diff(pts, axis=0)
    lengths = np.linalg.norm(legs, axis=1)
    keep = lengths > 0
    legs, lengths, starts = legs[keep], lengths[keep], pts[:-1][keep]
    if lengths.size == 0:
        raise GpoccError("a simulated route needs two distinct waypoints")
    cum = np.concatenate(([0.0], np.cumsum(lengths)))
    duration = cum[-1] / speed
    n = int(math.floor(duration * rate + 1e-9)) + 1
    k = np.arange(n)
    dist = speed * k / rate
    leg = np.clip(np.searchsorted(cum, dist, side="right") - 1, 0, lengths.size - 1)
    frac = (dist - cum[leg]) / lengths[leg]
    xy = starts[leg] + frac[:, None] * legs[leg]
    yaw = np.arctan2(legs[leg, 1], legs[leg, 0])
    return t0 + k / rate, np.column_stack((xy, yaw))


@dataclass(frozen=True, eq=False)
class RobotRun:
    """One platform's simulated log.

    Attributes:
        platform: the robot and laser.
        stamps: (S,) seconds.
        true_poses: (S, 3) (x m, y m, yaw rad).
        poses: (S, 3) recorded poses (true poses plus pose noise).
        pose_covariance: (3, 3) covariance the pose messages carry.
        ranges: (S, B) measured ranges, metres; ``+inf`` for no return.
        true_ranges: (S, B) noiseless ranges from the true pose at the nominal bearings,
            metres; ``+inf`` where nothing is within the platform's range.
        route: (n, 2) waypoints followed, metres.
    """

    platform: Platform
    stamps: np.ndarray
    true_poses: np.ndarray
    poses: np.ndarray
    pose_covariance: np.ndarray
    ranges: np.ndarray
    true_ranges: np.ndarray
    route: np.ndarray

    @property
    def n_scans(self) -> int:
        return int(self.ranges.shape[0])

    @property
    def route_length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.route, axis=0), axis=1).sum())

    @property
    def duration_s(self) -> float:
        """Time to drive the route, seconds; the run has floor(duration * rate) + 1 scans."""
        return self.route_length_m / self.platform.speed_m_s

    def batch(self, source: str = "simulation") -> ScanBatch:
        """The run as a reader would return it (recorded poses, honest covariances)."""
        p = self.platform
        return ScanBatch(
            sensor=p.name,
            source=source,
            stamps=self.stamps.copy(),
            angles=p.angles,
            ranges=self.ranges.copy(),
            poses=self.poses.copy(),
            pose_covariances=np.broadcast_to(self.pose_covariance,
                                             (self.n_scans, 3, 3)).copy(),
            range_min=p.range_min_m,
            range_max=p.max_range_m,
            has_pose_covariance=True,
        )


def _scan_rays(poses: np.ndarray, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Origins (S*B, 2) and directions (S*B,) radians of every beam of every scan.

    ``angles`` are bearings (B,) shared by all scans, or (S, B) per scan.
    """
    b = angles.shape[-1]
    return np.repeat(poses[:, :2], b, axis=0), (poses[:, 2:3] + angles).reshape(-1)


def simulate_run(
    world: World,
    platform: Platform,
    waypoints: np.ndarray,
    rng: np.random.Generator,
    pose_noise: PoseNoise | None = None,
) -> RobotRun:
    """Drive ``platform`` along ``waypoints`` in ``world`` and record its noisy scans.

    See the module docstring for the noise model. Draw order (for reproducibility from
    one ``rng``): bearing errors (S, B), range errors (S, B), pose errors (S, 3).
    """
    pose_noise = pose_noise or PoseNoise()
    stamps, true_poses = route_poses(waypoints, platform.speed_m_s, platform.scan_rate_hz)
    s, b = true_poses.shape[0], platform.n_beams
    angles = platform.angles
    sd_b = math.radians(math.sqrt(platform.bearing_variance_deg2))
    sd_r = math.sqrt(platform.range_variance_m2)
    d_bearing = rng.normal(0.0, sd_b, size=(s, b))
    d_range = rng.normal(0.0, sd_r, size=(s, b))
    origins, phi = _scan_rays(true_poses, angles[None, :] + d_bearing)
    cast = world.cast(origins, phi, platform.max_range_m).reshape(s, b)
    measured = cast + d_range
    measured[~(measured < platform.max_range_m)] = np.inf
    origins, phi = _scan_rays(true_poses, angles)
    true_ranges = world.cast(origins, phi, platform.max_range_m).reshape(s, b)
    cov = pose_noise.covariance
    poses = true_poses.copy()
    if pose_noise.enabled:
        poses += rng.multivariate_normal(np.zeros(3), cov, size=s)
        poses[:, 2] = np.angle(np.exp(1j * poses[:, 2]))
    return RobotRun(platform=platform, stamps=stamps, true_poses=true_poses, poses=poses,
                    pose_covariance=cov, ranges=measured, true_ranges=true_ranges,
                    route=np.asarray(waypoints, dtype=float))


def stretch_covariances(n_scans: int, stretch_scans: int,
                        levels: tuple[PoseNoise, ...]) -> np.ndarray:
    """(S, 3, 3) pose covariances that change between stretches of a log.

    Scan ``k`` belongs to stretch ``k // stretch_scans`` and gets the covariance of
    ``levels[stretch % len(levels)]``: e.g. quiet, noisy, very noisy, quiet, ... like
    a localiser that loses and regains its map.
    """
    if stretch_scans < 1 or not levels:
        raise GpoccError("pose-noise stretches need at least one level and one scan each")
    which = (np.arange(n_scans) // stretch_scans) % len(levels)
    return np.stack([levels[i].covariance for i in which]) if n_scans else np.zeros((0, 3, 3))


def perturb_poses(poses: np.ndarray, covariances: np.ndarray,
                  rng: np.random.Generator) -> np.ndarray:
    """Poses (S, 3) plus independent N(0, covariances[k]) errors, yaw wrapped to (-pi, pi].

    The covariances (S, 3, 3) are then the honest covariances of the perturbed poses
    around the given ones (one draw of 3 standard normals per scan, in scan order).
    """
    z = rng.standard_normal((len(poses), 3))
    roots = np.linalg.cholesky(covariances + 1e-18 * np.eye(3))
    out = np.asarray(poses, dtype=float) + np.einsum("sij,sj->si", roots, z)
    out[:, 2] = np.angle(np.exp(1j * out[:, 2]))
    return out


def region_truth(labels: np.ndarray, spec: GridSpec, quiet: tuple[RobotRun, ...]) -> np.ndarray:
    """The truth ``labels`` (H, W) restricted to cells no ``quiet`` run's rays reached.

    With the quiet (accurate) platform's runs, this is the area seen only by the noisy
    platform: where a map must rely on noisy inputs alone. Other cells become 255.
    """
    seen = np.zeros(spec.shape, dtype=bool)
    for run in quiet:
        visited, hit = observed_cells(spec, run)
        seen |= visited | hit
    out = labels.copy()
    out[seen] = NO_DATA
    return out


@dataclass(frozen=True, eq=False)
class Simulation:
    """A simulated multi-robot log: the world, the seed and one run per platform."""

    world: World
    seed: int
    pose_noise: PoseNoise
    runs: tuple[RobotRun, ...] = field(default_factory=tuple)


def simulate(
    world: str | World = "default",
    seed: int = 0,
    pose_noise: PoseNoise | None = None,
    platforms: tuple[Platform, ...] | None = None,
) -> Simulation:
    """Run every platform on its route of ``world`` (platform i on ``world.routes[i]``;
    default: :func:`platforms_for` the world).

    Deterministic for a given ``seed``: one ``numpy.random.default_rng(seed)`` is used
    for the platforms in order.
    """
    w = make_world(world) if isinstance(world, str) else world
    platforms = platforms or platforms_for(w)
    if len(platforms) > len(w.routes):
        raise GpoccError(f"world '{w.name}' has {len(w.routes)} routes for "
                         f"{len(platforms)} platforms")
    pose_noise = pose_noise or PoseNoise()
    rng = np.random.default_rng(seed)
    runs = tuple(simulate_run(w, p, w.routes[i], rng, pose_noise)
                 for i, p in enumerate(platforms))
    return Simulation(world=w, seed=seed, pose_noise=pose_noise, runs=runs)


# --------------------------------------------------------------------------- ground truth


def truth_spec(world: World, resolution: float = 0.1, margin: float = 0.5) -> GridSpec:
    """The world's bounding box plus ``margin`` metres at ``resolution`` metres."""
    x0, y0, x1, y1 = world.bounds
    return GridSpec.from_bounds(x0 - margin, y0 - margin, x1 + margin, y1 + margin, resolution)


def observed_cells(spec: GridSpec, run: RobotRun) -> tuple[np.ndarray, np.ndarray]:
    """Cells seen by a run's noiseless rays (true poses, nominal bearings).

    A ray runs to its true hit, or to the platform's range when nothing is within it.

    Returns:
        visited (H, W) bool: cells any ray crossed (hit cells included);
        hit (H, W) bool: cells holding a true hit point.
    """
    p = run.platform
    visited = np.zeros(spec.width * spec.height, dtype=bool)
    hit = np.zeros_like(visited)
    origins, phi = _scan_rays(run.true_poses, p.angles)
    true = run.true_ranges.reshape(-1)
    is_hit = np.isfinite(true)
    length = np.where(is_hit, true, p.max_range_m)
    for i0 in range(0, origins.shape[0], _RAY_CHUNK):
        sl = slice(i0, i0 + _RAY_CHUNK)
        # The simulated laser sits at the base (no mount): the laser pose is (origin, phi).
        ends = beam_rules.beam_points(np.column_stack((origins[sl], phi[sl])), 0.0, length[sl])
        cells = ray_cells(spec, origins[sl], ends)
        visited[cells.row * spec.width + cells.col] = True
        row, col, inside = spec.index_of(ends[is_hit[sl]])
        hit[(row * spec.width + col)[inside]] = True
    return visited.reshape(spec.shape), hit.reshape(spec.shape)


def outline_cells(spec: GridSpec, world: World) -> np.ndarray:
    """(H, W) bool: cells crossed by any obstacle outline (circles as 256-gons)."""
    seg = world.boundary_segments()
    cells = ray_cells(spec, seg[:, 0], seg[:, 1])
    out = np.zeros(spec.shape, dtype=bool)
    out[cells.row, cells.col] = True
    return out


def truth_raster(
    world: World, runs: tuple[RobotRun, ...] | list[RobotRun], resolution: float = 0.1
) -> tuple[np.ndarray, GridSpec]:
    """Ground-truth classes of the observed area: 1 occupied, 0 free, 255 no data.

    Occupied: a cell holding a true hit point, or holding an obstacle outline that some
    ray entered. Free: any other cell a noiseless ray crossed. No data: the rest.

    Returns:
        (labels (H, W) uint8, grid) on :func:`truth_spec` of the world.
    """
    spec = truth_spec(world, resolution)
    visited = np.zeros(spec.shape, dtype=bool)
    hit = np.zeros(spec.shape, dtype=bool)
    for run in runs:
        v, h = observed_cells(spec, run)
        visited |= v
        hit |= h
    occupied = hit | (outline_cells(spec, world) & visited)
    labels = np.full(spec.shape, NO_DATA, dtype=np.uint8)
    labels[visited] = 0
    labels[occupied] = 1
    return labels, spec


def sim_config(sim: Simulation, resolution: float = 0.1) -> dict:
    """A gpocc config (plain data for YAML) matching the simulation's sensors exactly."""
    sensors = []
    for run in sim.runs:
        p = run.platform
        sensors.append({
            "name": p.name,
            "scan_topic": p.scan_topic,
            "pose_topic": p.pose_topic,
            "range_variance_m2": p.range_variance_m2,
            "bearing_variance_deg2": p.bearing_variance_deg2,
            "pose_covariance": [[float(v) for v in row] for row in run.pose_covariance],
            "no_return_free_m": round(p.no_return_free_m, 3),
        })
    return {"seed": int(sim.seed), "sensors": sensors, "map": {"resolution_m": resolution}}
