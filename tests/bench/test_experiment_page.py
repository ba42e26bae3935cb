"""bench/experiment.py's generated results page from a constructed run."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from bench import experiment


def _scores(rng: np.random.Generator) -> dict[str, float]:
    return {"auc": float(rng.uniform(0.8, 1.0)), "fpr_at_tpr97": float(rng.uniform(0, 1)),
            "brier": float(rng.uniform(0, 0.3)), "log_loss": float(rng.uniform(0, 1)),
            "ece": float(rng.uniform(0, 0.2)), "coverage": 1.0}


def _run(methods: tuple[str, ...]) -> dict:
    rng = np.random.default_rng(0)
    cases = []
    for i in range(5):
        protocols = experiment.HELDOUT_PROTOCOLS + (("cells",) if i < 3 else ())
        cases.append({"case": f"case {i}", "kind": "sim" if i < 3 else "real",
                      "scores": {p: {m: _scores(rng) for m in methods} for p in protocols}})
    return {"stamp": {"date": "2026-01-01 00:00 UTC", "commit": "abc1234",
                      "machine": "CPU X, 2 logical cores (2 usable), Linux",
                      "python": "3.11.7"},
            "variant": "defaults", "seed": 0, "quick": False, "work": "out/experiment",
            "cases": cases, "loop": None,
            "commands": [f"gpocc split {experiment.ROOT}/data/x.mcap --every 10"]}


def test_summary_counts_wins_per_protocol_and_the_page_is_stamped():
    run = _run(("grid", "gp-no-input-noise", "gp-input-noise"))
    text = experiment.page(run)
    assert "commit `abc1234`" in text and "CPU X" in text and "make experiment" in text
    assert "(left out in this run)" in text and "| octomap |" not in text
    assert "gpocc split data/x.mcap --every 10" in text  # paths relative to the repository
    for protocol in ("union", "cells"):
        rows = [c["scores"][protocol] for c in run["cases"] if protocol in c["scores"]]
        on = np.array([r["gp-input-noise"]["auc"] for r in rows])
        off = np.array([r["gp-no-input-noise"]["auc"] for r in rows])
        brier = np.array([r["gp-input-noise"]["brier"] - r["gp-no-input-noise"]["brier"]
                          for r in rows])
        line = next(x for x in text.splitlines()
                    if x.startswith(f"| {protocol} | gp-input-noise vs gp-no-input-noise |"))
        cells = [c.strip() for c in line.split("|")[1:-1]]
        assert cells[2] == f"{(on > off).sum()}/{len(rows)}"
        assert cells[3] == f"{(on - off).mean():+.4f}"
        assert cells[4] == f"{(on - off).min():+.4f}"
        assert cells[6] == f"{(brier < 0).sum()}/{len(rows)}"
        assert f"## Protocol `{protocol}`" in text


#: What ``offset-holdout`` and the variants of it pin, as the page lists overrides.
PINNED = ("`samples.label_weights: none`, `model.training.learn_input_noise_scale: True`, "
          "`model.training.classifier_offset_range: wide`, "
          "`model.training.classifier_offset: holdout`, `model.training.isotropic: False`, "
          "`model.training.patch_offset_m: 0.0`")


def test_the_page_compares_the_gp_with_each_variant_case_by_case():
    run = _run(("grid", "gp-no-input-noise", "gp-input-noise"))
    other = _run(("grid", "gp-no-input-noise", "gp-input-noise"))["cases"]
    rng = np.random.default_rng(5)
    for case in other:  # the variant's GP differs; it ran one case fewer
        for scores in case["scores"].values():
            scores["gp-input-noise"] = _scores(rng)
    other = other[1:]
    text = experiment.page(run, {"offset-holdout": other})
    assert ("| offset-holdout | " + PINNED + " | this run |") in text
    ours = {c["case"]: c["scores"] for c in run["cases"]}
    for protocol in ("union", "cells"):
        pairs = [(ours[c["case"]][protocol]["gp-input-noise"],
                  c["scores"][protocol]["gp-input-noise"])
                 for c in other if protocol in c["scores"]]
        auc = np.array([a["auc"] - b["auc"] for a, b in pairs])
        brier = np.array([a["brier"] - b["brier"] for a, b in pairs])
        line = next(x for x in text.splitlines() if x.startswith(
            f"| {protocol} | gp-input-noise vs gp-input-noise (offset-holdout) |"))
        cells = [c.strip() for c in line.split("|")[1:-1]]
        assert cells[2] == f"{(auc > 0).sum()}/{len(pairs)}"
        assert cells[3] == f"{auc.mean():+.4f}" and cells[4] == f"{auc.min():+.4f}"
        assert cells[6] == f"{(brier < 0).sum()}/{len(pairs)}"
        assert cells[7] == f"{brier.mean():+.4f}"


def test_a_variant_of_another_variant_is_compared_with_that_variants_run():
    """``hit-gap-0.25`` pins ``offset-holdout``'s settings: its table compares it with
    that run's GP, not with this run's."""
    run = _run(("grid", "gp-no-input-noise", "gp-input-noise"))
    rng = np.random.default_rng(6)
    runs = {}
    for name in ("offset-holdout", "hit-gap-0.25"):
        runs[name] = _run(("grid", "gp-no-input-noise", "gp-input-noise"))["cases"]
        for case in runs[name]:
            for scores in case["scores"].values():
                scores["gp-input-noise"] = _scores(rng)
    text = experiment.page(run, runs)
    lines = text.splitlines()
    assert ("| hit-gap-0.25 | `samples.hit_gap_m: 0.25`, " + PINNED
            + " | offset-holdout |") in lines
    assert not any("vs gp-input-noise (hit-gap-0.25)" in x and "(offset-holdout) vs" not in x
                   for x in lines)
    for protocol in ("union", "cells"):
        pairs = [(a["scores"][protocol]["gp-input-noise"], b["scores"][protocol]["gp-input-noise"])
                 for a, b in zip(runs["offset-holdout"], runs["hit-gap-0.25"], strict=True)
                 if protocol in a["scores"]]
        auc = np.array([a["auc"] - b["auc"] for a, b in pairs])
        line = next(x for x in lines if x.startswith(
            f"| {protocol} | gp-input-noise (offset-holdout) vs gp-input-noise (hit-gap-0.25) |"))
        cells = [c.strip() for c in line.split("|")[1:-1]]
        assert cells[2:5] == [f"{(auc > 0).sum()}/{len(pairs)}", f"{auc.mean():+.4f}",
                              f"{auc.min():+.4f}"]
    # Without the run it is compared with, the page says so instead of comparing.
    alone = experiment.page(run, {"hit-gap-0.25": runs["hit-gap-0.25"]})
    assert "`offset-holdout`'s run was not given" in alone
    assert not any(x.startswith("| union | gp-input-noise") and "(hit-gap-0.25)" in x
                   for x in alone.splitlines())


def test_octomap_rows_appear_when_the_run_has_them():
    text = experiment.page(_run(experiment.METHODS))
    assert "| union | gp-input-noise vs octomap |" in text
    assert "(left out in this run)" not in text


def test_family_rows_count_wins_and_check_the_table_two_order():
    run = _run(("grid", "gp-no-input-noise", "gp-input-noise"))
    families = ("hall", "hall", "offices")
    for case, family in zip(run["cases"][:3], families, strict=True):
        case["family"] = family
    text = experiment.page(run)
    assert "## By world family" in text
    hall = [c["scores"]["cells"] for c in run["cases"][:2]]
    diff = np.array([h["gp-input-noise"]["auc"] - h["gp-no-input-noise"]["auc"] for h in hall])
    mean = {m: np.mean([h[m]["auc"] for h in hall])
            for m in ("gp-input-noise", "gp-no-input-noise", "grid")}
    order = mean["gp-input-noise"] > mean["gp-no-input-noise"] > mean["grid"]
    line = next(x for x in text.splitlines() if x.startswith("| hall | 2 | cells |"))
    cells = [c.strip() for c in line.split("|")[1:-1]]
    assert cells[3] == f"{(diff > 0).sum()}/2"
    assert cells[4] == f"{diff.min():+.4f}"
    assert cells[7].split(" / ")[0] == ("yes" if order else "no")


def test_a_variants_run_with_the_gp_with_input_noise_alone_makes_a_page():
    """A variant's or seed's run (every_method false) has no GP without input noise and
    no grid: its page has no family section, and the rest is made without them."""
    run = _run(("gp-input-noise",))
    for case in run["cases"][:3]:
        case["family"] = "hall"
    text = experiment.page(run)
    assert "## By world family" not in text
    assert "## Protocol `union`" in text


def test_world_families():
    assert [experiment.world_family(w) for w in
            ("default", "office", "grown-3", "hall-4", "clutter-0", "offices-12")] == [
        "hand-drawn", "hand-drawn", "grown", "hall", "clutter", "offices"]
    assert len(experiment.WORLDS) >= 20


def _steps(work: Path, log: Path) -> None:
    """A cut of the real-log pipeline: split, the perturbed bag's library step, the shared
    grid and BHM maps (all cached by their output files) and one GP (never cached)."""
    held = experiment.split(log, log.with_suffix(".yaml"), work / "split", 5)
    if experiment.library_step("perturbed_training_bag", held / "train-noisy.mcap"):
        (held / "train-noisy.mcap").write_text("bag\n")
    bag = held / "train-noisy.mcap"
    experiment.grid_map([bag], held / "train.yaml", work / "grid", None)
    experiment.grid_map([bag], held / "train.yaml", work / "bhm", None, "bhm")
    experiment.gp_map([bag], held / "train.yaml", "on", work / "gp")


def test_a_rerun_over_a_cached_work_folder_lists_every_command(tmp_path, monkeypatch):
    made: list[list[str]] = []

    def fake_gpocc(cmd: list[str]) -> str:
        """Writes the one file of each command the experiment checks for, as gpocc would."""
        made.append(cmd)
        out = Path(cmd[cmd.index("--out") + 1])
        out.mkdir(parents=True, exist_ok=True)
        (out / {"split": "heldout.csv", "grid": "probability.tif",
                "bhm": "probability.tif"}.get(cmd[0], "made")).write_text("x\n")
        return ""

    monkeypatch.setattr(experiment, "run_gpocc", fake_gpocc)
    monkeypatch.setattr(experiment, "COMMANDS", [])
    log = experiment.ROOT / "data" / "sample" / "intel_sample.mcap"
    _steps(tmp_path, log)
    first = list(experiment.COMMANDS)
    assert [c["reused"] for c in first] == [False] * len(first)
    assert len(made) == 5  # split, grid, bhm, train, map (the bag is a library step)

    monkeypatch.setattr(experiment, "COMMANDS", [])
    made.clear()
    _steps(tmp_path, log)
    second = list(experiment.COMMANDS)
    # The re-run made only the GP's two commands, and lists every step all the same.
    assert [m[0] for m in made] == ["train", "map"]
    assert [c["command"] for c in second] == [c["command"] for c in first]
    reused = [c["command"].split()[:2] for c in second if c["reused"]]
    assert reused == [["gpocc", "split"], ["#", "library:"], ["gpocc", "grid"],
                      ["gpocc", "bhm"]]

    run = _run(("grid", "gp-no-input-noise", "gp-input-noise"))
    run["commands"] = second
    text = experiment.page(run)
    section = text[text.index("## Commands"):]
    assert "4 of these 6 steps were not run again" in section
    listed = section[section.index("```sh\n") + 6:section.rindex("```")].splitlines()
    assert len(listed) == len(first)
    for line, step in zip(listed, second, strict=True):
        command = step["command"].replace(str(experiment.ROOT) + "/", "")
        assert line == command + ("  # reused" if step["reused"] else "")
    assert "gpocc split data/sample/intel_sample.mcap --every 5" in section


def test_a_summary_of_plain_command_strings_still_makes_a_page():
    run = _run(("grid", "gp-input-noise"))
    assert "gpocc split data/x.mcap --every 10\n```" in experiment.page(run)
    assert "not run again" not in experiment.page(run)


def _learned(rng: np.random.Generator, g_bound: float) -> dict:
    """A model's learned record with g drawn up to ``g_bound`` (on it when drawn above)."""
    g = min(float(rng.uniform(1.0, 2.0 * g_bound)), g_bound)
    on = {"input-noise scale g": "upper"} if g == g_bound else {}
    if rng.uniform() < 0.5:
        on["label-noise variance"] = "lower"
    return {"log_marginal_likelihood": float(rng.uniform(-1500, -900)),
            "values": {"input-noise scale g": g, "label-noise variance": 0.1,
                       "classifier slope a": 1000.0},
            "on_bounds": on}


