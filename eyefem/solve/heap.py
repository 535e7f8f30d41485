"""The process's heap: give freed memory back to the system between Newton iterations.

Every Newton iteration allocates and frees the same large host arrays (the element
blocks, the tangent's values, the factorisation's work space; tens of MB each). glibc's
malloc raises its mmap threshold each time such a block is freed (up to 32 MB), so later
blocks of that size come from the heap, whose freed middle is never returned: the
resident memory creeps up by 10-20 MB per iteration on FEBio's mesh of
``benchmarks/bench_core.py --sizes 20:5`` and peaks at 1.22 GB. Fixed thresholds (blocks
of 4 MB and more mapped on their own and unmapped when freed; the heap's top trimmed
above 32 MB free) bring that peak to 0.98 GB, and default case 1's from 2.86 to 2.62 GB,
for 2-6 % of the run time: the page faults of blocks mapped afresh
(docs/performance.md, "Where the memory goes").

Entry points call :func:`return_freed_memory` once, before the work; a library user may
too. It changes nothing but the allocator's thresholds, leaves thresholds the user set
through glibc's environment variables (``MALLOC_MMAP_THRESHOLD_``,
``MALLOC_TRIM_THRESHOLD_``) alone, does nothing where the C library is not glibc, and
nothing when ``EYEFEM_HEAP=glibc`` is set (glibc's own dynamic thresholds: on the default
eye about 6 % faster and 8 % larger).
"""

from __future__ import annotations

import ctypes
import os
import platform
import sys

M_TRIM_THRESHOLD = -1  # mallopt parameters (glibc's malloc.h)
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 4 << 20
"""Blocks of at least this size (4 MiB) are mapped on their own and returned when freed."""
TRIM_THRESHOLD_BYTES = 32 << 20
"""The heap's top is given back once this much (32 MiB) of it is free."""
USER_VARIABLES = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")
"""glibc's variables: a threshold set through one of them is the user's choice."""
KEEP_GLIBC = ("EYEFEM_HEAP", "glibc")
"""The environment variable and value that keep glibc's dynamic thresholds."""


def return_freed_memory(mmap_threshold: int = MMAP_THRESHOLD_BYTES,
                        trim_threshold: int = TRIM_THRESHOLD_BYTES) -> bool:
    """Fix glibc malloc's mmap and trim thresholds (bytes); True when they were set.

    False (and nothing changed) off glibc, when the user set either threshold in the
    environment, or with ``EYEFEM_HEAP=glibc``.
    """
    if sys.platform != "linux" or platform.libc_ver()[0] != "glibc":
        return False
    if (any(v in os.environ for v in USER_VARIABLES)
            or os.environ.get(KEEP_GLIBC[0]) == KEEP_GLIBC[1]):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    return bool(libc.mallopt(M_MMAP_THRESHOLD, int(mmap_threshold)) == 1
                and libc.mallopt(M_TRIM_THRESHOLD, int(trim_threshold)) == 1)
