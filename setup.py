"""The compiled loops (gpocc/_kernels.c); everything else is in pyproject.toml."""

from setuptools import Extension, setup

# No input of these loops is NaN or infinite (see the file's header): these flags let GCC
# vectorise the branch-free arcsin (vector min/max and blends) without changing a result.
# -O3: their loops are the map's and the training's hot path. -ffp-contract=fast: a * b + c
# becomes one fused multiply-add (one rounding instead of two) where the CPU has FMA;
# -std=c11 alone turns contraction off, and a map anchor's covariances took 25% longer
# (measured in commit dc508e1).
FLAGS = ["-O3", "-fno-math-errno", "-fno-trapping-math", "-ffinite-math-only",
         "-fno-signed-zeros", "-std=c11", "-ffp-contract=fast"]

setup(ext_modules=[Extension("gpocc._kernels", ["gpocc/_kernels.c"], extra_compile_args=FLAGS)])
