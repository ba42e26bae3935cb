"""Faults around outputs: contended --out, --force over foreign files, signals, OS errors.

The oracles are the file system and the process table: which folders exist afterwards,
which processes are still alive, what the claim holder's pid is.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from gpocc.cli import app
from gpocc.config import Config, ModelConfig, TrainingConfig
from gpocc.errors import GpoccError
from gpocc.gp.model import build_model, save_model
from gpocc.io import atomic
from gpocc.io.atomic import atomic_directory, is_gpocc_output, prepare_output, rename_noreplace
from gpocc.samples.sampleset import SampleSet

runner = CliRunner()
GPOCC = [sys.executable, "-m", "gpocc"]


def _samples(seed: int = 0) -> SampleSet:
    """A 4 x 3 m room: wall samples occupied, interior free."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, 40, endpoint=False)
    walls = np.vstack([np.column_stack([-2 + 4 * t, np.full_like(t, s)]) for s in (-1.5, 1.5)]
                      + [np.column_stack([np.full_like(t, s), -1.5 + 3 * t]) for s in (-2, 2)])
    free = rng.uniform([-1.8, -1.3], [1.8, 1.3], size=(150, 2))
    means = np.vstack([walls, free])
    n = len(means)
    labels = np.concatenate([np.ones(len(walls)), -np.ones(len(free))])
    covs = np.einsum("n,ij->nij", rng.uniform(0.0005, 0.004, n), np.eye(2))
    return SampleSet(means, covs, labels, rng.integers(0, 20, n).astype(np.int64),
                     rng.normal(0.0, 0.01, (n, 2, 3)), np.zeros(n, dtype=np.int16))


@pytest.fixture(scope="module")
def model_path(tmp_path_factory) -> Path:
    config = Config(model=ModelConfig(neighbours=60, block_size_m=0.6,
                                      training=TrainingConfig(learn=False, patches=2,
                                                              patch_size=40)))
    path = tmp_path_factory.mktemp("model") / "model.npz"
    save_model(build_model(_samples(), config), path)
    return path


def _one_error_line(stderr: str, name: str) -> str:
    lines = [line for line in stderr.splitlines() if "error:" in line]
    assert len(lines) == 1, stderr
    assert name in lines[0] and "Traceback" not in stderr
    return lines[0]


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if ".gpocc-" in p.name)


# ------------------------------------------------------------------ claims and --force


