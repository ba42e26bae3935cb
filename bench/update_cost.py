"""Cost and accuracy of ``gpocc update`` against training on all logs at once.

Run ``.venv/bin/python bench/update_cost.py [--logs intel.gfs.log ...] [--cuts 0.5 ...]``.
For each CARMEN log and cut (a share of its laser scans), the log is cut by lines into
a first part A and a second part B (``<stem>_a.log``, ``<stem>_b.log``), and each part
is split with ``gpocc split --every 10`` (every 10th scan held out; ``--every`` changes
it). Then ``gpocc train A`` (once), and, interleaved ``--repeats`` times, ``gpocc update
A.npz B`` and ``gpocc train A B``: wall seconds and the commands' CPU seconds (user +
system, the process and its workers). The last repeat's models are mapped at 0.1 m and
scored with ``gpocc evaluate`` on the held-out points of both parts. Prints one row per
(log, cut) and the medians' ratio update / train; the issue asks AUC and Brier within
0.002 and a ratio of at most 0.75. ``--json FILE`` also writes the rows.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CARMEN = ROOT.parent / "shared" / "data" / "carmen"
CONFIGS = {"intel.gfs.log": "carmen_intel.yaml",
           "freiburg-079-corrected.log": "carmen_freiburg.yaml"}
#: Part names matching the configs' sensor ``inputs`` globs (``intel*.log``, ...).
STEMS = {"intel.gfs.log": "intel", "freiburg-079-corrected.log": "freiburg"}
GPOCC = [sys.executable, "-m", "gpocc"]


def run(*args: str) -> tuple[float, float]:
    """Run ``gpocc ARGS`` quietly; its wall and CPU seconds (user + system, children)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    subprocess.run([*GPOCC, *args, "--quiet"], check=True, cwd=ROOT,
                   stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


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
    results = json.loads((work / f"eval-{name}" / "results.json").read_text())
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
    times: dict[str, list[tuple[float, float]]] = {"update": [], "train": []}
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
    med = {k: (statistics.median(w for w, _ in v), statistics.median(c for _, c in v))
           for k, v in times.items()}
    return {"log": log.name, "cut": share, "every": every, "repeats": repeats,
            "update_wall_s": med["update"][0], "train_wall_s": med["train"][0],
            "update_cpu_s": med["update"][1], "train_cpu_s": med["train"][1],
            "wall_ratio": med["update"][0] / med["train"][0],
            "cpu_ratio": med["update"][1] / med["train"][1],
            "scores": {name: {"auc_update": updated[name]["auc"],
                              "auc_train": trained[name]["auc"],
                              "brier_update": updated[name]["brier"],
                              "brier_train": trained[name]["brier"]} for name in updated}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--logs", nargs="*", default=list(CONFIGS), choices=list(CONFIGS))
    parser.add_argument("--cuts", nargs="*", type=float, default=[0.5, 0.4, 0.6])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--every", type=int, default=10,
                        help="hold out every K-th scan of each part (gpocc split --every)")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--data", type=Path, default=CARMEN,
                        help="folder of the CARMEN logs (default: ../shared/data/carmen)")
    args = parser.parse_args()
    rows = []
    print("| log | cut | every | update wall s | train A B wall s | wall ratio | CPU ratio | "
          "protocol | AUC update / train | Brier update / train |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in args.logs:
        log = args.data / name
        if not log.is_file():
            raise SystemExit(f"{log} not found: pass --data with the CARMEN logs' folder")
        for share in args.cuts:
            with tempfile.TemporaryDirectory(prefix="gpocc-update-") as tmp:
                r = case(Path(tmp), log, share, args.repeats, args.every)
            rows.append(r)
            for i, (protocol, s) in enumerate(r["scores"].items()):
                head = (f"| {name} | {share:g} | {args.every} | {r['update_wall_s']:.2f} | "
                        f"{r['train_wall_s']:.2f} | {r['wall_ratio']:.2f} | "
                        f"{r['cpu_ratio']:.2f} |" if i == 0 else "| | | | | | | |")
                print(f"{head} {protocol} | {s['auc_update']:.4f} / {s['auc_train']:.4f} | "
                      f"{s['brier_update']:.4f} / {s['brier_train']:.4f} |", flush=True)
    scores = [s for r in rows for s in r["scores"].values()]
    worst_auc = max(abs(s["auc_update"] - s["auc_train"]) for s in scores)
    worst_brier = max(abs(s["brier_update"] - s["brier_train"]) for s in scores)
    print(f"\nlargest |AUC difference| {worst_auc:.4f}, |Brier difference| {worst_brier:.4f} "
          f"(target: at most 0.002); largest wall ratio "
          f"{max(r['wall_ratio'] for r in rows):.2f} (target: at most 0.75)")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
