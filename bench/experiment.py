"""Accuracy experiments: two-robot worlds, real logs with honest pose noise, loop closure.

Run ``make experiment`` (all of it) or ``.venv/bin/python bench/experiment.py sim``,
``... real``, ``... loop``. Every gpocc step is a ``gpocc`` command, printed before it
runs, so each table can be reproduced by hand; the few steps that are not (perturbing a
log's poses, the region truth, the loop-closure figure) are library calls in this file.
Prints markdown tables for docs/results.md and writes ``summary-<variant>.json``.

* ``sim``: per world (``default``, ``office``, ``warehouse`` and grown worlds
  ``grown-<seed>``), ``gpocc simulate --world W --seed S`` (paper Table I platforms) ->
  ``gpocc grid``, ``gpocc train --input-noise off|on`` + ``map`` -> ``gpocc evaluate``
  against the truth raster, and against the truth of the region only the noisy
  platform II saw (``truth-noisy-only.tif``).
* ``real``: per CARMEN log, ``gpocc split --every 10``; the training scans' poses are
  perturbed by a covariance that changes every ``STRETCH_SCANS`` scans (quiet, noisy,
  very noisy; see :data:`REAL_LEVELS`) and written with that covariance to
  ``train-noisy.mcap``; grid and both GPs are trained on it and scored on the held-out
  scans (whose points use the corrected poses).
* ``loop``: intel_poses_odom_vs_corrected.txt: the Intel log mapped with its raw
  odometry (before loop closure; pose covariance growing with distance travelled since
  the start) and with the corrected poses (after), same GP settings: mean predictive
  variance and map sharpness of each, and a side-by-side figure.

``--variant`` picks one set of config overrides for the GP rows (:data:`VARIANTS`);
simulations, splits and grids are shared between variants.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
GPOCC = [sys.executable, "-m", "gpocc"]
WORLDS = ("default", "office", "warehouse", "grown-1", "grown-2", "grown-3")
REAL_LOGS = {"intel.gfs.log": "carmen_intel.yaml",
             "freiburg-079-corrected.log": "carmen_freiburg.yaml"}
#: Pose-noise levels of the real-log stretches: (sigma x/y metres, sigma yaw degrees).
REAL_LEVELS = ((0.02, 0.5), (0.08, 1.5), (0.15, 3.0))
STRETCH_SCANS = 50
METHODS = ("grid", "gp-no-input-noise", "gp-input-noise")

#: Config overrides (dotted keys) of the GP rows per variant. Every variant names the
#: classifier hold-out, the label-noise floor, whether g is learned, the patch centres and
#: the free-sample clearance and the blend overlap, so that it keeps its meaning when
#: defaults change (today's default is ``hit-patches-clearance-0.05``).
_PUBLISHED = {"model.training.classifier_holdout": "sample",
              "model.training.min_noise_variance": 0.01,
              "model.training.learn_input_noise_scale": False,
              "model.training.patch_centres": "samples",
              "samples.free_clearance_m": 0.0,
              "model.blend_overlap": 1.0}
#: The learned input-noise scale with the label-noise floor 0.1 (the default before
#: session 6); the later variants change one or two things on top of it.
_LEARNED = {**_PUBLISHED, "model.training.learn_input_noise_scale": True,
            "model.training.min_noise_variance": 0.1}
#: Today's default (session 6).
_DEFAULT = {**_LEARNED, "model.training.patch_centres": "hits",
            "samples.free_clearance_m": 0.05}
VARIANTS: dict[str, dict[str, object]] = {
    "published": _PUBLISHED,
    "scan-cv": {**_PUBLISHED, "model.training.classifier_holdout": "scan"},
    "floor-0.1": {**_PUBLISHED, "model.training.classifier_holdout": "scan",
                  "model.training.min_noise_variance": 0.1},
    "free-range": {**_PUBLISHED, "model.training.classifier_holdout": "scan",
                   "samples.free_range_variance": True},
    "free-range-floor-0.1": {**_PUBLISHED, "model.training.classifier_holdout": "scan",
                             "model.training.min_noise_variance": 0.1,
                             "samples.free_range_variance": True},
    "learned-scale": {**_PUBLISHED, "model.training.learn_input_noise_scale": True},
    "learned-scale-floor-0.1": _LEARNED,
    "learned-scale-max-2": {**_LEARNED, "model.training.max_input_noise_scale": 2.0},
    "beam-offset": {**_LEARNED, "model.training.classifier_offset": "beams"},
    "dense-samples": {**_LEARNED, "samples.thin_cell_m": 0.1, "model.neighbours": 256},
    "clearance-0.05": {**_LEARNED, "samples.free_clearance_m": 0.05},
    "hit-patches": {**_LEARNED, "model.training.patch_centres": "hits"},
    "hit-patches-clearance-0.05": _DEFAULT,
    # Session 9: neighbouring blocks blended across half a block instead of a whole one.
    "blend-0.5": {**_DEFAULT, "model.blend_overlap": 0.5},
    # Session 13: fewer (issue 14's speed) and more (the knob table's most exact) training
    # samples per map anchor; maps only (docs/results.md, session 13).
    "neighbours-96": {**_DEFAULT, "model.neighbours": 96},
    "neighbours-256": {**_DEFAULT, "model.neighbours": 256},
}


def carmen_folder() -> Path:
    """../shared/data/carmen next to the repository, or /work/shared/data/carmen."""
    for candidate in (ROOT.parent / "shared" / "data" / "carmen",
                      ROOT.parents[1] / "shared" / "data" / "carmen",
                      Path("/work/shared/data/carmen")):
        if candidate.is_dir():
            return candidate
    return ROOT.parent / "shared" / "data" / "carmen"


def gpocc(*args: str | Path) -> str:
    """Run one gpocc command (echoed on stderr) and return its stdout."""
    cmd = [str(a) for a in args]
    print("$ gpocc " + " ".join(cmd), file=sys.stderr, flush=True)
    done = subprocess.run([*GPOCC, *cmd], cwd=ROOT, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"gpocc {' '.join(cmd)} failed:\n{done.stderr}")
    return done.stdout


def with_overrides(config: Path, overrides: dict[str, object], out: Path) -> Path:
    """Write ``config`` with dotted-key ``overrides`` applied to ``out``."""
    data = yaml.safe_load(config.read_text()) or {}
    for key, value in overrides.items():
        node = data
        *parents, last = key.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[last] = value
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    return out


def evaluate(maps: list[Path], truth: Path, out: Path) -> dict[str, dict]:
    gpocc("evaluate", *maps, "--ground-truth", truth, "--out", out, "--force")
    results = json.loads((out / "results.json").read_text())
    return {row["name"]: row for row in results["maps"]}


def gp_map(inputs: list[Path], config: Path, noise: str, folder: Path,
           bounds: list[str] | None = None) -> float:
    """Train and map one GP at 0.1 m; returns the wall time (s)."""
    started = time.perf_counter()
    model = folder.with_suffix(".npz")
    gpocc("train", *inputs, "--config", config, "--input-noise", noise, "--out", model, "--force")
    extra = ["--bounds", *bounds] if bounds else []
    gpocc("map", model, "--resolution", "0.1", "--out", folder, "--force", *extra)
    return time.perf_counter() - started


def grid_map(inputs: list[Path], config: Path, folder: Path, bounds: list[str] | None) -> None:
    if (folder / "probability.tif").is_file():
        return
    extra = ["--bounds", *bounds] if bounds else []
    gpocc("grid", *inputs, "--config", config, "--resolution", "0.1", "--out", folder,
          "--force", *extra)


def truth_bounds(truth_tif: Path) -> list[str]:
    from gpocc.io.rasters import read_raster

    _, spec, _ = read_raster(truth_tif)
    return [f"{v:.3f}" for v in spec.bounds]


def scores(row: dict) -> dict[str, float]:
    return {k: float(row[k]) for k in ("auc", "fpr_at_tpr97", "brier", "log_loss", "ece")}


def noisy_only_truth(sim: Path, world: str, seed: int) -> Path:
    """truth-noisy-only.tif: the truth where only platform II's rays went."""
    from gpocc.evaluation.simulate import region_truth, simulate, truth_raster
    from gpocc.io.rasters import write_geotiff

    out = sim / "truth-noisy-only.tif"
    if not out.is_file():
        s = simulate(world, seed=seed)
        labels, spec = truth_raster(s.world, s.runs, 0.1)
        write_geotiff(out, region_truth(labels, spec, s.runs[:1]), spec, nodata=255)
    return out