def test_the_bounds_section_counts_values_on_bounds_and_what_widening_gains():
    run = _run(("grid", "gp-no-input-noise", "gp-input-noise"))
    wide = _run(("grid", "gp-no-input-noise", "gp-input-noise"))["cases"]
    rng = np.random.default_rng(3)
    # g-max-16 changes a setting of offset-holdout: its gains are against that run, whose
    # learned values are this run's (the classifier's offset does not move them).
    base = _run(("grid", "gp-no-input-noise", "gp-input-noise"))["cases"]
    for ours, theirs, held in zip(run["cases"], wide, base, strict=True):
        ours["learned"] = held["learned"] = _learned(rng, 4.0)
        theirs["learned"] = _learned(rng, 16.0)
        for scores in (*theirs["scores"].values(), *held["scores"].values()):
            scores["gp-input-noise"] = _scores(rng)
    text = experiment.page(run, {"offset-holdout": base, "g-max-16": wide})
    assert "## Learned values on their bounds" in text
    lines = text.splitlines()

    def row(start: str, width: int = 0) -> list[str]:
        rows = ([c.strip() for c in x.split("|")[1:-1]] for x in lines if x.startswith(start))
        return next(r for r in rows if not width or len(r) == width)

    g_here = [c["learned"]["values"]["input-noise scale g"] for c in run["cases"]]
    on_here = sum("input-noise scale g" in c["learned"]["on_bounds"] for c in run["cases"])
    assert row("| input-noise scale g |") == ["input-noise scale g", "0/5", f"{on_here}/5",
                                              f"{np.median(g_here):.4g}"]
    on_there = sum("input-noise scale g" in c["learned"]["on_bounds"] for c in wide)
    g_there = [c["learned"]["values"]["input-noise scale g"] for c in wide]
    assert row("| g-max-16 | input-noise scale g |")[2:] == [
        f"{on_here}/5", f"{on_there}/5", f"{np.median(g_here):.4g}",
        f"{np.median(g_there):.4g}"]
    # The variant's rows read variant minus this run: the sign opposite to the
    # "Against other settings" table's.
    lml = np.array([b["learned"]["log_marginal_likelihood"]
                    - a["learned"]["log_marginal_likelihood"]
                    for a, b in zip(run["cases"], wide, strict=True)])
    pairs = [(a["scores"]["cells"]["gp-input-noise"], b["scores"]["cells"]["gp-input-noise"])
             for a, b in zip(base, wide, strict=True) if "cells" in a["scores"]]
    auc = np.array([b["auc"] - a["auc"] for a, b in pairs])
    brier = np.array([b["brier"] - a["brier"] for a, b in pairs])
    gains = row("| g-max-16 | ", width=11)
    assert gains[1:3] == [f"{np.median(lml):+.1f}", f"{lml.max():+.1f}"]
    assert gains[7:11] == [f"{(auc > 0).sum()}/{auc.size}", f"{auc.mean():+.4f}",
                           f"{(brier < 0).sum()}/{brier.size}", f"{brier.mean():+.4f}"]


