"""What blurs the walls: one knob at a time, on held-out real logs and simulated worlds.

Run ``.venv/bin/python bench/walls.py run KNOB [KNOB ...] [--logs ...] [--worlds ...]
[--seeds 0 1]`` then ``.venv/bin/python bench/walls.py report`` (writes out/walls/walls.md
from every result gathered so far in ``out/walls/results.json``): a research tool whose
report stays in the work folder; the knobs users set are measured on the results page
(``make experiment``'s variants).

Per real log and split seed (``gpocc split --every 10 --seed S``; the training scans'
poses perturbed by stretch as in bench/experiment.py, seed S), the GP with input noise
is trained with one knob changed from a pinned baseline (:data:`KNOBS`) and scored on
the held-out points: AUC, Brier and log-loss per protocol (``hits+free``,
``hits+near-wall``, ``union``) and the mean p of the held-out hits and near-wall free
points, beside the grid, OctoMap (with the bench extra) and BHM trained on the same
scans. Per simulated world the same GP is scored on the held-out points and per cell
against the truth raster. The learned parameters (input-noise scale g, Platt slope a,
label noise, kernel) are recorded with each run. Every gpocc step is a gpocc command
(bench/experiment.py's runner); the steps that are not (perturbing poses, OctoMap) are
its library calls.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))

import experiment as ex  # noqa: E402  (bench/ is not a package on this path)

ROOT = ex.ROOT
WORK = ROOT / "out" / "walls"
RESULTS = WORK / "results.json"
PROFILES = WORK / "profiles.json"
DOC = WORK / "walls.md"

#: knob -> config overrides (dotted keys) of the GP with input noise. ``baseline`` pins
#: the defaults the knobs were measured against (before hit_gap_m became 0.15), so that
#: every row keeps its meaning; the others change one setting from it.
BASELINE: dict[str, object] = {"samples.hit_gap_m": 0.25,
                               "model.training.classifier_variance": "label",
                               "model.training.classifier_temperature": "none",
                               "model.training.classifier_offset": "holdout"}
KNOBS: dict[str, dict[str, object]] = {
    "baseline": BASELINE,
    "g=1": {"model.training.learn_input_noise_scale": False},
    "g<=1": {"model.training.max_input_noise_scale": 1.0},
    "clearance=0": {"samples.free_clearance_m": 0.0},
    "clearance=0.15": {"samples.free_clearance_m": 0.15},
    "hit_gap=0.15": {"samples.hit_gap_m": 0.15},
    "hit_gap=0.1": {"samples.hit_gap_m": 0.1},
    "hit_gap=0.05": {"samples.hit_gap_m": 0.05},
    "hit_gap=0.05,clearance=0": {"samples.hit_gap_m": 0.05, "samples.free_clearance_m": 0.0},
    "thin=0.1": {"samples.thin_cell_m": 0.1},
    "thin=0.25": {"samples.thin_cell_m": 0.25},
    "free_spacing=0.2": {"samples.free_spacing_m": 0.2},
    "free_spacing=0.8": {"samples.free_spacing_m": 0.8},
    "kernel_width=6": {"model.training.log_bounds_width": 6.0},
    "weight_var=120": {"model.hyperparameters.weight_variance": [120.0, 120.0]},
    "noise_floor=0.03": {"model.training.min_noise_variance": 0.03},
    "two-draw": {"model.diagonal": "two-draw"},
    "g_max=16": {"model.training.max_input_noise_scale": 16.0},
    "hit_gap=0.05,g_max=16": {"samples.hit_gap_m": 0.05,
                              "model.training.max_input_noise_scale": 16.0},
    "platt=latent": {"model.training.classifier_variance": "latent"},
    "hit_gap=0.05,platt=latent": {"samples.hit_gap_m": 0.05,
                                  "model.training.classifier_variance": "latent"},
}

PROTOCOLS = ("hits+free", "hits+near-wall", "union")


def load() -> list[dict]:
    """Every run gathered: out/walls/results*.json (one file per concurrent runner)."""
    rows = []
    for path in sorted(WORK.glob("results*.json")):
        rows += json.loads(path.read_text())
    return rows


def load_profiles() -> list[dict]:
    return json.loads(PROFILES.read_text()) if PROFILES.is_file() else []


def save(rows: list[dict]) -> None:
    """Write this runner's rows (those not in another runner's file) to RESULTS."""
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    others = set()
    for path in WORK.glob("results*.json"):
        if path != RESULTS:
            others |= {_key(r) for r in json.loads(path.read_text())}
    tmp = RESULTS.with_suffix(".tmp")
    tmp.write_text(json.dumps([r for r in rows if _key(r) not in others], indent=1))
    tmp.replace(RESULTS)


def _key(row: dict) -> tuple:
    return (row["knob"], row["kind"], row["case"], row["seed"])


def learned(model_path: Path) -> dict[str, float]:
    """The model's learned values: g, Platt a and offset, label noise, kernel."""
    from gpocc.gp.bounds import values_on_bounds
    from gpocc.gp.model import load_model

    m = load_model(model_path)
    out = {"g": float(m.input_noise_scale), "a": m.classifier.a,
           "offset": float(m.classifier.offset), "noise": float(m.noise_variance)}
    for name, value in ex.dataclasses.asdict(m.kernel).items():
        out[f"k.{name}"] = value if not isinstance(value, tuple) else list(value)
    out["on_bounds"] = [b.name for b in values_on_bounds(m)]
    return out


