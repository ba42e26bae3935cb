"""Cost and accuracy of ``gpocc update`` against training on all logs at once.

Registered as the benchmark ``update-cost`` (``python -m bench.run_bench --only
update-cost``). For each CARMEN log and cut (a share of its laser scans), the log is cut
by lines into a first part A and a second part B (``<stem>_a.log``, ``<stem>_b.log``),
and each part is split with ``gpocc split --every 10`` (every 10th scan held out). Then
``gpocc train A`` (once), and, interleaved ``--repeats`` times, ``gpocc update A.npz B``
and ``gpocc train A B``: wall seconds and the commands' CPU seconds (user +
system, the process and its workers). The last repeat's models are mapped at 0.1 m and
scored with ``gpocc evaluate`` on the held-out points of both parts. One row per
(log, cut, protocol) with the medians' ratio update / train, and a second table of where
the time goes: each command's stages as it prints them, its start-up (wall seconds
outside its own timer: the interpreter and imports) and the likelihood evaluations of
its hyperparameter learning.
"""

from __future__ import annotations

import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

from gpocc.constants import RESULTS_FILE

from .harness import printed, stage_times
from .paths import FREIBURG, INTEL, ROOT
from .registry import Context, Result, Table, benchmark, require

CONFIGS = {"intel.gfs.log": "carmen_intel.yaml",
           "freiburg-079-corrected.log": "carmen_freiburg.yaml"}
#: Part names matching the configs' sensor ``inputs`` globs (``intel*.log``, ...).
STEMS = {"intel.gfs.log": "intel", "freiburg-079-corrected.log": "freiburg"}
GPOCC = [sys.executable, "-m", "gpocc"]
#: Where each log is cut (share of its scans in A): several splits, since one split's
#: difference between update and train is one draw of the learning's own spread. Halves
#: (0.5) are the usual case; the others show a small and a large second part.
CUTS = (0.2, 0.35, 0.5, 0.65, 0.8)