def test_a_held_claim_refuses_a_second_writer_naming_its_pid(tmp_path):
    out = tmp_path / "map"
    holder = subprocess.Popen(
        [sys.executable, "-c",
         "import sys; from gpocc.io.atomic import prepare_output; "
         f"prepare_output({str(out)!r}, False); print('held', flush=True); sys.stdin.read()"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(GpoccError, match=f"another gpocc run \\(pid {holder.pid}\\)"):
            prepare_output(out, force=True)
    finally:
        holder.communicate("")
    # The holder exited: its claim went with it, and the output is free again.
    prepare_output(out, force=False)
    atomic.release_all_claims()
    assert _leftovers(tmp_path) == []


def test_a_claim_left_by_a_killed_run_does_not_block_and_its_temporaries_are_removed(tmp_path):
    out = tmp_path / "grid"
    code = ("import os, sys; from gpocc.io.atomic import atomic_directory\n"
            f"with atomic_directory({str(out)!r}) as tmp:\n"
            "    (tmp / 'half.tif').write_bytes(b'x')\n"
            "    print('writing', flush=True); sys.stdin.read()\n")
    victim = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    assert victim.stdout.readline().strip() == "writing"
    victim.kill()
    victim.wait()
    assert any(".gpocc-tmp-" in name for name in _leftovers(tmp_path))  # SIGKILL: no clean-up
    with atomic_directory(out) as tmp:
        (tmp / "metadata.json").write_text(json.dumps({"gpocc_version": "test"}))
    assert _leftovers(tmp_path) == []
    assert sorted(p.name for p in out.iterdir()) == ["metadata.json"]


def test_two_concurrent_map_runs_on_one_out_exactly_one_wins(model_path, tmp_path):
    out = tmp_path / "map"
    args = [*GPOCC, "map", str(model_path), "--resolution", "0.1", "--workers", "1",
            "--out", str(out)]
    runs = [subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            for _ in range(2)]
    results = [(run.wait(), run.stderr.read()) for run in runs]
    for run in runs:
        run.stdout.close()
        run.stderr.close()
    codes = sorted(code for code, _ in results)
    assert codes[0] == 0 and codes[1] != 0, results
    loser = next(err for code, err in results if code != 0)
    line = _one_error_line(loser, str(out))
    assert "another gpocc run" in line or "already exists" in line
    assert (out / "metadata.json").is_file()
    assert _leftovers(tmp_path) == []


def test_force_replaces_only_gpocc_outputs(model_path, tmp_path):
    user = tmp_path / "mine"
    user.mkdir()
    (user / "thesis.tex").write_text("precious")
    result = runner.invoke(app, ["map", str(model_path), "--resolution", "0.3",
                                 "--out", str(user), "--force"])
    assert result.exit_code == 2
    assert "not one" in result.stderr and str(user) in result.stderr
    assert (user / "thesis.tex").read_text() == "precious"

    # A model file may be replaced by a model file, not by a folder, and not a user file.
    result = runner.invoke(app, ["map", str(model_path), "--resolution", "0.3",
                                 "--out", str(model_path), "--force"])
    assert result.exit_code == 2 and "writes a folder" in result.stderr
    notes = tmp_path / "notes.npz"
    notes.write_bytes(b"not a model")
    with pytest.raises(GpoccError, match="not one"):
        save_model(build_model(_samples(), Config(model=ModelConfig(
            training=TrainingConfig(learn=False, patches=1, patch_size=20)))), notes, force=True)
    assert notes.read_bytes() == b"not a model"

    # A previous gpocc map folder is replaced, and nothing is left beside it.
    out = tmp_path / "map"
    for _ in range(2):
        result = runner.invoke(app, ["map", str(model_path), "--resolution", "0.3",
                                     "--out", str(out), "--force", "--workers", "1"])
        assert result.exit_code == 0, result.output
    assert is_gpocc_output(out) and is_gpocc_output(model_path)
    assert not is_gpocc_output(user) and not is_gpocc_output(notes)
    assert _leftovers(tmp_path) == []


def test_force_never_replaces_an_output_that_holds_an_input(tmp_path):
    """`gpocc build SPLIT/train.mcap --config SPLIT/train.yaml --out SPLIT --force` would
    delete the log it reads: refused before any work, naming the input."""
    split = tmp_path / "split"
    split.mkdir()
    (split / "train.yaml").write_text("# Written by gpocc split: reads train.mcap beside it.\n")
    (split / "train.mcap").write_bytes(b"log")
    assert is_gpocc_output(split)
    for inputs, named in (([split / "train.mcap", None], "train.mcap"),
                          ([tmp_path / "other.log", split / "train.yaml"], "train.yaml"),
                          ([split], "is the input")):
        with pytest.raises(GpoccError, match=named):
            prepare_output(split, True, inputs=inputs)
        atomic.release_all_claims()
    assert sorted(p.name for p in split.iterdir()) == ["train.mcap", "train.yaml"]
    assert _leftovers(tmp_path) == []
    # An input beside (not inside) the output does not stop --force.
    prepare_output(split, True, inputs=[tmp_path / "split.log", tmp_path / "splitx" / "a"])
    atomic.release_all_claims()


def test_rename_noreplace_never_clobbers(tmp_path):
    src, dst = tmp_path / "a", tmp_path / "b"
    src.write_text("new")
    dst.write_text("old")
    with pytest.raises(FileExistsError):
        rename_noreplace(src, dst)
    assert dst.read_text() == "old" and src.read_text() == "new"
    (tmp_path / "d1").mkdir()
    (tmp_path / "d2").mkdir()  # an empty folder: plain rename would replace it
    with pytest.raises(FileExistsError):
        rename_noreplace(tmp_path / "d1", tmp_path / "d2")


# ------------------------------------------------------------------ OS errors


def test_out_under_a_regular_file_is_one_line(model_path, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    for args in (["map", str(model_path), "--resolution", "0.3"],
                 ["simulate"],
                 ["train", str(blocker)]):
        out = blocker / "sub" / "out"
        result = runner.invoke(app, [*args, "--out", str(out)])
        assert result.exit_code == 2, result.output
        line = _one_error_line(result.stderr, str(out))
        assert "not a folder" in line


def test_out_naming_the_current_folder_is_one_line(model_path, tmp_path):
    """An empty folder counts as a previous output that --force may replace, but not when
    it is the folder the command runs in (or holds it): the rename would have no name."""
    here = tmp_path / "empty"
    here.mkdir()
    for out in (".", "", "..", str(tmp_path)):
        for args in (["map", str(model_path), "--resolution", "0.3"], ["simulate"]):
            run = subprocess.run([*GPOCC, *args, "--out", out, "--force"], cwd=here,
                                 capture_output=True, text=True, timeout=120)
            assert run.returncode == 2, run.stderr
            assert "current folder" in _one_error_line(run.stderr, "error:")
            assert list(here.iterdir()) == []


def test_an_absolute_out_works_from_a_deleted_current_folder(tmp_path, monkeypatch):
    gone = tmp_path / "gone"
    gone.mkdir()
    monkeypatch.chdir(gone)
    gone.rmdir()
    prepare_output(tmp_path / "out", force=False)  # no FileNotFoundError from the cwd
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("err", [errno.ENOSPC, errno.EACCES, errno.EROFS])
def test_a_write_failure_is_one_line_and_leaves_nothing(model_path, tmp_path, monkeypatch, err):
    # A full disk or a read-only folder cannot be made portably as root in a container,
    # so the GeoTIFF writer fails the way the OS would.
    import gpocc.mapping.folder as folder

    def full(path, *args, **kwargs):
        raise OSError(err, os.strerror(err))

    monkeypatch.setattr(folder, "write_geotiff", full)
    out = tmp_path / "map"
    result = runner.invoke(app, ["map", str(model_path), "--resolution", "0.3",
                                 "--workers", "1", "--out", str(out)])
    assert result.exit_code == 2
    line = _one_error_line(result.stderr, str(out))
    assert os.strerror(err).lower() in line.lower()
    assert not out.exists() and _leftovers(tmp_path) == []


def _small_file_system(folder: Path, size: str) -> bool:
    """Mount a tmpfs of ``size`` at ``folder``: False where mounting is not allowed (or
    there is no mount command)."""
    folder.mkdir(exist_ok=True)
    if shutil.which("mount") is None or shutil.which("umount") is None:
        return False
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs",
                           str(folder)], capture_output=True).returncode == 0


@pytest.mark.skipif(sys.platform != "linux", reason="mounts a tmpfs (Linux)")
def test_a_really_full_disk_is_one_line_at_every_stage(model_path, tmp_path):
    # A real full disk, at several sizes so that it fills up in different writers
    # (GeoTIFFs, the memory-mapped map_server image, PNGs, map.mcap): each must end in one
    # line and a non-zero status (not a traceback from GDAL, not SIGBUS) and leave nothing.
    disk = tmp_path / "disk"
    if not _small_file_system(disk, "16k"):
        pytest.skip("cannot mount a tmpfs here (needs root or CAP_SYS_ADMIN)")
    failed = 0
    try:
        for size in ("16k", "64k", "128k", "256k", "512k", "2m"):
            subprocess.run(["mount", "-o", f"remount,size={size}", str(disk)], check=True)
            out = disk / "map"
            run = subprocess.run([*GPOCC, "map", str(model_path), "--resolution", "0.01",
                                  "--out", str(out)], capture_output=True, text=True,
                                 timeout=300)
            if run.returncode == 0:
                shutil.rmtree(out)
                continue
            failed += 1
            assert run.returncode == 2, (size, run.returncode, run.stderr)
            line = _one_error_line(run.stderr, str(out))
            assert "no space left on device" in line, line
            assert list(disk.iterdir()) == [], size
    finally:
        subprocess.run(["umount", str(disk)], capture_output=True)
    assert failed >= 2  # the smallest sizes cannot hold the map


def test_an_unwritable_folder_is_one_line(model_path, tmp_path, monkeypatch):
    def denied(*args, **kwargs):
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(tmp_path))

    monkeypatch.setattr(atomic.os, "open", denied)  # the claim file is the first write
    result = runner.invoke(app, ["map", str(model_path), "--resolution", "0.3",
                                 "--out", str(tmp_path / "map")])
    assert result.exit_code == 2
    assert "Permission denied" in _one_error_line(result.stderr, str(tmp_path / "map"))


