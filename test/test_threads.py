"""threads.py: kernels loaded from numba's cache before a run steps."""
import os
import subprocess
import sys
import textwrap

import numpy as np


def test_preload_kernels_loads_cached_kernels_without_compiling():
    """A fresh process that imported a module has none of its kernels loaded; after
    threads.preload_kernels() the kernel this process compiled (and numba cached) is
    there, served from the cache (a cache hit, no compilation), and a second call loads
    nothing more."""
    from mdss_ros.reduced import sparse_rows
    out = np.empty(2)
    sparse_rows._matvec(np.zeros((2, 1), dtype=np.int64), np.ones((2, 1)), np.ones(2, dtype=np.int64),
                        np.ones(1), out)                          # compiled and cached here if it was not
    code = textwrap.dedent("""
        from mdss_ros.reduced import sparse_rows
        from mdss_ros.threads import preload_kernels
        assert len(sparse_rows._matvec.overloads) == 0
        n = preload_kernels()
        hits, misses = sum(sparse_rows._matvec._cache_hits.values()), sum(sparse_rows._matvec._cache_misses.values())
        print(n, len(sparse_rows._matvec.overloads), hits, misses, preload_kernels())
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=dict(os.environ),
                         timeout=300)
    assert run.returncode == 0, run.stderr
    n, overloads, hits, misses, again = map(int, run.stdout.split())
    assert n >= 1 and overloads >= 1 and hits >= 1 and misses == 0 and again == 0
