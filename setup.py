"""The compiled loops (gpocc/_kernels.c); everything else is in pyproject.toml."""

import tempfile
from pathlib import Path
from typing import Any

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

# No input of these loops is NaN or infinite (gpocc/compiled.py refuses them, see the C
# file's header): these flags let GCC vectorise the branch-free arcsin (vector min/max
# and blends) without changing a result. -O3: their loops are the map's and the
# training's hot path. -ffp-contract=fast: a * b + c becomes one fused multiply-add (one
# rounding instead of two) where the CPU has FMA; -std=c11 alone turns contraction off,
# and a map anchor's covariances took 25% longer (measured in commit dc508e1).
FLAGS = ["-O3", "-fno-math-errno", "-fno-trapping-math", "-ffinite-math-only",
         "-fno-signed-zeros", "-std=c11", "-ffp-contract=fast"]
#: MSVC's spelling of the same intent; it has no finite-math-only short of /fp:fast,
#: which also reassociates sums (results would change), so the loops keep /fp:precise.
MSVC_FLAGS = ["/O2", "/std:c11"]


def accepted_flags(compiler: Any, flags: list[str]) -> list[str]:
    """The flags of ``flags`` that ``compiler`` (a distutils ``CCompiler``) accepts, in
    order: each is tried on an empty program (warnings as errors: clang only warns about
    some unknown ``-f`` options), so that GCC gets them all and another compiler builds
    the loops too."""
    return [flag for flag in flags if _accepts(compiler, flag)]


def _accepts(compiler: Any, flag: str) -> bool:
    with tempfile.TemporaryDirectory() as tmp:
        source = Path(tmp) / "flag.c"
        source.write_text("int gpocc_flag_probe(void) { return 0; }\n")
        try:
            compiler.compile([str(source)], output_dir=tmp, extra_postargs=[flag, "-Werror"])
        except Exception:  # CompileError, or a compiler that cannot run at all
            return False
    return True


class BuildWithAcceptedFlags(build_ext):
    """``build_ext`` with the flags of :data:`FLAGS` the C compiler accepts
    (:func:`accepted_flags`; tests/gp/test_build_flags.py builds with a compiler that
    refuses some)."""

    def build_extensions(self) -> None:
        if self.compiler.compiler_type == "msvc":
            flags = MSVC_FLAGS
        else:
            flags = accepted_flags(self.compiler, FLAGS)
        for extension in self.extensions:
            extension.extra_compile_args = flags
        super().build_extensions()


setup(ext_modules=[Extension("gpocc._kernels", ["gpocc/_kernels.c"])],
      cmdclass={"build_ext": BuildWithAcceptedFlags})