def test_a_run_without_learned_records_has_no_bounds_section():
    run = _run(("grid", "gp-no-input-noise", "gp-input-noise"))
    assert "## Learned values on their bounds" not in experiment.page(run)


def test_free_points_by_wall_distance_against_brute_force(tmp_path):
    from gpocc.constants import NO_DATA
    from gpocc.gridspec import GridSpec
    from gpocc.io.rasters import write_geotiff

    rng = np.random.default_rng(7)
    # 7 cm cells: no distance between cell centres falls on a bucket edge.
    spec = GridSpec(0.0, 0.0, 0.07, 20, 10)
    values = rng.uniform(0, 1, (spec.height, spec.width)).astype(np.float32)
    values[0, :] = NO_DATA  # the north row has no data: p = 0.5 there
    (tmp_path / "m").mkdir()
    write_geotiff(tmp_path / "m" / "probability.tif", values, spec, nodata=NO_DATA)
    # Points at cell centres (no nearest-cell ambiguity), some off the map.
    cols, rows = rng.integers(-2, spec.width + 2, 300), rng.integers(0, spec.height, 300)
    xs, ys = spec.cell_centres_at(rows, cols)
    kinds = np.where(rng.uniform(size=300) < 0.3, "hit", "free")
    lines = ["x,y,label,kind"] + [f"{x:.6f},{y:.6f},{1 if k == 'hit' else 0},{k}"
                                  for x, y, k in zip(xs, ys, kinds, strict=True)]
    (tmp_path / "heldout.csv").write_text("\n".join(lines) + "\n")
    got = experiment.free_by_wall_distance(tmp_path / "heldout.csv", {"m": tmp_path / "m"})
    hits = [(x, y) for x, y, k in zip(xs, ys, kinds, strict=True) if k == "hit"]
    edges = experiment.WALL_DISTANCE_EDGES
    buckets: list[list[float]] = [[] for _ in edges]
    for x, y, r, c, k in zip(xs, ys, rows, cols, kinds, strict=True):
        if k != "free":
            continue
        d = min(((x - hx) ** 2 + (y - hy) ** 2) ** 0.5 for hx, hy in hits)
        b = max(i for i, e in enumerate(edges) if d >= e)
        inside = 0 <= c < spec.width and values[r, c] != NO_DATA
        buckets[b].append(float(values[r, c]) if inside else 0.5)
    for (n, mean, brier), want in zip(got["m"], buckets, strict=True):
        assert n == len(want)
        if want:
            assert mean == pytest.approx(np.mean(want)) and brier == pytest.approx(
                np.mean(np.square(want)))


