"""Accuracy experiments on every held-out protocol; writes docs/results.md.

Run ``make experiment`` (everything) or ``.venv/bin/python -m bench.experiment [steps]
[--quick]`` from the repository's root. Every gpocc step is a ``gpocc`` command, printed
before it runs and listed in the generated page, so each number can be reproduced by hand;
the few steps that are not (perturbing a log's poses, the region truth, the OctoMap row,
the loop-closure figure) are library calls in this file and its neighbours.

* ``sim``: per world (``default``, ``office``, ``warehouse`` and grown worlds
  ``grown-<seed>``), ``gpocc simulate`` (paper Table I platforms) -> ``gpocc split
  --every 10`` -> ``gpocc grid``, ``gpocc train --input-noise off|on`` + ``map`` (and
  OctoMap when pyoctomap is installed) on the training scans -> ``gpocc evaluate``
  against the held-out scans (three protocols, below) and per cell against the truth
  raster, whole and in the region only the noisy platform II saw.
* ``real``: per CARMEN log, ``gpocc split --every 10``; the training scans' poses are
  perturbed by a covariance that changes every ``STRETCH_SCANS`` scans (quiet, noisy,
  very noisy; :data:`REAL_LEVELS`) and written with that covariance to
  ``train-noisy.mcap``; every method is trained on it and scored on the held-out scans
  (whose points use the recorded poses), and on their free points by distance to the
  nearest held-out hit. Real logs have no per-cell truth.
* ``clean``: the same splits with every method trained on the training scans as logged
  (the corrected poses, the log's config): how the methods rank on an accurate lidar and
  accurate poses. ``make experiment`` runs it for the defaults and every variant and seed.
* ``loop``: intel_poses_odom_vs_corrected.txt, the Intel log mapped before and after
  loop closure (bench/loop_closure.py).
* ``report``: rewrite the page from the last run's summary without running anything.

``--merge`` keeps the cases of the variant's stored summary that this run does not make
again (``clean --variant X --merge`` adds the as-logged cases to an earlier ``sim real``
run of X).

Held-out protocols (``gpocc split``'s kinds): ``hits+free`` (each held-out hit and free
points uniform along its beam), ``hits+near-wall`` (the hits and free points 0.05-0.3 m
in front of them), ``union`` (all three kinds); on the simulated worlds also
``union-truth`` (the union's points labelled by the truth raster, ``gpocc evaluate
--labels-from``: the held-out scans are measured with the platforms' noise, so some of
their points carry labels the world contradicts); per-cell protocols: ``cells`` (the
truth raster) and ``cells-noisy-only`` (the cells only platform II saw).

``--quick``: one world (``default``) and one log cut (the repository's 50-scan Intel
sample, every 5th scan held out), to check the pipeline and the page generator in
minutes. ``--variant`` picks config overrides for the GP rows (:data:`VARIANTS`;
``defaults``: none, gpocc as shipped); a variant's run maps with the GP with input noise
alone, the one row the page compares (``--every-method``: every row); ``--compare`` adds
a variant's run to the page, and the variants of :data:`WIDENING` also to its section on
learned values on bounds.
Each case records the GP's learned values (:func:`learned_values`).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from gpocc.constants import RESULTS_FILE
from gpocc.gridspec import GridSpec

from .paths import CARMEN, CONFIGS, ROOT
from .stamp import commit, machine

GPOCC = [sys.executable, "-m", "gpocc"]
#: Worlds of two generators: the hand-drawn and grown corridor buildings, and five of
#: each family of the second generator (:mod:`gpocc.evaluation.families`).
WORLDS = ("default", "office", "warehouse", "grown-1", "grown-2", "grown-3",
          *(f"{family}-{seed}" for family in ("offices", "hall", "clutter")
            for seed in range(5)))
#: name -> (log file under the CARMEN folder, config under configs/).
REAL_LOGS = {"intel": ("intel.gfs.log", "carmen_intel.yaml"),
             "freiburg-079": ("freiburg-079-corrected.log", "carmen_freiburg.yaml")}
#: The quick run's log cut: the repository's Intel sample (50 scans).
QUICK_LOG = ("intel-sample", ROOT / "data" / "sample" / "intel_sample.mcap",
             ROOT / "data" / "sample" / "sample.yaml")
#: Pose-noise levels of the real-log stretches: (sigma x/y metres, sigma yaw degrees).
REAL_LEVELS = ((0.02, 0.5), (0.08, 1.5), (0.15, 3.0))
STRETCH_SCANS = 50
HELD_OUT_EVERY = 10
RESOLUTION = "0.1"
METHODS = ("grid", "octomap", "bhm", "gp-no-input-noise", "gp-input-noise")
HELDOUT_PROTOCOLS = ("hits+free", "hits+near-wall", "union")
#: Simulated worlds only: the union's points with the truth raster's labels.
TRUTH_PROTOCOLS = ("union-truth",)
CELL_PROTOCOLS = ("cells", "cells-noisy-only")
PROTOCOLS = (*HELDOUT_PROTOCOLS, *TRUTH_PROTOCOLS, *CELL_PROTOCOLS)
DOC = ROOT / "docs" / "results.md"

#: Config overrides (dotted keys) of the GP rows per variant; ``defaults`` is gpocc as
#: shipped. Most change one or a few settings of the defaults; the families of
#: ``published`` and ``offset-holdout`` pin the settings they depend on, so that they keep
#: their meaning when defaults change.
_PUBLISHED = {"model.training.classifier_holdout": "sample",
              "model.training.min_noise_variance": 0.01,
              "model.training.learn_input_noise_scale": False,
              "model.training.patch_centres": "samples",
              "samples.free_clearance_m": 0.0,
              "model.blend_overlap": 1.0,
              "samples.hit_gap_m": 0.25,
              "model.training.classifier_temperature": "none",
              "model.training.classifier_offset": "holdout",
              "samples.label_weights": "none",
              "model.training.patch_offset_m": 0.0}
_LEARNED = {**_PUBLISHED, "model.training.learn_input_noise_scale": True,
            "model.training.min_noise_variance": 0.1}
_HIT_PATCHES = {**_LEARNED, "model.training.patch_centres": "hits",
                "samples.free_clearance_m": 0.05}
#: Finer samples, more neighbours, then g = 1 and denser free samples: each adds to the last.
_THIN_N192 = {"samples.thin_cell_m": 0.1, "model.neighbours": 192}
_THIN_N256 = {**_THIN_N192, "model.neighbours": 256}
_THIN_N256_FIXED_SCALE = {**_THIN_N256, "model.training.learn_input_noise_scale": False}
_ACCURATE_POSES = {**_THIN_N256_FIXED_SCALE, "samples.free_spacing_m": 0.3}
#: The three settings whose defaults changed together before ``classifier_targets``, at
#: their values before: every kept sample weighs the same, g is learned, the classifier's
#: offset may run to +-100.
_BEFORE_COUNT = {"samples.label_weights": "none",
                 "model.training.learn_input_noise_scale": True,
                 "model.training.classifier_offset_range": "wide"}
#: Learning seeds of the run-to-run spread (seed 0 is the defaults' run).
SPREAD_SEEDS = (1, 2, 3, 4)

VARIANTS: dict[str, dict[str, object]] = {
    "defaults": {},
    "published": _PUBLISHED,
    "scan-cv": {**_PUBLISHED, "model.training.classifier_holdout": "scan"},
    "floor-0.1": {**_PUBLISHED, "model.training.classifier_holdout": "scan",
                  "model.training.min_noise_variance": 0.1},
    "learned-scale": {**_PUBLISHED, "model.training.learn_input_noise_scale": True},
    "learned-scale-floor-0.1": _LEARNED,
    "learned-scale-max-2": {**_LEARNED, "model.training.max_input_noise_scale": 2.0},
    "beam-offset": {**_LEARNED, "model.training.classifier_offset": "beams"},
    "clearance-0.05": {**_LEARNED, "samples.free_clearance_m": 0.05},
    "hit-patches": {**_LEARNED, "model.training.patch_centres": "hits"},
    "hit-patches-clearance-0.05": _HIT_PATCHES,
    "blend-0.5": {**_HIT_PATCHES, "model.blend_overlap": 0.5},
    "neighbours-96": {**_HIT_PATCHES, "model.neighbours": 96},
    "neighbours-256": {**_HIT_PATCHES, "model.neighbours": 256},
    "fixed-scale": {"model.training.learn_input_noise_scale": False},
    "two-draw": {"model.diagonal": "two-draw"},
    "hit-gap-0.25": {"samples.hit_gap_m": 0.25},
    "hit-gap-0.1": {"samples.hit_gap_m": 0.1},
    "no-temperature": {"model.training.classifier_temperature": "none"},
    "temperature": {"model.training.classifier_temperature": "samples"},
    "temperature-latent": {"model.training.classifier_temperature": "samples",
                           "model.training.classifier_variance": "latent"},
    "label-map": {"model.training.classifier_variance": "label-map"},
    "thin-0.1": {"samples.thin_cell_m": 0.1},
    "patches-20": {"model.training.patches": 20},
    "label-weights": {"samples.label_weights": "share"},
    "anneal-1": {"model.training.anneal_maxfun": 1},
    "overlap-0.5": {"model.blend_overlap": 0.5},
    "clearance-0": {"samples.free_clearance_m": 0.0},
    "pose-scale": {"model.training.input_noise_scale_part": "pose"},
    "clearance-0-pose-scale": {"samples.free_clearance_m": 0.0,
                               "model.training.learn_input_noise_scale": True,
                               "model.training.input_noise_scale_part": "pose"},
    # The NN kernel's bias variance held where learning leaves it in most cases (its
    # upper bound, 10 e^4), a likelihood ridge along which the maps do not change.
    "fixed-bias": {"model.hyperparameters.bias_variance": 545.98,
                   "model.training.fixed": ["bias_variance"]},
    "two-draw-pose-scale": {"model.diagonal": "two-draw",
                            "model.training.input_noise_scale_part": "pose"},
    "bounds-6": {"model.training.log_bounds_width": 6.0},
    "g-max-16": {"model.training.max_input_noise_scale": 16.0},
    "floor-0.03": {"model.training.min_noise_variance": 0.03},
    # Finer samples with more of them per local problem (about the area 0.15 m and 128
    # cover): walls kept at 0.1 m.
    "thin-0.1-n192": _THIN_N192,
    "thin-0.1-n256": _THIN_N256,
    # The same with g = 1: on accurately localised logs the learned g runs to its bound.
    "thin-0.1-n256-fixed-scale": _THIN_N256_FIXED_SCALE,
    # The same with denser free samples along beams: settings for accurately localised
    # logs, picked on the real logs' held-out points as logged (so not checked apart).
    "accurate-poses": _ACCURATE_POSES,
    # The classifier's offset fitted on left-out samples (leave-one-out, as published)
    # instead of on held-out scans' points with its temperature, with the settings of
    # before-count (the family of variants that change one of its settings, HOLDOUT_BASED).
    # isotropic: false and no patch offset too, the defaults when this run and its
    # variants were made.
    "offset-holdout": {**_BEFORE_COUNT, "model.training.classifier_offset": "holdout",
                       "model.training.isotropic": False,
                       "model.training.patch_offset_m": 0.0},
    "accurate-poses-offset-beams": {**_ACCURATE_POSES,
                                    "model.training.classifier_offset": "beams"},
    # The same with more of the finer samples per local problem, or free samples as
    # dense as bench BHM's (0.2 m): more of the data each local problem sees.
    "accurate-poses-n384-offset-beams": {**_ACCURATE_POSES, "model.neighbours": 384,
                                         "model.training.classifier_offset": "beams"},
    "accurate-poses-free-0.2-offset-beams": {**_ACCURATE_POSES,
                                             "samples.free_spacing_m": 0.2,
                                             "model.training.classifier_offset": "beams"},
    # Finer samples and more neighbours with the default classifier offset.
    "thin-0.1-n192-offset-beams": {**_THIN_N192, "model.training.classifier_offset": "beams"},
    "thin-0.1-n256-offset-beams": {**_THIN_N256, "model.training.classifier_offset": "beams"},
    # Cheaper steps toward finer samples: each local problem covers less area than 0.15
    # and 128 did (fewer neighbours per sample density).
    "thin-0.1-n160-offset-beams": {**_THIN_N192, "model.neighbours": 160,
                                   "model.training.classifier_offset": "beams"},
    "thin-0.12-n160-offset-beams": {"samples.thin_cell_m": 0.12, "model.neighbours": 160,
                                    "model.training.classifier_offset": "beams"},
    "isotropic": {"model.training.isotropic": True},
    # Mapping knobs at today's defaults: half the blend band (each cell from 2.25 local
    # problems on average instead of 4: faster maps), and smaller blocks with fewer
    # neighbours each (four times the local problems, each a quarter the size).
    "half-overlap": {"model.blend_overlap": 0.5},
    "blocks-0.5-n64": {"model.block_size_m": 0.5, "model.neighbours": 64},
    # Learning's patches centred on the hits as drawn (the default before): the default
    # moves each hit centre by the blend's tent over one block, where a map's anchors lie
    # from the walls.
    "no-patch-offset": {"model.training.patch_offset_m": 0.0},
    "anisotropic": {"model.training.isotropic": False},
    # The map's local systems (and the classifier's held-out predictions) in double
    # precision throughout: the single-precision default's accuracy cost.
    "double-precision": {"model.covariance_precision": "double"},
    # The classifier's temperature fitted without near-wall free points (the default
    # before): hits and free points along the beams of held-out scans only.
    "calibration-along-beam": {"model.training.calibration_near_wall": 0},
    # Learning's local search: Fisher scoring (as `gpocc update` refines), and from the
    # annealing's three best distinct points.
    "scoring": {"model.training.local_search": "scoring"},
    "scoring-3-starts": {"model.training.local_search": "scoring",
                         "model.training.local_starts": 3},
    # The defaults before count-weighted labels, g = 1 and the latent offset range, and
    # each of the three changes undone alone.
    "before-count": _BEFORE_COUNT,
    "no-label-weights": {"samples.label_weights": "none"},
    "share-labels": {"samples.label_weights": "share"},
    "learned-g": {"model.training.learn_input_noise_scale": True},
    "wide-offset": {"model.training.classifier_offset_range": "wide"},
    "hard-targets": {"model.training.classifier_targets": "hard"},
    # The learning seed alone (patches, annealing, the classifier's draws; the worlds,
    # their noise and the held-out points stay): how far a setting's result moves by
    # chance, the yardstick for the differences between settings.
    **{f"seed-{k}": {"seed": k} for k in SPREAD_SEEDS},
}
#: Variants that change one setting of ``offset-holdout`` (the classifier's offset fitted
#: on left-out samples, with the settings of ``before-count``): each pins those and is
#: compared with ``offset-holdout``'s run (:func:`base_of`), so its stored run stays the
#: run of its overrides.
HOLDOUT_BASED = ("hit-gap-0.25", "no-temperature", "label-map", "fixed-scale", "thin-0.1",
                 "patches-20", "label-weights", "anneal-1", "bounds-6", "g-max-16",
                 "floor-0.03", "overlap-0.5", "clearance-0", "pose-scale",
                 "two-draw-pose-scale", "fixed-bias", "thin-0.1-n192", "thin-0.1-n256",
                 "thin-0.1-n256-fixed-scale", "accurate-poses", "isotropic",
                 "calibration-along-beam")
for _name in HOLDOUT_BASED:
    VARIANTS[_name] = {**VARIANTS[_name], **{k: v for k, v in VARIANTS["offset-holdout"].items()
                                             if k not in VARIANTS[_name]}}


def base_of(name: str) -> str:
    """The variant whose run variant ``name``'s is compared with on the page:
    ``offset-holdout`` for the variants that pin its classifier offset, else
    ``defaults``."""
    pinned = VARIANTS[name].get("model.training.classifier_offset") == "holdout"
    return "offset-holdout" if pinned and name != "offset-holdout" else "defaults"


def compared_with(name: str) -> str:
    """What the page says variant ``name`` is compared with: ``this run`` or its base
    variant (:func:`base_of`)."""
    base = base_of(name)
    return "this run" if base == "defaults" else base


#: The variants that widen the box of learned values (:mod:`gpocc.gp.bounds`), and the
#: values (name prefixes, as :func:`gpocc.gp.bounds.values_on_bounds` names them) whose
#: bound each moves: the page's "Learned values on their bounds" compares where those
#: values end and what the maps gain.
WIDENING = {"bounds-6": ("kernel ", "label-noise variance"),
            "g-max-16": ("input-noise scale g",),
            "floor-0.03": ("label-noise variance",)}

#: Every step the page's results depend on, in order (the page's "Commands" section):
#: ``{"command": line, "reused": bool}``, a ``gpocc ...`` command or a ``# library: ...``
#: line for the steps that are library calls; ``reused`` when its output was already in the
#: work folder (made by an earlier run), so this run did not make it again.
COMMANDS: list[dict[str, object]] = []


def record(line: str, reused: bool) -> None:
    """Note one step in :data:`COMMANDS` and echo it on stderr."""
    COMMANDS.append({"command": line, "reused": reused})
    print("$ " + line + ("  # reused: its output is in the work folder" if reused else ""),
          file=sys.stderr, flush=True)


def run_gpocc(cmd: list[str]) -> str:
    """``gpocc`` with the arguments ``cmd`` in a subprocess; its stdout."""
    done = subprocess.run([*GPOCC, *cmd], cwd=ROOT, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"gpocc {' '.join(cmd)} failed:\n{done.stderr}")
    return done.stdout


def gpocc(*args: str | Path, creates: Path | None = None) -> str:
    """Run one gpocc command (echoed on stderr, recorded) and return its stdout; with
    ``creates`` (a file the command writes), only record it when that file exists."""
    cmd = [str(a) for a in args]
    reused = creates is not None and creates.exists()
    record("gpocc " + " ".join(cmd), reused)
    return "" if reused else run_gpocc(cmd)


def library_step(what: str, out: Path) -> bool:
    """Record the library call ``what`` that writes ``out``; True if it must run (``out``
    is not there yet)."""
    reused = out.exists()
    record(f"# library: {what} -> {out}", reused)
    return not reused


#: The sections of a config that say how to map, not what was recorded.
SETTINGS_SECTIONS = ("samples", "model", "classify", "map", "grid", "bhm")


def with_overrides(config: Path, overrides: dict[str, object], out: Path,
                   settings: Path | None = None) -> Path:
    """Write ``config`` with dotted-key ``overrides`` applied to ``out``. With
    ``settings`` (the config a split was made with), the :data:`SETTINGS_SECTIONS` are
    that file's instead of ``config``'s: the train.yaml of a split made before gpocc
    split wrote only the settings that differ from the defaults spells out every default
    of the gpocc that made it, and a stored split must not pin those."""
    data = yaml.safe_load(config.read_text()) or {}
    if settings is not None:
        given = yaml.safe_load(settings.read_text()) or {}
        for section in SETTINGS_SECTIONS:
            data.pop(section, None)
            if section in given:
                data[section] = given[section]
    for key, value in overrides.items():
        node = data
        *parents, last = key.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[last] = value
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    return out


def scores(row: dict) -> dict[str, float]:
    return {k: float(row[k]) for k in ("auc", "fpr_at_tpr97", "brier", "log_loss", "ece",
                                       "coverage")}


def evaluate(maps: dict[str, Path], truth: Path, out: Path,
             labels_from: Path | None = None) -> dict[str, dict[str, dict]]:
    """protocol -> method -> scores of ``maps`` (method -> folder) against ``truth``
    (with ``labels_from``, a truth raster, its points labelled by it).

    A truth with kinds gives the held-out protocols; one without (a raster) gives one
    protocol, ``all``."""
    extra = ["--labels-from", labels_from] if labels_from is not None else []
    gpocc("evaluate", *maps.values(), "--ground-truth", truth, *extra, "--out", out,
          "--force")
    results = json.loads((out / RESULTS_FILE).read_text())
    by_folder = {str(p): m for m, p in maps.items()}
    return {g["name"]: {by_folder[row["path"]]: scores(row) for row in g["maps"]}
            for g in results["protocols"]}


def gp_map(inputs: list[Path], config: Path, noise: str, folder: Path,
           bounds: list[str] | None = None) -> float:
    """Train and map one GP; returns the wall time (s)."""
    started = time.perf_counter()
    model = folder.with_suffix(".npz")
    gpocc("train", *inputs, "--config", config, "--input-noise", noise, "--out", model, "--force")
    extra = ["--bounds", *bounds] if bounds else []
    gpocc("map", model, "--resolution", RESOLUTION, "--out", folder, "--force", *extra)
    return time.perf_counter() - started


def moved_whole(frame: GridSpec, shift_cells: int) -> GridSpec:
    """``frame`` (a map's lattice frame, :func:`gpocc.mapping.mapper.map_frame`) grown by
    ``shift_cells`` cells west and north: its lattice, which hangs from the north-west
    corner, moves that much, and every cell of ``frame`` keeps its centre."""
    res = frame.resolution
    return GridSpec(frame.x0 - shift_cells * res, frame.y0, res, frame.width + shift_cells,
                    frame.height + shift_cells)


def moved_map(model_path: Path, like: Path, folder: Path, shift_m: float) -> None:
    """The map of ``model_path`` on the cells of the map folder ``like``, with the anchor
    lattice of ``like`` moved by ``shift_m`` (whole cells) west and north, into
    ``folder`` (replaced)."""
    from gpocc.commands.map import write_map
    from gpocc.gp.model import load_model
    from gpocc.io.atomic import atomic_directory
    from gpocc.mapping.mapper import map_frame

    model = load_model(model_path)
    meta = json.loads((like / "metadata.json").read_text())
    spec = GridSpec.from_bounds(*meta["bounds_m"], meta["resolution_m"])
    whole = moved_whole(map_frame(model, spec).grid, round(shift_m / spec.resolution))
    with atomic_directory(folder, force=True) as tmp:
        write_map(model, str(model_path), spec, tmp, None, None, whole=whole)


def moved_anchors(vdir: Path, heldout: Path, truth: Path | None) -> dict:
    """The GP with input noise's model of ``vdir`` mapped again with its anchor lattice
    moved by half a spacing west and north on the same cells (:func:`moved_map`), both
    maps scored on the points of ``heldout`` inside the first map's bounds (``union``
    protocol) and, with ``truth``, per cell: what the placement of the anchors alone
    changes (the page's "Anchor placement"). Returns the shift (m) and each map's scores
    (``page``, ``moved``) per protocol."""
    from gpocc.evaluation.truth import load_truth_kinds, write_points

    main = vdir / "gp-input-noise"
    meta = json.loads((main / "metadata.json").read_text())
    half, resolution = meta["anchor_spacing_m"] / 2, meta["resolution_m"]
    if abs(half / resolution - round(half / resolution)) > 1e-6:
        raise ValueError(f"half a spacing ({half} m) is not whole cells of {resolution} m: "
                         "the moved map's cells would not be the page's")
    x0, y0, x1, y1 = meta["bounds_m"]
    folder = vdir / "gp-input-noise-anchors-moved"
    # Made again from this run's model, always.
    shutil.rmtree(folder, ignore_errors=True)
    library_step(f"bench/experiment.py moved_map of {main.with_suffix('.npz')} on the "
                 f"cells of {main}, anchors {half:g} m west and north", folder)
    moved_map(main.with_suffix(".npz"), main, folder, half)
    points, labels, kinds = load_truth_kinds(heldout)
    inside = ((points[:, 0] >= x0) & (points[:, 0] < x1) & (points[:, 1] >= y0)
              & (points[:, 1] < y1))
    kept = vdir / "heldout-inside-map.csv"
    write_points(kept, points[inside], labels[inside], kinds[inside])
    maps = {"page": main, "moved": folder}
    union = evaluate(maps, kept, vdir / "evaluation-heldout-anchors-moved")["union"]
    scored = {name: {"union": union[name]} for name in maps}
    if truth is not None:
        cells = evaluate(maps, truth, vdir / "evaluation-cells-anchors-moved")["all"]
        for name in maps:
            scored[name]["cells"] = cells[name]
    return {"shift_m": half, **scored}


def grid_map(inputs: list[Path], config: Path, folder: Path, bounds: list[str] | None,
             command: str = "grid") -> None:
    """A baseline's map folder (``gpocc grid`` or ``gpocc bhm``), made once."""
    extra = ["--bounds", *bounds] if bounds else []
    gpocc(command, *inputs, "--config", config, "--resolution", RESOLUTION, "--out", folder,
          "--force", *extra, creates=folder / "probability.tif")


def octomap_row(inputs: list[Path], config: Path, folder: Path, like: Path) -> bool:
    """The OctoMap map on the grid of ``like`` (a map folder); False when pyoctomap is
    not installed (``pip install -e '.[bench]'``)."""
    try:
        import pyoctomap  # noqa: F401  (octomap_map imports it only when called)

        from .octomap_map import octomap_probability
    except ImportError:
        return False
    if library_step(f"bench/octomap_map.py octomap_probability of "
                    f"{' '.join(map(str, inputs))} on the grid of {like}",
                    folder / "probability.tif"):
        octomap_probability(inputs, config, folder, like / "probability.tif")
    return True


def truth_bounds(truth_tif: Path) -> list[str]:
    from gpocc.io.rasters import read_raster

    _, spec, _ = read_raster(truth_tif)
    return [f"{v:.3f}" for v in spec.bounds]


def noisy_only_truth(sim: Path, world: str, seed: int) -> Path:
    """truth-noisy-only.tif: the truth where only platform II's rays went."""
    from gpocc.constants import NO_DATA
    from gpocc.evaluation.simulate import region_truth, simulate, truth_raster
    from gpocc.io.rasters import write_geotiff

    out = sim / "truth-noisy-only.tif"
    if library_step(f"bench/experiment.py noisy_only_truth of world {world}, seed {seed}",
                    out):
        s = simulate(world, seed=seed)
        labels, spec = truth_raster(s.world, s.runs, 0.1)
        write_geotiff(out, region_truth(labels, spec, s.runs[:1]), spec, nodata=NO_DATA)
    return out


def every_method(variant: str, asked: bool = False) -> bool:
    """Whether a run of ``variant`` maps with every method, or (False) with the GP with
    input noise alone: the page reads nothing else from a variant's or a seed's run (it
    compares their GPs with input noise with this run's), so their other rows would be
    maps nobody reads. ``asked``: every method anyway (``--every-method``)."""
    return asked or variant == "defaults"


def run_methods(inputs: list[Path], base_config: Path, variant: str, vdir: Path,
                shared: Path, bounds: list[str] | None,
                settings: Path, all_methods: bool = True) -> tuple[dict[str, Path], dict]:
    """Every method's map folder on ``inputs``: the grid, BHM and OctoMap (shared between
    variants, in ``shared``) and both GPs (in ``vdir``, with ``settings``' sections, see
    :func:`with_overrides`); and the GPs' wall seconds. ``all_methods=False``
    (:func:`every_method`): the GP with input noise alone."""
    vdir.mkdir(parents=True, exist_ok=True)
    maps = {}
    if all_methods:
        grid_map(inputs, base_config, shared / "grid", bounds)
        grid_map(inputs, base_config, shared / "bhm", bounds, "bhm")
        maps = {"grid": shared / "grid", "bhm": shared / "bhm"}
        if octomap_row(inputs, base_config, shared / "octomap", shared / "grid"):
            maps["octomap"] = shared / "octomap"
    overrides = dict(VARIANTS[variant])
    if bounds is not None:
        # Every variant's GPs on one anchor lattice, from the bounds' north-west corner:
        # a comparison of settings is not one of anchor placements too.
        overrides.setdefault("map.anchor_origin_m", [float(bounds[0]), float(bounds[3])])
    config = with_overrides(base_config, overrides, vdir / "config.yaml", settings)
    seconds = {}
    gps = (("off", "gp-no-input-noise"), ("on", "gp-input-noise"))
    for noise, name in gps if all_methods else gps[1:]:
        seconds[name] = gp_map(inputs, config, noise, vdir / name, bounds)
        maps[name] = vdir / name
    return maps, seconds


#: Edges (m) of the distance from a held-out free point to the nearest held-out hit, for
#: the page's "Free space next to walls"; the last bucket is open.
WALL_DISTANCE_EDGES = (0.0, 0.05, 0.1, 0.2, 0.3)


def free_by_wall_distance(truth: Path, maps: dict[str, Path]) -> dict[str, list[list[float]]]:
    """Each map's held-out free points of ``truth`` (a ``heldout.csv``) by their distance
    to the nearest held-out hit (:data:`WALL_DISTANCE_EDGES`): method -> one ``[points,
    mean p, Brier]`` per bucket (p = 0.5 where the map has no value, as the page scores
    it)."""
    from scipy.spatial import cKDTree

    from gpocc.evaluation.report import sample_map

    table = np.genfromtxt(truth, delimiter=",", names=True, dtype=None, encoding="utf-8")
    points = np.column_stack((table["x"], table["y"])).astype(float)
    kind = np.asarray(table["kind"], dtype=str)
    free = points[kind == "free"]
    distance, _ = cKDTree(points[kind == "hit"]).query(free)
    bucket = np.digitize(distance, WALL_DISTANCE_EDGES[1:])
    masks = [bucket == b for b in range(len(WALL_DISTANCE_EDGES))]
    result = {}
    for method, folder in maps.items():
        p, inside = sample_map(folder / "probability.tif", free)
        p = np.where(inside & np.isfinite(p), p, 0.5)
        result[method] = [[int(m.sum()), float(p[m].mean()), float((p[m] ** 2).mean())]
                          if m.any() else [0, math.nan, math.nan] for m in masks]
    return result


def learned_values(model: Path) -> dict:
    """What the bounds section reads from a GP model file: its patch log marginal
    likelihood (nats), its learned values by name and which of them ended on a bound of
    their search (name -> ``lower`` or ``upper``; :func:`gpocc.gp.bounds.values_on_bounds`)."""
    from gpocc.gp.bounds import theta_names, values_on_bounds
    from gpocc.gp.model import load_model

    m = load_model(model)
    values = dict(zip((f"kernel {n}" for n in theta_names(m.kernel)),
                      (float(v) for v in np.exp(m.kernel.theta)), strict=True))
    values.update({"label-noise variance": m.noise_variance,
                   "input-noise scale g": m.input_noise_scale,
                   "classifier slope a": m.classifier.a})
    return {"log_marginal_likelihood": float(m.training["log_marginal_likelihood"]),
            "evaluations": int(m.training["evaluations"]),
            "values": values,
            "on_bounds": {b.name: b.side for b in values_on_bounds(m)}}


def split(log: Path, config: Path, out: Path, every: int) -> Path:
    gpocc("split", log, "--every", str(every), "--config", config, "--out", out, "--force",
          creates=out / "heldout.csv")
    return out


def run_sim(work: Path, variant: str, worlds: list[str], seed: int,
            all_methods: bool = True) -> list[dict]:
    """The ``sim`` step's cases (``all_methods``: :func:`run_methods`)."""
    cases = []
    for world in worlds:
        sim = work / "sim" / f"{world}-s{seed}"
        gpocc("simulate", "--out", sim, "--world", world, "--seed", str(seed), "--force",
              creates=sim / "sim.mcap")
        held = split(sim / "sim.mcap", sim / "sim.yaml", sim / "split", HELD_OUT_EVERY)
        truth = sim / "truth.tif"
        bounds = truth_bounds(truth)
        vdir = work / variant / "sim" / sim.name
        maps, seconds = run_methods([held / "train.mcap"], held / "train.yaml", variant, vdir,
                                    sim, bounds, sim / "sim.yaml", all_methods)
        result = evaluate(maps, held / "heldout.csv", vdir / "evaluation-heldout")
        result["union-truth"] = evaluate(maps, held / "heldout.csv",
                                         vdir / "evaluation-heldout-truth", truth)["union"]
        result["cells"] = evaluate(maps, truth, vdir / "evaluation-cells")["all"]
        region = noisy_only_truth(sim, world, seed)
        result["cells-noisy-only"] = evaluate(maps, region,
                                              vdir / "evaluation-cells-noisy-only")["all"]
        cases.append({"case": f"{world} (seed {seed})", "kind": "sim", "scores": result,
                      "contradicted": contradicted_share(held / "heldout.csv", truth),
                      "family": world_family(world), "gp_seconds": seconds,
                      "learned": learned_values(vdir / "gp-input-noise.npz"),
                      **({"moved_anchors": moved_anchors(vdir, held / "heldout.csv", truth)}
                         if all_methods else {})})
    return cases


def contradicted_share(heldout: Path, truth: Path) -> float:
    """The share of the held-out points on labelled cells of ``truth`` whose label the
    truth contradicts (a noisy hit in free space, a free point past a wall)."""
    from gpocc.evaluation.truth import labels_at, load_truth

    points, labels = load_truth(heldout)
    truth_labels, known = labels_at(points, truth)
    return float(np.mean(truth_labels[known] != labels[known]))


def world_family(world: str) -> str:
    """The generator family a world belongs to: ``hand-drawn`` (default, office,
    warehouse), ``grown``, or a family of :mod:`gpocc.evaluation.families`."""
    head = world.rsplit("-", 1)[0] if world[-1:].isdigit() else world
    return head if head in ("grown", "offices", "hall", "clutter") else "hand-drawn"


def perturbed_training_bag(split_dir: Path, seed: int) -> Path:
    """train-noisy.mcap: the split's training scans with stretch-wise pose noise."""
    from gpocc.config import load_config
    from gpocc.evaluation.simulate import PoseNoise, perturb_poses, stretch_covariances
    from gpocc.io.bags import write_bag
    from gpocc.io.inputs import read_inputs

    out = split_dir / "train-noisy.mcap"
    if not library_step(f"bench/experiment.py perturbed_training_bag of {split_dir}, "
                        f"seed {seed}", out):
        return out
    config = load_config(split_dir / "train.yaml")
    batches = read_inputs([split_dir / "train.mcap"], config)
    rng = np.random.default_rng(seed)
    levels = tuple(PoseNoise(*lv) for lv in REAL_LEVELS)
    noisy, topics = [], []
    sensors = {s.name: s for s in config.sensors}
    for batch in batches:
        cov = stretch_covariances(batch.n_scans, STRETCH_SCANS, levels)
        poses = perturb_poses(batch.poses, cov, rng)
        noisy.append(dataclasses.replace(batch, poses=poses, pose_covariances=cov,
                                         has_pose_covariance=True))
        s = sensors[batch.sensor]
        topics.append((s.scan_topic, s.pose_topic))
    write_bag(out, noisy, topics, "mcap", force=True)
    return out


def real_logs(names: list[str], quick: bool) -> list[tuple[str, Path, Path, int]]:
    """(name, log, config, held-out period) of each log to run."""
    if quick:
        name, log, config = QUICK_LOG
        return [(name, log, config, 5)]
    return [(n, CARMEN / REAL_LOGS[n][0], CONFIGS / REAL_LOGS[n][1], HELD_OUT_EVERY)
            for n in names]


def run_real(work: Path, variant: str, logs: list[tuple[str, Path, Path, int]],
             seed: int, as_logged: bool = False, all_methods: bool = True) -> list[dict]:
    """The ``real`` step's cases, or with ``as_logged`` the ``clean`` step's: every method
    trained on the split's training scans with their recorded poses and the log's
    config (``all_methods``: :func:`run_methods`)."""
    cases = []
    for name, path, log_config, every in logs:
        if not path.is_file():
            print(f"skipping {name}: {path} not found", file=sys.stderr)
            continue
        held = split(path, log_config, work / "real" / name / "split", every)
        if as_logged:
            bag, base = held / "train.mcap", held / "train.yaml"
            shared, how = held.parent / "as-logged", "poses as logged"
            vdir = work / variant / "real-as-logged" / name
        else:
            bag = perturbed_training_bag(held, seed)
            base = held.with_name("train-noisy.yaml")
            cfg = yaml.safe_load((held / "train.yaml").read_text())
            for sensor in cfg["sensors"]:
                sensor["override_pose_covariance"] = False  # the bag carries the truth
            base.write_text(yaml.safe_dump(cfg, sort_keys=False))
            shared, how = held.parent, "pose noise by stretch"
            vdir = work / variant / "real" / name
        shared.mkdir(parents=True, exist_ok=True)
        maps, seconds = run_methods([bag], base, variant, vdir, shared, None, log_config,
                                    all_methods)
        result = evaluate(maps, held / "heldout.csv", vdir / "evaluation-heldout")
        cases.append({"case": f"{path.name} (every {every}th scan held out, {how})",
                      "kind": "real", "as_logged": as_logged, "scores": result,
                      "gp_seconds": seconds,
                      "learned": learned_values(vdir / "gp-input-noise.npz"),
                      "free_by_wall_distance": free_by_wall_distance(held / "heldout.csv",
                                                                     maps),
                      **({"moved_anchors": moved_anchors(vdir, held / "heldout.csv", None)}
                         if all_methods else {})})
    return cases


# ---- the page -----------------------------------------------------------------------------

def stamp() -> dict[str, str]:
    return {"date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
            "commit": commit(), "machine": machine(), "python": platform.python_version()}


def _methods(cases: list[dict]) -> list[str]:
    seen = {m for c in cases for p in c["scores"].values() for m in p}
    return [m for m in METHODS if m in seen]


def protocol_table(cases: list[dict], protocol: str) -> list[str]:
    rows = [c for c in cases if protocol in c["scores"]]
    if not rows:
        return []
    lines = ["| case | method | AUC | FPR@TPR0.97 | Brier | log-loss | ECE | coverage |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for c in rows:
        for m in _methods([c]):
            s = c["scores"][protocol].get(m)
            if s is None:
                continue
            lines.append(f"| {c['case']} | {m} | {s['auc']:.4f} | {s['fpr_at_tpr97']:.3f} | "
                         f"{s['brier']:.4f} | {s['log_loss']:.3f} | {s['ece']:.3f} | "
                         f"{100 * s['coverage']:.1f}% |")
    return lines


def comparison(cases: list[dict], protocol: str, a: str, b: str) -> str | None:
    """One line: method ``a`` against ``b`` under ``protocol`` over the cases with both."""
    pairs = [(c["scores"][protocol][a], c["scores"][protocol][b]) for c in cases
             if protocol in c["scores"] and a in c["scores"][protocol]
             and b in c["scores"][protocol]]
    if not pairs:
        return None
    auc = np.array([x["auc"] - y["auc"] for x, y in pairs])
    brier = np.array([x["brier"] - y["brier"] for x, y in pairs])
    fpr = np.array([x["fpr_at_tpr97"] - y["fpr_at_tpr97"] for x, y in pairs])
    return (f"| {protocol} | {a} vs {b} | {int((auc > 0).sum())}/{auc.size} | "
            f"{auc.mean():+.4f} | {auc.min():+.4f} | {int((fpr < 0).sum())}/{fpr.size} | "
            f"{int((brier < 0).sum())}/{brier.size} | {brier.mean():+.4f} |")


def summary_table(cases: list[dict]) -> list[str]:
    lines = ["| protocol | comparison | AUC wins | mean AUC diff | worst AUC diff | "
             "FPR@TPR0.97 wins | Brier wins | mean Brier diff |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    methods = _methods(cases)
    pairs = [("gp-input-noise", "gp-no-input-noise")] + [
        ("gp-input-noise", m) for m in ("grid", "octomap", "bhm") if m in methods]
    for protocol in PROTOCOLS:
        for a, b in pairs:
            line = comparison(cases, protocol, a, b)
            if line:
                lines.append(line)
    return lines


def variant_table(cases: list[dict], variants: dict[str, list[dict]],
                  spread: dict[str, dict[str, float]] | None = None,
                  base: str | None = None) -> list[str]:
    """The GP with input noise of ``cases`` (this run's, or variant ``base``'s run)
    against the same GP of each of ``variants`` (name -> that run's cases), on the cases
    both ran, per protocol: wins count the cases where the GP of ``cases`` is better.
    With ``spread`` (:func:`seed_spread`), two more columns count the cases whose AUC and
    Brier differ by more than the case's spread over learning seeds: better in ``cases``
    / better in the variant."""
    beyond = spread is not None
    lines = ["| protocol | comparison | AUC wins | mean AUC diff | worst AUC diff | "
             "FPR@TPR0.97 wins | Brier wins | mean Brier diff |"
             + (" AUC beyond the spread | Brier beyond the spread |" if beyond else ""),
             "|---|---|---:|---:|---:|---:|---:|---:|" + ("---:|---:|" if beyond else "")]
    gp = "gp-input-noise"
    ours = f"{gp} ({base})" if base else gp
    for name, other in variants.items():
        theirs = f"{gp} ({name})"
        by_case = {c["case"]: c["scores"] for c in other}
        merged = [{**c, "scores": {p: {ours: s[gp], theirs: by_case[c["case"]][p][gp]}
                                   for p, s in c["scores"].items()
                                   if gp in s and gp in by_case.get(c["case"], {}).get(p, {})}}
                  for c in cases]
        for protocol in PROTOCOLS:
            line = comparison(merged, protocol, ours, theirs)
            if line and beyond:
                line += "".join(f" {_beyond(merged, protocol, ours, theirs, metric, spread)} |"
                                for metric in ("auc", "brier"))
            if line:
                lines.append(line)
    return lines


def _beyond(cases: list[dict], protocol: str, ours: str, theirs: str, metric: str,
            spread: dict[str, dict[str, float]]) -> str:
    """``better here / better there``: the cases of ``protocol`` whose ``metric`` differs
    between the GPs ``ours`` and ``theirs`` by more than the case's seed spread."""
    here = there = 0
    for c in cases:
        scores = c["scores"].get(protocol, {})
        width = spread.get(c["case"], {}).get(f"{protocol} {metric}")
        if ours not in scores or theirs not in scores or width is None:
            continue
        diff = scores[ours][metric] - scores[theirs][metric]
        gain = diff if metric == "auc" else -diff
        if abs(diff) > width:
            here, there = here + (gain > 0), there + (gain < 0)
    return f"{here} / {there}"


def seed_spread(cases: list[dict], seed_runs: list[list[dict]]) -> dict[str, dict[str, float]]:
    """case -> ``"PROTOCOL METRIC"`` -> max - min of the GP with input noise's score over
    this run and ``seed_runs`` (the same settings with other learning seeds), for the
    cases and protocols every run scored."""
    runs = [{c["case"]: c["scores"] for c in run} for run in seed_runs]
    spread: dict[str, dict[str, float]] = {}
    for c in cases:
        for protocol, scores in c["scores"].items():
            if "gp-input-noise" not in scores:
                continue
            others = [r.get(c["case"], {}).get(protocol, {}).get("gp-input-noise")
                      for r in runs]
            if not runs or any(o is None for o in others):
                continue
            for metric in ("auc", "brier"):
                values = [scores["gp-input-noise"][metric], *(o[metric] for o in others)]
                spread.setdefault(c["case"], {})[f"{protocol} {metric}"] = (
                    max(values) - min(values))
    return spread


def spread_table(cases: list[dict], spread: dict[str, dict[str, float]],
                 seeds: int) -> list[str]:
    """Per protocol, over the cases: the median and largest spread (max - min over
    ``seeds`` learning seeds) of the GP with input noise's AUC and Brier, then each real
    log's union spread."""
    lines = ["| protocol | cases | AUC spread, median | AUC spread, largest | "
             "Brier spread, median | Brier spread, largest |",
             "|---|---:|---:|---:|---:|---:|"]
    for protocol in PROTOCOLS:
        auc = [s[f"{protocol} auc"] for s in spread.values() if f"{protocol} auc" in s]
        brier = [s[f"{protocol} brier"] for s in spread.values()
                 if f"{protocol} brier" in s]
        if auc:
            lines.append(f"| {protocol} | {len(auc)} | {np.median(auc):.4f} | "
                         f"{max(auc):.4f} | {np.median(brier):.4f} | {max(brier):.4f} |")
    real = [c["case"] for c in cases if c["kind"] == "real" and "union auc" in
            spread.get(c["case"], {})]
    if real:
        lines += ["", f"Real logs, `union` over the {seeds} seeds:", "",
                  "| log | AUC spread | Brier spread |", "|---|---:|---:|",
                  *(f"| {name} | {spread[name]['union auc']:.4f} | "
                    f"{spread[name]['union brier']:.4f} |" for name in real)]
    return lines


def _learned(cases: list[dict]) -> dict[str, dict]:
    """case -> its ``learned`` record, for the cases that have one."""
    return {c["case"]: c["learned"] for c in cases if c.get("learned")}


def bounds_table(cases: list[dict]) -> list[str]:
    """Per learned value that ended on a bound of its search in some case: how many
    cases on its lower and upper bound, and its median over the cases."""
    learned = _learned(cases)
    names = sorted({n for rec in learned.values() for n in rec["on_bounds"]})
    if not names:
        return []
    lines = ["| learned value | on its lower bound | on its upper bound | median |",
             "|---|---:|---:|---:|"]
    for name in names:
        sides = [rec["on_bounds"].get(name) for rec in learned.values()]
        median = np.median([rec["values"][name] for rec in learned.values()
                            if name in rec["values"]])
        lines.append(f"| {name} | {sides.count('lower')}/{len(sides)} | "
                     f"{sides.count('upper')}/{len(sides)} | {median:.4g} |")
    return lines


def _base_run(name: str, cases: list[dict], variants: dict[str, list[dict]]) -> list[dict]:
    """The cases variant ``name`` is compared with: this run's (``cases``) or those of its
    base variant's run (:func:`base_of`) among ``variants`` (none when it is not there)."""
    base = base_of(name)
    return cases if base == "defaults" else variants.get(base, [])


def widening_tables(cases: list[dict], variants: dict[str, list[dict]]) -> list[str]:
    """For each compared variant of :data:`WIDENING`, on the cases it and the run it is
    compared with (:func:`_base_run`, "here") both recorded: where the values whose box
    it widens end (cases on a bound and median, here and in the variant), then what it
    gains: the patch log marginal likelihood (variant minus here, nats) and the GP's
    held-out scores (variant minus here, mean over the cases; wins count the cases where
    the variant is better)."""
    values, gains = [], []
    for name, prefixes in WIDENING.items():
        base = _base_run(name, cases, variants)
        ours = _learned(base)
        theirs = _learned(variants.get(name, []))
        both = [c for c in ours if c in theirs]
        if not both:
            continue
        names = sorted({n for c in both for rec in (ours[c], theirs[c])
                        for n in rec["on_bounds"] if n.startswith(prefixes)})
        for value in names:
            here = sum(value in ours[c]["on_bounds"] for c in both)
            there = sum(value in theirs[c]["on_bounds"] for c in both)
            med_here = np.median([ours[c]["values"][value] for c in both])
            med_there = np.median([theirs[c]["values"][value] for c in both])
            values.append(f"| {name} | {value} | {here}/{len(both)} | {there}/{len(both)} | "
                          f"{med_here:.4g} | {med_there:.4g} |")
        lml = np.array([theirs[c]["log_marginal_likelihood"]
                        - ours[c]["log_marginal_likelihood"] for c in both])
        row = [f"| {name} | {np.median(lml):+.1f} | {lml.max():+.1f}"]
        by_case = {c["case"]: c["scores"] for c in variants[name]}
        for protocol in ("union", "cells"):
            pairs = [(c["scores"][protocol]["gp-input-noise"],
                      by_case[c["case"]][protocol]["gp-input-noise"])
                     for c in base if c["case"] in by_case and protocol in c["scores"]
                     and protocol in by_case[c["case"]]]
            auc = np.array([b["auc"] - a["auc"] for a, b in pairs])
            brier = np.array([b["brier"] - a["brier"] for a, b in pairs])
            row.append(f"{int((auc > 0).sum())}/{auc.size} | {auc.mean():+.4f} | "
                       f"{int((brier < 0).sum())}/{brier.size} | {brier.mean():+.4f}"
                       if pairs else "| | |")
        gains.append(" | ".join(row) + " |")
    if not gains:
        return []
    return ["| variant | learned value | on its bound here | on its bound in the variant | "
            "median here | median in the variant |", "|---|---|---:|---:|---:|---:|",
            *values, "",
            "| variant | LML gain, median nats | LML gain, largest | union AUC wins | "
            "union AUC diff | union Brier wins | union Brier diff | cells AUC wins | "
            "cells AUC diff | cells Brier wins | cells Brier diff |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|", *gains]


def wall_distance_table(cases: list[dict]) -> list[str]:
    """Per real log and method: the held-out free points' mean p and Brier score by their
    distance to the nearest held-out hit (:func:`free_by_wall_distance`)."""
    rows = [c for c in cases if c.get("free_by_wall_distance")]
    if not rows:
        return []
    edges = WALL_DISTANCE_EDGES
    names = [f"{a:g}-{b:g} m" for a, b in zip(edges, edges[1:], strict=False)]
    names.append(f">= {edges[-1]:g} m")
    lines = ["| case | method | " + " | ".join(names) + " |",
             "|---|---|" + "---:|" * len(names)]
    for case in rows:
        by_method = case["free_by_wall_distance"]
        counts = next(iter(by_method.values()))
        lines.append(f"| {case['case']} | free points | "
                     + " | ".join(str(n) for n, _, _ in counts) + " |")
        for method in _methods([case]):
            if method in by_method:
                lines.append(f"|  | {method} | " + " | ".join(
                    f"{p:.3f} / {b:.4f}" if n else "" for n, p, b in by_method[method])
                    + " |")
    return lines


def moved_anchors_table(cases: list[dict]) -> list[str]:
    """Per case, the GP with input noise's scores with the page's anchors and with them
    moved by half a spacing (:func:`moved_anchors`), then the mean and largest absolute
    difference per protocol and metric."""
    rows = [c for c in cases if c.get("moved_anchors")]
    if not rows:
        return []
    lines = ["| case | union AUC | moved | union Brier | moved | cells AUC | moved |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    columns = (("union", "auc", "union AUC"), ("union", "brier", "union Brier"),
               ("cells", "auc", "cells AUC"))
    diffs: dict[str, list[float]] = {name: [] for _, _, name in columns}
    for case in rows:
        cells = []
        for protocol, metric, name in columns:
            here = case["moved_anchors"]["page"].get(protocol)
            moved = case["moved_anchors"]["moved"].get(protocol)
            if here and moved:
                cells += [f"{here[metric]:.4f}", f"{moved[metric]:.4f}"]
                diffs[name].append(moved[metric] - here[metric])
            else:
                cells += ["", ""]
        lines.append(f"| {case['case']} | " + " | ".join(cells) + " |")
    lines += ["", "| protocol, metric | cases | mean moved - page | mean abs | largest abs |",
              "|---|---:|---:|---:|---:|"]
    for name, d in diffs.items():
        if not d:
            continue
        a = np.array(d)
        lines.append(f"| {name} | {a.size} | {a.mean():+.4f} | {np.abs(a).mean():.4f} | "
                     f"{np.abs(a).max():.4f} |")
    return lines


def real_log_table(cases: list[dict], variants: dict[str, list[dict]]) -> list[str]:
    """The GP with input noise on each real log (``union`` protocol), this run and each
    variant: AUC / Brier, on the perturbed poses and (``clean`` step) as logged."""
    real = [c for c in cases if c["kind"] == "real" and "union" in c["scores"]]
    if not real:
        return []
    heads = [c["case"].split(" (")[0] + (" as logged" if c.get("as_logged") else "")
             for c in real]
    lines = ["| settings | " + " | ".join(heads) + " |", "|---|" + "---:|" * len(real)]
    runs = {"this run": cases, **variants}
    for name, run in runs.items():
        by_case = {c["case"]: c["scores"].get("union", {}).get("gp-input-noise") for c in run}
        cells = [by_case.get(c["case"]) for c in real]
        lines.append(f"| {name} | " + " | ".join(
            f"{s['auc']:.4f} / {s['brier']:.4f}" if s else "" for s in cells) + " |")
    return lines


def cost_table(cases: list[dict], variants: dict[str, list[dict]]) -> list[str]:
    """What each variant costs against the run it is compared with (:func:`_base_run`),
    on the cases both ran: the median over cases of the GP with input noise's train + map
    wall time, variant over that run, and the median likelihood evaluations of its
    learning, there and in the variant (where both runs recorded them)."""
    lines = ["| variant | against | train + map time, median ratio | likelihood "
             "evaluations, median there / in the variant |", "|---|---|---:|---:|"]
    for name, other in variants.items():
        ours = {c["case"]: c for c in _base_run(name, cases, variants)}
        both = [(ours[c["case"]], c) for c in other if c["case"] in ours]
        timed = [b["gp_seconds"]["gp-input-noise"] / a["gp_seconds"]["gp-input-noise"]
                 for a, b in both if "gp_seconds" in a and "gp_seconds" in b]
        counted = [(a["learned"]["evaluations"], b["learned"]["evaluations"]) for a, b in both
                   if "evaluations" in a.get("learned", {})
                   and "evaluations" in b.get("learned", {})]
        evaluations = (f"{np.median([a for a, _ in counted]):g} / "
                       f"{np.median([b for _, b in counted]):g}" if counted else "")
        ratio = f"{np.median(timed):.2f}" if timed else ""
        lines.append(f"| {name} | {compared_with(name)} | {ratio} | {evaluations} |")
    return lines


def _contradicted_text(cases: list[dict]) -> str:
    """A sentence on the share of held-out labels the truth contradicts, per world."""
    shares = [c["contradicted"] for c in cases if "contradicted" in c]
    if not shares:
        return ""
    return (f"The truth contradicts the label of {100 * min(shares):.0f}-"
            f"{100 * max(shares):.0f}% of a world's held-out points (median "
            f"{100 * float(np.median(shares)):.0f}%, over the points on cells it labels): "
            "noisy hits in free space and free points past walls. ")


def family_table(cases: list[dict]) -> list[str]:
    """Per world family: input noise against none and the grid (wins, worst AUC
    difference), and whether the mean AUC and FPR@TPR0.97 follow the method paper's
    Table II ordering (input noise > no input noise > grid), on ``cells``, ``union`` and
    ``union-truth``."""
    families = sorted({c["family"] for c in cases if c.get("family")})
    if not families:
        return []
    lines = ["| family | worlds | protocol | AUC wins vs no input noise | worst AUC diff | "
             "Brier wins | AUC wins vs grid | Table II order (AUC / FPR@TPR0.97) |",
             "|---|---:|---|---:|---:|---:|---:|---|"]
    compared = ("gp-input-noise", "gp-no-input-noise", "grid")
    for family in families:
        rows = [c for c in cases if c.get("family") == family]
        for protocol in ("cells", "union", "union-truth"):
            # A variant's run maps with the GP with input noise alone (every_method).
            have = [c["scores"][protocol] for c in rows if protocol in c["scores"]
                    and all(m in c["scores"][protocol] for m in compared)]
            if not have:
                continue
            a = np.array([h["gp-input-noise"]["auc"] - h["gp-no-input-noise"]["auc"]
                          for h in have])
            brier = np.array([h["gp-input-noise"]["brier"] - h["gp-no-input-noise"]["brier"]
                              for h in have])
            g = np.array([h["gp-input-noise"]["auc"] - h["grid"]["auc"] for h in have])
            mean = {m: (np.mean([h[m]["auc"] for h in have]),
                        np.mean([h[m]["fpr_at_tpr97"] for h in have]))
                    for m in compared}
            auc_order = (mean["gp-input-noise"][0] > mean["gp-no-input-noise"][0]
                         > mean["grid"][0])
            fpr_order = (mean["gp-input-noise"][1] < mean["gp-no-input-noise"][1]
                         < mean["grid"][1])
            lines.append(
                f"| {family} | {len(have)} | {protocol} | {int((a > 0).sum())}/{a.size} | "
                f"{a.min():+.4f} | {int((brier < 0).sum())}/{brier.size} | "
                f"{int((g > 0).sum())}/{g.size} | "
                f"{'yes' if auc_order else 'no'} / {'yes' if fpr_order else 'no'} |")
    return lines if len(lines) > 2 else []


def section(title: str, text: str, table: list[str]) -> list[str]:
    """A page section's lines: its title, ``text`` and ``table``; none without a table."""
    return ["## " + title, "", text, "", *table, ""] if table else []


def page(run: dict, variants: dict[str, list[dict]] | None = None,
         seed_runs: list[list[dict]] | None = None) -> str:
    """docs/results.md from a run's summary (:func:`main` writes it as JSON too), the
    cases of the ``variants`` it is compared with (name -> cases) and of the runs of the
    same settings with other learning seeds (``seed_runs``)."""
    cases, st = run["cases"], run["stamp"]
    spread = seed_spread(cases, seed_runs) if seed_runs else None
    quick = run["quick"]
    work = run["work"].replace(str(ROOT) + "/", "")
    lines = [
        "# Accuracy results",
        "",
        f"Generated by `bench/experiment.py` on {st['date']} at commit `{st['commit']}` "
        f"(Python {st['python']}; {st['machine']}). Variant `{run['variant']}`"
        + (" (gpocc's defaults)" if run["variant"] == "defaults"
           else f": {VARIANTS[run['variant']]}") + f"; noise seed {run['seed']}. "
        "This page is overwritten by each run; do not edit it by hand.",
        "",
    ]
    if quick:
        lines += ["**Quick run** (`--quick`): one world and one 50-scan log cut, a check of "
                  "the pipeline, not the suite. `make experiment` runs all of it.", ""]
    lines += [
        "## Reproduce",
        "",
        "```sh",
        "make install",
        "make experiment" if not quick else ".venv/bin/python -m bench.experiment --quick",
        "```",
        "",
        "The OctoMap rows need the bench extra (`.venv/bin/python -m pip install -e "
        "'.[bench]'`, pyoctomap); without it they are left out"
        + (" (left out in this run)." if "octomap" not in _methods(cases) else "."),
        "Every step the results depend on is listed at the end of this page (paths under "
        f"`{work}`), those an earlier run made and this one reused from the work folder "
        "too (marked `reused`); the steps that are not gpocc commands (the real logs' "
        "perturbed poses, the noisy-only truth, the OctoMap rows, the loop-closure figure) "
        "are library calls in bench/experiment.py, bench/octomap_map.py and "
        "bench/loop_closure.py, listed as `# library:` lines.",
        "",
        "## What is measured",
        "",
        "Methods: `grid` (`gpocc grid`, log-odds), `octomap` (pyoctomap, the same scans "
        "ray-cast at the same resolution, its occupancy probability per cell; unknown cells "
        "score p = 0.5), `bhm` (`gpocc bhm`, a Bayesian Hilbert map with gpocc's "
        "defaults), `gp-no-input-noise` and `gp-input-noise` (`gpocc train "
        "--input-noise off|on`, `gpocc map`). Every map at "
        f"{RESOLUTION} m, trained on the same scans.",
        "",
        "Held-out protocols (`gpocc split`: every 10th scan held out of training; the "
        "quick run's log every 5th): `hits+free` each held-out hit (occupied) and three free "
        "points uniform along its beam, `hits+near-wall` the hits and one free point "
        "uniform 0.05-0.3 m in front of each hit, `union` all of them. Per-cell protocols "
        "(simulated worlds only): `cells` every labelled cell of the truth raster, "
        "`cells-noisy-only` the cells only the noisy platform II saw. Decisions about "
        "defaults use `union` and `cells`, never one protocol alone. On the simulated "
        "worlds the held-out points are measured like the training scans, with each "
        "platform's range and bearing noise (platform II: range variance 0.8 m^2), so they "
        "are themselves noisy there; the truth raster is exact. "
        + _contradicted_text(cases)
        + "`union-truth` scores the union's points with the truth raster's labels instead "
        "(`gpocc evaluate --labels-from truth.tif`; points on cells the truth does not "
        "label are left out).",
        "",
        "Real logs: the training scans' poses are perturbed stretch by stretch "
        f"({STRETCH_SCANS} scans each; sigma x/y, yaw: "
        + ", ".join(f"{a} m / {b} deg" for a, b in REAL_LEVELS)
        + ") and the bag carries that covariance; the held-out points use the recorded "
        "poses. Points a map does not cover score p = 0.5. The same splits are also "
        "trained as logged (cases marked `poses as logged`: the corrected poses, the log's "
        "config), counted like the other cases in the comparisons with other settings "
        "and in the spread.",
        "",
        "## Summary",
        "",
        "Wins count the cases where the first method is better (higher AUC, lower FPR at "
        "TPR 0.97, lower Brier); differences are first minus second.",
        "",
        *summary_table(cases),
        "",
    ]
    if spread:
        lines += section(
            "Run-to-run spread",
            f"The same settings learned with {len(seed_runs)} other learning seeds "
            f"({', '.join(f'`seed: {k}`' for k in SPREAD_SEEDS[:len(seed_runs)])}; each "
            "made with `.venv/bin/python -m bench.experiment sim real clean --variant seed-K`): "
            "the seed draws the likelihood's patches, the annealing and the classifier's "
            "held-out draws, while the worlds, logs and held-out points stay. The spread of "
            "a case is the largest minus the smallest score of the GP with input noise over "
            f"the {len(seed_runs) + 1} runs: a difference between settings smaller than it "
            "may be chance.", spread_table(cases, spread, len(seed_runs) + 1))
    if variants:
        groups: dict[str, dict[str, list[dict]]] = {}
        for name, other in variants.items():
            groups.setdefault(base_of(name), {})[name] = other
        against = []
        for base, group in groups.items():
            if base == "defaults":
                continue
            against += ["", f"Against `{base}`'s run (the variants that change one of its "
                        "settings and pin the others): wins count the cases where "
                        f"`{base}` is better; differences are `{base}` minus the variant.",
                        "", *(variant_table(variants[base], group, spread, base=base)
                              if base in variants else
                              [f"(`{base}`'s run was not given: `--compare {base}`.)"])]
        lines += ["## Against other settings", "",
                  "The GP with input noise of this run against the same GP with the "
                  "settings of each variant's overrides changed (each made with "
                  "`.venv/bin/python -m bench.experiment "
                  "sim real clean --variant NAME`, on the same worlds, logs and held-out points): "
                  "each variant against the defaults. Wins count the cases where this run is "
                  "better; differences are this run minus the variant. A variant whose "
                  "`compared with` is another variant changes one setting of that one "
                  "(its overrides include that variant's) and is compared with that "
                  "variant's run, in its own table below.", "",
                  "| variant | overrides | compared with |", "|---|---|---|",
                  *(f"| {name} | " + ", ".join(f"`{k}: {v}`" for k, v in
                                               VARIANTS[name].items())
                    + f" | {compared_with(name)} |"
                    for name in variants), "",
                  *((["The last two columns count the cases whose score differs by more "
                      "than that case's run-to-run spread (section above): better here / "
                      "better in the variant.", ""]) if spread else []),
                  *variant_table(cases, groups.get("defaults", {}), spread), *against, "",
                  "On the real logs (union protocol, AUC / Brier; with perturbed poses and "
                  "as logged):", "",
                  *real_log_table(cases, variants), "",
                  "What each costs: the GP with input noise's train + map wall time on this "
                  "machine (each variant ran at another time, so small ratios are noise), "
                  "and its learning's likelihood evaluations.", "",
                  *cost_table(cases, variants), ""]
    lines += section(
        "Real logs as logged",
        "The real logs' splits trained on their recorded (corrected) poses with the log's "
        "config, as a user with an accurate lidar and SLAM poses would: every method on "
        "the `union` protocol (the other protocols are in their sections below).",
        protocol_table([c for c in cases if c.get("as_logged")], "union"))
    on_bounds = bounds_table(cases)
    if on_bounds:
        lines += ["## Learned values on their bounds", "",
                  "A learned value on a bound of its search (`gpocc train` warns, `gpocc "
                  "info` lists it) was stopped by the box, not chosen by the data. The GP "
                  "with input noise of this run, per learned value that ended on a bound in "
                  "some case:", "", *on_bounds, ""]
        widened = widening_tables(cases, variants or {})
        if widened:
            lines += ["Each variant below widens the box of some of them (its overrides are "
                      "in the table above): where those values end, and what the wider box "
                      "gains, variant minus the run it is compared with (its `compared "
                      "with` above; log marginal likelihood of the "
                      "training patches; held-out scores of the maps, mean over the cases, "
                      "wins where the variant is better). A likelihood that keeps rising "
                      "while the maps do not improve says the bound is not what limits the "
                      "maps.", "", *widened, ""]
    lines += section(
        "Free space next to walls (real logs)",
        "The held-out free points of the real logs (trained on perturbed poses or as "
        "logged, the held-out points on the recorded ones) by their distance to the nearest "
        "held-out "
        "hit: how many, then each map's mean p / Brier score on them. Free points a few "
        "centimetres from a hit are the free space just in front of walls that grazing "
        "beams cross; a map that blurs its walls scores them high.",
        wall_distance_table(cases))
    lines += section(
        "Anchor placement",
        "Each local problem of a map is centred on its anchor (the NN kernel is not "
        "translation invariant), and its predictions are sharpest near that centre. Here "
        "each case's GP with input noise (the same model file) is mapped again with its "
        "anchor lattice moved by half a spacing west and north (the library call "
        "`moved_map` below: the cells stay where they were), and both maps are scored "
        "on the held-out points inside "
        "the page's map (`union`) and per cell: the difference is what the placement of "
        "the anchors alone changes, at no change of the model. On the real logs the "
        "page's maps have the anchors of the model's whole map (its samples' extent plus "
        "`map.margin_m`), half a spacing inside its north-west corner; on the simulated "
        "worlds every variant's config pins them (`map.anchor_origin_m`) to the world "
        "map's north-west corner, x = -0.5 m, so they fall on whole metres of x (the "
        "worlds' west walls stand at x = 0).",
        moved_anchors_table(cases))
    lines += section(
        "By world family",
        "Simulated worlds by generator family (the second generator's `offices`, `hall` and "
        "`clutter` draw their platforms' noise around Table I's): `gp-input-noise` against "
        "`gp-no-input-noise` and `grid`; Table II order compares the family's mean AUC and "
        "FPR@TPR0.97.", family_table(cases))
    for protocol in PROTOCOLS:
        table = protocol_table(cases, protocol)
        if table:
            lines += [f"## Protocol `{protocol}`", "", *table, ""]
    if run.get("loop"):
        lines += ["## Loop closure (intel_poses_odom_vs_corrected.txt)", "", run["loop"], ""]
    lines += ["## Commands", "", *command_lines(run["commands"]), ""]
    return "\n".join(lines)


def command_lines(commands: list[dict | str]) -> list[str]:
    """The page's "Commands" section body: every step of :data:`COMMANDS` in order, paths
    relative to the repository, the reused ones marked (a plain string: a step of a
    summary written before steps were marked, made by that run)."""
    reused = sum(1 for c in commands if isinstance(c, dict) and c["reused"])
    lines = []
    if reused:
        lines += [f"{reused} of these {len(commands)} steps were not run again: their "
                  "output was already in the work folder, made by an earlier run with the "
                  "same command; delete the work folder to make everything anew.", ""]
    lines.append("```sh")
    for c in commands:
        line, was_reused = (c["command"], c["reused"]) if isinstance(c, dict) else (c, False)
        line = str(line).replace(str(ROOT) + "/", "")
        lines.append(line + ("  # reused" if was_reused else ""))
    lines.append("```")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    steps = ("sim", "real", "clean", "loop", "report")
    # Checked by hand: argparse (3.11) checks an empty or default list against choices.
    parser.add_argument("what", nargs="*",
                        help=f"steps of {steps} (default: sim real clean loop)")
    parser.add_argument("--work", type=Path, default=ROOT / "out" / "experiment")
    parser.add_argument("--variant", default="defaults", choices=list(VARIANTS))
    parser.add_argument("--worlds", nargs="*", default=list(WORLDS))
    parser.add_argument("--logs", nargs="*", default=list(REAL_LOGS), choices=list(REAL_LOGS))
    parser.add_argument("--seed", type=int, default=0, help="noise seed of worlds and logs")
    parser.add_argument("--quick", action="store_true",
                        help="one world and one log cut (the Intel sample); no loop closure")
    parser.add_argument("--doc", type=Path, default=DOC, help="page to write")
    parser.add_argument("--merge", action="store_true",
                        help="keep the stored summary's cases that this run does not make "
                        "again (add a step to an earlier run)")
    parser.add_argument("--compare", action="append", default=[], choices=list(VARIANTS),
                        metavar="VARIANT", help="compare with this variant's run in the work "
                        "folder (its summary-VARIANT.json; repeatable)")
    parser.add_argument("--every-method", action="store_true",
                        help="map with every method in a variant's run too (by default "
                        "only the defaults' run does; a variant's runs the GP with input "
                        "noise alone, all the page compares)")
    parser.add_argument("--spread", action="store_true",
                        help="add the run-to-run spread from the runs of the variants "
                        + ", ".join(f"seed-{k}" for k in SPREAD_SEEDS)
                        + " in the work folder")
    args = parser.parse_args()
    args.what = args.what or (["sim", "real"] if args.quick
                              else ["sim", "real", "clean", "loop"])
    unknown = sorted(set(args.what) - set(steps))
    if unknown:
        parser.error(f"unknown step(s) {unknown}; choose from {steps}")
    args.work.mkdir(parents=True, exist_ok=True)
    summary = args.work / f"summary-{args.variant}{'-quick' if args.quick else ''}.json"
    if args.what == ["report"]:
        run = json.loads(summary.read_text())
    else:
        worlds = ["default"] if args.quick else args.worlds
        cases: list[dict] = []
        all_methods = every_method(args.variant, args.every_method)
        if "sim" in args.what:
            cases += run_sim(args.work, args.variant, worlds, args.seed, all_methods)
        if "real" in args.what:
            cases += run_real(args.work, args.variant, real_logs(args.logs, args.quick),
                              args.seed, all_methods=all_methods)
        if "clean" in args.what:
            cases += run_real(args.work, args.variant, real_logs(args.logs, args.quick),
                              args.seed, as_logged=True, all_methods=all_methods)
        stored = (json.loads(summary.read_text()) if args.merge and summary.is_file()
                  else {"cases": [], "loop": None, "commands": []})
        made = {c["case"] for c in cases}
        cases = [c for c in stored["cases"] if c["case"] not in made] + cases
        loop = stored["loop"]
        if "loop" in args.what:
            from .loop_closure import loop_closure_experiment

            loop = loop_closure_experiment(args.work / "loop", CARMEN, gpocc)
        run = {"stamp": stamp(), "variant": args.variant, "seed": args.seed,
               "quick": args.quick, "work": str(args.work), "cases": cases, "loop": loop,
               "commands": stored["commands"] + COMMANDS}
        summary.write_text(json.dumps(run, indent=2) + "\n")
    def stored_cases(name: str, flag: str) -> list[dict]:
        """The cases of variant ``name``'s run in the work folder (``flag`` asked for it)."""
        other = args.work / f"summary-{name}{'-quick' if args.quick else ''}.json"
        if not other.is_file():
            parser.error(f"{flag}: {other} not found; run `python -m bench.experiment "
                         f"sim real clean --variant {name}` first")
        return json.loads(other.read_text())["cases"]

    # A variant compared with another variant's run needs that run too.
    compare = list(dict.fromkeys(
        [*(base_of(n) for n in args.compare if base_of(n) != "defaults"), *args.compare]))
    variants = {name: stored_cases(name, f"--compare {name}") for name in compare}
    seed_runs = [stored_cases(f"seed-{k}", "--spread")
                 for k in (SPREAD_SEEDS if args.spread else ())]
    text = page(run, variants, seed_runs)
    args.doc.write_text(text)
    print(text, flush=True)
    print(f"wrote {args.doc} and {summary}", file=sys.stderr)


if __name__ == "__main__":
    main()