def evaluate(maps: dict[str, Path], truth: Path, out: Path) -> tuple[dict, dict]:
    """(protocol -> method -> scores, kind -> method -> mean p)."""
    scores = ex.evaluate(maps, truth, out)
    results = json.loads((out / "results.json").read_text())
    # the per-kind summary names maps by their folders' names (grid, bhm, octomap, gp)
    kinds = {kind: {name: v["mean_p"] for name, v in summary["maps"].items()}
             for kind, summary in (results.get("kinds") or {}).items()}
    return scores, kinds


def real_case(name: str, seed: int) -> tuple[Path, Path, dict[str, Path]]:
    """(training bag, its config, baseline map folders) of a log split at ``seed``."""
    log, cfg = ex.REAL_LOGS[name]
    path = ex.carmen_folder() / log
    base_dir = WORK / "real" / f"{name}-s{seed}"
    held = base_dir / "split"
    if not (held / "heldout.csv").is_file():
        ex.gpocc("split", path, "--every", str(ex.HELD_OUT_EVERY), "--config",
                 ROOT / "configs" / cfg, "--seed", str(seed), "--out", held, "--force")
    bag = ex.perturbed_training_bag(held, seed)
    base = base_dir / "train-noisy.yaml"
    if not base.is_file():
        data = yaml.safe_load((held / "train.yaml").read_text())
        for sensor in data["sensors"]:
            sensor["override_pose_covariance"] = False
        base.write_text(yaml.safe_dump(data, sort_keys=False))
    ex.grid_map([bag], base, base_dir / "grid", None)
    ex.grid_map([bag], base, base_dir / "bhm", None, "bhm")
    maps = {"grid": base_dir / "grid", "bhm": base_dir / "bhm"}
    if ex.octomap_row([bag], base, base_dir / "octomap", base_dir / "grid"):
        maps["octomap"] = base_dir / "octomap"
    return bag, base, maps


def sim_case(world: str, seed: int) -> tuple[Path, Path, list[str], Path]:
    sim = WORK / "sim" / f"{world}-s{seed}"
    if not (sim / "sim.mcap").is_file():
        ex.gpocc("simulate", "--out", sim, "--world", world, "--seed", str(seed), "--force")
    held = ex.split(sim / "sim.mcap", sim / "sim.yaml", sim / "split", ex.HELD_OUT_EVERY)
    return held / "train.mcap", held / "train.yaml", ex.truth_bounds(sim / "truth.tif"), sim