def test_the_wall_distance_table_lists_each_method_per_real_log():
    run = _run(("grid", "bhm", "gp-input-noise"))
    record = {"grid": [[3, 0.25, 0.1], [0, math.nan, math.nan], [1, 0.5, 0.25],
                       [2, 0.125, 0.02], [5, 0.01, 0.0001]],
              "bhm": [[3, 0.2, 0.05], [0, math.nan, math.nan], [1, 0.1, 0.01],
                      [2, 0.1, 0.01], [5, 0.02, 0.0004]]}
    run["cases"][3]["free_by_wall_distance"] = record
    lines = experiment.page(run).splitlines()
    at = lines.index("## Free space next to walls (real logs)")
    table = lines[at:]
    assert table[4] == ("| case | method | 0-0.05 m | 0.05-0.1 m | 0.1-0.2 m | 0.2-0.3 m | "
                        ">= 0.3 m |")
    assert table[6] == "| case 3 | free points | 3 | 0 | 1 | 2 | 5 |"
    assert table[7] == ("|  | grid | 0.250 / 0.1000 |  | 0.500 / 0.2500 | 0.125 / 0.0200 | "
                        "0.010 / 0.0001 |")
    assert table[8].startswith("|  | bhm | 0.200 / 0.0500 |")
    assert not table[9].startswith("|  | gp-input-noise")  # no record for it


def test_the_cost_table_gives_time_ratios_and_evaluations_per_variant():
    run = _run(("grid", "gp-no-input-noise", "gp-input-noise"))
    other = _run(("grid", "gp-no-input-noise", "gp-input-noise"))["cases"]
    rng = np.random.default_rng(9)
    for ours, theirs in zip(run["cases"], other, strict=True):
        ours["gp_seconds"] = {"gp-input-noise": float(rng.uniform(1, 5))}
        theirs["gp_seconds"] = {"gp-input-noise": float(rng.uniform(1, 5))}
        for case in (ours, theirs):
            case["learned"] = {"evaluations": int(rng.integers(30, 50)), "on_bounds": {},
                               "values": {}, "log_marginal_likelihood": -1000.0}
    other = other[1:]  # the variant ran one case fewer
    text = experiment.page(run, {"offset-holdout": other})
    ours = {c["case"]: c for c in run["cases"]}
    ratio = np.median([c["gp_seconds"]["gp-input-noise"]
                       / ours[c["case"]]["gp_seconds"]["gp-input-noise"] for c in other])
    here = np.median([ours[c["case"]]["learned"]["evaluations"] for c in other])
    there = np.median([c["learned"]["evaluations"] for c in other])
    assert (f"| offset-holdout | this run | {ratio:.2f} | {here:g} / {there:g} |"
            in text.splitlines())


def test_the_real_log_table_lists_each_variant_on_each_log():
    run = _run(("grid", "gp-no-input-noise", "gp-input-noise"))
    other = _run(("grid", "gp-no-input-noise", "gp-input-noise"))["cases"]
    rng = np.random.default_rng(4)
    for case in other:
        case["scores"]["union"]["gp-input-noise"] = _scores(rng)
    other = [c for c in other if c["case"] != "case 4"]  # the variant lacks one log
    lines = experiment.page(run, {"clearance-0": other}).splitlines()
    real = [c for c in run["cases"] if c["kind"] == "real"]
    assert "| settings | case 3 | case 4 |" in lines

    def cell(case: dict) -> str:
        s = case["scores"]["union"]["gp-input-noise"]
        return f"{s['auc']:.4f} / {s['brier']:.4f}"

    assert f"| this run | {cell(real[0])} | {cell(real[1])} |" in lines
    variant = next(c for c in other if c["case"] == "case 3")
    assert f"| clearance-0 | {cell(variant)} |  |" in lines


def test_the_run_to_run_spread_and_the_differences_beyond_it():
    run = _run(("grid", "gp-no-input-noise", "gp-input-noise"))
    rng = np.random.default_rng(11)
    seeds = []
    for _ in range(2):
        other = _run(("grid", "gp-no-input-noise", "gp-input-noise"))["cases"]
        for case in other:
            for scores in case["scores"].values():
                scores["gp-input-noise"] = _scores(rng)
        seeds.append(other)
    variant = _run(("grid", "gp-no-input-noise", "gp-input-noise"))["cases"]
    for case in variant:
        for scores in case["scores"].values():
            scores["gp-input-noise"] = _scores(rng)
    text = experiment.page(run, {"offset-holdout": variant}, seeds)
    assert "## Run-to-run spread" in text

    def width(case: int, protocol: str, metric: str) -> float:
        values = [r[case]["scores"][protocol]["gp-input-noise"][metric]
                  for r in (run["cases"], *seeds)]
        return max(values) - min(values)

    for protocol in ("union", "cells"):
        cases = [i for i, c in enumerate(run["cases"]) if protocol in c["scores"]]
        auc = [width(i, protocol, "auc") for i in cases]
        brier = [width(i, protocol, "brier") for i in cases]
        line = next(x for x in text.splitlines() if x.startswith(f"| {protocol} | {len(cases)} |"))
        cells = [c.strip() for c in line.split("|")[1:-1]]
        assert cells[2:] == [f"{np.median(auc):.4f}", f"{max(auc):.4f}",
                             f"{np.median(brier):.4f}", f"{max(brier):.4f}"]
        line = next(x for x in text.splitlines() if x.startswith(
            f"| {protocol} | gp-input-noise vs gp-input-noise (offset-holdout) |"))
        cells = [c.strip() for c in line.split("|")[1:-1]]
        for column, metric in ((8, "auc"), (9, "brier")):
            here = there = 0
            for i in cases:
                diff = (run["cases"][i]["scores"][protocol]["gp-input-noise"][metric]
                        - variant[i]["scores"][protocol]["gp-input-noise"][metric])
                if abs(diff) > width(i, protocol, metric):
                    better_here = diff > 0 if metric == "auc" else diff < 0
                    here, there = here + better_here, there + (not better_here)
            assert cells[column] == f"{here} / {there}"
    for i, c in enumerate(run["cases"]):
        if c["kind"] == "real":
            assert (f"| {c['case']} | {width(i, 'union', 'auc'):.4f} | "
                    f"{width(i, 'union', 'brier'):.4f} |") in text


