"""setup.py keeps only the compiler flags the C compiler accepts.

The stand-in compiler is a script named by ``CC`` (distutils' own way to pick the compiler)
that logs each call and refuses chosen flags as clang refuses an unknown option, and hands
everything else to the system's compiler; the oracle is its log: the compile of
gpocc/_kernels.c must carry exactly the flags of setup.FLAGS the stand-in accepts, and the
library built must load with every loop gpocc declares.
"""

from __future__ import annotations

import runpy
import shutil
import stat
import sysconfig
from pathlib import Path

import pytest
import setuptools

from gpocc import compiled

ROOT = Path(__file__).resolve().parents[2]
REAL_CC = shutil.which((sysconfig.get_config_var("CC") or "cc").split()[0])


def _setup_py(monkeypatch) -> dict:
    """setup.py's names, without running its ``setup()``."""
    monkeypatch.setattr(setuptools, "setup", lambda **kwargs: None)
    return runpy.run_path(str(ROOT / "setup.py"), run_name="gpocc_setup")


def _stand_in(tmp: Path, refused: list[str]) -> tuple[Path, Path]:
    """A compiler script that refuses ``refused``; returns it and its log."""
    log = tmp / "cc.log"
    script = tmp / "stand-in-cc"
    script.write_text(
        "#!/bin/sh\n"
        f'echo "$*" >> "{log}"\n'
        'for arg in "$@"; do\n'
        f'  case " {" ".join(refused)} " in *" $arg "*)\n'
        "    echo \"stand-in-cc: error: unknown argument: '$arg'\" >&2; exit 1;;\n"
        "  esac\n"
        "done\n"
        f'exec "{REAL_CC}" "$@"\n')
    script.chmod(script.stat().st_mode | stat.S_IXUSR)
    return script, log


@pytest.mark.skipif(REAL_CC is None, reason="no C compiler on PATH")
@pytest.mark.parametrize("refused", [
    [],  # the system's compiler as it is (GCC here): every flag kept
    ["-ffinite-math-only", "-fno-trapping-math", "-ffp-contract=fast"],
], ids=["system-compiler", "refuses-gcc-only-flags"])
def test_the_loops_build_with_the_flags_the_compiler_accepts(tmp_path, monkeypatch, refused):
    setup_py = _setup_py(monkeypatch)
    flags = setup_py["FLAGS"]
    assert set(refused) <= set(flags)
    cc, log = _stand_in(tmp_path, refused)
    monkeypatch.setenv("CC", str(cc))
    kernels_c = ROOT / "gpocc" / "_kernels.c"
    dist = setuptools.Distribution({
        "name": "gpocc-build-flags-test",
        "ext_modules": [setuptools.Extension("gpocc._kernels", [str(kernels_c)])]})
    build = setup_py["BuildWithAcceptedFlags"](dist)
    build.build_lib, build.build_temp = str(tmp_path / "lib"), str(tmp_path / "tmp")
    build.ensure_finalized()
    build.run()
    calls = [c.split() for c in log.read_text().splitlines()]
    (kernels,) = [c for c in calls if str(kernels_c) in c]
    # setup.py's flags come last (distutils' extra_postargs), after Python's own.
    assert kernels[kernels.index("-o") + 2:] == [f for f in flags if f not in refused]
    # Each refused flag was tried (and refused) on the probe program, then left out.
    for flag in refused:
        assert any(flag in c and "-Werror" in c for c in calls)
    (library,) = (tmp_path / "lib" / "gpocc").glob("_kernels*.so")
    assert compiled.load(library).gpocc_kernels_compiler()


def test_msvc_gets_its_own_flags_without_probes(monkeypatch):
    """MSVC takes setup.MSVC_FLAGS as they stand (it has no finite-math-only short of
    /fp:fast): no flag is probed on it and no GCC flag reaches it."""
    setup_py = _setup_py(monkeypatch)
    built: list[list[str]] = []

    class Msvc:
        compiler_type = "msvc"

        def compile(self, *args, **kwargs):
            raise AssertionError("a flag was probed on MSVC")

    def record(self) -> None:
        built.extend(ext.extra_compile_args for ext in self.extensions)

    monkeypatch.setattr(setup_py["build_ext"], "build_extensions", record)
    dist = setuptools.Distribution({
        "name": "gpocc-build-flags-test",
        "ext_modules": [setuptools.Extension("gpocc._kernels", ["gpocc/_kernels.c"])]})
    build = setup_py["BuildWithAcceptedFlags"](dist)
    build.ensure_finalized()
    build.compiler = Msvc()
    build.build_extensions()
    assert built == [setup_py["MSVC_FLAGS"]]
