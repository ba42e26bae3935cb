"""gpocc.allocator: freed memory kept for later arrays."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

#: Allocate, touch and free a 64 MiB array, then count the page faults of touching a
#: second one, in the main thread and in another: memory given back to the system must
#: be faulted in again, memory kept is not. numpy (and its BLAS threads) come after the
#: allocator is set, as in the ``gpocc`` command.
_PROBE = textwrap.dedent("""
    import resource, sys, threading
    from gpocc.allocator import keep_freed_memory, keeps_freed_memory
    environ = {"GPOCC_KEEP_FREED_MEMORY": "0"} if sys.argv[1] == "off" else {}
    applied = keep_freed_memory(environ) if sys.argv[1] != "plain" else None
    import numpy as np
    size = 8 << 20  # float64 values: 64 MiB

    def faults_of_touching_a_second_array():
        first = np.ones(size)
        del first
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        second = np.ones(size)
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

    main = faults_of_touching_a_second_array()
    threaded = []
    worker = threading.Thread(target=lambda: threaded.append(faults_of_touching_a_second_array()))
    worker.start()
    worker.join()
    print(applied, keeps_freed_memory(), main, threaded[0])
""")


def _faults(mode: str) -> tuple[str, str, int, int]:
    # Without the caller's malloc settings or another malloc preloaded.
    env = {k: v for k, v in os.environ.items()
           if k not in ("LD_PRELOAD", "GLIBC_TUNABLES") and not k.startswith("MALLOC_")}
    done = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True,
                          text=True, check=True, env=env)
    applied, kept, main, threaded = done.stdout.split()
    return applied, kept, int(main), int(threaded)


def _largest_page_bytes() -> int:
    """The size of a transparent huge page (the fewest faults 64 MiB can take)."""
    size = Path("/sys/kernel/mm/transparent_hugepage/hpage_pmd_size")
    try:
        return int(size.read_text())
    except (OSError, ValueError):
        return 2 << 20


def test_freed_memory_is_reused_without_page_faults_in_every_thread():
    """Without it, a second 64 MiB array is faulted in again (at least one fault per huge
    page); with it, the freed first array's memory serves the second with almost no
    faults, in the main thread and in another thread alike; turned off from the
    environment, nothing changes."""
    applied, kept, kept_main, kept_thread = _faults("keep")
    if applied == "False":
        pytest.skip("the C library is not glibc: keep_freed_memory changes nothing")
    assert applied == kept == "True"
    fewest = (64 << 20) // _largest_page_bytes()
    _, plain_kept, plain_main, plain_thread = _faults("plain")
    assert plain_kept == "False"
    assert plain_main >= fewest and plain_thread >= fewest
    assert 4 * kept_main <= fewest and 4 * kept_thread <= fewest
    applied, off_kept, off_main, off_thread = _faults("off")
    assert applied == off_kept == "False" and off_main >= fewest and off_thread >= fewest


def test_pool_workers_apply_the_setting_when_their_parent_did():
    """A worker pool's initialiser applies the allocator setting when the parent process
    had it, and only then: a worker that is not forked (the forkserver and spawn start
    methods) inherits nothing. Run in fresh processes, as a worker is."""
    probe = textwrap.dedent("""
        import os, sys
        from gpocc.allocator import keeps_freed_memory
        from gpocc.parallel import _init_worker
        _init_worker(os.getppid(), sys.argv[1] == "keep", os.getpid, ())
        print(keeps_freed_memory())
    """)
    for mode in ("keep", "plain"):
        done = subprocess.run([sys.executable, "-c", probe, mode], capture_output=True,
                              text=True, check=True)
        if mode == "keep" and _faults("keep")[0] == "False":
            pytest.skip("the C library is not glibc: keep_freed_memory changes nothing")
        assert done.stdout.split() == ["True" if mode == "keep" else "False"]