def test_without_seed_runs_the_page_has_no_spread():
    run = _run(("grid", "gp-no-input-noise", "gp-input-noise"))
    text = experiment.page(run, {"fixed-bias": run["cases"]})
    assert "Run-to-run spread" not in text and "beyond the spread" not in text


def test_make_experiment_runs_every_compared_variant_and_spread_seed():
    makefile = (experiment.ROOT / "Makefile").read_text()

    def words(name: str) -> list[str]:
        text = makefile.split(f"\n{name} ", 1)[1].split("=", 1)[1]
        lines = []
        for line in text.splitlines():
            lines.append(line.rstrip("\\"))
            if not line.endswith("\\"):
                break
        return " ".join(lines).split()

    assert set(words("EXPERIMENT_COMPARE")) <= set(experiment.VARIANTS)
    assert words("EXPERIMENT_SPREAD") == [f"seed-{k}" for k in experiment.SPREAD_SEEDS]


def test_logs_trained_as_logged_have_their_own_section_and_stay_out_of_comparisons():
    run = _run(("grid", "bhm", "gp-no-input-noise", "gp-input-noise"))
    rng = np.random.default_rng(8)
    logged = {"case": "log.gfs.log (every 10th scan held out, poses as logged)",
              "kind": "real", "as_logged": True,
              "scores": {p: {m: _scores(rng) for m in ("grid", "bhm", "gp-no-input-noise",
                                                       "gp-input-noise")}
                         for p in experiment.HELDOUT_PROTOCOLS}}
    run["cases"].append(logged)
    other = [dict(c) for c in run["cases"] if not c.get("as_logged")]
    text = experiment.page(run, {"offset-holdout": other})
    section = text.split("## Real logs as logged")[1].split("\n## ")[0]
    rows = [x for x in section.splitlines() if x.startswith("| log.gfs.log")]
    assert len(rows) == 4  # one per method, the union protocol's scores
    union = logged["scores"]["union"]
    for row in rows:
        method = row.split("|")[2].strip()
        assert f"| {union[method]['auc']:.4f} |" in row
        assert f"| {union[method]['brier']:.4f} |" in row
    # The variant did not run it: its real-log table and comparison counts leave it out.
    assert "| settings | case 3 | case 4 |" in text
    line = next(x for x in text.splitlines()
                if x.startswith("| union | gp-input-noise vs gp-input-noise (offset-holdout) |"))
    assert line.split("|")[3].strip().endswith("/5")
    # The summary counts it with the other cases.
    line = next(x for x in text.splitlines()
                if x.startswith("| union | gp-input-noise vs bhm |"))
    assert line.split("|")[3].strip().endswith("/6")


def test_a_run_without_logs_as_logged_has_no_such_section():
    assert "## Real logs as logged" not in experiment.page(
        _run(("grid", "gp-no-input-noise", "gp-input-noise")))


def test_the_real_log_table_tells_logs_as_logged_apart():
    run = _run(("grid", "gp-no-input-noise", "gp-input-noise"))
    run["cases"][4]["as_logged"] = True
    lines = experiment.page(run, {"clearance-0": run["cases"]}).splitlines()
    assert "| settings | case 3 | case 4 as logged |" in lines


def test_a_variants_run_maps_with_the_gp_with_input_noise_alone(tmp_path, monkeypatch):
    """The page reads only the GP with input noise of a variant's or seed's run: such a run
    trains and maps that GP alone (no baseline, no GP without input noise); the defaults'
    run, or --every-method, maps with every method."""
    made: list[list[str]] = []

    def fake_gpocc(cmd: list[str]) -> str:
        made.append(cmd)
        Path(cmd[cmd.index("--out") + 1]).mkdir(parents=True, exist_ok=True)
        return ""

    monkeypatch.setattr(experiment, "run_gpocc", fake_gpocc)
    monkeypatch.setattr(experiment, "COMMANDS", [])
    config = experiment.ROOT / "data" / "sample" / "sample.yaml"
    bag = experiment.ROOT / "data" / "sample" / "intel_sample.mcap"
    maps, seconds = experiment.run_methods(
        [bag], config, "fixed-bias", tmp_path / "fixed-bias", tmp_path / "shared", None,
        config, experiment.every_method("fixed-bias"))
    assert list(maps) == list(seconds) == ["gp-input-noise"]
    assert [m[0] for m in made] == ["train", "map"]
    assert made[0][made[0].index("--input-noise") + 1] == "on"
    assert not (tmp_path / "shared").exists()
    assert experiment.every_method("defaults")
    assert not experiment.every_method("seed-1")
    assert experiment.every_method("seed-1", asked=True)


