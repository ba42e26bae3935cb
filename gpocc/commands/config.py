"""``gpocc config``: print the effective config, with defaults and comments."""

from __future__ import annotations

import dataclasses
import inspect
import typing
from pathlib import Path
from typing import Annotated, Any

import typer
import yaml

from gpocc.config import Config, InputConfig, SensorConfig, config_to_dict, load_config


def _comment(cls: type, indent: str) -> list[str]:
    doc = inspect.cleandoc(cls.__doc__ or "")
    return [f"{indent}# {line}".rstrip() for line in doc.splitlines()]


def _scalar(value: Any) -> str:
    text = yaml.safe_dump(value, default_flow_style=True, width=10_000).strip()
    return text.removesuffix("\n...").removesuffix("...").strip()


def _section(cls: type, data: dict[str, Any], indent: str) -> list[str]:
    hints = typing.get_type_hints(cls)
    lines: list[str] = []
    for f in dataclasses.fields(cls):
        value = data[f.name]
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            lines += ["", *_comment(tp, indent), f"{indent}{f.name}:"]
            lines += _section(tp, value, indent + "  ")
        elif f.name == "sensors":
            lines += ["", *_comment(SensorConfig, indent)]
            if not value:
                example = config_to_dict(Config(sensors=(SensorConfig(),)))["sensors"]
                lines.append(f"{indent}# No entries: each input's one LaserScan and pose topic "
                             "(a CARMEN log: its FLASER lines) with these defaults:")
                lines += [f"{indent}# {line}" for line in
                          _entries(example, "").splitlines()]
                lines.append(f"{indent}sensors: []")
            else:
                lines.append(f"{indent}sensors:")
                lines += [f"{indent}{line}" for line in _entries(value, "").splitlines()]
        elif f.name == "inputs" and cls is Config:
            lines += ["", *_comment(InputConfig, indent),
                      f"{indent}# e.g. inputs: [{{path: day2.mcap, transform: {{x_m: 12.0, "
                      "y_m: -3.5, yaw_deg: 90.0}}]",
                      f"{indent}{f.name}: {_scalar(value)}"]
        else:
            lines.append(f"{indent}{f.name}: {_scalar(value)}")
    return lines


def _entries(entries: list[dict[str, Any]], indent: str) -> str:
    out = []
    for entry in entries:
        body = _section(SensorConfig, entry, indent + "  ")
        body = [line for line in body if line.strip()]
        first = body[0].lstrip()
        out.append(f"{indent}- {first}")
        out += body[1:]
    return "\n".join(out)


def annotated_yaml(config: Config) -> str:
    """The config as YAML with every key (defaults included) and each section's
    documentation as comments; ``load_config`` reads it back to the same config."""
    lines = ["# gpocc job config (printed by `gpocc config`): every key with its value.",
             *_comment(Config, "")]
    lines += _section(Config, config_to_dict(config), "")
    return "\n".join(lines) + "\n"


def config_command(
    path: Annotated[Path | None, typer.Argument(
        metavar="[FILE]", help="A YAML config to validate; default: the built-in defaults.")
    ] = None,
) -> None:
    """Print the effective config (defaults and comments), or validate FILE and print its
    effective form."""
    typer.echo(annotated_yaml(load_config(path)), nl=False)
