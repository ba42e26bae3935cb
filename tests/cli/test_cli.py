"""CLI conventions: --version, -h, completion, --quiet/--verbose, `gpocc config`,
`gpocc info MODEL.npz`, one --bounds wording, map metadata, and no import cycle."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

import gpocc
from gpocc.cli import COMMANDS, app
from gpocc.config import Config, ModelConfig, TrainingConfig, config_from_dict, load_config
from gpocc.gp.model import build_model, load_model, save_model
from gpocc.samples.sampleset import SampleSet

REPO = Path(__file__).resolve().parents[2]
runner = CliRunner()


def _samples() -> SampleSet:
    """A 4 x 3 m room from two sensors: walls occupied (sensor 0), inside free (sensor 1)."""
    rng = np.random.default_rng(1)
    t = np.linspace(0, 1, 50, endpoint=False)
    walls = np.vstack([np.column_stack((-2 + 4 * t, np.full_like(t, y))) for y in (-1.5, 1.5)]
                      + [np.column_stack((np.full_like(t, x), -1.5 + 3 * t)) for x in (-2, 2)])
    free = rng.uniform([-1.8, -1.3], [1.8, 1.3], size=(200, 2))
    means = np.vstack([walls, free])
    n = len(means)
    labels = np.concatenate([np.ones(len(walls)), -np.ones(len(free))])
    sensor_ids = np.concatenate([np.zeros(len(walls)), np.ones(len(free))]).astype(np.int16)
    return SampleSet(means, np.einsum("n,ij->nij", rng.uniform(1e-4, 1e-3, n), np.eye(2)),
                     labels, np.arange(n, dtype=np.int64) // 10, np.zeros((n, 2, 3)), sensor_ids,
                     sensor_names=("left", "right"))


@pytest.fixture(scope="module")
def model_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    config = Config(model=ModelConfig(neighbours=80, block_size_m=1.0, training=TrainingConfig(
        patches=2, patch_size=60, anneal_maxfun=5, lbfgs_maxiter=5)))
    model = build_model(_samples(), config, inputs=("a.mcap", "b.mcap"))
    model = type(model)(**{**model.__dict__,
                           "training": {**model.training, "timings_s": {"learn": 1.25}}})
    path = tmp_path_factory.mktemp("model") / "model.npz"
    save_model(model, path)
    return path


def test_version_and_short_help() -> None:
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0 and result.output.strip() == f"gpocc {gpocc.__version__}"
    short, long = runner.invoke(app, ["-h"]), runner.invoke(app, ["--help"])
    assert short.exit_code == 0 and short.output == long.output
    for name, _ in COMMANDS:
        assert name in short.output
        sub = runner.invoke(app, [name, "-h"])
        assert sub.exit_code == 0 and "--quiet" in sub.output and "--verbose" in sub.output


def test_shell_completion_is_offered() -> None:
    out = runner.invoke(app, ["--help"]).output
    assert "--install-completion" in out and "--show-completion" in out


def test_one_bounds_wording_for_map_and_grid() -> None:
    def bounds_help(command: str) -> str:
        # The option's help text, from click's own description of the command.
        click_cmd = __import__("typer").main.get_command(app).commands[command]
        [opt] = [p for p in click_cmd.params if "--bounds" in getattr(p, "opts", [])]
        return f"{opt.metavar} {opt.help}"

    assert bounds_help("map") == bounds_help("grid")


def test_quiet_silences_stderr_and_verbose_adds_lines(model_path: Path, tmp_path: Path) -> None:
    args = ["map", str(model_path), "--resolution", "0.5", "--workers", "1"]
    noisy = subprocess.run([sys.executable, "-m", "gpocc", *args, "--out", str(tmp_path / "a")],
                           capture_output=True, text=True, cwd=REPO)
    quiet = subprocess.run([sys.executable, "-m", "gpocc", *args, "--out", str(tmp_path / "b"),
                            "--quiet"], capture_output=True, text=True, cwd=REPO)
    assert noisy.returncode == 0 and quiet.returncode == 0
    assert "mapping" in noisy.stderr and quiet.stderr == ""
    assert quiet.stdout.replace(str(tmp_path / "b"), "X").splitlines()[:3] == \
        noisy.stdout.replace(str(tmp_path / "a"), "X").splitlines()[:3]
    verbose = subprocess.run([sys.executable, "-m", "gpocc", *args, "--out",
                              str(tmp_path / "v"), "--verbose"], capture_output=True, text=True,
                             cwd=REPO)
    assert verbose.returncode == 0
    # The model's details are a verbose-only line (rich may wrap it: compare words).
    assert "from sensors left, right;" in " ".join(verbose.stderr.split())
    assert "from sensors" not in noisy.stderr
    both = subprocess.run([sys.executable, "-m", "gpocc", *args, "--out", str(tmp_path / "c"),
                           "-q", "-v"], capture_output=True, text=True, cwd=REPO)
    assert both.returncode == 2 and "exclude each other" in both.stderr
    assert not (tmp_path / "c").exists()


def test_config_prints_every_default_with_comments() -> None:
    result = runner.invoke(app, ["config"])
    assert result.exit_code == 0
    # What it prints is a config that loads back to the defaults ...
    assert config_from_dict(yaml.safe_load(result.output)) == Config()
    # ... and every section is documented.
    for section in ("samples", "model", "classify", "map", "grid"):
        i = result.output.splitlines().index(f"{section}:")
        assert result.output.splitlines()[i - 1].startswith("#")


@pytest.mark.parametrize("name", ["carmen_intel.yaml", "carmen_freiburg.yaml"])
def test_config_file_prints_its_effective_form(name: str, tmp_path: Path) -> None:
    result = runner.invoke(app, ["config", str(REPO / "configs" / name)])
    assert result.exit_code == 0
    (tmp_path / "effective.yaml").write_text(result.output)
    assert load_config(tmp_path / "effective.yaml") == load_config(REPO / "configs" / name)


def test_config_file_that_is_invalid_is_one_error_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("samples:\n  free_spacing: 0.4\n")
    result = runner.invoke(app, ["config", str(bad)])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and str(bad) in lines[0] and "free_spacing" in lines[0]


def test_info_describes_a_model_file(model_path: Path) -> None:
    model = load_model(model_path)
    result = runner.invoke(app, ["info", str(model_path)])
    assert result.exit_code == 0, result.output
    out = result.output
    n_occ = int((model.samples.labels > 0).sum())
    assert f"samples: {len(model.samples)} ({n_occ} occupied" in out
    assert f"left ({n_occ} samples), right ({len(model.samples) - n_occ} samples)" in out
    assert f"gpocc {gpocc.__version__}" in out and f"numpy {np.__version__}" in out
    assert f"noise_variance: {model.noise_variance:.6g}" in out
    assert "training time: learn 1.2 s" in out or "training time: learn 1.3 s" in out
    assert "a.mcap, b.mcap" in out


def test_model_file_keeps_sensor_names_and_versions(model_path: Path) -> None:
    model = load_model(model_path)
    assert model.samples.sensor_names == ("left", "right")
    assert model.versions["gpocc"] == gpocc.__version__
    assert model.versions["numpy"] == np.__version__


def test_map_metadata_names_the_models_versions(model_path: Path, tmp_path: Path) -> None:
    out = tmp_path / "map"
    result = runner.invoke(app, ["map", str(model_path), "--resolution", "0.25", "--out",
                                 str(out), "--workers", "1", "--bounds", "-2.5", "-2", "2.5",
                                 "2"])
    assert result.exit_code == 0, result.output
    meta = json.loads((out / "metadata.json").read_text())
    with np.load(model_path) as data:
        file_meta = json.loads(bytes(data["metadata"]).decode())
    assert meta["model_versions"] == file_meta["versions"] and meta["model_versions"]
    assert meta["model_sensors"] == ["left", "right"]
    assert meta["method"] == "gp" and meta["size_cells"] == [20, 16]
    assert meta["bounds_m"] == [-2.5, -2.0, 2.5, 2.0] and meta["resolution_m"] == 0.25
    assert meta["kernel"] == file_meta["kernel"]
    assert sum(meta["class_counts"].values()) == 20 * 16
    assert meta["versions"]["gpocc"] == gpocc.__version__


def test_command_modules_do_not_import_the_cli() -> None:
    code = ("import sys, gpocc.commands.map, gpocc.commands.grid, gpocc.commands.train, "
            "gpocc.commands.info, gpocc.commands.split, gpocc.commands.simulate, "
            "gpocc.commands.evaluate, gpocc.commands.config; "
            "print('gpocc.cli' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=REPO)
    assert done.returncode == 0 and done.stdout.strip() == "False", done.stderr


def test_console_script_imports_only_the_command_it_runs() -> None:
    """`gpocc map` does not pay for the other commands' imports (the learner's
    scipy.optimize, the bag readers); the top-level help still lists every command."""
    # The report runs as an exit handler: main() ends the process itself, after them.
    code = ("import atexit, sys\n"
            "mods = ('gpocc.commands.map', 'gpocc.commands.train', 'gpocc.commands.evaluate',"
            " 'scipy.optimize')\n"
            "atexit.register(lambda: print(*[m in sys.modules for m in mods], file=sys.stderr))\n"
            "from gpocc.cli import main\n"
            "sys.argv = ['gpocc'] + sys.argv[1:]\n"
            "main()\n")
    env = {k: v for k, v in os.environ.items() if not k.endswith("_COMPLETE")}
    one = subprocess.run([sys.executable, "-c", code, "map", "-h"], capture_output=True,
                         text=True, cwd=REPO, env=env)
    assert one.returncode == 0 and "--resolution" in one.stdout
    assert one.stderr.split()[-4:] == ["True", "False", "False", "False"], one.stderr
    every = subprocess.run([sys.executable, "-c", code, "--help"], capture_output=True,
                           text=True, cwd=REPO, env=env)
    assert all(name in every.stdout for name, _ in COMMANDS)
    assert every.stderr.split()[-4:-1] == ["True", "True", "True"], every.stderr


def test_console_script_ends_without_teardown_but_with_all_its_output(tmp_path) -> None:
    """main() skips the interpreter's teardown: exit statuses, the whole of stdout (also
    into a pipe) and the error line must be as from the in-process app."""
    env = {k: v for k, v in os.environ.items() if not k.endswith("_COMPLETE")}

    def console(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "gpocc", *args], capture_output=True,
                              text=True, cwd=REPO, env=env)

    full = console("config")
    assert full.returncode == 0
    assert full.stdout == runner.invoke(app, ["config"]).stdout and len(full.stdout) > 2000
    bad = tmp_path / "bad.yaml"
    bad.write_text("model: [\n")
    failed = console("config", str(bad))
    assert failed.returncode == 2 and failed.stdout == ""
    assert failed.stderr.strip().splitlines()[-1].startswith("gpocc config: error: ")
    assert console("map").returncode == 2  # usage error: click's status


def test_a_reader_that_goes_away_ends_the_command_quietly() -> None:
    """`gpocc config | head -1`-style: stdout's reader closes first; the command ends
    with SIGPIPE's status and no error line or traceback."""
    env = {k: v for k, v in os.environ.items() if not k.endswith("_COMPLETE")}
    proc = subprocess.Popen([sys.executable, "-m", "gpocc", "config"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=REPO, env=env)
    proc.stdout.close()  # before the interpreter has even started importing gpocc
    stderr = proc.stderr.read()
    assert proc.wait(timeout=60) == 141, stderr
    assert "error" not in stderr and "Traceback" not in stderr


def test_ctrl_c_while_the_command_loads_is_one_line(monkeypatch, capsys) -> None:
    """Ctrl-C in the second or two the command's modules take to import (before its own
    handler runs) ends with status 130 and one line, not a KeyboardInterrupt traceback."""
    from gpocc import cli

    def interrupted(name: str):
        raise KeyboardInterrupt

    def exit_code(code):
        raise SystemExit(code)

    monkeypatch.setattr(cli.importlib, "import_module", interrupted)
    monkeypatch.setattr(cli, "_exit_without_teardown", exit_code)
    monkeypatch.setattr(sys, "argv", ["gpocc", "build", "in.log", "--out", "x"])
    with pytest.raises(SystemExit) as ended:
        cli.main()
    assert ended.value.code == 130
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == ["gpocc: interrupted before any output was written"]


def _run_script(script: str) -> subprocess.CompletedProcess:
    """``script`` in a fresh interpreter from the repository, its output captured."""
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          cwd=REPO, timeout=60)


