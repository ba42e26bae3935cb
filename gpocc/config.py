"""Job configuration: YAML validated into frozen dataclasses.

Units are in the key names: ``_m`` metres, ``_m2`` square metres, ``_deg`` degrees,
``_deg2`` square degrees, ``_rad2`` square radians, ``_s`` seconds. Every error names the
key and the file. Unknown keys are errors (a typo must not silently fall back to a default).
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from gpocc.errors import GpoccError, check_regular_file


@dataclass(frozen=True)
class MountConfig:
    """Static laser mount on the robot base: offset (metres), yaw (degrees), and
    upside_down (rolled 180 degrees about its x axis, so it sweeps clockwise seen from
    above: its bearings are mirrored)."""

    x_m: float = 0.0
    y_m: float = 0.0
    yaw_deg: float = 0.0
    upside_down: bool = False


@dataclass(frozen=True)
class SensorConfig:
    """One robot's laser and pose source, with its noise model.

    ``inputs``: globs on the input's file name (or path) this entry applies to ([]: every
    input). ``scan_topic``: a LaserScan or PointCloud2 topic; ``pose_topic``: the pose
    (and covariance) source (null: found in the scan's namespace).
    ``range_variance_m2``, ``bearing_variance_deg2``: the laser's noise.
    ``pose_covariance`` is the 3x3 covariance of (x, y, yaw) in (m^2, m^2, rad^2, with
    m*rad off-diagonals). It is used for inputs that carry no covariance (CARMEN logs,
    PoseStamped-like sources) or for every scan when ``override_pose_covariance`` is set.
    ``mount``: the laser on the pose's frame, only where TF does not give it.
    A scan takes the pose interpolated between two poses at most ``max_pose_gap_s``
    apart, or one within ``stamp_tolerance_s``. ``max_tilt_deg``: scans whose laser
    plane TF tilts more than this from level are skipped. Beams without a return clear
    ``no_return_free_m``; ``range_min_m`` / ``range_max_m`` override the message's
    limits. With TF, the pose is the chain ``map_frame`` -> the scan's frame unless
    ``position_from_tf`` is false (then the pose topic gives it, with ``mount``);
    covariance entries at or above ``covariance_sentinel`` (or NaN) are unknown, a pose
    topic's covariance is held up to ``max_covariance_age_s``, and
    ``repair_pose_covariance`` sets a non-PSD one's negative eigenvalues to zero instead
    of refusing it.
    PointCloud2 only: ``height_band_m`` above the floor (``base_height_m`` below the
    ``base_frame``'s origin) are obstacles, bearings binned at
    ``horizontal_resolution_deg`` (null: from the cloud's layout).
    """

    name: str = "robot"
    inputs: tuple[str, ...] = ()
    scan_topic: str | None = None
    pose_topic: str | None = None
    range_variance_m2: float = 0.0004
    bearing_variance_deg2: float = 0.01
    pose_covariance: tuple[tuple[float, ...], ...] = (
        (0.0025, 0.0, 0.0),
        (0.0, 0.0025, 0.0),
        (0.0, 0.0, 0.0003),
    )
    override_pose_covariance: bool = False
    mount: MountConfig = field(default_factory=MountConfig)
    max_pose_gap_s: float = 0.25
    # A planar laser (LaserScan) whose scan plane TF tilts more than this from level is
    # not mapped: its beams climb or fall by range x sin(tilt) and meet floors, tables
    # and ceilings that flattening would draw as walls (gpocc.io.laserpose).
    max_tilt_deg: float = 5.0
    # A scan within this of a pose sample takes it when it cannot be interpolated
    # (header stamps of one driver vs. another's, or log times: never exact equality).
    stamp_tolerance_s: float = 0.02
    no_return_free_m: float = 5.0
    range_min_m: float | None = None
    range_max_m: float | None = None
    # Bags with TF (gpocc.io.laserpose): the laser pose is the TF chain map_frame ->
    # the scan's frame; the covariance comes from pose_topic (held up to
    # max_covariance_age_s), entries >= covariance_sentinel or NaN meaning "unknown".
    map_frame: str = "map"
    position_from_tf: bool = True
    covariance_sentinel: float = 1e3
    max_covariance_age_s: float = 30.0
    repair_pose_covariance: bool = False
    # 3-D lidars (scan_topic a sensor_msgs/PointCloud2; gpocc.io.cloudread): returns
    # between the heights height_band_m above the floor are obstacles; the floor is
    # base_height_m below the base frame's origin (0: the base frame is on the floor, as
    # REP 105's base_footprint). Bearings are binned at horizontal_resolution_deg (null:
    # from the cloud's layout). base_frame: the frame whose x-y plane is the ground
    # plane (null: the frame TF moves the robot by, e.g. base_footprint).
    height_band_m: tuple[float, float] = (0.1, 2.0)
    base_height_m: float = 0.0
    horizontal_resolution_deg: float | None = None
    base_frame: str | None = None

    @property
    def bearing_variance_rad2(self) -> float:
        return self.bearing_variance_deg2 * (math.pi / 180.0) ** 2

    @property
    def pose_covariance_matrix(self) -> np.ndarray:
        """(3, 3) covariance of (x, y, yaw)."""
        return np.asarray(self.pose_covariance, dtype=float)


@dataclass(frozen=True)
class UnscentedConfig:
    """Unscented-transform spread (alpha), prior (beta) and secondary scaling (kappa).

    The defaults put the sigma points at sqrt(3) standard deviations (alpha^2 (n + kappa)
    = 3 for the 5-D input, Julier's choice that matches the Gaussian's fourth moments);
    against Monte Carlo at 15 deg heading noise they keep the covariance within 2%, where
    alpha = 1, beta = 2 was 7-8% off (tests/samples/test_unscented.py).
    """

    alpha: float = 0.7745966692414834
    beta: float = 0.5
    kappa: float = 0.0


#: The values of ``model.training.classifier_offset_range``.
OFFSET_RANGES: tuple[str, ...] = ("wide", "latent")

#: The values of ``model.training.classifier_targets``.
CLASSIFIER_TARGETS: tuple[str, ...] = ("platt", "hard")

#: The values of ``samples.label_weights``.
LABEL_WEIGHTS: tuple[str, ...] = ("none", "share", "count")


@dataclass(frozen=True)
class SamplesConfig:
    """How beams become training samples.

    Free samples lie along each beam every ``free_spacing_m`` from the sensor, stopping
    short of the hit by ``hit_gap_m`` or ``hit_gap_sigmas`` range standard deviations,
    whichever is larger (the true surface may be that much nearer than the reading).
    The band this leaves empty before each hit is what blurs walls (the GP carries the
    hits' +1 into it); ``make experiment``'s variants ``hit-gap-0.25`` and ``hit-gap-0.1``
    measure a wider and a narrower gap.
    ``thin_cell_m`` keeps at most one sample of each label
    per square cell of that side (the most certain one), which bounds the training set by
    the mapped area instead of the log length; 0 disables thinning.

    ``min_label_share`` (with thinning) drops a cell's kept sample of one label when that
    label is less than this share of all the samples that fell in the cell over the whole
    log: a person seen once in a corridor crossed by a hundred beams, or a wall cell that
    pose jitter let a few beams pass. Thinning alone would keep one sample of each label
    and forget the counts. 0 (the default, the method as published) keeps every label;
    0.1 suits long real logs with moving people (configs/carmen_*.yaml). On the static
    simulated world it removes the noisy platform's scattered hits, which is what the
    input-noise model is there to handle.

    ``free_clearance_m`` drops free samples within that distance of an occupied sample
    (after thinning): beams that graze a wall leave free samples centimetres from its
    hits, and held-out hits on that wall then come out free. 0 keeps them (the method as
    published; ``make experiment``'s variant ``clearance-0`` measures it).

    ``free_range_variance``: free samples of a beam that hit carry that beam's range
    variance, like its hit (false: free samples carry no range variance, as published);
    see gpocc.samples.beams.build_samples.

    ``label_weights`` (with thinning): ``none`` (as published) gives every kept sample
    the learned label noise; ``share`` multiplies it by 1 / (the share of the sample's
    label among all samples counted in its cell, up to 1000), so a kept sample weighs as
    the labels it stands for: in a cell seen free 90 times and occupied 10 times, the
    GP's mean there leans to the count-weighted -0.8 instead of the 0 of one sample each
    (for samples at one point, the GP of every counted label exactly). ``count``
    (default) does what ``share`` does and also divides the noise by the label's count in
    the cell to the power ``label_count_power``: a wall cell hit by a hundred beams pins
    the map harder than a cell one beam crossed. In a cell that saw one label, power 1 is
    the GP of every counted sample as an independent observation at one point; lower
    powers temper it, since a cell's samples share their scans' pose errors. The learned
    label noise is then that of a sample counted once. docs/results.md ("Against other
    settings", variant ``no-label-weights``) compares ``none``; variant ``share-labels``
    of ``make experiment`` measures ``share``.
    """

    free_spacing_m: float = 0.4
    hit_gap_m: float = 0.15
    hit_gap_sigmas: float = 2.0
    beam_stride: int = 1
    scan_stride: int = 1
    thin_cell_m: float = 0.15
    min_label_share: float = 0.0
    free_clearance_m: float = 0.05
    free_range_variance: bool = False
    label_weights: str = "count"
    label_count_power: float = 0.5
    unscented: UnscentedConfig = field(default_factory=UnscentedConfig)

    @property
    def counts_labels(self) -> bool:
        """Whether thinning counts each cell's labels (for ``min_label_share`` or
        ``label_weights``)."""
        return self.thin_cell_m > 0 and (self.min_label_share > 0
                                         or self.label_weights != "none")

    @property
    def weighs_labels(self) -> bool:
        """Whether kept samples carry label-noise factors (``label_weights``: ``share``
        or ``count``)."""
        return self.thin_cell_m > 0 and self.label_weights != "none"


@dataclass(frozen=True)
class HyperparametersConfig:
    """Initial (or fixed) kernel hyperparameters.

    Neural-network kernel: ``signal_variance`` (dimensionless, labels are +-1),
    ``bias_variance`` and ``weight_variance`` (1/m^2, per axis x, y). Squared exponential:
    ``signal_variance`` and ``lengthscale_m`` (per axis). ``noise_variance`` is the
    label-noise variance added to the diagonal.
    """

    signal_variance: float = 4.0
    bias_variance: float = 10.0
    weight_variance: tuple[float, float] = (30.0, 30.0)
    lengthscale_m: tuple[float, float] = (0.5, 0.5)
    noise_variance: float = 0.1


#: What the learned input-noise scale g multiplies (``input_noise_scale_part``;
#: :func:`gpocc.gp.inputscale.scale_input_noise`): whole input covariances, or their pose
#: part.
INPUT_NOISE_SCALE_PARTS = ("all", "pose")


@dataclass(frozen=True)
class TrainingConfig:
    """Hyperparameter learning: log marginal likelihood summed over local patches.

    ``patches`` neighbourhoods of ``patch_size`` samples each, centred on randomly chosen
    samples (spatially stratified), each centred at the origin as at inference; at least
    ``patches_per_sensor`` times the number of sensors, so that a site of many separate
    buildings (each input its own sensor without a config) learns from patches spread
    over all of them rather than from ten at its edges, where the hyperparameters of
    the buildings at the edges are learned for all (docs/benchmarks.md, "City").
    ``patch_centres``: ``hits`` (default) draws the centres from the occupied samples, so
    every patch holds a boundary; ``samples`` from all samples, where a draw of mostly open
    space can learn a kernel far too smooth for the walls. ``patch_offset_m``: each centre
    is then moved by the sum of two uniform draws in [-patch_offset_m / 2, patch_offset_m
    / 2] per axis (a tent over [-patch_offset_m, patch_offset_m], the weights a cell
    takes from the anchors around it with ``model.blend_overlap: 1`` when it is
    ``model.block_size_m``), and the patch is the samples nearest the moved centre: a
    map's local problems are centred on a lattice that pays no heed to the walls, and the
    neural-network kernel is not translation invariant (a wall far from a problem's centre
    needs a larger bias variance to stay sharp), so patches centred on hits alone learn a
    kernel for walls through the centre. Unset (default): ``model.block_size_m``
    (:attr:`ModelConfig.effective_training`); 0: the centres as drawn (variant
    ``no-patch-offset`` of ``make experiment``). The
    classifier is fitted on the same kind of patches. Global
    stage: ``scipy.optimize.dual_annealing`` limited to ``anneal_maxfun`` evaluations
    (20: on ten logs and worlds, 60 reached the same optimum with 29-54 more evaluations;
    docs/benchmarks.md, 'Annealing budget of hyperparameter learning', re-measures it on
    the real logs; its job is to leave a start whose covariance is not positive definite,
    where L-BFGS-B alone stays); then L-BFGS-B for at most
    ``lbfgs_maxiter`` iterations, within ``log_bounds_width``
    (natural log) of the initial values. The label-noise variance is kept at or above
    ``min_noise_variance``: with uncertain inputs the one-point diagonal already carries
    input-induced noise, and without a floor the likelihood of a few patches can drive
    the label noise to zero and interpolate the accurate samples' labels exactly.
    ``learn: false`` keeps the initial values; ``fixed`` keeps only the named ones (the
    kernel's parameter names, e.g. ``bias_variance`` or ``weight_variance_x``, and
    ``noise_variance``) at their initial values while the others are learned.
    ``classifier_holdout``: how the Platt
    classifier's training labels are held out, ``sample`` (leave one sample out, the method
    as published, default) or ``scan`` (leave one scan out); see gpocc.gp.classify
    (leave-one-scan-out measured worse calibrated on held-out data: docs/results.md,
    'Summary', made with ``python -m bench.experiment --variant scan-cv``).
    ``classifier_variance`` (with ``classifier_holdout: sample``): the variance of each
    held-out prediction the classifier is fitted on, ``label`` (the leave-one-out
    predictive variance of the noisy label, as published) or ``latent`` (of the latent
    function: that minus the label-noise variance, the quantity a map cell's variance is;
    gpocc.gp.classify). ``classifier_temperature``: ``none``, or then fit a temperature
    T, p = Phi((mu + c) / (T sqrt(s + var))), on the same held-out samples with the
    latent variance (``samples``) or on labelled points of held-out scans predicted as
    map cells are (``beams``, default: the points of ``classifier_offset: beams``): the
    probabilities of map cells move, their ranking (AUC) does not (gpocc.gp.classify).
    ``make experiment``'s variant ``no-temperature`` measures ``none``.
    ``classifier_offset: beams`` (default) then re-fits the classifier's offset on
    labelled points of every ``calibration_every``-th scan (those known to
    ``calibration_max_position_std_m``), predicted from the other scans' samples in up to
    ``calibration_blocks`` map blocks, together with the temperature when that is fitted
    there too: probabilities calibrated where beams end, hits and the free space along and
    in front of them, as map cells are predicted. ``holdout`` keeps the leave-one-out
    fit's offset (``make experiment``'s variant ``offset-holdout``).
    ``classifier_offset_range``: the range of that re-fitted offset c. ``wide`` within
    +-100; ``latent`` (default) within the largest |mu| of the points it is fitted on, so
    the decision stays among the latent means it saw. Where those means barely separate the
    labels, a wide fit can run c and T far out together, and p then follows the latent
    variance alone (gpocc.gp.classify.fit_offset_and_temperature).
    ``classifier_targets``: what the offset and temperature fits aim at (on held-out
    scans' points, or with ``classifier_temperature: samples`` on held-out samples).
    ``platt`` (default) gives each point Platt's out-of-sample target (N + 1) / (N + 2)
    of its label (N the points of that label), ``hard`` the label itself (0 or 1). Where
    the latent means put (nearly) every point on its label's side, hard targets drive the
    temperature to its lower bound: the map's probabilities then reach 0 and 1 in float32
    almost everywhere, those cells tie, and the map loses its ranking. Platt's targets
    keep a finite temperature there and change little elsewhere (``make experiment``'s
    variant ``hard-targets``).
    ``learn_input_noise_scale``: also learn a scale g on every input covariance (S -> g S,
    pose factors -> sqrt(g) A; gpocc.gp.inputscale) within ``[min_input_noise_scale,
    max_input_noise_scale]``, starting at 1; false (default) keeps g = 1, the covariances
    as the config and the log state them. A learned g often ends on its upper bound: the
    patches' likelihood keeps rising with it while the maps' walls blur (variant
    ``learned-g``, docs/results.md "Against other settings"). The method as published is
    ``learn_input_noise_scale: false`` with ``min_noise_variance: 0.01`` (variant
    ``published``). ``input_noise_scale_part``: what g scales,
    ``all`` of each input's covariance (default) or only its ``pose`` part (the scan's
    pose error, ``pose_factors``; the sensor's range and bearing noise stay as stated).
    ``calibration_near_wall``: near-wall free points per hit (0.05-0.3 m in front of it,
    as ``gpocc split`` draws them) added to those labelled points, so that the temperature
    and offset are fitted on the space in front of walls too.
    ``isotropic`` (default true): learn one value for both axes of each per-axis kernel
    parameter (the NN kernel's ``weight_variance``, the SE kernel's ``lengthscale``; their
    initial values must then be equal): a map frame's axes mean nothing in the world, while
    a pair learned from a few patches takes its ratio from the walls those patches happen
    to hold (on Freiburg 079 the two weight variances came out 73 and 495); tied, the
    kernel does not depend on which way the map's axes point. False learns one value per
    axis (variant ``anisotropic`` of ``make experiment``).
    ``local_search``: the stage after the annealing, ``lbfgs`` (L-BFGS-B, default) or
    ``scoring`` (Fisher scoring, gpocc.gp.refine, as ``gpocc update`` refines: the same
    optimum in fewer evaluations; L-BFGS-B where the loops give no derivative in g).
    ``local_starts``: local searches from that many distinct points the annealing visited
    (its best first, then the next best at least a factor e apart in some parameter),
    keeping the best: the patches' likelihood has several optima, and the annealing's
    best point does not always lie in the best one's basin (docs/benchmarks.md,
    "Learning's local search").
    """

    learn: bool = True
    patches: int = 10
    patches_per_sensor: int = 2
    patch_size: int = 128
    patch_centres: str = "hits"
    patch_offset_m: float | None = None
    anneal_maxfun: int = 20
    lbfgs_maxiter: int = 40
    local_search: str = "lbfgs"
    local_starts: int = 1
    fixed: tuple[str, ...] = ()
    isotropic: bool = True
    log_bounds_width: float = 4.0
    min_noise_variance: float = 0.1
    classifier_holdout: str = "sample"
    classifier_offset: str = "beams"
    classifier_offset_range: str = "latent"
    classifier_variance: str = "label"
    classifier_temperature: str = "beams"
    classifier_targets: str = "platt"
    calibration_every: int = 10
    calibration_blocks: int = 64
    calibration_near_wall: int = 1
    calibration_max_position_std_m: float = 0.075
    learn_input_noise_scale: bool = False
    min_input_noise_scale: float = 0.05
    max_input_noise_scale: float = 4.0
    input_noise_scale_part: str = "all"

    @property
    def uses_beam_points(self) -> bool:
        """Whether the classifier's offset or temperature is fitted on labelled points of
        held-out scans (gpocc.samples.heldout.calibration_points)."""
        return "beams" in (self.classifier_offset, self.classifier_temperature)


@dataclass(frozen=True)
class ModelConfig:
    """The GP model and its local inference.

    ``kernel``: ``nn`` (neural network / arcsin, default) or ``se``. ``input_noise``: use
    the samples' covariances (false is the GP-without-input-uncertainty baseline).
    ``quadrature_level``: Gauss-Hermite nodes per dimension. ``neighbours``: training
    samples per local problem. ``block_size_m``: side of the square block of queries that
    shares one neighbourhood. ``blend_overlap``: the share of a block, across each block
    boundary, over which two neighbouring blocks' predictions are blended (0 < o <= 1).
    1 blends bilinearly across whole blocks, so every cell is predicted by four local
    problems; smaller values predict a block's central (1 - o)^2 by its own problem
    alone, so each cell costs (1 + o)^2 problems on average instead of four.
    ``backend``: where the expected kernels are computed (:mod:`gpocc.gp.backends`):
    ``compiled`` (C loops for the kernels they serve, numpy for the others), ``numpy``
    (the reference; slower) or ``auto`` (compiled where built).
    ``diagonal``: the training covariance's diagonal E[k(x_i, x_i)]: ``one-point`` (one
    random point) or ``two-draw`` (two draws of a sample's input that share its scan's
    pose error and have independent sensor noise: the double integral of the method's
    K(u_i, u_j) taken at i = j).
    ``covariance_precision``: the arithmetic of the map's local problems (and of the
    classifier's held-out predictions): ``single`` (default) computes the neural-network
    kernel's expected training covariances between samples and the cross-covariances to
    the queries in single precision, about twice as fast, within about 1e-6 of the
    kernel's scale (each arcsine argument's distance from +-1 is formed without
    cancellation); the diagonal, same-scan pairs, Cholesky factor and solves stay double.
    ``double``: everything in double. Training's likelihoods are always double.
    """

    kernel: str = "nn"
    input_noise: bool = True
    quadrature_level: int = 2
    neighbours: int = 128
    block_size_m: float = 1.0
    blend_overlap: float = 1.0
    backend: str = "auto"
    diagonal: str = "one-point"
    covariance_precision: str = "single"
    hyperparameters: HyperparametersConfig = field(default_factory=HyperparametersConfig)
    training: TrainingConfig = field(default_factory=TrainingConfig)

    @property
    def effective_training(self) -> TrainingConfig:
        """``training`` with an unset ``patch_offset_m`` set to ``block_size_m``: the
        patches' centres move as a map cell lies from the anchors that blend it."""
        if self.training.patch_offset_m is not None:
            return self.training
        return dataclasses.replace(self.training, patch_offset_m=self.block_size_m)


@dataclass(frozen=True)
class ClassifyConfig:
    """Thresholds on p(occupied): above ``occupied`` is occupied, below ``free`` is free.

    A cell whose latent predictive variance is above ``max_variance_ratio`` times its
    prior variance is unsure whatever its probability: the data there explain too little
    of the prior for a decision (far from any sample the neural-network kernel's mean
    extrapolates, and its probability says little). On Intel's held-out points the
    ratio stays below 0.06, and 1 m or more from any sample it is above 0.21.
    """

    occupied: float = 0.65
    free: float = 0.35
    max_variance_ratio: float = 0.1


@dataclass(frozen=True)
class GeorefConfig:
    """Where the map frame sits in a projected CRS, so GeoTIFFs land where the robot was.

    ``easting_m``, ``northing_m``: the map frame's origin (x = y = 0) in the CRS, metres.
    ``yaw_deg``: the direction of the map frame's +x axis, degrees counter-clockwise from
    the CRS's east axis (the ROS / ENU convention). A map point (x, y) lands at
    ``E = easting + cos(yaw) x - sin(yaw) y``, ``N = northing + sin(yaw) x + cos(yaw) y``.
    """

    epsg: int = 0
    easting_m: float = 0.0
    northing_m: float = 0.0
    yaw_deg: float = 0.0


@dataclass(frozen=True)
class MapConfig:
    """Map output defaults.

    ``georef``: the map frame's place in a projected CRS (:class:`GeorefConfig`), or null
    for a local engineering frame in metres. ``epsg`` is the retired form (a CRS without
    an origin misplaces the map); any value other than null is an error naming the fix.
    ``max_pgm_pixels``: optional limit on the side of ``map.pgm``; a larger map is an
    error (the map_server image is never silently coarsened). Null: no limit.
    ``max_beam_distance_m``: cells farther than this from every beam (sensor to hit, or
    to the free extent of a no-return beam) are nodata in every layer, and blocks wholly
    that far are not computed; null maps everywhere. 1.5 m: beyond about 1 m from any
    sample the variance already exceeds ``classify.max_variance_ratio`` of the prior (the
    cells are unsure), so no classified cell is lost, and with the coverage raster's
    0.24 m error (:mod:`gpocc.samples.coverage`) every cell more than 2 m from a beam is
    nodata.
    ``max_cells``: the largest raster (map, grid, truth) a command may make; larger
    requests are refused before allocating (see :mod:`gpocc.limits`).
    ``anchor_origin_m``: [x, y] metres of the map frame (not of ``georef``'s CRS), a
    north-west corner of the GP map's anchor blocks (the local problems sit half a
    spacing east and south of it, then every spacing: ``model.block_size_m`` rounded down
    to whole cells). Maps of several models with the same value share their anchors at
    resolutions that divide ``model.block_size_m``, so they differ only by the models;
    the whole map then starts a whole number of blocks from it. Null (default): the
    north-west corner of the model's whole map (the samples' extent plus ``margin_m``, at
    ``resolution_m``). ``gpocc update`` keeps the model's unless its config states the
    key (``anchor_origin_m: null`` there unpins the update).
    """

    resolution_m: float = 0.1
    margin_m: float = 1.0
    anchor_origin_m: tuple[float, float] | None = None
    georef: GeorefConfig | None = None
    epsg: int | None = None
    tile_pixels: int = 4096
    max_pgm_pixels: int | None = None
    max_beam_distance_m: float | None = 1.5
    max_cells: int = 200_000_000


@dataclass(frozen=True)
class GridConfig:
    """Log-odds occupancy grid baseline (inverse sensor model, clamped log-odds).

    Each hit adds ``log_odds_occupied`` to its cell, each beam ``log_odds_free`` to the
    cells it crosses, clamped to [``clamp_min``, ``clamp_max``]. ``spread_hits``: share
    each hit's update among nearby cells by its position's Gaussian (the same sensor and
    pose noise as the GP's samples) instead of its endpoint cell alone.
    """

    log_odds_occupied: float = 0.85
    log_odds_free: float = -0.4
    clamp_min: float = -4.0
    clamp_max: float = 4.0
    spread_hits: bool = False


@dataclass(frozen=True)
class TransformConfig:
    """A rigid transform from an input's map frame into the job's map frame: a point
    (x, y) of the input lands at ``(x_m + cos(yaw) x - sin(yaw) y, y_m + sin(yaw) x +
    cos(yaw) y)``, and headings turn by ``yaw_deg`` (degrees, counter-clockwise)."""

    x_m: float = 0.0
    y_m: float = 0.0
    yaw_deg: float = 0.0


@dataclass(frozen=True)
class InputConfig:
    """Settings of one input: ``path`` matches an input like a sensor's ``inputs`` globs
    (its file name or its path), ``transform`` places its poses in the job's map frame
    (a recording made in another map frame, on another day)."""

    path: str = ""
    transform: TransformConfig = field(default_factory=TransformConfig)


@dataclass(frozen=True)
class BHMConfig:
    """Bayesian Hilbert map baseline (Senanayake and Ramos, CoRL 2017): gpocc.baselines.bhm.

    Features: a bias and squared-exponential kernels ``exp(-gamma d^2)`` (``gamma`` in
    1/m^2) centred on a square lattice of inducing points ``inducing_spacing_m`` apart,
    cut to zero beyond ``3 / sqrt(gamma)`` (where a kernel is below 1.3e-4). Training
    points: each hit (occupied) and free points every ``free_spacing_m`` along each beam
    up to ``hit_gap_m`` before its hit (a no-return beam: up to its free extent),
    counted per label in squares of ``sample_cell_m`` (0: every point kept on its own;
    a count weights its point's likelihood exactly as that many repeated points would).
    The weights' prior is N(0, 1 / prior_precision) each; ``em_iterations`` EM passes of
    the variational (Jaakkola-Jordan) update; ``mean_update``: ``coupled`` (the
    factorised posterior's exact means, default) or ``diagonal`` (the paper's per-weight
    shortcut, overconfident where features overlap: held-out AUC 0.50 on Intel). Defaults
    were tuned lightly on one held-out real log only (Intel, every 10th scan held out,
    predicted at the held-out points): 0.25 m and gamma 25 gave AUC 0.994, Brier 0.034,
    against 0.981 and 0.065 at 0.5 m and gamma 6; 10 EM passes against 3 gained 0.004
    in AUC, 20 another 0.0004. Prior precision 0.01 had the higher evidence bound and
    scored better at the points (AUC 0.995, Brier 0.031) but worse on the 0.1 m map
    `gpocc evaluate` reads (Brier 0.051 against 0.047) and fitted twice as slowly.
    """

    inducing_spacing_m: float = 0.25
    gamma: float = 25.0
    prior_precision: float = 0.1
    em_iterations: int = 10
    free_spacing_m: float = 0.2
    hit_gap_m: float = 0.05
    sample_cell_m: float = 0.05
    mean_update: str = "coupled"


@dataclass(frozen=True)
class Config:
    """A whole job's configuration."""

    seed: int = 0
    sensors: tuple[SensorConfig, ...] = ()
    inputs: tuple[InputConfig, ...] = ()
    samples: SamplesConfig = field(default_factory=SamplesConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    classify: ClassifyConfig = field(default_factory=ClassifyConfig)
    map: MapConfig = field(default_factory=MapConfig)
    grid: GridConfig = field(default_factory=GridConfig)
    bhm: BHMConfig = field(default_factory=BHMConfig)


# --------------------------------------------------------------------------- loading


class _Loader(yaml.SafeLoader):
    """``yaml.safe_load`` with two YAML 1.1 traps closed.

    A repeated key is an error (PyYAML keeps the last one, so a second ``model:`` block
    would silently drop the first). ``1e-6`` is a number (YAML 1.1 reads a float without
    a dot as the string '1e-6', and the key would then be refused as not a number).
    """

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: set[str] = set()
        for key_node, _ in node.value:
            if isinstance(key_node, yaml.ScalarNode) and key_node.tag != "tag:yaml.org,2002:merge":
                if key_node.value in seen:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"key '{key_node.value}' is given twice",
                        key_node.start_mark)
                seen.add(key_node.value)
        return super().construct_mapping(node, deep)


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


_NON_NEGATIVE_SUFFIXES = ("_m2", "_deg2", "_rad2", "variance")
_NON_NEGATIVE_KEYS = {
    "max_pose_gap_s", "no_return_free_m", "hit_gap_m", "thin_cell_m", "margin_m",
    "free_clearance_m", "sample_cell_m", "stamp_tolerance_s", "calibration_near_wall",
    "min_noise_variance", "min_label_share", "max_beam_distance_m", "max_covariance_age_s",
    "range_min_m", "range_max_m", "beta", "kappa", "log_bounds_width", "hit_gap_sigmas",
    "patches_per_sensor", "patch_offset_m",
}
_POSITIVE_KEYS = {
    "free_spacing_m", "resolution_m", "block_size_m", "signal_variance", "noise_variance",
    "alpha", "neighbours", "quadrature_level", "beam_stride", "scan_stride", "patches",
    "patch_size", "tile_pixels", "anneal_maxfun", "lbfgs_maxiter", "local_starts",
    "lengthscale_m",
    "max_variance_ratio", "max_pgm_pixels", "covariance_sentinel",
    "min_input_noise_scale", "max_input_noise_scale", "calibration_blocks",
    "horizontal_resolution_deg",
    "calibration_max_position_std_m",
    "weight_variance", "bias_variance", "max_cells",
    "inducing_spacing_m", "gamma", "prior_precision", "em_iterations",
}


#: Larger variances (1 km, 1000 rad or deg standard deviation) are unit mistakes, and
#: overflow the sigma-point and kernel arithmetic.
_MAX_VARIANCE = 1e6
#: A laser mount farther than this from the robot base is a unit mistake.
_MAX_MOUNT_M = 1e3
#: An input transform moving farther than this is a unit mistake (as for poses,
#: gpocc.io.scans.MAX_POSITION_M).
_MAX_TRANSLATION_M = 1e7
#: A map border wider than this around the data is a unit mistake.
_MAX_MARGIN_M = 1e4
#: The widest learning box: e^20 (5e8) times each initial value either way; wider boxes
#: put bounds at 0 or infinity in floating point.
_MAX_LOG_BOUNDS_WIDTH = 20.0
#: Unscented-transform settings beyond these overflow its weights (alpha^2 (n + kappa)).
_MAX_UT_ALPHA = 10.0
_MAX_UT_WEIGHT = 1e6
#: Initial kernel values above this are unit mistakes (a signal variance of 1e300 overflowed
#: the map's float32 variance).
_MAX_HYPERPARAMETER = 1e12
#: Most samples in one local problem: its covariance is factored per map block (4096:
#: 134 MB and seconds each).
_MAX_LOCAL_SAMPLES = 4096
#: The coarsest map cell (map.resolution_m, --resolution): 1000 km is a unit mistake
#: (and beyond float32, the map's own number type, from 3.4e38 on).
MAX_RESOLUTION_M = 1e6
#: The largest integer a config key may hold (2^32 - 1: seeds and counts fit in int64).
_MAX_INT = 2**32 - 1


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _convert(value: Any, tp: Any, key: str, source: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _convert(value, inner[0], key, source)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise GpoccError(f"{source}: key '{key}' must be a mapping, got {value!r}")
        return _build(tp, value, key, source)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise GpoccError(f"{source}: key '{key}' must be a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(v, args[0], f"{key}[{i}]", source) for i, v in enumerate(value))
        if len(value) != len(args):
            raise GpoccError(f"{source}: key '{key}' must have {len(args)} entries, got {value!r}")
        pairs = enumerate(zip(value, args, strict=True))
        return tuple(_convert(v, a, f"{key}[{i}]", source) for i, (v, a) in pairs)
    if tp is bool:
        if not isinstance(value, bool):
            raise GpoccError(f"{source}: key '{key}' must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise GpoccError(f"{source}: key '{key}' must be an integer, got {value!r}")
        if abs(value) > _MAX_INT:  # beyond numpy's int64 indices and counts
            raise GpoccError(f"{source}: key '{key}' must be at most {_MAX_INT}, got {value}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise GpoccError(f"{source}: key '{key}' must be a number, got {value!r}")
        if not math.isfinite(value):
            raise GpoccError(f"{source}: key '{key}' must be finite, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise GpoccError(f"{source}: key '{key}' must be a string, got {value!r}")
        return value
    raise GpoccError(f"{source}: key '{key}' has unsupported type {_type_name(tp)}")


def _check_range(name: str, value: Any, key: str, source: str) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return
    if name in _POSITIVE_KEYS and value <= 0:
        raise GpoccError(f"{source}: key '{key}' must be positive, got {value!r}")
    if (name in _NON_NEGATIVE_KEYS or name.endswith(_NON_NEGATIVE_SUFFIXES)) and value < 0:
        raise GpoccError(f"{source}: key '{key}' must not be negative, got {value!r}")


def _build(cls: Any, data: dict[str, Any], prefix: str, source: str) -> Any:
    hints = typing.get_type_hints(cls)
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - known, key=str)  # YAML keys may be numbers or null
    if unknown:
        where = f"under '{prefix}'" if prefix else "at top level"
        raise GpoccError(
            f"{source}: unknown key '{unknown[0]}' {where}; known keys: {', '.join(sorted(known))}"
        )
    kwargs = {}
    for name, value in data.items():
        key = f"{prefix}.{name}" if prefix else name
        converted = _convert(value, hints[name], key, source)
        if isinstance(converted, tuple):
            for i, v in enumerate(converted):
                if isinstance(v, (int, float)):
                    _check_range(name, v, f"{key}[{i}]", source)
        else:
            _check_range(name, converted, key, source)
        kwargs[name] = converted
    try:
        return cls(**kwargs)
    except TypeError as exc:  # pragma: no cover - guarded by the unknown-key check
        raise GpoccError(f"{source}: {exc}") from None


def _one_of(value: str, choices: tuple[str, ...], key: str, source: str) -> None:
    """One error line unless the config's ``key`` is one of ``choices``."""
    if value not in choices:
        listed = " or ".join((", ".join(f"'{c}'" for c in choices[:-1]), f"'{choices[-1]}'"))
        raise GpoccError(f"{source}: key '{key}' must be {listed}, got {value!r}")


def _check_fixed(config: Config, source: str) -> None:
    """``model.training.fixed`` names only values the model's kernel learns, and
    ``isotropic`` ties pairs that start equal and are both held or both learned."""
    from gpocc.gp.kernels import axis_pairs, learned_names, make_kernel  # they import this

    kernel = make_kernel(config.model.kernel, config.model.hyperparameters)
    learnable = learned_names(kernel)
    for name in config.model.training.fixed:
        if name not in learnable:
            raise GpoccError(
                f"{source}: key 'model.training.fixed' names {name!r}, which the "
                f"'{config.model.kernel}' kernel does not learn; use some of "
                f"{', '.join(learnable)}")
    training = config.model.training
    if training.isotropic:
        for x, y in axis_pairs(kernel):
            names = (learnable[x], learnable[y])
            if kernel.theta[x] != kernel.theta[y]:
                raise GpoccError(
                    f"{source}: 'model.training.isotropic' learns one {names[0][:-2]} for "
                    f"both axes, but its initial values differ; give both axes one value, or "
                    "set model.training.isotropic: false to learn one per axis")
            if (names[0] in training.fixed) != (names[1] in training.fixed):
                raise GpoccError(
                    f"{source}: 'model.training.isotropic' ties {names[0]} to {names[1]}, "
                    f"but 'model.training.fixed' holds only one of them; hold both or neither, "
                    "or set model.training.isotropic: false")
    noise = config.model.hyperparameters.noise_variance
    if "noise_variance" in training.fixed and noise < training.min_noise_variance:
        raise GpoccError(
            f"{source}: 'model.training.fixed' holds noise_variance at {noise:g}, below "
            f"model.training.min_noise_variance ({training.min_noise_variance:g}); raise "
            f"the one or lower the other")


def _validate(config: Config, source: str) -> Config:
    if not 0 <= config.seed < 2**32:
        raise GpoccError(f"{source}: key 'seed' must be an integer in [0, 2^32), got "
                         f"{config.seed}")
    names = [s.name for s in config.sensors]
    if len(set(names)) != len(names):
        raise GpoccError(f"{source}: sensor names must be unique, got {names}")
    for i, sensor in enumerate(config.sensors):
        key = f"sensors[{i}].pose_covariance"
        rows = sensor.pose_covariance
        if len(rows) != 3 or any(len(row) != 3 for row in rows):
            raise GpoccError(f"{source}: key '{key}' must be a 3x3 matrix of (x, y, yaw): "
                             "three rows of three numbers")
        cov = np.asarray(rows, dtype=float)
        if not np.allclose(cov, cov.T, atol=1e-12):
            raise GpoccError(f"{source}: key '{key}' must be symmetric")
        if np.abs(cov).max() > _MAX_VARIANCE:
            raise GpoccError(f"{source}: key '{key}' has an entry beyond {_MAX_VARIANCE:g} "
                             f"(m^2, rad^2): a 1 km standard deviation; check its units")
        for name in ("range_variance_m2", "bearing_variance_deg2"):
            if getattr(sensor, name) > _MAX_VARIANCE:
                raise GpoccError(f"{source}: key 'sensors[{i}].{name}' must be at most "
                                 f"{_MAX_VARIANCE:g}, got {getattr(sensor, name)}")
        if max(abs(sensor.mount.x_m), abs(sensor.mount.y_m)) > _MAX_MOUNT_M:
            raise GpoccError(f"{source}: key 'sensors[{i}].mount' puts the laser more than "
                             f"{_MAX_MOUNT_M:g} m from the robot base; check its units (metres)")
        if np.linalg.eigvalsh(cov).min() < -1e-12:
            raise GpoccError(
                f"{source}: key '{key}' is not positive semi-definite; fix its off-diagonals"
            )
        low, high = sensor.height_band_m
        if not low < high:
            raise GpoccError(f"{source}: key 'sensors[{i}].height_band_m' must be [min, max] "
                             f"heights above the floor with min < max, got {[low, high]}")
        if not 0.0 < sensor.max_tilt_deg <= 90.0:
            raise GpoccError(f"{source}: key 'sensors[{i}].max_tilt_deg' must be in (0, 90] "
                             f"degrees, got {sensor.max_tilt_deg}")
        res = sensor.horizontal_resolution_deg
        if res is not None and not 0.01 <= res <= 10.0:
            raise GpoccError(f"{source}: key 'sensors[{i}].horizontal_resolution_deg' must be "
                             f"in [0.01, 10] degrees, got {res}")
        if sensor.range_min_m is not None and sensor.range_max_m is not None:
            if sensor.range_min_m >= sensor.range_max_m:
                raise GpoccError(f"{source}: key 'sensors[{i}].range_min_m' must be < range_max_m")
    paths = [entry.path for entry in config.inputs]
    if any(not p for p in paths) or len(set(paths)) != len(paths):
        raise GpoccError(f"{source}: key 'inputs' needs a distinct, non-empty path in every "
                         f"entry, got {paths}")
    for i, entry in enumerate(config.inputs):
        if max(abs(entry.transform.x_m), abs(entry.transform.y_m)) > _MAX_TRANSLATION_M:
            raise GpoccError(f"{source}: key 'inputs[{i}].transform' moves the input more "
                             f"than {_MAX_TRANSLATION_M:g} m; check its units (metres)")
    c = config.classify
    if not 0.0 < c.free <= c.occupied < 1.0:
        raise GpoccError(
            f"{source}: key 'classify' needs 0 < free <= occupied < 1, got {c.free}, {c.occupied}"
        )
    from gpocc.gp import backends  # gp.kernels imports this module: here, not on top
    from gpocc.gp.kernels import KERNELS, kernel_names_text

    if config.model.kernel not in KERNELS:
        raise GpoccError(f"{source}: key 'model.kernel' must be {kernel_names_text()}, "
                         f"got {config.model.kernel!r}")
    if config.model.backend not in backends.NAMES:
        raise GpoccError(f"{source}: key 'model.backend' must be one of "
                         f"{', '.join(backends.NAMES)}, got {config.model.backend!r}")
    if config.model.diagonal not in backends.DIAGONALS:
        raise GpoccError(f"{source}: key 'model.diagonal' must be one of "
                         f"{', '.join(backends.DIAGONALS)}, got {config.model.diagonal!r}")
    if config.model.covariance_precision not in backends.PRECISIONS:
        raise GpoccError(f"{source}: key 'model.covariance_precision' must be one of "
                         f"{', '.join(backends.PRECISIONS)}, got "
                         f"{config.model.covariance_precision!r}")
    if config.map.epsg is not None:
        raise GpoccError(
            f"{source}: key 'map.epsg' is retired: a CRS code without the map frame's origin "
            f"puts the map in the wrong place; use map.georef with epsg, easting_m, "
            f"northing_m and yaw_deg (or remove map.epsg for a local frame)"
        )
    georef = config.map.georef
    if georef is not None and not 1024 <= georef.epsg < 32767:
        raise GpoccError(
            f"{source}: key 'map.georef.epsg' must be a projected EPSG code (e.g. 32633 for "
            f"UTM 33N), got {georef.epsg}"
        )
    _one_of(config.samples.label_weights, LABEL_WEIGHTS, "samples.label_weights", source)
    if not 0.0 <= config.samples.label_count_power <= 1.0:
        raise GpoccError(f"{source}: key 'samples.label_count_power' must be between 0 and 1 "
                         f"(1: every counted sample an independent observation), got "
                         f"{config.samples.label_count_power}")
    t = config.model.training
    if t.fixed or t.isotropic:
        _check_fixed(config, source)
    for key, choices in (("classifier_holdout", ("scan", "sample")),
                         ("input_noise_scale_part", INPUT_NOISE_SCALE_PARTS),
                         ("patch_centres", ("hits", "samples")),
                         ("classifier_variance", ("label", "label-map", "latent")),
                         ("classifier_temperature", ("none", "samples", "beams")),
                         ("classifier_offset", ("holdout", "beams")),
                         ("classifier_offset_range", OFFSET_RANGES),
                         ("classifier_targets", CLASSIFIER_TARGETS),
                         ("local_search", ("lbfgs", "scoring"))):
        _one_of(getattr(t, key), choices, f"model.training.{key}", source)
    if t.classifier_variance == "label-map" and t.classifier_temperature == "samples":
        raise GpoccError(
            f"{source}: 'model.training.classifier_temperature: samples' fits T on the "
            f"held-out samples' latent variance, which 'classifier_variance: label-map' does "
            f"not use; set classifier_temperature to 'beams' or 'none'"
        )
    if t.calibration_every < 2:
        raise GpoccError(
            f"{source}: key 'model.training.calibration_every' must be at least 2 (one "
            f"held-out scan in that many), got {t.calibration_every}"
        )
    if not t.min_input_noise_scale <= 1.0 <= t.max_input_noise_scale:
        raise GpoccError(
            f"{source}: keys 'model.training.min_input_noise_scale' and "
            f"'max_input_noise_scale' must enclose 1 (the stated covariances), got "
            f"{t.min_input_noise_scale} and {t.max_input_noise_scale}"
        )
    if config.samples.min_label_share > 1.0:
        raise GpoccError(f"{source}: key 'samples.min_label_share' is a share of a cell's "
                         f"samples, in [0, 1], got {config.samples.min_label_share}")
    g = config.grid
    if not (g.log_odds_free < 0.0 < g.log_odds_occupied and g.clamp_min < 0.0 < g.clamp_max):
        raise GpoccError(
            f"{source}: key 'grid' needs log_odds_free < 0 < log_odds_occupied and "
            f"clamp_min < 0 < clamp_max, got {g.log_odds_free}, {g.log_odds_occupied}, "
            f"{g.clamp_min}, {g.clamp_max}"
        )
    _validate_bhm(config.bhm, source)
    if config.model.quadrature_level > 10:
        raise GpoccError(f"{source}: key 'model.quadrature_level' must be at most 10")
    if not 0.0 < config.model.blend_overlap <= 1.0:
        raise GpoccError(f"{source}: key 'model.blend_overlap' must be above 0 and at most 1 "
                         f"(1: bilinear across whole blocks), got {config.model.blend_overlap}")
    origin = config.map.anchor_origin_m
    if origin is not None and max(abs(v) for v in origin) > _MAX_TRANSLATION_M:
        raise GpoccError(f"{source}: key 'map.anchor_origin_m' must lie within "
                         f"{_MAX_TRANSLATION_M:g} m of the map frame's origin, got "
                         f"{list(origin)}; check its units (metres)")
    if config.map.margin_m > _MAX_MARGIN_M:
        raise GpoccError(f"{source}: key 'map.margin_m' must be at most {_MAX_MARGIN_M:g} m (the "
                         f"border around the data), got {config.map.margin_m:g}; check its "
                         "units (metres)")
    return config


def _check_limits(config: Config, source: str) -> None:
    """Limits on values a config states that a model file stored by an older gpocc may
    hold beyond (its embedded config is not checked against them: it was valid then)."""
    t = config.model.training
    if not 0.0 < t.log_bounds_width <= _MAX_LOG_BOUNDS_WIDTH:
        raise GpoccError(f"{source}: key 'model.training.log_bounds_width' must be above 0 and "
                         f"at most {_MAX_LOG_BOUNDS_WIDTH:g} (the search box spans e^-w to "
                         f"e^w times each initial value), got {t.log_bounds_width:g}")
    ut = config.samples.unscented
    for name, limit in (("alpha", _MAX_UT_ALPHA), ("beta", _MAX_UT_WEIGHT),
                        ("kappa", _MAX_UT_WEIGHT)):
        if getattr(ut, name) > limit:
            raise GpoccError(f"{source}: key 'samples.unscented.{name}' must be at most "
                             f"{limit:g}, got {getattr(ut, name):g}")
    hyper = config.model.hyperparameters
    for name in ("signal_variance", "noise_variance", "bias_variance", "weight_variance",
                 "lengthscale_m"):
        values = np.atleast_1d(np.asarray(getattr(hyper, name), dtype=float))
        if (values > _MAX_HYPERPARAMETER).any():
            raise GpoccError(f"{source}: key 'model.hyperparameters.{name}' must be at most "
                             f"{_MAX_HYPERPARAMETER:g}, got {getattr(hyper, name)}; check "
                             "its units")
    for key, value in (("model.neighbours", config.model.neighbours),
                       ("model.training.patch_size", t.patch_size)):
        if value > _MAX_LOCAL_SAMPLES:
            raise GpoccError(f"{source}: key '{key}' must be at most {_MAX_LOCAL_SAMPLES} "
                             f"samples (each local problem factors a matrix of that side), "
                             f"got {value}")
    if config.map.resolution_m > MAX_RESOLUTION_M:
        raise GpoccError(f"{source}: key 'map.resolution_m' must be at most "
                         f"{MAX_RESOLUTION_M:g} m, got {config.map.resolution_m:.10g}; check its "
                         "units (metres)")


#: Most inducing points one training point or map cell may see (features are local).
_MAX_BHM_NEIGHBOURS = 441


def _validate_bhm(b: BHMConfig, source: str) -> None:
    _one_of(b.mean_update, ("coupled", "diagonal"), "bhm.mean_update", source)
    reach = 3.0 / math.sqrt(b.gamma)
    if reach < b.inducing_spacing_m:
        raise GpoccError(
            f"{source}: key 'bhm.gamma' ({b.gamma:g} 1/m^2) makes each feature reach "
            f"{reach:.3g} m, less than bhm.inducing_spacing_m ({b.inducing_spacing_m:g} m): "
            f"points between inducing points would see no feature; lower gamma to at most "
            f"{9.0 / b.inducing_spacing_m**2:.3g} or the spacing")
    if (2 * math.ceil(reach / b.inducing_spacing_m) + 1) ** 2 > _MAX_BHM_NEIGHBOURS:
        raise GpoccError(
            f"{source}: key 'bhm.gamma' ({b.gamma:g} 1/m^2) makes each feature reach "
            f"{reach:.3g} m, over {_MAX_BHM_NEIGHBOURS} inducing points "
            f"{b.inducing_spacing_m:g} m apart; raise gamma or bhm.inducing_spacing_m")


def config_from_dict(data: dict[str, Any] | None, source: str = "<config>",
                     limits: bool = True) -> Config:
    """Validate a parsed YAML mapping into a :class:`Config`. ``limits=False`` skips the
    limits a config's values must keep (:func:`_check_limits`), for a model file's
    embedded config, which an older gpocc checked against its own."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise GpoccError(f"{source}: the config must be a YAML mapping of keys to values")
    config = _validate(_build(Config, data, "", source), source)
    if limits:
        _check_limits(config, source)
    return config


def load_config(path: str | Path | None) -> Config:
    """Read and validate a YAML config; ``None`` gives the defaults."""
    if path is None:
        return Config()
    return config_from_dict(read_config_mapping(path), str(path))


def read_config_mapping(path: str | Path) -> Any:
    """The parsed YAML of a config file, before validation: the keys it states (what
    :func:`load_config` fills with defaults)."""
    p = Path(path)
    check_regular_file(p, "config file", "check the path")
    try:
        data = yaml.load(p.read_text(encoding="utf-8"), Loader=_Loader)  # noqa: S506 - safe
    except (UnicodeDecodeError, ValueError):
        raise GpoccError(f"{p}: not a text (UTF-8) YAML file; give the job's "
                         "YAML config") from None
    except OSError as exc:
        raise GpoccError(f"{p}: cannot read the config ({exc.strerror or exc}); check "
                         "its permissions") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None)
        what = f" ({problem})" if problem else ""
        raise GpoccError(f"{p}: not valid YAML{where}{what}; fix the syntax") from None
    if data is None:  # an empty file, or only comments: legal, but likely the wrong file
        from gpocc.progress import log  # here: the config is read where rich is not needed

        log(f"warning: {p}: the config sets nothing (empty, or only comments)")
    return data


def config_to_dict(config: Config) -> dict[str, Any]:
    """Plain-data form of a config (lists for tuples), for model files and metadata."""

    def plain(value: Any) -> Any:
        if isinstance(value, tuple):
            return [plain(v) for v in value]
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        return value

    return plain(dataclasses.asdict(config))


def changed_settings(config: Config) -> dict[str, Any]:
    """:func:`config_to_dict` of ``config`` without the values equal to the defaults'
    (sections without a change left out; lists, such as ``sensors``, kept whole):
    what a config file must say to give ``config`` (``config_from_dict`` of it equals
    ``config``), and no more, so that a written file does not pin today's defaults."""
    return _changed(config_to_dict(config), config_to_dict(Config()))


def _changed(given: dict[str, Any], default: dict[str, Any]) -> dict[str, Any]:
    changed = {}
    for key, value in given.items():
        base = default.get(key)
        if isinstance(value, dict) and isinstance(base, dict):
            inner = _changed(value, base)
            if inner:
                changed[key] = inner
        elif key not in default or value != base:
            changed[key] = value
    return changed


def replace(config: Any, **changes: Any) -> Any:
    """``dataclasses.replace`` re-exported for nested frozen configs."""
    return dataclasses.replace(config, **changes)
