"""Atomic, exclusive output: claim the target, write a temporary, rename without replacing.

Every top-level output (a map, grid, split, simulation or evaluation folder, a model
file) goes through three steps:

1. **Claim.** An exclusive ``flock`` on a claim file ``.NAME.gpocc-claim`` beside the
   target; a second run on the same ``--out`` fails at once, naming the pid holding it.
   The kernel drops the lock when its process dies (even by SIGKILL), so a dead run
   never blocks the next one; under the claim, temporaries a dead run left beside the
   target (``.NAME.gpocc-tmp-*``, ``.NAME.gpocc-old-*``) are known to be stale and removed.
2. **Write** into a temporary beside the target, removed on any exception (Ctrl-C and
   SIGTERM included, see :mod:`gpocc.lifecycle`).
3. **Rename** with ``RENAME_NOREPLACE`` (``renameat2``; a hard link for files where the
   file system lacks it), so an output created meanwhile by anything else is never
   clobbered. With ``force`` an existing target is replaced only if it is a previous
   gpocc output (:func:`is_gpocc_output`); anything else is an error naming the path.

An ``OSError`` while writing becomes one :class:`GpoccError` naming the target and cause.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import errno
import fcntl
import json
import os
import shutil
import tempfile
import zipfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from gpocc.constants import FOLDER_MARKERS
from gpocc.errors import GpoccError, first_line

_CLAIM = ".gpocc-claim"
_TMP = ".gpocc-tmp-"
_OLD = ".gpocc-old-"
_SPLIT_HEADER = "# Written by gpocc split"

# Claims this process holds: absolute target -> (claim file, open descriptor).
_claims: dict[Path, tuple[Path, int]] = {}


def _umask() -> int:
    """The process's umask, read without setting it where the system allows (Linux):
    setting it to read it would, for that instant, give files that other threads create
    (gpocc build's model file, written beside the map's own) a mode of 0666."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _one_line(exc: OSError) -> str:
    return exc.strerror or first_line(exc)


def _write_error(target: Path, exc: OSError) -> GpoccError:
    where = f" ({exc.filename})" if exc.filename and str(exc.filename) != str(target) else ""
    if exc.errno == errno.ENOSPC:
        return GpoccError(f"{target}: cannot write{where}: no space left on device; free "
                          "some space there, or choose another --out on another disk")
    return GpoccError(
        f"{target}: cannot write{where}: {_one_line(exc)}; check that the folder exists, is "
        f"writable and has free space, or choose another --out"
    )


# --------------------------------------------------------------------------- claims


def _claim_file(target: Path) -> Path:
    return target.parent / f".{target.name}{_CLAIM}"