def overrides(knob: str) -> dict[str, object]:
    """The knob's settings on top of :data:`BASELINE`."""
    return {**BASELINE, **KNOBS[knob]}


def run_knob(knob: str, kind: str, case: str, seed: int, rows: list[dict]) -> None:
    if any(r["knob"] == knob and r["case"] == case and r["seed"] == seed for r in rows):
        return
    if kind == "real":
        bag, base, maps = real_case(case, seed)
        bounds, truth_cells = None, None
        heldout = base.parent / "split" / "heldout.csv"
    else:
        bag, base, bounds, sim = sim_case(case, seed)
        maps = {}
        heldout = sim / "split" / "heldout.csv"
        truth_cells = sim / "truth.tif"
    vdir = WORK / "knobs" / knob / kind / f"{case}-s{seed}"
    vdir.mkdir(parents=True, exist_ok=True)
    config = ex.with_overrides(base, overrides(knob), vdir / "config.yaml")
    seconds = ex.gp_map([bag], config, "on", vdir / "gp", bounds)
    maps = {**maps, "gp": vdir / "gp"}
    scores, kinds = evaluate(maps, heldout, vdir / "evaluation-heldout")
    if truth_cells is not None:
        scores["cells"] = ex.evaluate({"gp": vdir / "gp"}, truth_cells,
                                      vdir / "evaluation-cells")["all"]
    rows.append({"knob": knob, "kind": kind, "case": case, "seed": seed, "scores": scores,
                 "mean_p": kinds, "learned": learned(vdir / "gp.npz"),
                 "gp_seconds": seconds})
    save(rows)


def profile(knob: str, case: str, seed: int) -> dict:
    """Slices of the training objectives through a trained model's learned values.

    The patch log marginal likelihood (the learner's own patches, its seed) along log g
    and along the label-noise variance, every other value held at the learned one; and
    the Platt classifier's held-out log probability (the leave-one-out predictions it
    was fitted on) along its extra variance s = 1/a^2, the offset re-fitted at each s,
    down through s = 0 (a = infinity) to negative s (a sharper squashing than the
    predictive distribution's own; only defined while s + var > 0 for every point)."""
    from scipy.optimize import minimize_scalar

    from gpocc.gp import backends
    from gpocc.gp.classify import held_out_log_probability, holdout_predictions
    from gpocc.gp.inputscale import scale_input_noise
    from gpocc.gp.model import load_model
    from gpocc.gp.train import make_patches, negative_log_likelihood

    vdir = WORK / "knobs" / knob / "real" / f"{case}-s{seed}"
    m = load_model(vdir / "gp.npz")
    cfg = m.config.model
    g = float(m.input_noise_scale)
    stated = scale_input_noise(m.samples, 1.0 / g)
    patches = make_patches(stated, cfg.effective_training, m.config.seed)
    level, backend = cfg.quadrature_level, backends.choose(cfg.backend, cfg.diagonal,
                                                          cfg.covariance_precision)
    params = [*m.kernel.theta, math.log(m.noise_variance)]

    def lml(noise: float, scale: float) -> float:
        value, _ = negative_log_likelihood(
            ex.np.array([*params[:-1], math.log(noise)]), m.kernel, patches, level,
            with_gradient=False, input_scale=scale, backend=backend)
        return -value

    out: dict = {"knob": knob, "case": case, "seed": seed, "g": g,
                 "noise": m.noise_variance, "a": m.classifier.a}
    out["g_slice"] = [(s, lml(m.noise_variance, s))
                      for s in (0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0)]
    out["noise_slice"] = [(n, lml(n, g)) for n in (0.01, 0.02, 0.05, 0.1, 0.2, 0.5)]
    # The classifier's own points: fresh patches (seed + 1) as gpocc.gp.model fits it.
    fit_patches = make_patches(m.samples, cfg.effective_training, m.config.seed + 1)
    mu, var, y = holdout_predictions(m.kernel, m.noise_variance, fit_patches, level,
                                     cfg.training.classifier_holdout, backend,
                                     latent=cfg.training.classifier_variance == "latent")
    floor = float(var.min())

    def best(s: float) -> float:
        r = minimize_scalar(lambda c: -held_out_log_probability(c, s, mu, var, y),
                            bounds=(-5.0, 5.0), method="bounded")
        return -float(r.fun)

    grid = [1.0, 0.3, 0.1, 0.03, 0.01, 1e-3, 1e-6, 0.0,
            -0.25 * floor, -0.5 * floor, -0.75 * floor, -0.9 * floor, -0.99 * floor]
    out["platt_s_slice"] = [(s, best(s)) for s in grid]
    out["min_loo_variance"] = floor
    out["n_loo"] = int(y.size)
    return out