def test_windowed_cases_pin_every_variants_anchors_to_the_windows_corner(tmp_path,
                                                                          monkeypatch):
    """With bounds (the simulated worlds), each variant's config pins the GPs' anchor
    lattice to the bounds' north-west corner, so variants are compared on one lattice."""
    monkeypatch.setattr(experiment, "run_gpocc",
                        lambda cmd: Path(cmd[cmd.index("--out") + 1]).mkdir(
                            parents=True, exist_ok=True) or "")
    monkeypatch.setattr(experiment, "COMMANDS", [])
    config = experiment.ROOT / "data" / "sample" / "sample.yaml"
    bag = experiment.ROOT / "data" / "sample" / "intel_sample.mcap"
    for variant in ("fixed-bias", "seed-1"):
        experiment.run_methods([bag], config, variant, tmp_path / variant, tmp_path / "s",
                               ["-0.500", "-0.500", "40.500", "25.500"], config, False)
        written = yaml.safe_load((tmp_path / variant / "config.yaml").read_text())
        assert written["map"]["anchor_origin_m"] == [-0.5, 25.5]
    experiment.run_methods([bag], config, "seed-1", tmp_path / "real", tmp_path / "s", None,
                           config, False)
    written = yaml.safe_load((tmp_path / "real" / "config.yaml").read_text())
    assert "anchor_origin_m" not in (written.get("map") or {})


@pytest.mark.parametrize("all_methods", [False, True])
def test_a_variants_real_log_step_maps_with_the_gp_with_input_noise_alone(tmp_path,
                                                                          monkeypatch,
                                                                          all_methods):
    """The real-log steps pass the choice on to every log (a log's held-out period is a
    different thing): the GP with input noise alone, or both GPs and the baselines."""
    made: list[str] = []
    config = experiment.ROOT / "data" / "sample" / "sample.yaml"

    def fake_gpocc(cmd: list[str]) -> str:
        made.append(cmd[0])
        out = Path(cmd[cmd.index("--out") + 1])
        out.mkdir(parents=True, exist_ok=True)
        if cmd[0] == "split":
            (out / "train.yaml").write_text(config.read_text())
        return ""

    monkeypatch.setattr(experiment, "run_gpocc", fake_gpocc)
    monkeypatch.setattr(experiment, "COMMANDS", [])
    monkeypatch.setattr(experiment, "octomap_row", lambda *args: False)
    monkeypatch.setattr(experiment, "evaluate",
                        lambda maps, truth, out: {"union": {m: {} for m in maps}})
    monkeypatch.setattr(experiment, "free_by_wall_distance", lambda truth, maps: {})
    monkeypatch.setattr(experiment, "learned_values", lambda model: {})
    monkeypatch.setattr(experiment, "moved_anchors",
                        lambda vdir, heldout, truth: made.append("moved anchors") or {})
    cases = experiment.run_real(tmp_path, "fixed-bias", experiment.real_logs([], True), 0,
                                as_logged=True, all_methods=all_methods)
    if all_methods:
        assert made == ["split", "grid", "bhm", "train", "map", "train", "map",
                        "moved anchors"]
        assert sorted(cases[0]["scores"]["union"]) == ["bhm", "gp-input-noise",
                                                        "gp-no-input-noise", "grid"]
    else:
        assert made == ["split", "train", "map"]
        assert list(cases[0]["scores"]["union"]) == ["gp-input-noise"]


def test_merge_adds_a_step_to_a_stored_run(tmp_path, monkeypatch):
    def fake_run_real(work, variant, logs, seed, as_logged=False, all_methods=True):
        assert not all_methods  # a variant's run
        name = "clean case" if as_logged else "real case"
        return [{"case": name, "kind": "real", "as_logged": as_logged,
                 "scores": {"union": {"gp-input-noise": _scores(np.random.default_rng(1))}}}]

    monkeypatch.setattr(experiment, "run_real", fake_run_real)
    monkeypatch.setattr(experiment, "real_logs", lambda names, quick: [])
    summary = tmp_path / "summary-fixed-bias.json"

    def main(*argv: str) -> list[str]:
        monkeypatch.setattr(experiment, "COMMANDS", [])
        monkeypatch.setattr("sys.argv", ["experiment", *argv, "--variant", "fixed-bias",
                                         "--work", str(tmp_path), "--doc", "/dev/null"])
        experiment.main()
        return [c["case"] for c in json.loads(summary.read_text())["cases"]]

    assert main("real") == ["real case"]
    assert main("clean") == ["clean case"]  # without --merge a run replaces the summary
    main("real")
    assert main("clean", "--merge") == ["real case", "clean case"]
    assert main("clean", "--merge") == ["real case", "clean case"]  # made again, not twice


@pytest.mark.parametrize("name", sorted(experiment.VARIANTS))
def test_every_variant_overrides_keys_a_config_has(tmp_path, name):
    from bench.paths import INTEL_CONFIG
    from gpocc.config import config_to_dict, load_config

    out = experiment.with_overrides(INTEL_CONFIG, experiment.VARIANTS[name],
                                    tmp_path / "config.yaml")
    loaded = config_to_dict(load_config(out))
    for key, value in experiment.VARIANTS[name].items():
        node = loaded
        for part in key.split("."):
            node = node[part]
        assert (list(node) if isinstance(node, tuple) else node) == value, key


@pytest.mark.parametrize("name", experiment.HOLDOUT_BASED)
def test_a_variant_of_offset_holdout_keeps_its_pins_and_changes_one_of_them(tmp_path, name):
    """Each ``HOLDOUT_BASED`` variant states every setting ``offset-holdout`` pins, with
    its own value where it changes one, and so differs from that run's config."""
    from bench.paths import INTEL_CONFIG
    from gpocc.config import load_config

    base, variant = experiment.VARIANTS["offset-holdout"], experiment.VARIANTS[name]
    assert set(base) <= set(variant)
    assert all(variant[k] == v for k, v in base.items() if k not in _OWN.get(name, ()))
    configs = [load_config(experiment.with_overrides(INTEL_CONFIG, o, tmp_path / f"{i}.yaml"))
               for i, o in enumerate((base, variant))]
    assert configs[0] != configs[1]