def run(*args: str) -> tuple[float, float, str]:
    """Run ``gpocc ARGS`` quietly; its wall and CPU seconds (user + system, children)
    and its stdout."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    done = subprocess.run([*GPOCC, *args, "--quiet"], check=True, cwd=ROOT,
                          stdout=subprocess.PIPE, text=True)
    wall = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
            done.stdout)


def where_time_goes(wall_s: float, stdout: str, model: Path) -> dict:
    """A learning command's printed stages, its start-up (``wall_s`` minus the total it
    prints: interpreter, imports, process exit), its likelihood evaluations and the log
    marginal likelihood it reached on its patches."""
    from gpocc.gp.model import load_model

    total = printed(stdout, r"time: ([0-9.]+) s")
    training = load_model(model).training
    return {"stages": stage_times(stdout),
            "startup_s": wall_s - float(total.group(1)) if total else float("nan"),
            "evaluations": training.get("evaluations"),
            "log_marginal_likelihood": training.get("log_marginal_likelihood")}


def cut_log(log: Path, share: float, first: Path, second: Path) -> None:
    """Cut a CARMEN log by lines before its laser scan number ``share`` x scans."""
    lines = log.read_text().splitlines(keepends=True)
    scans = [i for i, line in enumerate(lines) if line.startswith(("FLASER", "ROBOTLASER1"))]
    at = scans[int(round(share * len(scans)))]
    first.write_text("".join(lines[:at]))
    second.write_text("".join(lines[at:]))


def score(work: Path, model: Path, truth: Path, name: str) -> dict[str, dict]:
    """AUC and Brier of the model's map at 0.1 m per evaluation protocol (held-out hits
    with free points along beams, with near-wall free points, and all points)."""
    run("map", str(model), "--resolution", "0.1", "--workers", "2",
        "--out", str(work / f"map-{name}"))
    run("evaluate", str(work / f"map-{name}"), "--ground-truth", str(truth),
        "--out", str(work / f"eval-{name}"))
    results = json.loads((work / f"eval-{name}" / RESULTS_FILE).read_text())
    return {p["name"]: {"auc": p["maps"][0]["auc"], "brier": p["maps"][0]["brier"]}
            for p in results.get("protocols", [{"name": "all", "maps": results["maps"]}])}


def case(work: Path, log: Path, share: float, repeats: int, every: int = 10) -> dict:
    stem = STEMS[log.name]
    a, b = work / f"{stem}_a.log", work / f"{stem}_b.log"
    cut_log(log, share, a, b)
    config = str(ROOT / "configs" / CONFIGS[log.name])
    for part, held in ((a, "heldA"), (b, "heldB")):
        run("split", str(part), "--every", str(every), "--config", config,
            "--out", str(work / held))
    train_a, train_b = work / "heldA" / "train.mcap", work / "heldB" / "train.mcap"
    job = str(work / "heldA" / "train.yaml")
    truth = work / "heldout.csv"
    rows_b = (work / "heldB" / "heldout.csv").read_text().splitlines(keepends=True)[1:]
    truth.write_text((work / "heldA" / "heldout.csv").read_text() + "".join(rows_b))
    run("train", str(train_a), "--config", job, "--out", str(work / "A.npz"))
    times: dict[str, list[tuple[float, float, str]]] = {"update": [], "train": []}
    for i in range(repeats):
        # Alternating order: a drift of the machine's speed hits both commands alike.
        order = ("update", "train") if i % 2 == 0 else ("train", "update")
        for what in order:
            if what == "update":
                times[what].append(run("update", str(work / "A.npz"), str(train_b),
                                       "--out", str(work / "AB-update.npz"), "--force"))
            else:
                times[what].append(run("train", str(train_a), str(train_b), "--config", job,
                                       "--out", str(work / "AB-train.npz"), "--force"))
    updated = score(work, work / "AB-update.npz", truth, "update")
    trained = score(work, work / "AB-train.npz", truth, "train")
    med = {k: (statistics.median(w for w, _, _ in v), statistics.median(c for _, c, _ in v))
           for k, v in times.items()}
    detail = {what: where_time_goes(times[what][-1][0], times[what][-1][2],
                                    work / f"AB-{what}.npz") for what in times}
    return {"log": log.name, "cut": share, "every": every, "repeats": repeats,
            "update_wall_s": med["update"][0], "train_wall_s": med["train"][0],
            "update_cpu_s": med["update"][1], "train_cpu_s": med["train"][1],
            "wall_ratio": med["update"][0] / med["train"][0],
            "cpu_ratio": med["update"][1] / med["train"][1], "detail": detail,
            "scores": {name: {"auc_update": updated[name]["auc"],
                              "auc_train": trained[name]["auc"],
                              "brier_update": updated[name]["brier"],
                              "brier_train": trained[name]["brier"]} for name in updated}}


@benchmark("update-cost", "Updating a model against training on all logs")
def update_cost(ctx: Context) -> Result:
    """`gpocc update A.npz B` against `gpocc train A B` for each CARMEN log cut in two
    parts by lines at 20%, 35%, 50%, 65% and 80% of its scans (A the first part),
    each part split
    with `gpocc split --every 10`: median wall and CPU seconds of the interleaved repeats
    (1, Intel cut at 50% only, in a quick run), and AUC and Brier of both models' maps at
    0.1 m on the held-out points of both parts, per protocol, with the largest absolute
    difference update - train of AUC and Brier (the target: at most 0.002). A
    second table gives, for the last repeat of each command, its start-up, its printed
    stages and its likelihood evaluations."""
    logs = [INTEL] if ctx.quick else [INTEL, FREIBURG]
    cuts = (0.5,) if ctx.quick else CUTS
    require(*logs)
    repeats = 1 if ctx.quick else ctx.repeats
    rows, costs = [], []
    for log in logs:
        for cut in cuts:
            work = ctx.work / f"update-{log.stem}-{cut}"
            work.mkdir(parents=True, exist_ok=True)
            r = case(work, log, cut, repeats)
            for head, what, command in (([log.name, f"{cut:.2f}"], "update", "update"),
                                        (["", ""], "train", "train A B")):
                d = r["detail"][what]
                costs.append([*head, command, f"{d['startup_s']:.2f}", d["stages"],
                              str(d["evaluations"]), f"{d['log_marginal_likelihood']:.1f}"])
            for i, (protocol, sc) in enumerate(r["scores"].items()):
                gap = max(abs(sc["auc_update"] - sc["auc_train"]),
                          abs(sc["brier_update"] - sc["brier_train"]))
                head = ([log.name, f"{cut:.2f}", str(repeats), f"{r['update_wall_s']:.2f}",
                         f"{r['train_wall_s']:.2f}", f"{r['wall_ratio']:.2f}",
                         f"{r['cpu_ratio']:.2f}"] if i == 0 else [""] * 7)
                rows.append([*head, protocol,
                             f"{sc['auc_update']:.4f} / {sc['auc_train']:.4f}",
                             f"{sc['brier_update']:.4f} / {sc['brier_train']:.4f}",
                             f"{gap:.4f}"])
    result = Result()
    result.add(Table(("log", "cut", "repeats", "update wall s", "train A B wall s",
                      "wall ratio", "CPU ratio", "protocol", "AUC update / train",
                      "Brier update / train", "max difference"), rows))
    result.add(Table(("log", "cut", "command", "start-up s", "stages (printed, s)",
                      "likelihood evaluations", "log marginal likelihood"), costs),
               "Where the time of the last repeat goes: start-up is the wall time outside "
               "the command's own timer (interpreter, imports, exit), the same for both "
               "commands; an update reads and samples only B but refines the "
               "hyperparameters on all samples by Fisher scoring from A's values. Both "
               "commands draw the same patches; the log marginal likelihood each reached "
               "on them (nats) shows whether they found the same optimum (where the "
               "update's is higher, training's annealing ended in a worse one).")
    return result


#: The site of ``update-site``: its side in buildings (the last building is the one added).
SITE_SIDE = 5


def _building_scores(model: Path, out: Path, building, source) -> tuple[float, float]:
    """AUC and Brier of ``model``'s map at 0.1 m over ``building``'s extent (its source's
    held-out points moved into place, plus 5 m) on those points."""
    from gpocc.evaluation.report import probability_raster, read_probability

    from .city import map_roc

    points = building.apply(source.points)
    low, high = points.min(axis=0) - 5.0, points.max(axis=0) + 5.0
    run("map", str(model), "--resolution", "0.1", "--workers", "2", "--bounds",
        *(f"{v:.2f}" for v in (*low, *high)), "--out", str(out), "--force")
    roc = map_roc(*read_probability(probability_raster(out)[1]), points, source.labels)
    return roc.auc, roc.calibration.brier


@benchmark("update-site", "Adding a building to a site's model")
def update_site(ctx: Context) -> Result:
    """A site of 5 x 5 buildings laid out as the city's (`bench/city.py`: copies of the
    logs' training scans, 62.5 m apart, no config): `gpocc train` on all but the last
    once, then, interleaved `--repeats` times (once in a quick run), `gpocc update` of
    that model with the last building's log against `gpocc train` on all of them. Median
    wall seconds and their ratio, each command's stages and the log marginal likelihood
    it reached on the same patches, and AUC and Brier of each model's map at 0.1 m over
    the added building, on its source's held-out points moved into place."""
    from gpocc.gp.model import load_model

    from .campus import grid_layout, write_site
    from .city import EVERY, KEEP, split_source, training_scans

    require(INTEL, FREIBURG)
    layout = grid_layout(SITE_SIDE, 62.5)
    work = ctx.work / "update-site"
    logs, scans = write_site(work / "logs", layout,
                             {b.source.name: training_scans(b.source) for b in layout})
    old, added = logs[:-1], logs[-1]
    run("train", *map(str, old), "--out", str(work / "old.npz"))
    repeats = 1 if ctx.quick else ctx.repeats
    times: dict[str, list[tuple[float, float, str]]] = {"update": [], "train": []}
    for i in range(repeats):
        for what in (("update", "train") if i % 2 == 0 else ("train", "update")):
            if what == "update":
                times[what].append(run("update", str(work / "old.npz"), str(added),
                                       "--out", str(work / "update.npz"), "--force"))
            else:
                times[what].append(run("train", *map(str, logs), "--out",
                                       str(work / "train.npz"), "--force"))
    source = split_source(ctx, layout[-1].source, 0.1)
    rows = []
    medians = {k: statistics.median(w for w, _, _ in v) for k, v in times.items()}
    for what, command in (("update", "update (+1 building)"), ("train", "train (all)")):
        model = work / f"{what}.npz"
        auc, brier = _building_scores(model, work / f"map-{what}", layout[-1], source)
        training = load_model(model).training
        rows.append([command, f"{len(logs) - 1} + 1" if what == "update" else str(len(logs)),
                     f"{medians[what]:.2f}", stage_times(times[what][-1][2]),
                     str(training["evaluations"]),
                     f"{training['log_marginal_likelihood']:.1f}", f"{auc:.4f}",
                     f"{brier:.4f}"])
    result = Result()
    result.add(Table(("command", "buildings", "median wall s",
                      "stages (last repeat)", "likelihood evaluations",
                      "log marginal likelihood", "added building AUC",
                      "added building Brier"), rows),
               f"{len(logs)} buildings, {scans} scans (the training scans of `gpocc split "
               f"--every {EVERY}` of each source log, Freiburg's thinned to every "
               f"{KEEP[FREIBURG.name]}th), {repeats} repeat(s); update / train wall ratio "
               f"{medians['update'] / medians['train']:.2f}.")
    return result