# ------------------------------------------------------------------ signals


def _children(pid: int) -> list[int]:
    found = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            found += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return found


def _alive(pid: int) -> bool:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    return "\nState:\tZ" not in status


def _wait_for(predicate, seconds: float = 120.0) -> None:
    deadline = time.monotonic() + seconds
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached")
        time.sleep(0.1)


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux /proc")
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_a_stopped_map_leaves_no_workers_and_no_temporary(model_path, tmp_path, sig):
    out = tmp_path / "map"
    run = subprocess.Popen([*GPOCC, "map", str(model_path), "--resolution", "0.01",
                            "--workers", "2", "--out", str(out)],
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        _wait_for(lambda: len(_children(run.pid)) >= 2 or run.poll() is not None)
        workers = _children(run.pid)
        assert run.poll() is None and len(workers) >= 2
        run.send_signal(sig)
        code = run.wait(timeout=120)
        stderr = run.stderr.read()
    finally:
        if run.poll() is None:
            run.kill()
        run.stderr.close()
    assert code != 0, stderr
    _wait_for(lambda: not any(_alive(w) for w in workers), 30)
    assert not out.exists()
    if sig == signal.SIGTERM:
        assert "interrupted" in stderr and "Traceback" not in stderr
        assert _leftovers(tmp_path) == []
    else:
        # SIGKILL cannot be handled: the next run on the same --out removes the leftovers.
        result = runner.invoke(app, ["map", str(model_path), "--resolution", "0.3",
                                     "--workers", "1", "--out", str(out)])
        assert result.exit_code == 0, result.output
        assert _leftovers(tmp_path) == []


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="reads /proc (Linux)")
def test_outputs_take_the_umask_without_the_umask_being_set(tmp_path, monkeypatch):
    # Setting the umask to read it (os.umask(0), then back) gives files that another
    # thread creates in that instant mode 0666: gpocc build writes its model file on a
    # thread beside the map's own files.
    previous = os.umask(0o027)
    try:
        def refuse(mask):
            raise AssertionError(f"os.umask({mask:o}) called while writing outputs")

        monkeypatch.setattr(atomic.os, "umask", refuse)
        with atomic.atomic_path(tmp_path / "layer.tif") as tmp:
            tmp.write_bytes(b"x")
        with atomic.atomic_output_file(tmp_path / "model.npz") as tmp:
            tmp.write_bytes(b"x")
    finally:
        monkeypatch.undo()
        os.umask(previous)
    assert (tmp_path / "layer.tif").stat().st_mode & 0o777 == 0o640
    assert (tmp_path / "model.npz").stat().st_mode & 0o777 == 0o640


def test_a_failed_run_removes_the_folders_it_created_for_its_output(model_path, tmp_path,
                                                                     monkeypatch):
    """An interrupted or failed map under new folders left them behind, empty; folders
    that existed before, or hold anything else, stay."""
    import gpocc.mapping.folder as folder

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(folder, "write_geotiff", interrupted)
    (tmp_path / "kept").mkdir()
    out = tmp_path / "kept" / "n1" / "n2" / "map"
    result = runner.invoke(app, ["map", str(model_path), "--resolution", "0.3",
                                 "--out", str(out)])
    assert result.exit_code == 130, result.output
    assert list(tmp_path.iterdir()) == [tmp_path / "kept"]
    assert list((tmp_path / "kept").iterdir()) == []
    dotted = tmp_path / "kept" / "n1" / ".." / "n3" / "map"  # n1 is created, then left
    result = runner.invoke(app, ["map", str(model_path), "--resolution", "0.3",
                                 "--out", str(dotted)])
    assert result.exit_code == 130, result.output
    assert list((tmp_path / "kept").iterdir()) == []