#: The settings of offset-holdout that a variant of it changes (the others add a setting).
_OWN = {"fixed-scale": ("model.training.learn_input_noise_scale",),
        "label-weights": ("samples.label_weights",),
        "thin-0.1-n256-fixed-scale": ("model.training.learn_input_noise_scale",),
        "accurate-poses": ("model.training.learn_input_noise_scale",),
        "isotropic": ("model.training.isotropic",)}


@pytest.mark.parametrize("name", sorted(set(experiment.VARIANTS) - {"defaults"}))
def test_every_variant_changes_a_setting_of_the_defaults(tmp_path, name):
    """A variant whose overrides all equal today's defaults would compare the defaults
    with themselves (as one does when a default changes to its value)."""
    from bench.paths import INTEL_CONFIG
    from gpocc.config import load_config

    def loaded(overrides: dict, file: str):
        return load_config(experiment.with_overrides(INTEL_CONFIG, overrides, tmp_path / file))

    assert loaded(experiment.VARIANTS[name], "variant.yaml") != loaded({}, "defaults.yaml")


def test_a_stored_splits_defaults_do_not_pin_the_gps_settings(tmp_path):
    """The train.yaml of a split made by an older gpocc spells out every default of that
    gpocc; the GP's config takes its mapping settings from the config the split was made
    with."""
    split = tmp_path / "train.yaml"
    split.write_text("seed: 3\nsensors: [{name: r1, scan_topic: /r1/scan}]\n"
                     "samples: {hit_gap_m: 0.25, thin_cell_m: 0.15}\n"
                     "model: {training: {classifier_offset: holdout}}\n")
    source = tmp_path / "log.yaml"
    source.write_text("sensors: [{name: r1}]\nsamples: {min_label_share: 0.1}\n")
    out = experiment.with_overrides(split, {"model.neighbours": 64}, tmp_path / "gp.yaml",
                                    source)
    assert yaml.safe_load(out.read_text()) == {
        "seed": 3, "sensors": [{"name": "r1", "scan_topic": "/r1/scan"}],
        "samples": {"min_label_share": 0.1}, "model": {"neighbours": 64}}
    plain = experiment.with_overrides(split, {}, tmp_path / "plain.yaml")
    assert yaml.safe_load(plain.read_text())["model"] == {
        "training": {"classifier_offset": "holdout"}}


def test_the_page_states_how_many_held_out_labels_the_truth_contradicts():
    run = _run(("grid", "gp-no-input-noise", "gp-input-noise"))
    rng = np.random.default_rng(3)
    for share, case in zip((0.12, 0.31, 0.2), run["cases"][:3], strict=True):
        case["contradicted"] = share
        case["scores"]["union-truth"] = {m: _scores(rng) for m in case["scores"]["union"]}
    text = experiment.page(run)
    assert "contradicts the label of 12-31% of a world's held-out points (median 20%" in text
    assert "## Protocol `union-truth`" in text
    assert "| union-truth | gp-input-noise vs gp-no-input-noise | " in text


def test_contradicted_share_counts_labels_the_truth_raster_contradicts(tmp_path):
    from gpocc.gridspec import GridSpec
    from gpocc.io.rasters import write_geotiff

    spec = GridSpec(x0=0.0, y0=0.0, resolution=1.0, width=4, height=2)
    # Row 0 is north (y in [1, 2)): occupied at x in [0, 1), unknown at [3, 4).
    truth = np.array([[1, 0, 0, 255], [0, 0, 1, 0]], dtype=np.uint8)
    write_geotiff(tmp_path / "truth.tif", truth, spec, nodata=255)
    # (x, y, stated label) -> truth: 1 agrees, 0 contradicts, 255 or outside: not counted.
    rows = [(0.5, 1.5, 1), (1.5, 1.5, 1), (2.5, 0.5, 1), (2.5, 0.5, 0), (3.5, 1.5, 1),
            (9.0, 9.0, 0), (0.5, 0.5, 0)]
    (tmp_path / "heldout.csv").write_text(
        "x,y,label\n" + "".join(f"{x},{y},{label}\n" for x, y, label in rows))
    share = experiment.contradicted_share(tmp_path / "heldout.csv", tmp_path / "truth.tif")
    # Counted by hand: 5 points on labelled cells, 2 contradicted ((1.5, 1.5) stated 1 on
    # a free cell, (2.5, 0.5) stated 0 on an occupied one).
    assert share == pytest.approx(2 / 5)


def test_anchor_placement_table_gives_each_case_and_the_differences():
    def case(name, union, cells, moved_union, moved_cells):
        page, moved = {"union": union}, {"union": moved_union}
        if cells is not None:
            page["cells"], moved["cells"] = cells, moved_cells
        return {"case": name, "scores": {},
                "moved_anchors": {"shift_m": 0.5, "page": page, "moved": moved}}

    cases = [case("w", {"auc": 0.95, "brier": 0.05}, {"auc": 0.97, "brier": 0.02},
                  {"auc": 0.94, "brier": 0.06}, {"auc": 0.965, "brier": 0.03}),
             case("log", {"auc": 0.90, "brier": 0.08}, None,
                  {"auc": 0.92, "brier": 0.07}, None),
             {"case": "variant run", "scores": {}}]
    lines = experiment.moved_anchors_table(cases)
    assert lines[2] == "| w | 0.9500 | 0.9400 | 0.0500 | 0.0600 | 0.9700 | 0.9650 |"
    assert lines[3] == "| log | 0.9000 | 0.9200 | 0.0800 | 0.0700 |  |  |"
    summary = {line.split(" | ")[0]: line for line in lines[5:]}
    # union AUC: -0.01 and +0.02: mean +0.005, mean abs 0.015, largest 0.02.
    assert summary["| union AUC"] == "| union AUC | 2 | +0.0050 | 0.0150 | 0.0200 |"
    assert summary["| cells AUC"] == "| cells AUC | 1 | -0.0050 | 0.0050 | 0.0050 |"
    assert experiment.moved_anchors_table([{"case": "x", "scores": {}}]) == []