def run_sim(work: Path, variant: str, worlds: list[str], seed: int) -> list[dict]:
    cases = []
    for world in worlds:
        sim = work / "sim" / f"{world}-s{seed}"
        if not (sim / "sim.mcap").is_file():
            gpocc("simulate", "--out", sim, "--world", world, "--seed", str(seed), "--force")
        truth = sim / "truth.tif"
        bounds = truth_bounds(truth)
        grid_map([sim / "sim.mcap"], sim / "sim.yaml", sim / "grid", bounds)
        vdir = work / variant / "sim" / sim.name
        vdir.mkdir(parents=True, exist_ok=True)
        config = with_overrides(sim / "sim.yaml", VARIANTS[variant], vdir / "config.yaml")
        seconds = {}
        for noise, name in (("off", "gp-no-input-noise"), ("on", "gp-input-noise")):
            seconds[name] = gp_map([sim / "sim.mcap"], config, noise, vdir / name, bounds)
        maps = [sim / "grid", vdir / "gp-no-input-noise", vdir / "gp-input-noise"]
        region = noisy_only_truth(sim, world, seed)
        for scope, t in (("all", truth), ("noisy-only", region)):
            result = evaluate(maps, t, vdir / f"evaluation-{scope}")
            cases.append({"case": f"{world} (seed {seed})", "kind": "sim", "region": scope,
                          "folder": str(vdir), "truth": str(t),
                          "methods": {m: scores(result[m]) for m in METHODS},
                          "gp_seconds": seconds})
    return cases