def claim_output(path: str | os.PathLike[str]) -> None:
    """Hold an exclusive claim on output ``path`` until :func:`release_claim` or exit.

    Raises:
        GpoccError: another process holds the claim, or the folder is not writable.
    """
    target = Path(path)
    key = target.absolute()
    if key in _claims:
        return
    claim = _claim_file(target)
    while True:
        try:
            fd = os.open(claim, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        except OSError as exc:
            raise _write_error(target, exc) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise GpoccError(
                f"{target}: another gpocc run (pid {holder}) is writing this output; wait "
                f"for it to finish or choose another --out"
            ) from None
        # The holder before us may have removed the claim file after we opened it: our
        # lock is then on a deleted file, and a third run may hold the new one.
        try:
            same = os.stat(claim).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    except OSError as exc:  # a full disk: leave no claim file behind
        with contextlib.suppress(OSError):
            claim.unlink()
        os.close(fd)
        raise _write_error(target, exc) from None
    _claims[key] = (claim, fd)
    _remove_stale(target)


def release_claim(path: str | os.PathLike[str]) -> None:
    """Give up the claim on ``path`` (if held) and remove its claim file."""
    entry = _claims.pop(Path(path).absolute(), None)
    if entry is None:
        return
    claim, fd = entry
    with contextlib.suppress(OSError):
        claim.unlink()
    os.close(fd)


@atexit.register
def release_all_claims() -> None:
    """Release every claim this process holds (end of a command, or exit)."""
    for key in list(_claims):
        release_claim(key)


def _remove_stale(target: Path) -> None:
    """Remove temporaries of dead runs; only called while holding the claim."""
    for prefix in (_TMP, _OLD):
        for stale in target.parent.glob(f".{target.name}{prefix}*"):
            if stale.is_dir() and not stale.is_symlink():
                shutil.rmtree(stale, ignore_errors=True)
            else:
                with contextlib.suppress(OSError):
                    stale.unlink()


# --------------------------------------------------------------------------- recognition


def _is_model_file(path: Path) -> bool:
    try:
        with zipfile.ZipFile(path) as zf:
            if "metadata.npy" not in zf.namelist():
                return False
            import numpy as np

            with zf.open("metadata.npy") as fh:
                raw = np.lib.format.read_array(fh, allow_pickle=False)
        meta = json.loads(bytes(raw).decode())
    except (OSError, ValueError, zipfile.BadZipFile, UnicodeDecodeError, EOFError):
        return False
    return isinstance(meta, dict) and meta.get("format") == "gpocc-model"


def _is_gpocc_folder(path: Path) -> bool:
    try:
        entries = list(path.iterdir())
    except OSError:
        return False
    if not entries:
        return True  # nothing of the user's to lose
    for name in FOLDER_MARKERS:  # a folder output holds one (see is_gpocc_output)
        try:
            meta = json.loads((path / name).read_text())
        except (OSError, ValueError):
            continue
        if isinstance(meta, dict) and (
            "gpocc_version" in meta or ("ground_truth" in meta and "maps" in meta)
        ):
            return True
    try:
        with (path / "train.yaml").open() as fh:
            return fh.readline().startswith(_SPLIT_HEADER)
    except (OSError, ValueError):
        return False


def is_gpocc_output(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is something gpocc wrote, which ``--force`` may replace.

    A folder: empty, or holding a ``metadata.json`` / ``simulation.json`` that names the
    gpocc version, an evaluation's ``results.json``, or a split's ``train.yaml``. A file:
    a gpocc model file (``.npz`` whose metadata says ``gpocc-model``). Symlinks never are.
    """
    p = Path(path)
    if p.is_symlink():
        return False
    if p.is_dir():
        return _is_gpocc_folder(p)
    if p.is_file():
        return _is_model_file(p)
    return False


def check_can_write(path: str | os.PathLike[str], force: bool) -> None:
    """Refuse to overwrite an existing file or folder unless ``force`` is set.

    The plain existence check for library writers (bags); commands use
    :func:`prepare_output`, which also claims the output and limits ``force``.
    """
    if Path(path).exists() and not force:
        raise GpoccError(f"{path}: already exists; pass --force to overwrite it")


def _refuse_existing(target: Path, force: bool, folder: bool | None) -> None:
    if not (target.exists() or target.is_symlink()):
        return
    if not force:
        raise GpoccError(f"{target}: already exists; pass --force to overwrite it")
    is_dir = target.is_dir() and not target.is_symlink()
    if folder is not None and folder != is_dir:
        raise GpoccError(
            f"{target}: is a {'folder' if is_dir else 'file'}, and this command writes a "
            f"{'folder' if folder else 'file'}; --force will not replace one with the "
            f"other. Choose another --out"
        )
    if not is_gpocc_output(target):
        raise GpoccError(
            f"{target}: --force replaces only a previous gpocc output, and this "
            f"{'folder' if is_dir else 'file'} is not one (no gpocc metadata); move it "
            f"away or choose another --out"
        )


def prepare_output(path: str | os.PathLike[str], force: bool, folder: bool = True,
                   inputs: Iterable[str | os.PathLike[str] | None] = ()) -> None:
    """At a command's start: claim output ``path`` and check it may be written.

    An existing ``path`` is refused unless ``force``, and with ``force`` unless it is a
    previous gpocc output of the same kind (``folder`` or file) that holds none of the
    command's ``inputs`` (replacing it would delete an input the command reads, e.g.
    ``gpocc evaluate MAP --out MAP --force``). So a refused or contended output fails
    before any work. When the parent folder does not exist yet, the claim is taken when
    writing (creating folders here would leave them behind on a later error).
    """
    target = Path(path)
    _refuse_current_folder(path, target)
    if target.parent.is_dir():
        claim_output(target)
    else:
        _check_ancestor(target)
    _refuse_existing(target, force, folder)
    _refuse_inputs_inside(target, inputs)


def _refuse_current_folder(given: str | os.PathLike[str], target: Path) -> None:
    """An output is written beside its final path and renamed onto it: the current
    folder, or a folder holding it, cannot be that path (``--out .``, ``--out ""``,
    ``--out ..``)."""
    try:
        here = Path.cwd().resolve()
    except FileNotFoundError:  # the current folder was deleted: no output can be it
        return
    resolved = target.resolve()
    if not os.fspath(given) or resolved == here or resolved in here.parents:
        raise GpoccError(
            f"{os.fspath(given)!r}: names the current folder or a folder holding it, which "
            "an output cannot replace; give the output a new name (e.g. --out out/map)")


def _refuse_inputs_inside(target: Path, inputs: Iterable[str | os.PathLike[str] | None]
                          ) -> None:
    if not (target.exists() or target.is_symlink()):
        return
    resolved = target.resolve()
    for given in inputs:
        if given is None:
            continue
        path = Path(given).resolve()
        if path == resolved or resolved in path.parents:
            what = "is" if path == resolved else "holds"
            raise GpoccError(
                f"{target}: {what} the input {given}, which replacing it with --force would "
                f"delete; choose another --out"
            )


def _check_ancestor(target: Path) -> None:
    """Fail fast when the missing parent folders of ``target`` cannot be created."""
    ancestor = target.parent
    while not (ancestor.exists() or ancestor.is_symlink()) and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise GpoccError(f"{target}: {ancestor} is a file, not a folder; choose another --out")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise GpoccError(f"{target}: cannot create folders in {ancestor} (permission denied); "
                         f"choose another --out")


# --------------------------------------------------------------------------- renaming

_RENAME_NOREPLACE = 1
_AT_FDCWD = -100


def _renameat2() -> object | None:
    try:
        return ctypes.CDLL(None, use_errno=True).renameat2
    except (AttributeError, OSError):  # pragma: no cover - old glibc or not Linux
        return None


def rename_noreplace(src: Path, dst: Path) -> None:
    """Rename ``src`` to ``dst``, failing with FileExistsError if ``dst`` exists."""
    call = _renameat2()
    if call is not None:
        if call(_AT_FDCWD, os.fsencode(src), _AT_FDCWD, os.fsencode(dst),
                _RENAME_NOREPLACE) == 0:
            return
        err = ctypes.get_errno()
        if err not in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP):
            raise OSError(err, os.strerror(err), str(dst))
    # Fallbacks: a hard link never replaces; a folder rename fails onto a non-empty one.
    if src.is_dir():
        if dst.exists() or dst.is_symlink():
            raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), str(dst))
        os.rename(src, dst)
    else:
        os.link(src, dst)
        os.unlink(src)


def _install(tmp: Path, target: Path, force: bool) -> None:
    """Move finished ``tmp`` onto ``target``; an existing target needs ``force`` and ours."""
    if target.exists() or target.is_symlink():
        _refuse_existing(target, force, tmp.is_dir())
        old = target.with_name(f".{target.name}{_OLD}{os.getpid()}")
        os.rename(target, old)
        try:
            rename_noreplace(tmp, target)
        except BaseException:
            with contextlib.suppress(OSError):
                rename_noreplace(old, target)
            raise
        if old.is_dir():
            shutil.rmtree(old, ignore_errors=True)
        else:
            old.unlink(missing_ok=True)
        return
    try:
        rename_noreplace(tmp, target)
    except FileExistsError:
        raise GpoccError(
            f"{target}: was created by another program while gpocc was writing it; nothing "
            f"was replaced. Move it away or choose another --out"
        ) from None


def _prepare(target: Path) -> list[Path]:
    """Create ``target``'s missing parent folders and claim it; the folders created,
    innermost first (removed again if the output is never installed)."""
    missing = []
    folder = target.parent
    while not folder.exists() and folder != folder.parent:
        # 'a/new/..' is 'a', which existed: never one to remove.
        if folder.name not in ("..", "."):
            missing.append(folder)
        folder = folder.parent
    if not target.parent.is_dir():
        _check_ancestor(target)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _write_error(target, exc) from None
    claim_output(target)
    return missing


def _remove_if_empty(folders: list[Path]) -> None:
    """Remove each of ``folders`` (innermost first) that is empty: a run that wrote
    nothing leaves no folders it created."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:  # not empty (another run's output), or already gone
            continue


@contextlib.contextmanager
def _claimed_temporary(path: str | os.PathLike[str], force: bool, folder: bool
                       ) -> Iterator[Path]:
    """Claim ``path``, yield a temporary file or folder beside it, install it on success.

    The temporary is removed on any exit; the claim is released.
    """
    target = Path(path)
    created = _prepare(target)
    installed = False
    try:
        _refuse_existing(target, force, folder=folder)
        prefix = f".{target.name}{_TMP}{os.getpid()}-"
        try:
            if folder:
                tmp = Path(tempfile.mkdtemp(prefix=prefix, dir=target.parent))
            else:
                fd, tmp_name = tempfile.mkstemp(prefix=prefix, suffix=target.suffix or ".tmp",
                                                dir=target.parent)
                os.close(fd)
                tmp = Path(tmp_name)
        except OSError as exc:
            raise _write_error(target, exc) from None
        try:
            yield tmp
            os.chmod(tmp, (0o777 if folder else 0o666) & ~_umask())
            _install(tmp, target, force)
            installed = True
        except OSError as exc:
            raise _write_error(target, exc) from None
        except GpoccError as exc:
            # A writer's error names the file it wrote: the user knows the output.
            if str(tmp) not in str(exc):
                raise
            raise GpoccError(str(exc).replace(str(tmp), str(target))) from None
        finally:
            if folder:
                shutil.rmtree(tmp, ignore_errors=True)
            else:
                tmp.unlink(missing_ok=True)
    finally:
        release_claim(target)
        if not installed:
            _remove_if_empty(created)


@contextlib.contextmanager
def atomic_output_file(path: str | os.PathLike[str], force: bool = False) -> Iterator[Path]:
    """Yield a temporary file beside top-level output ``path``; install it on success.

    The claim, ``force`` rule and no-replace rename of the module docstring apply. The
    temporary keeps the suffix, so libraries choosing a format by extension still work.
    """
    with _claimed_temporary(path, force, folder=False) as tmp:
        yield tmp


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    For files inside a folder being written (already private to this run); top-level
    outputs use :func:`atomic_output_file`. On any exception (Ctrl-C included) the
    temporary file is removed, so a reader never sees a half-written file.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(
        prefix=f".{target.stem}.", suffix=target.suffix or ".tmp", dir=target.parent
    )
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        # mkstemp makes owner-only files; outputs get the usual umask-derived mode.
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike[str], force: bool = False) -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; move it onto ``path`` on success.

    An existing ``path`` is refused unless ``force`` and it is a gpocc output; it is
    replaced only after the new folder is complete, so a failure leaves it untouched.
    """
    with _claimed_temporary(path, force, folder=True) as tmp:
        yield tmp