def test_moved_whole_moves_the_lattice_half_a_spacing_on_the_same_cells():
    from gpocc.gridspec import GridSpec
    from gpocc.mapping.blocks import Anchor, AnchorLattice

    page = GridSpec.from_bounds(-13.02143854931841, -26.51194820983702, 21.378561450681588,
                                13.788051790162985, 0.1)
    moved = experiment.moved_whole(page, 5)
    # Five cells more west and north; every cell of the page's frame keeps its centre.
    assert (moved.width, moved.height) == (page.width + 5, page.height + 5)
    rows, cols = np.array([0, 17, page.height - 1]), np.array([0, 9, page.width - 1])
    np.testing.assert_allclose(np.column_stack(page.cell_centres_at(rows, cols)),
                               np.column_stack(moved.cell_centres_at(rows + 5, cols + 5)),
                               rtol=0, atol=1e-9)
    # The lattice hangs from the north-west corner: its anchors moved half a spacing.
    np.testing.assert_allclose(AnchorLattice(moved, 10).centre(Anchor(0, 0))
                               - AnchorLattice(page, 10).centre(Anchor(0, 0)),
                               [-0.5, 0.5], rtol=0, atol=1e-9)


def test_moved_map_has_the_page_maps_cells_and_moved_anchors(tmp_path):
    from typer.testing import CliRunner

    from gpocc.cli import app
    from gpocc.config import Config, ModelConfig, TrainingConfig
    from gpocc.gp.model import build_model, save_model
    from gpocc.samples.sampleset import SampleSet

    rng = np.random.default_rng(0)
    walls = np.array([(x, y) for x in np.arange(-2, 2, 0.1) for y in (-1.5, 1.5)]
                     + [(x, y) for x in (-2, 2) for y in np.arange(-1.5, 1.5, 0.1)])
    free = rng.uniform([-1.8, -1.3], [1.8, 1.3], size=(200, 2))
    means = np.vstack([walls, free])
    n = len(means)
    samples = SampleSet(means, np.einsum("n,ij->nij", rng.uniform(0.001, 0.003, n), np.eye(2)),
                        np.r_[np.ones(len(walls)), -np.ones(len(free))],
                        rng.integers(0, 20, n), rng.normal(0, 0.01, (n, 2, 3)),
                        np.zeros(n, dtype=np.int16))
    config = Config(model=ModelConfig(neighbours=60, training=TrainingConfig(
        patches=2, patch_size=60, anneal_maxfun=5, lbfgs_maxiter=5)))
    model_path = tmp_path / "gp-input-noise.npz"
    save_model(build_model(samples, config), model_path)
    page = tmp_path / "gp-input-noise"
    # The page's map is a window (as the simulated worlds' are): not the model's whole map.
    result = CliRunner().invoke(app, ["map", str(model_path), "--resolution", "0.1", "--out",
                                      str(page), "--bounds", "-2.23", "-1.71", "2.41", "1.87"])
    assert result.exit_code == 0, result.output
    experiment.moved_map(model_path, page, tmp_path / "moved", 0.5)
    page_meta = json.loads((page / "metadata.json").read_text())
    moved_meta = json.loads((tmp_path / "moved" / "metadata.json").read_text())
    assert moved_meta["bounds_m"] == page_meta["bounds_m"]
    np.testing.assert_allclose(np.subtract(moved_meta["anchor_origin_m"],
                                           page_meta["anchor_origin_m"]), [-0.5, 0.5],
                               rtol=0, atol=1e-9)


def test_moved_anchors_scores_both_maps_on_the_points_inside_the_page_map(tmp_path,
                                                                          monkeypatch):
    vdir = tmp_path / "v"
    main = vdir / "gp-input-noise"
    main.mkdir(parents=True)
    bounds = [-13.02143854931841, -26.51194820983702, 21.378561450681588, 13.788051790162985]
    (main / "metadata.json").write_text(json.dumps(
        {"anchor_spacing_m": 1.0, "resolution_m": 0.1, "bounds_m": bounds}))
    heldout = tmp_path / "heldout.csv"
    heldout.write_text("x,y,label,kind\n0.5,0.5,1,hit\n1.0,0.5,0,free\n"
                       "21.5,0.5,1,hit\n0.5,-26.6,0,near-wall\n")
    moved, evaluated = [], []

    def fake_moved_map(model_path, like, folder, shift_m):
        moved.append((model_path, like, folder, shift_m))
        folder.mkdir()

    def fake_evaluate(maps, truth, out):
        evaluated.append((dict(maps), Path(truth).read_text() if truth.suffix == ".csv"
                          else truth))
        return {"union": {m: {"auc": 0.9} for m in maps},
                "all": {m: {"auc": 0.8} for m in maps}}

    monkeypatch.setattr(experiment, "moved_map", fake_moved_map)
    monkeypatch.setattr(experiment, "COMMANDS", [])
    monkeypatch.setattr(experiment, "evaluate", fake_evaluate)
    (vdir / "gp-input-noise-anchors-moved").mkdir()  # from an earlier run: made again
    result = experiment.moved_anchors(vdir, heldout, tmp_path / "truth.tif")
    assert result == {"shift_m": 0.5, "page": {"union": {"auc": 0.9}, "cells": {"auc": 0.8}},
                      "moved": {"union": {"auc": 0.9}, "cells": {"auc": 0.8}}}
    folder = vdir / "gp-input-noise-anchors-moved"
    assert moved == [(main.with_suffix(".npz"), main, folder, 0.5)]
    assert [c["reused"] for c in experiment.COMMANDS] == [False]
    # Both maps are scored on the same points: those inside the page's map.
    (maps, text), (_, truth) = evaluated
    assert maps == {"page": main, "moved": folder}
    assert text.splitlines() == ["x,y,label,kind", "0.5000,0.5000,1,hit",
                                 "1.0000,0.5000,0,free"]
    assert truth == tmp_path / "truth.tif"
