"""``gpocc info``: what the inputs hold and what training samples they would give."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from gpocc.commands.options import ConfigFile
from gpocc.config import Config, load_config
from gpocc.errors import GpoccError
from gpocc.gp.bounds import GUIDE_SECTION, values_on_bounds
from gpocc.gp.growth import input_listing
from gpocc.gp.model import GPModel, kernel_parameters, load_model, patch_summary
from gpocc.io.inputs import (
    InputSummary,
    check_distinct,
    describe_input,
    read_input,
    sensors_for_input,
)
from gpocc.io.records import content_hash, warn_repeated_content
from gpocc.io.scans import ScanBatch
from gpocc.samples.sampleset import SampleSet


def _span(summary: InputSummary) -> str:
    if summary.start_s is None or summary.end_s is None:
        return "time span: (no messages)"
    length = summary.end_s - summary.start_s
    # A CARMEN log's scans may be stamped by line order instead (see gpocc.io.carmen).
    which = " (logger stamps)" if summary.format == "carmen" else ""
    return (f"time span{which}: {summary.start_s:.3f} .. {summary.end_s:.3f} s "
            f"({length:.1f} s)" + (f"; {summary.clock_note}" if summary.clock_note else ""))


def format_input(summary: InputSummary) -> list[str]:
    """Lines describing one input: format, time span and topics (CARMEN: message counts)."""
    lines = [f"input {summary.path}", f"  format: {summary.format_name}", f"  {_span(summary)}"]
    if summary.format != "carmen":
        width = max((len(t.name) for t in summary.topics), default=0)
        lines.append("  topics:")
        lines += [f"    {t.name:<{width}}  {t.msgtype}  {t.count}" for t in summary.topics]
    else:
        counts = ", ".join(f"{t.name} {t.count}" for t in summary.topics)
        lines.append(f"  messages: {counts}")
    return lines


def format_input_sensors(summary: InputSummary, config: Config) -> list[str]:
    """Lines naming the sensors (and their topics) that would be read from one input."""
    sensors = sensors_for_input(summary, config)
    if summary.format == "carmen":
        return [f"  sensor: {s.name} (FLASER scans and poses)" for s in sensors]
    return [f"  sensor: {s.name} (scans {s.scan_topic}, poses {s.pose_topic})" for s in sensors]


def format_sensors(batches: Sequence[ScanBatch]) -> list[str]:
    """Per sensor: scans used and skipped, beams per scan, range limits, pose covariance."""
    lines = ["sensors"]
    for name in dict.fromkeys(b.sensor for b in batches):
        own = [b for b in batches if b.sensor == name]
        used = sum(b.n_scans for b in own)
        skipped = sum(b.skipped_scans for b in own)
        beams = "/".join(str(n) for n in sorted({b.n_beams for b in own}))
        # A TF batch always carries per-scan covariances (the config's, carried to the
        # laser, when the bag has none): its provenance says where they came from.
        from_input = [b.has_pose_covariance if b.provenance is None
                      else not b.provenance.covariance_source.startswith("config") for b in own]
        covariance = "input" if all(from_input) else (
            "config" if not any(from_input) else "input and config")
        limits = "/".join(sorted({f"{b.range_min:g}..{b.range_max:g}" for b in own}))
        lines.append(
            f"  {name}: {used} scans used, {skipped} skipped, {beams} beams per scan, "
            f"range {limits} m, pose covariance from {covariance}"
        )
        lines += provenance_lines(own)
    return lines


def provenance_lines(batches: Sequence[ScanBatch]) -> list[str]:
    """Per input of one sensor: pose source, TF chain, covariance source, skips, repairs."""
    lines = []
    for b in batches:
        p = b.provenance
        if p is None:
            continue
        lines.append(f"    {Path(b.source).name}: pose from {p.pose_source}")
        if p.frame_chain:
            lines.append(f"      frame chain: {p.frame_chain}")
        lines.append(f"      covariance: {p.covariance_source}")
        if p.stamps:
            lines.append(f"      stamps: {p.stamps}")
        lines += [f"      skipped {n}: {why} (config key {key})" for why, key, n in p.skipped]
        lines += [f"      note: {note}" for note in p.notes]
        lines += [f"      {line}" for line in p.sensor_lines]
    return lines


def format_samples(batches: list[ScanBatch], config: Config) -> list[str]:
    """Counts of occupied and free training samples and their mean position spread."""
    from gpocc.samples.beams import build_samples

    samples = build_samples(batches, config)
    occupied = int(np.count_nonzero(samples.labels > 0))
    free = len(samples) - occupied
    trace = np.trace(samples.covariances, axis1=1, axis2=2)
    spread = float(np.mean(np.sqrt(np.maximum(trace, 0.0)))) if len(samples) else float("nan")
    thin = config.samples.thin_cell_m
    return [
        "training samples" + (f" (thinned to one per {thin:g} m cell and label)" if thin else ""),
        f"  occupied: {occupied}",
        f"  free: {free}",
        f"  mean sqrt(trace(covariance)): {spread:.4f} m",
    ]


def _weights_note(samples: SampleSet) -> str:
    """How many samples carry a label-noise factor other than 1 (``samples.label_weights``)."""
    factors = samples.noise_factors
    if factors is None:
        return ""
    return (f"; label weights: {int(np.count_nonzero(factors > 1.0))} with more label "
            f"noise, {int(np.count_nonzero(factors < 1.0))} with less (factors "
            f"{float(factors.min()):.3g} to {float(factors.max()):.3g})")


def format_model(path: Path, model: GPModel) -> list[str]:
    """Lines describing a model file: versions, hyperparameters, samples, sensors, training."""
    samples = model.samples
    occupied = int(np.count_nonzero(samples.labels > 0))
    names = samples.sensor_names or tuple(f"sensor {i}" for i in np.unique(samples.sensor_ids))
    per_sensor = np.bincount(samples.sensor_ids.astype(np.int64), minlength=len(names))
    training = model.training
    timings = training.get("timings_s", {})
    params = ", ".join(f"{k}={v}" for k, v in kernel_parameters(model.kernel).items())
    lines = [
        f"model {path}",
        "  versions: " + (", ".join(f"{k} {v}" for k, v in model.versions.items())
                          or "(not recorded)"),
        f"  kernel: {params}",
        f"  noise_variance: {model.noise_variance:.6g}",
        f"  input noise: {'on' if model.input_noise else 'off'}"
        + (f", input covariances{_scaled_part(model)} scaled by "
           f"{model.input_noise_scale:.4g}"
           if model.input_noise and model.input_noise_scale != 1.0 else ""),
        f"  classifier: {model.classifier.summary()}), thresholds "
        f"occupied {model.config.classify.occupied:g}, free {model.config.classify.free:g}",
        f"  samples: {len(samples)} ({occupied} occupied, {len(samples) - occupied} free) "
        f"from {len(np.unique(samples.scan_ids))} scans" + _weights_note(samples),
        "  sensors: " + ", ".join(f"{n} ({c} samples)" for n, c in
                                  zip(names, per_sensor, strict=False)),
        *_input_lines(model),
    ]
    on_bounds = values_on_bounds(model)
    lines.append("  learned values on a bound: " + ("none" if not on_bounds
                                                      else f"{len(on_bounds)} ({GUIDE_SECTION})"))
    lines += [f"    {b.message()}" for b in on_bounds]
    if "log_marginal_likelihood" in training:
        kept = training.get("hyperparameters") == "kept"  # gpocc update --keep
        lines.append(f"  log marginal likelihood: {training['log_marginal_likelihood']:.3f} "
                     + ("(kept by the last update with the hyperparameters, from training on "
                        "the earlier logs' patches)" if kept else
                        f"({training.get('evaluations', '?')} evaluations"
                        + patch_summary(training) + ")"))
    updates = training.get("updates") or []
    if updates:
        lines.append(f"  updates: {len(updates)} (" + "; ".join(
            f"{len(u.get('inputs', []))} input(s), hyperparameters {u.get('hyperparameters')}"
            for u in updates) + ")")
    lines.append("  training time: " + (
        ", ".join(f"{k} {v:.1f} s" for k, v in timings.items())
        + f" (total {sum(timings.values()):.1f} s)" if timings else "(not recorded)"))
    return lines


def _scaled_part(model: GPModel) -> str:
    """`` (pose part)`` when the learned scale multiplies the pose part alone."""
    return (" (pose part)" if model.config.model.training.input_noise_scale_part == "pose"
            else "")


def _input_lines(model: GPModel) -> list[str]:
    """The model's inputs, one line each: scans, time span, transform, sensors."""
    listing = input_listing(model.growth, model.inputs)
    if model.growth is None or not listing:  # no records: the paths alone
        return ["  inputs: " + (", ".join(model.inputs) or "(not recorded)")]
    lines = ["  inputs:"]
    for entry in listing:
        if "scans" not in entry:
            lines.append(f"    {entry['path']} (not recorded: added by an older gpocc)")
            continue
        span = ("no scans" if entry["start_s"] is None else
                f"{entry['start_s']:.3f} .. {entry['end_s']:.3f} s")
        t = entry["transform"]
        lines.append(f"    {entry['path']}: {entry['scans']} scans, time span {span}, "
                     f"transform x {t['x_m']:g} m, y {t['y_m']:g} m, yaw {t['yaw_deg']:g} "
                     f"deg, sensors {', '.join(entry['sensors']) or '(none)'}")
    return lines