def test_ctrl_c_while_the_cli_itself_loads_is_one_line() -> None:
    """Ctrl-C while ``gpocc.cli`` imports typer (before its own handler can exist): the
    console script's entry point ends with status 130 and one line, no traceback. The
    interrupt is raised by the import of typer in a fresh interpreter."""
    script = (
        "import builtins, sys\n"
        "real = builtins.__import__\n"
        "def importing(name, *args, **kwargs):\n"
        "    if name == 'typer':\n"
        "        raise KeyboardInterrupt\n"
        "    return real(name, *args, **kwargs)\n"
        "builtins.__import__ = importing\n"
        "sys.argv = ['gpocc', 'config']\n"
        "from gpocc.entry import main\n"
        "main()\n"
    )
    proc = _run_script(script)
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        "gpocc: interrupted before any output was written"]


@pytest.mark.parametrize(("args", "line"), [
    (["map", "--nonsense"],
     "gpocc map: error: No such option: --nonsense (see 'gpocc map --help')"),
    (["map"], "gpocc map: error: Missing argument 'MODEL'. (see 'gpocc map --help')"),
    (["mapp"], "gpocc: error: No such command 'mapp'. Did you mean 'map'? "
               "(see 'gpocc --help')"),
    (["build", "in.log", "--out", "x", "--resolution", "fine"],
     "gpocc build: error: Invalid value for '--resolution': "),
])
def test_usage_errors_are_one_line(args: list[str], line: str) -> None:
    """A mistyped command line gets one error line (status 2) like any other error, not
    typer's usage line, hint and box."""
    proc = subprocess.run([sys.executable, "-m", "gpocc", *args], capture_output=True,
                          text=True, cwd=REPO, timeout=120)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(line)
    assert proc.stdout == ""


def test_an_abort_in_a_command_is_one_line_not_a_traceback() -> None:
    """An EOFError escaping a command becomes typer's Abort, which the standalone mode
    printed as "Aborted." (status 1); without standalone mode it must not end in a
    traceback."""
    script = (
        "import functools, sys\n"
        "import gpocc.commands.config as c\n"
        "real = c.config_command\n"
        "@functools.wraps(real)\n"
        "def eof(*args, **kwargs):\n"
        "    raise EOFError\n"
        "c.config_command = eof\n"
        "sys.argv = ['gpocc', 'config']\n"
        "from gpocc.entry import main\n"
        "main()\n"
    )
    proc = _run_script(script)
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines() == ["Aborted."]
