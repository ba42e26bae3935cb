"""Keep the memory a gpocc command frees for its own later arrays (glibc's malloc).

glibc's malloc serves each allocation at or above a threshold (128 KiB at first, rising
to 32 MiB as it goes) with a mapping of its own and unmaps it when freed, and gives the
free top of its heap back to the system. A map's tiles, the samples' chunks and the
models' arrays are such allocations, made and freed over and over, so each one starts on
pages the kernel must fault in and zero again. On virtual machines that hand freed guest
memory back to the host (virtio-balloon free page reporting: Firecracker and many cloud
VMs), the host must supply those pages anew as well, which is far slower and varies from
run to run.

:func:`keep_freed_memory` has malloc serve every allocation from one heap that it never
shrinks: freed memory is reused by the next arrays of the process instead of being
handed back before it exits, and the heap's fragmentation can raise its peak. A
command's results do not depend on it. The ``gpocc`` command and its worker processes
call it at their start unless the environment sets ``GPOCC_KEEP_FREED_MEMORY=0``; a
program that imports gpocc decides for itself.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Mapping

#: glibc's mallopt parameters (malloc.h).
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
M_ARENA_MAX = -8
#: The environment variable that turns :func:`keep_freed_memory` off (exactly ``0``).
ENVIRONMENT_SWITCH = "GPOCC_KEEP_FREED_MEMORY"
_kept = False


def keeps_freed_memory() -> bool:
    """Whether :func:`keep_freed_memory` applied in this process (or the one it was
    forked from): worker pools apply it in their workers too (gpocc.parallel)."""
    return _kept


def keep_freed_memory(environ: Mapping[str, str] = os.environ) -> bool:
    """Make glibc's malloc keep freed memory for this process's later allocations: one
    heap for every thread (``M_ARENA_MAX`` 1: other threads' heaps map each allocation
    above 64 MiB on its own), no mapping per allocation (``M_MMAP_MAX`` 0) and no
    trimming of the heap's top (``M_TRIM_THRESHOLD`` -1). Call it before threads
    allocate. True if applied; False, and nothing changed, where ``environ`` sets
    :data:`ENVIRONMENT_SWITCH` to ``0``, the C library is not glibc, or another malloc
    (jemalloc, tcmalloc: ``LD_PRELOAD``) serves the process."""
    if environ.get(ENVIRONMENT_SWITCH) == "0" or not sys.platform.startswith("linux"):
        return False
    import ctypes  # here: an interpreter built without it still runs gpocc

    try:
        process, glibc = ctypes.CDLL(None), ctypes.CDLL("libc.so.6")
        glibc.gnu_get_libc_version  # noqa: B018 - glibc's own (musl has no libc.so.6)
        mallopt = glibc.mallopt
    except (OSError, AttributeError):
        return False

    def address(function) -> int | None:
        return ctypes.cast(function, ctypes.c_void_p).value

    if address(process.malloc) != address(glibc.malloc):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    applied = [mallopt(param, value) == 1 for param, value in
               ((M_ARENA_MAX, 1), (M_MMAP_MAX, 0), (M_TRIM_THRESHOLD, -1))]
    global _kept
    _kept = all(applied)
    return _kept