def _is_model_file(path: Path) -> bool:
    return path.suffix.lower() == ".npz"


def info(
    inputs: Annotated[list[Path], typer.Argument(
        metavar="INPUT...", help="Bags, bag folders, .mcap files, CARMEN logs, or model "
        "files (.npz from `gpocc train`).")],
    config: ConfigFile = None,
) -> None:
    """Show what the inputs hold: topics, time span, scans per sensor, training samples;
    for a model file: hyperparameters, samples, sensors, versions and training time."""
    models = [p for p in inputs if _is_model_file(p)]
    if models:
        if len(models) != len(inputs):
            raise GpoccError("pass either model files (.npz) or logs, not both")
        typer.echo("\n".join(line for p in models for line in format_model(p, load_model(p))))
        return
    cfg = load_config(config)
    # As training would: a path given twice is refused, a log under two names warned of.
    check_distinct(inputs)
    if len(inputs) > 1:  # hashing reads each input whole: only where two may be one log
        warn_repeated_content(inputs, [content_hash(p) for p in inputs], cfg)
    batches: list[ScanBatch] = []
    for path in inputs:
        summary = describe_input(path)
        # Printed before choosing sensors, so a topic problem still shows what the input holds.
        typer.echo("\n".join(format_input(summary)))
        typer.echo("\n".join(format_input_sensors(summary, cfg)))
        batches.extend(read_input(path, cfg, summary))
    typer.echo("\n".join(format_sensors(batches)))
    typer.echo("\n".join(format_samples(batches, cfg)))
