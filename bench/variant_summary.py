"""Summary lines of finished ``bench/experiment.py sim real`` runs, one block per variant.

    .venv/bin/python bench/variant_summary.py VARIANT... [--work out/experiment]

Per region: AUC wins of the GP with input noise over the GP without, mean and worst
difference, cases where it has the lowest FPR@TPR0.97 of the three methods, its mean
AUC and Brier; per real log its AUC and Brier. Reads ``summary-<variant>-sim-real.json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from experiment import region_comparison


def summary(cases: list[dict]) -> list[str]:
    lines = []
    for region in ("all", "noisy-only"):
        compared = region_comparison(cases, region)
        if compared is None:
            continue
        chosen, on, _, diff = compared
        lowest = sum(c["methods"]["gp-input-noise"]["fpr_at_tpr97"]
                     <= min(m["fpr_at_tpr97"] for m in c["methods"].values()) for c in chosen)
        lines.append(
            f"- region {region}: AUC wins {int((diff > 0).sum())}/{diff.size}, mean "
            f"{diff.mean():+.4f}, worst {diff.min():+.4f}; lowest FPR@TPR0.97 in "
            f"{lowest}/{diff.size}; input noise mean AUC {np.mean([a['auc'] for a in on]):.4f}, "
            f"Brier {np.mean([a['brier'] for a in on]):.4f}, log-loss "
            f"{np.mean([a['log_loss'] for a in on]):.3f}, "
            f"ECE {np.mean([a['ece'] for a in on]):.3f}")
    for c in cases:
        if c["kind"] == "real":
            s, o = c["methods"]["gp-input-noise"], c["methods"]["gp-no-input-noise"]
            lines.append(f"- {c['case'].split(' ')[0]}: input noise AUC {s['auc']:.4f}, Brier "
                         f"{s['brier']:.4f} (without: {o['auc']:.4f}, {o['brier']:.4f})")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("variants", nargs="+")
    parser.add_argument("--work", type=Path, default=Path("out/experiment"))
    args = parser.parse_args()
    for variant in args.variants:
        cases = json.loads((args.work / f"summary-{variant}-sim-real.json").read_text())
        print(f"**{variant}**")
        print("\n".join(summary(cases)))


if __name__ == "__main__":
    main()