def perturbed_training_bag(split: Path, seed: int) -> Path:
    """train-noisy.mcap: the split's training scans with stretch-wise pose noise."""
    from gpocc.config import load_config
    from gpocc.evaluation.simulate import PoseNoise, perturb_poses, stretch_covariances
    from gpocc.io.bags import write_bag
    from gpocc.io.inputs import read_inputs

    out = split / "train-noisy.mcap"
    if out.is_file():
        return out
    config = load_config(split / "train.yaml")
    batches = read_inputs([split / "train.mcap"], config)
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


def run_real(work: Path, variant: str, logs: list[str], seed: int) -> list[dict]:
    cases = []
    carmen = carmen_folder()
    for log in logs:
        path = carmen / log
        if not path.is_file():
            print(f"skipping {log}: not in {carmen}", file=sys.stderr)
            continue
        stem = path.stem.split(".")[0].split("-")[0]
        split = work / "real" / stem / "split"
        if not (split / "heldout.csv").is_file():
            gpocc("split", path, "--every", "10", "--config", ROOT / "configs" / REAL_LOGS[log],
                  "--out", split, "--force")
        bag = perturbed_training_bag(split, seed)
        base = split.with_name("train-noisy.yaml")
        cfg = yaml.safe_load((split / "train.yaml").read_text())
        for sensor in cfg["sensors"]:
            sensor["override_pose_covariance"] = False  # the bag carries the truth
        base.write_text(yaml.safe_dump(cfg, sort_keys=False))
        grid_map([bag], base, split.parent / "grid", None)
        vdir = work / variant / "real" / stem
        vdir.mkdir(parents=True, exist_ok=True)
        config = with_overrides(base, VARIANTS[variant], vdir / "config.yaml")
        seconds = {}
        for noise, name in (("off", "gp-no-input-noise"), ("on", "gp-input-noise")):
            seconds[name] = gp_map([bag], config, noise, vdir / name)
        result = evaluate([split.parent / "grid", vdir / "gp-no-input-noise",
                           vdir / "gp-input-noise"], split / "heldout.csv", vdir / "evaluation")
        cases.append({"case": f"{log} (dense, pose noise by stretch)", "kind": "real",
                      "region": "all", "folder": str(vdir),
                      "truth": str(split / "heldout.csv"),
                      "methods": {m: scores(result[m]) for m in METHODS},
                      "gp_seconds": seconds})
    return cases


