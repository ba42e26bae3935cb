"""Single-threaded BLAS for gpocc's many small matrices.

Every linear-algebra call in gpocc is on a local problem of a few hundred samples. There,
a multi-threaded BLAS spends its time waking and synchronising threads: a 160 x 160
Cholesky took 75 ms with OpenBLAS's default threads against 0.3 ms with one, on a loaded
machine (docs/benchmarks.md, 'BLAS threads on small matrices', measures it on yours).
gpocc parallelises over processes instead (map blocks).
"""

from __future__ import annotations

from threadpoolctl import threadpool_limits


def single_threaded_blas() -> threadpool_limits:
    """Context manager (or plain call, for a whole process) limiting BLAS to one thread."""
    return threadpool_limits(limits=1, user_api="blas")
