"""``gpocc split``: hold out every K-th scan as labelled truth, keep the rest as a bag."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer
import yaml

from gpocc.commands.options import ConfigFile, Force, check_at_least
from gpocc.config import changed_settings, load_config
from gpocc.errors import GpoccError
from gpocc.evaluation.split import (
    merge_by_sensor,
    split_batch,
    topic_prefix,
    train_config,
)
from gpocc.evaluation.truth import write_points
from gpocc.io.atomic import atomic_directory, prepare_output
from gpocc.io.bags import write_bag
from gpocc.io.inputs import read_inputs
from gpocc.limits import MAX_HELDOUT_POINTS, check_seed
from gpocc.progress import log
from gpocc.samples import beam_rules
from gpocc.samples.heldout import NEAR_WALL


def split(
    input_path: Path = typer.Argument(
        ..., metavar="INPUT", help="Log to split: a bag, bag folder, .mcap or CARMEN log."
    ),
    every: int = typer.Option(..., "--every", help="Hold out scans with index % K == K - 1."),
    out: Path = typer.Option(..., "--out", help="Folder for train.mcap, train.yaml, heldout.csv."),
    config_path: ConfigFile = None,
    keep_every: int = typer.Option(1, "--keep-every", help="Keep every S-th training scan."),
    beam_every: int = typer.Option(1, "--beam-every", help="Keep every B-th training beam."),
    seed: int | None = typer.Option(
        None, "--seed", help="Seed for the free points (default: the config's seed)."),
    free_per_beam: int = typer.Option(3, "--free-per-beam", help="Free points per held-out beam."),
    near_wall_per_beam: int = typer.Option(
        1, "--near-wall-per-beam",
        help="Free points per held-out hit in the band 0.05-0.3 m in front of it."),
    force: Force = False,
) -> None:
    """Split a log into a training bag and held-out labelled points.

    Scans with index % K == K - 1 (per sensor, 0-based) are held out; their hits become
    occupied points (label 1, kind hit), each beam gives F free points (label 0, kind
    free) at random distances short of the hit, and each hit W free points uniform
    0.05-0.3 m in front of it (kind near-wall). The other scans (thinned by --keep-every /
    --beam-every) go to DIR/train.mcap with a config DIR/train.yaml that reads it; the
    labelled points go to DIR/heldout.csv (x,y,label,kind), usable as `gpocc evaluate
    --ground-truth`, which scores each kind of free point with the hits and all together.
    """
    prepare_output(out, force, inputs=[input_path, config_path])
    config = load_config(config_path)
    check_at_least("--every", every, 2, " (every scan would be held out)")
    check_at_least("--keep-every", keep_every, 1)
    check_at_least("--beam-every", beam_every, 1)
    check_at_least("--free-per-beam", free_per_beam, 0)
    check_at_least("--near-wall-per-beam", near_wall_per_beam, 0)
    check_seed(seed)
    rng = np.random.default_rng(config.seed if seed is None else seed)

    batches = merge_by_sensor(read_inputs([input_path], config))
    held_beams = sum((b.n_scans // every) * b.n_beams for b in batches)
    if held_beams * (1 + free_per_beam + near_wall_per_beam) > MAX_HELDOUT_POINTS:
        raise GpoccError(
            f"{input_path}: {held_beams} held-out beams x (1 + --free-per-beam "
            f"{free_per_beam} + --near-wall-per-beam {near_wall_per_beam}) points is more "
            f"than {MAX_HELDOUT_POINTS:.0e}; lower them or raise --every"
        )
    trains, topics, sensors, points, labels, kinds = [], [], [], [], [], []
    n_heldout = 0
    used_prefixes: set[str] = set()
    for batch in batches:
        sensor = beam_rules.sensor_config(batch, config)
        result = split_batch(
            batch,
            sensor,
            every=every,
            keep_every=keep_every,
            beam_every=beam_every,
            free_per_beam=free_per_beam,
            near_wall_per_beam=near_wall_per_beam,
            rng=rng,
        )
        if result.train.n_scans == 0:
            raise GpoccError(
                f"{batch.source}: sensor '{batch.sensor}' keeps no training scans "
                f"({batch.n_scans} scans); lower --every or --keep-every"
            )
        prefix = topic_prefix(batch.sensor)
        while prefix in used_prefixes:
            prefix += "_"
        used_prefixes.add(prefix)
        scan_topic, pose_topic = f"/{prefix}/scan", f"/{prefix}/pose"
        trains.append(result.train)
        topics.append((scan_topic, pose_topic))
        sensors.append((sensor, scan_topic, pose_topic))
        points.append(result.points)
        labels.append(result.labels)
        kinds.append(result.kinds)
        n_heldout += result.n_heldout
        log(
            f"{batch.sensor}: {batch.n_scans} scans -> {result.train.n_scans} training "
            f"({result.train.n_beams} beams), {result.n_heldout} held out"
        )

    if n_heldout == 0:
        counts = ", ".join(f"'{b.sensor}' {b.n_scans}" for b in batches)
        raise GpoccError(
            f"{input_path}: --every {every} holds out no scan (scans per sensor: {counts}); "
            "choose an --every no larger than a sensor's scan count"
        )
    all_points = np.concatenate(points)
    if len(all_points) == 0:
        raise GpoccError(
            f"{input_path}: the {n_heldout} held-out scans have no valid beam, so no labelled "
            "point; choose another --every"
        )
    all_labels = np.concatenate(labels)
    all_kinds = np.concatenate(kinds)
    new_config = train_config(config, sensors)
    with atomic_directory(out, force=force) as tmp:
        write_bag(tmp / "train.mcap", trains, topics, "mcap")
        (tmp / "train.yaml").write_text(
            "# Written by gpocc split: reads train.mcap beside it. Settings not given here\n"
            "# take gpocc's defaults.\n"
            + yaml.safe_dump(changed_settings(new_config), sort_keys=False,
                             default_flow_style=None)
        )
        write_points(tmp / "heldout.csv", all_points, all_labels, all_kinds)

    n_occupied = int(np.count_nonzero(all_labels == 1))
    typer.echo(f"sensors:          {len(batches)}")
    typer.echo(f"scans kept:       {sum(t.n_scans for t in trains)}")
    typer.echo(f"scans held out:   {n_heldout}")
    n_near = int(np.count_nonzero(all_kinds == NEAR_WALL))
    typer.echo(
        f"held-out points:  {all_labels.size} ({n_occupied} occupied, "
        f"{all_labels.size - n_occupied - n_near} free along beams, {n_near} near-wall free)"
    )
    typer.echo(f"wrote {out / 'train.mcap'}, {out / 'train.yaml'}, {out / 'heldout.csv'}")