def resquashed(folder: Path, old, new, out: Path) -> Path:
    """``folder``'s map squashed by classifier ``new`` instead of ``old``, same GP, in
    ``out`` (probability.tif only).

    The latent mean is recovered from the stored p and variance by inverting
    p = Phi((mu + c) / sqrt(s + var)).
    """
    from scipy.special import ndtri

    from gpocc.io.rasters import read_raster, write_geotiff

    out.mkdir(exist_ok=True)
    p, spec, _ = read_raster(folder / "probability.tif")
    v, _, _ = read_raster(folder / "variance.tif")
    p, v = p.astype(float), v.astype(float)
    z = ndtri(np.clip(p, 1e-12, 1 - 1e-12))
    mu = z * np.sqrt(old.extra_variance + v) - old.offset
    q = new.probability(mu, v).astype(np.float32)
    write_geotiff(out / "probability.tif", q, spec, nodata=np.nan)
    return out


def reclassified(model_path: Path, folder: Path, holdout: str) -> Path:
    """``folder``'s map with the classifier re-fitted by ``holdout``, same GP
    (:func:`resquashed`); the new classifier is fitted exactly as ``gpocc train`` does
    (same patches, seed + 1). Writes ``<folder>-<holdout>-cv``.
    """
    from gpocc.gp.classify import fit_classifier
    from gpocc.gp.model import load_model
    from gpocc.gp.train import make_patches

    model = load_model(model_path)
    cfg = model.config.model
    patches = make_patches(model.samples, cfg.training, model.config.seed + 1)
    new = fit_classifier(model.kernel, model.noise_variance, patches, cfg.quadrature_level,
                         holdout)
    old = model.classifier
    out = resquashed(folder, old, new, folder.with_name(f"{folder.name}-{holdout}-cv"))
    (out / "classifier.json").write_text(json.dumps(
        {"from": dataclasses.asdict(old), "to": dataclasses.asdict(new)}) + "\n")
    return out


def case_truths(work: Path, case_dir: Path) -> dict[str, Path]:
    """Scope name -> truth file of a finished case folder (sim or real)."""
    if case_dir.parent.name == "sim":
        sim = work / "sim" / case_dir.name
        return {"all": sim / "truth.tif", "noisy-only": sim / "truth-noisy-only.tif"}
    return {"all": work / "real" / case_dir.name / "split" / "heldout.csv"}


def run_reclassify(work: Path, variant: str, holdout: str) -> None:
    """Every finished case of ``variant`` with its GP classifiers re-fitted by ``holdout``:
    ``<case>/evaluation-<holdout>-cv-<scope>``."""
    for case_dir in sorted((work / variant).glob("*/*")):
        maps = [case_dir / m for m in METHODS[1:]]
        if not all((m / "probability.tif").is_file() for m in maps):
            continue
        new = [reclassified(m.with_suffix(".npz"), m, holdout) for m in maps]
        grid = work / case_dir.parent.name / case_dir.name / "grid"
        for scope, truth in case_truths(work, case_dir).items():
            evaluate([grid, *new], truth, case_dir / f"evaluation-{holdout}-cv-{scope}")


def collect(work: Path, variant: str, classifier: str) -> list[dict]:
    """Scores of every finished case of ``variant``; ``classifier``: ``scan`` (the
    evaluation written by the run) or ``sample`` (the re-fitted one)."""
    cases = []
    for case_dir in sorted((work / variant).glob("*/*")):
        for scope in case_truths(work, case_dir):
            if classifier == "sample":
                folder = case_dir / f"evaluation-sample-cv-{scope}"
            elif case_dir.parent.name == "sim":
                folder = case_dir / f"evaluation-{scope}"
            else:
                folder = case_dir / "evaluation"
            if not (folder / "results.json").is_file():
                continue
            rows = json.loads((folder / "results.json").read_text())["maps"]
            by = {r["name"].replace(f"-{classifier}-cv", ""): r for r in rows}
            cases.append({"case": case_dir.name, "kind": case_dir.parent.name, "region": scope,
                          "methods": {m: scores(by[m]) for m in METHODS}})
    return cases


