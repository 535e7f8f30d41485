"""The process's heap: give freed memory back to the system (``EYEFEM_HEAP``, default ``lean``).

Every Newton iteration allocates and frees the same large host arrays (the element
blocks, the tangent's values, the factorisation's work space; tens of MB each). glibc's
malloc raises its mmap threshold each time such a block is freed (up to 32 MB), so later
blocks of that size come from the heap, whose freed middle is never returned: the
resident memory creeps up by 10-20 MB per iteration. Fixed thresholds (blocks of 4 MB and
more mapped on their own and unmapped when freed; the heap's top trimmed above 32 MB free)
stop the creep, at the price of the page faults of blocks mapped afresh. Measured
(docs/performance.md, "Memory"): FEBio's mesh of ``benchmarks/bench_core.py
--sizes 20:5`` peaks at 0.98 GB instead of 1.15 GB (+5 % time); the eye saves a fixed
0.15-0.25 GB (default case 1 2.62 against 2.86 GB; the README main command, case 1's half
on ``fine``, 1.48 against 1.63 GB) for 3-6 % of the run time. So the fixed thresholds are
the default, and ``EYEFEM_HEAP=glibc`` in the environment keeps glibc's own.

XLA's compiler frees what it allocated, but glibc keeps the freed pages inside its arenas:
a machine's first run of the README main command, which compiles its kernels, peaked
about 100 MB higher than a run that reads them from JAX's cache. So ``lean`` also
returns the arenas' free pages (``malloc_trim``) after every compilation of at least
TRIM_AFTER_COMPILE_S (:func:`trim_after_compiles`: 22 in that run, its time unchanged;
1.50 against 1.56 GB).

Entry points call :func:`configure_heap` once, before the work (a sweep's workers inherit
the environment). Thresholds the user set through glibc's own variables
(``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_``) are left alone, and nothing
changes where the C library is not glibc.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import os
import platform
import sys

log = logging.getLogger(__name__)

M_TRIM_THRESHOLD = -1  # mallopt parameters (glibc's malloc.h)
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 4 << 20
"""Blocks of at least this size (4 MiB) are mapped on their own and returned when freed."""
TRIM_THRESHOLD_BYTES = 32 << 20
"""The heap's top is given back once this much (32 MiB) of it is free."""
USER_VARIABLES = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")
"""glibc's variables: a threshold set through one of them is the user's choice."""
HEAP_VARIABLE = "EYEFEM_HEAP"
"""The environment variable of :func:`configure_heap`: ``lean`` (the default) or ``glibc``."""
HEAP_CHOICES = ("glibc", "lean")
COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
"""jax.monitoring's event of one XLA compilation (its duration, s)."""
TRIM_AFTER_COMPILE_S = 0.2
"""Compilations of at least this long (s) are followed by ``malloc_trim``."""


def configure_heap() -> bool:
    """Apply ``EYEFEM_HEAP`` (unset or ``lean``: :func:`return_freed_memory`; ``glibc``:
    nothing); True when the fixed thresholds were set. An unknown value, or ``lean`` set
    where the thresholds cannot be set, is reported in the log and changes nothing (unset
    there: nothing, silently)."""
    asked = os.environ.get(HEAP_VARIABLE, "").strip().lower()
    choice = asked or "lean"
    if choice not in HEAP_CHOICES:
        log.warning("%s=%r is not one of %s: glibc's own heap thresholds are kept "
                    "(set %s=lean for the leaner heap, docs/performance.md)", HEAP_VARIABLE,
                    os.environ[HEAP_VARIABLE], ", ".join(HEAP_CHOICES), HEAP_VARIABLE)
        return False
    if choice == "glibc":
        return False
    if not return_freed_memory():
        if not asked:  # the default where it cannot apply: glibc's own, as asked for
            return False
        log.warning("%s=lean: the heap's thresholds were not set (the C library is not "
                    "glibc, or %s is set in the environment, which takes precedence)",
                    HEAP_VARIABLE, " or ".join(USER_VARIABLES))
        return False
    trim_after_compiles()
    return True


def _trim_heap() -> None:
    """Give the free pages of every malloc arena back to the system (glibc)."""
    ctypes.CDLL("libc.so.6").malloc_trim(0)


def _after_compile(event: str, duration: float, **kwargs) -> None:
    if event == COMPILE_EVENT and duration >= TRIM_AFTER_COMPILE_S:
        _trim_heap()


@functools.cache
def trim_after_compiles() -> bool:
    """Trim the heap (``malloc_trim``) after every XLA compilation of at least
    TRIM_AFTER_COMPILE_S, for the rest of the process (registered once; a jax.monitoring
    listener); True where it applies (glibc on Linux)."""
    if sys.platform != "linux" or platform.libc_ver()[0] != "glibc":
        return False
    import jax.monitoring

    jax.monitoring.register_event_duration_secs_listener(_after_compile)
    return True


def return_freed_memory(mmap_threshold: int = MMAP_THRESHOLD_BYTES,
                        trim_threshold: int = TRIM_THRESHOLD_BYTES) -> bool:
    """Fix glibc malloc's mmap and trim thresholds (bytes); True when they were set.

    False (and nothing changed) off glibc, or when the user set either threshold in the
    environment.
    """
    if sys.platform != "linux" or platform.libc_ver()[0] != "glibc":
        return False
    if any(v in os.environ for v in USER_VARIABLES):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    return bool(libc.mallopt(M_MMAP_THRESHOLD, int(mmap_threshold)) == 1
                and libc.mallopt(M_TRIM_THRESHOLD, int(trim_threshold)) == 1)