# ---- the page -----------------------------------------------------------------------------

def _f(v: float | None, digits: int = 4) -> str:
    return "" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def _profile_commands() -> list[str]:
    groups: dict[tuple, list[str]] = {}
    for p in load_profiles():
        knobs = groups.setdefault((p["case"], p["seed"]), [])
        if p["knob"] not in knobs:
            knobs.append(p["knob"])
    by_knobs: dict[tuple, list[tuple]] = {}
    for (case, seed), knobs in groups.items():
        by_knobs.setdefault(tuple(knobs), []).append((case, seed))
    return [".venv/bin/python bench/walls.py profile " + " ".join(f"'{k}'" for k in knobs)
            + " --logs " + " ".join(sorted({c for c, _ in cs}))
            + " --seeds " + " ".join(str(s) for s in sorted({s for _, s in cs}))
            for knobs, cs in by_knobs.items()]


def _difference_table(rows: list[dict]) -> list[str]:
    """Each knob minus ``baseline`` on the same case and seed: AUC and Brier of the
    union and of hits+near-wall (real logs) or of the cells (worlds)."""
    base = {(r["case"], r["seed"]): r for r in rows if r["knob"] == "baseline"}
    lines = ["", "## Each knob against the baseline", "",
             "Knob minus `baseline` on the same case and seed (AUC: higher is better;"
             " Brier: lower is better).", "",
             "| knob | case | seed | union AUC | union Brier | hits+near-wall AUC |"
             " hits+near-wall Brier | cells AUC | cells Brier |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in sorted(rows, key=lambda r: (r["knob"], r["kind"], r["case"], r["seed"])):
        d = base.get((r["case"], r["seed"]))
        if r["knob"] == "baseline" or d is None:
            continue
        cells = []
        for p in ("union", "hits+near-wall", "cells"):
            if p in r["scores"] and p in d["scores"]:
                a, b = r["scores"][p]["gp"], d["scores"][p]["gp"]
                cells += [f"{a['auc'] - b['auc']:+.4f}", f"{a['brier'] - b['brier']:+.4f}"]
            else:
                cells += ["", ""]
        lines.append(f"| {r['knob']} | {r['case']} | {r['seed']} | " + " | ".join(cells) + " |")
    return lines


def _commands(rows: list[dict]) -> list[str]:
    """One ``bench/walls.py run`` line per (seed, cases) group of the gathered rows."""
    groups: dict[tuple, list[str]] = {}
    for r in rows:
        cases = tuple(sorted({(x["kind"], x["case"]) for x in rows
                              if x["knob"] == r["knob"] and x["seed"] == r["seed"]}))
        knobs = groups.setdefault((r["seed"], cases), [])
        if r["knob"] not in knobs:
            knobs.append(r["knob"])
    lines = []
    for (seed, cases), knobs in groups.items():
        logs = [c for k, c in cases if k == "real"]
        worlds = [c for k, c in cases if k == "sim"]
        lines.append(".venv/bin/python bench/walls.py run " + " ".join(f"'{k}'" for k in knobs)
                     + " --logs " + " ".join(logs) + (" --worlds " + " ".join(worlds)
                                                      if worlds else "")
                     + f" --seeds {seed}")
    return lines


def page(rows: list[dict]) -> str:
    stamp = ex.stamp()
    lines = [
        "# What blurs the walls: one knob at a time",
        "",
        f"Generated by `bench/walls.py report` on {stamp['date']} at commit `{stamp['commit']}`"
        f" ({stamp['machine']}). Do not edit by hand.",
        "",
        "Each row trains the GP with input noise (`gpocc train --input-noise on`, `gpocc map`"
        " at 0.1 m) with ONE setting changed from `baseline` (the log's config with"
        " `samples.hit_gap_m: 0.25`, `model.training.classifier_variance: label`,"
        " `model.training.classifier_temperature: none` and"
        " `model.training.classifier_offset: holdout`,"
        " a baseline that differs from gpocc's defaults, whose `samples.hit_gap_m` is 0.15)."
        " Real logs: `gpocc split --every 10 --seed S`, the"
        " training scans' poses perturbed by stretch as in `bench/experiment.py` (seed S);"
        " the held-out points use the recorded poses. Worlds: `gpocc simulate --world W"
        " --seed S`, held out the same way, and scored per cell on the truth raster"
        " (`cells`). `p(hit)` and `p(near)` are the mean probabilities at held-out hits and"
        " at held-out free points 0.05-0.3 m in front of them. Learned values: input-noise"
        " scale `g`, Platt slope `a`, label-noise variance; `on bounds` lists what ended on"
        " a bound of its search.",
        "",
        "## Reproduce",
        "",
        "```sh",
        "make install && .venv/bin/python -m pip install -e '.[bench]'   # OctoMap rows",
        *_commands(rows),
        *_profile_commands(),
        ".venv/bin/python bench/walls.py report",
        "```",
        "",
        "Simulated worlds are scored for the GP alone (the peers' rows are in"
        " docs/results.md); differences there are knob against `baseline`.",
        "",
        "## Knobs",
        "",
        "| knob | overrides |",
        "|---|---|",
    ]
    used = list(dict.fromkeys(r["knob"] for r in rows))
    for knob in used:
        over = ", ".join(f"`{k}: {v}`" for k, v in KNOBS.get(knob, {}).items()) or "(none)"
        lines.append(f"| {knob} | {over} |")
    lines += _difference_table(rows)
    for kind, title in (("real", "Real logs"), ("sim", "Simulated worlds")):
        sel = [r for r in rows if r["kind"] == kind]
        if not sel:
            continue
        protocols = PROTOCOLS + (("cells",) if kind == "sim" else ())
        head = "| case | seed | method |" + "".join(
            f" {p} AUC | {p} Brier |" for p in protocols)
        head += " union log-loss | p(hit) | p(near) | g | a | label noise | on bounds |"
        lines += ["", f"## {title}", "", head,
                  "|---|---:|---|" + "---:|" * (2 * len(protocols) + 6) + "---|"]
        cases = list(dict.fromkeys((r["case"], r["seed"]) for r in sel))
        for case, seed in cases:
            here = [r for r in sel if (r["case"], r["seed"]) == (case, seed)]
            baselines = here[0]["scores"]["union"].keys() - {"gp"}
            for method in sorted(baselines):
                s = here[0]["scores"]
                mp = here[0]["mean_p"]
                cells = [f"{_f(s[p][method]['auc'])} | {_f(s[p][method]['brier'])}"
                         if method in s.get(p, {}) else " | " for p in protocols]
                lines.append(
                    f"| {case} | {seed} | {method} | " + " | ".join(cells)
                    + f" | {_f(s['union'][method]['log_loss'], 3)}"
                    + f" | {_f(mp.get('hit', {}).get(method), 3)}"
                    + f" | {_f(mp.get('near-wall', {}).get(method), 3)} | | | | |")
            for r in here:
                s, mp, lv = r["scores"], r["mean_p"], r["learned"]
                cells = [f"{_f(s[p]['gp']['auc'])} | {_f(s[p]['gp']['brier'])}"
                         for p in protocols]
                lines.append(
                    f"| {case} | {seed} | gp {r['knob']} | " + " | ".join(cells)
                    + f" | {_f(s['union']['gp']['log_loss'], 3)}"
                    + f" | {_f(mp.get('hit', {}).get('gp'), 3)}"
                    + f" | {_f(mp.get('near-wall', {}).get('gp'), 3)}"
                    + f" | {lv['g']:.3g} | {lv['a']:.3g} | {lv['noise']:.3g}"
                    + f" | {'; '.join(lv['on_bounds'])} |")
    return "\n".join(lines) + "\n"


def profile_page(profiles: list[dict]) -> str:
    if not profiles:
        return ""
    lines = ["", "## Likelihood slices through the learned values", "",
             "`bench/walls.py profile`: the patch log marginal likelihood (LML, summed over"
             " the learner's patches) with one value moved and every other held at the"
             " learned one; the Platt fit's held-out log probability (its leave-one-out"
             " points) along s = 1/a^2 with the offset re-fitted. Each row's maximum in"
             " bold.", ""]
    for p in profiles:
        lines.append(f"**{p['case']} seed {p['seed']}, {p['knob']}** (learned g ="
                     f" {p['g']:.3g}, label noise {p['noise']:.3g}, a = {p['a']:.3g};"
                     f" {p['n_loo']} leave-one-out points, smallest LOO variance"
                     f" {p['min_loo_variance']:.3g})")
        lines.append("")
        for key, label, fmt in (("g_slice", "g", "{:.3g}"),
                                ("noise_slice", "label noise", "{:.3g}"),
                                ("platt_s_slice", "Platt s", "{:.3g}")):
            xs = [fmt.format(x) for x, _ in p[key]]
            ys = [v for _, v in p[key]]
            top = max(range(len(ys)), key=lambda i: ys[i])
            # the learner's value for a covariance that is not positive definite
            cells = ["not PD" if v <= -1e9 else f"**{v:.1f}**" if i == top else f"{v:.1f}"
                     for i, v in enumerate(ys)]
            lines += [f"| {label} | " + " | ".join(xs) + " |",
                      "|---|" + "---:|" * len(xs),
                      "| log-lik | " + " | ".join(cells) + " |", ""]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("step", choices=("run", "profile", "report"))
    parser.add_argument("knobs", nargs="*", default=["baseline"])
    parser.add_argument("--logs", nargs="*", default=list(ex.REAL_LOGS))
    parser.add_argument("--worlds", nargs="*", default=[])
    parser.add_argument("--seeds", nargs="*", type=int, default=[0])
    parser.add_argument("--results", default="results.json",
                        help="file under out/walls this runner adds its rows to")
    args = parser.parse_args()
    global RESULTS
    RESULTS = WORK / args.results
    rows = load()
    if args.step == "run":
        unknown = set(args.knobs) - set(KNOBS)
        if unknown:
            raise SystemExit(f"unknown knobs {sorted(unknown)}; known: {sorted(KNOBS)}")
        for seed in args.seeds:
            for knob in args.knobs:
                for log in args.logs:
                    run_knob(knob, "real", log, seed, rows)
                for world in args.worlds:
                    run_knob(knob, "sim", world, seed, rows)
    if args.step == "profile":
        profiles = [p for p in load_profiles() if (p["knob"], p["case"], p["seed"]) not in
                    {(k, c, s) for k in args.knobs for c in args.logs for s in args.seeds}]
        for seed in args.seeds:
            for knob in args.knobs:
                for log in args.logs:
                    profiles.append(profile(knob, log, seed))
                    PROFILES.write_text(json.dumps(profiles, indent=1))
    DOC.write_text(page(load()) + profile_page(load_profiles()))
    print(f"wrote {DOC}", file=sys.stderr)


if __name__ == "__main__":
    main()