def region_comparison(cases: list[dict], region: str
                      ) -> tuple[list[dict], list[dict], list[dict], np.ndarray] | None:
    """The cases of ``region``, the input-noise and no-input-noise GP rows of each, and
    their AUC differences; None when the region has no case."""
    chosen = [c for c in cases if c["region"] == region]
    if not chosen:
        return None
    on = [c["methods"]["gp-input-noise"] for c in chosen]
    off = [c["methods"]["gp-no-input-noise"] for c in chosen]
    diff = np.array([a["auc"] - b["auc"] for a, b in zip(on, off, strict=True)])
    return chosen, on, off, diff


def tables(cases: list[dict]) -> str:
    lines = ["| case | region | method | AUC | FPR@TPR0.97 | Brier | log-loss | ECE |",
             "|---|---|---|---|---|---|---|---|"]
    for c in cases:
        for m in METHODS:
            s = c["methods"][m]
            lines.append(f"| {c['case']} | {c['region']} | {m} | {s['auc']:.4f} | "
                         f"{s['fpr_at_tpr97']:.3f} | {s['brier']:.4f} | {s['log_loss']:.3f} | "
                         f"{s['ece']:.3f} |")
    for region in ("all", "noisy-only"):
        compared = region_comparison(cases, region)
        if compared is None:
            continue
        _, on, off, diff = compared
        lines += ["", f"Region {region}: input noise vs none over {diff.size} cases: AUC wins "
                      f"{int((diff > 0).sum())}/{diff.size}, mean {diff.mean():+.4f}, worst "
                      f"{diff.min():+.4f}; mean Brier {np.mean([a['brier'] for a in on]):.4f} "
                      f"vs {np.mean([b['brier'] for b in off]):.4f}."]
    return "\n".join(lines)


def run_loop(work: Path) -> str:
    """Before/after loop closure on the Intel log (see the module docstring)."""
    from loop_closure import loop_closure_experiment

    return loop_closure_experiment(work / "loop", carmen_folder(), gpocc)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    steps = ("sim", "real", "loop", "reclassify", "report")
    # Checked by hand: argparse (3.11) checks an empty or default list against choices.
    parser.add_argument("what", nargs="*", help=f"steps of {steps} (default: sim real loop)")
    parser.add_argument("--work", type=Path, default=ROOT / "out" / "experiment")
    parser.add_argument("--variant", default="hit-patches-clearance-0.05",
                        choices=list(VARIANTS))
    parser.add_argument("--worlds", nargs="*", default=list(WORLDS))
    parser.add_argument("--logs", nargs="*", default=list(REAL_LOGS))
    parser.add_argument("--seed", type=int, default=0, help="noise seed of worlds and logs")
    args = parser.parse_args()
    args.what = args.what or ["sim", "real", "loop"]
    unknown = sorted(set(args.what) - set(steps))
    if unknown:
        parser.error(f"unknown step(s) {unknown}; choose from {steps}")
    args.work.mkdir(parents=True, exist_ok=True)
    cases: list[dict] = []
    if "sim" in args.what:
        cases += run_sim(args.work, args.variant, args.worlds, args.seed)
    if "real" in args.what:
        cases += run_real(args.work, args.variant, args.logs, args.seed)
    if "reclassify" in args.what:
        run_reclassify(args.work, args.variant, "sample")
    if "report" in args.what:
        for classifier in ("sample", "scan"):
            print(f"\n## Variant {args.variant}, {classifier} classifier\n")
            print(tables(collect(args.work, args.variant, classifier)), flush=True)
    if cases:
        summary = args.work / f"summary-{args.variant}-{'-'.join(args.what)}.json"
        summary.write_text(json.dumps(cases, indent=2) + "\n")
        print(f"\n## Variant {args.variant}: {VARIANTS[args.variant]}\n")
        print(tables(cases), flush=True)
    if "loop" in args.what:
        print("\n## Loop closure (intel_poses_odom_vs_corrected.txt)\n")
        print(run_loop(args.work), flush=True)


if __name__ == "__main__":
    main()
