"""eyefem.solve.heap: freed large blocks go back to the system (glibc)."""

import platform
import subprocess
import sys
import textwrap

import pytest

from eyefem.solve import heap

GLIBC = sys.platform == "linux" and platform.libc_ver()[0] == "glibc"

# Allocates forty 8 MB blocks, keeps one 0.5 MB block allocated after them (it pins the
# heap's top), frees the forty and prints how much of the resident memory stayed (MB).
# With glibc's dynamic thresholds the first freed block raises the mmap threshold above
# 8 MB, so the later blocks come from the heap, whose freed middle stays resident.
SCRIPT = textwrap.dedent("""
    import sys
    import numpy as np
    from eyefem.solve.heap import return_freed_memory

    def rss_mb():
        with open("/proc/self/status") as f:
            return next(int(l.split()[1]) for l in f if l.startswith("VmRSS")) / 1024

    if sys.argv[1] == "1":
        assert return_freed_memory()
    warm = np.ones(1 << 20); del warm  # an 8 MB block mapped and freed: glibc adapts
    before = rss_mb()
    blocks = [np.ones(1 << 20) for _ in range(40)]
    pin = np.ones(1 << 16)
    del blocks
    print(rss_mb() - before)
""")


def _kept_mb(call: bool) -> float:
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": ":".join(sys.path)}
    out = subprocess.run([sys.executable, "-c", SCRIPT, "1" if call else "0"], env=env,
                         capture_output=True, text=True, check=True)
    return float(out.stdout.split()[-1])


@pytest.mark.skipif(not GLIBC, reason="the thresholds are glibc malloc's (mallopt)")
def test_freed_blocks_return_to_the_system():
    kept_default, kept_fixed = _kept_mb(False), _kept_mb(True)
    # control: glibc's defaults keep the 320 MB freed behind the pinned block resident
    assert kept_default > 200, kept_default
    assert kept_fixed < 20, kept_fixed


def test_thresholds_the_user_set_are_left_alone(monkeypatch):
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "1048576")
    assert heap.return_freed_memory() is False


def test_the_environment_chooses_the_heap(monkeypatch, caplog):
    calls = []
    monkeypatch.setattr(heap, "return_freed_memory", lambda: calls.append(1) or True)
    monkeypatch.delenv("EYEFEM_HEAP", raising=False)
    assert heap.configure_heap() is True and calls == [1]  # the lean heap by default
    monkeypatch.setenv("EYEFEM_HEAP", "glibc")
    assert heap.configure_heap() is False and calls == [1]
    monkeypatch.setenv("EYEFEM_HEAP", "lean")
    assert heap.configure_heap() is True and calls == [1, 1]
    monkeypatch.setenv("EYEFEM_HEAP", "small")
    with caplog.at_level("WARNING", logger="eyefem.solve.heap"):
        assert heap.configure_heap() is False
    assert calls == [1, 1]
    assert "EYEFEM_HEAP='small' is not one of glibc, lean" in caplog.text
    monkeypatch.setattr(heap, "return_freed_memory", lambda: False)  # e.g. not glibc
    monkeypatch.delenv("EYEFEM_HEAP")
    caplog.clear()
    with caplog.at_level("WARNING", logger="eyefem.solve.heap"):
        assert heap.configure_heap() is False  # the default where it cannot apply: quiet
    assert caplog.text == ""
    monkeypatch.setenv("EYEFEM_HEAP", "lean")
    with caplog.at_level("WARNING", logger="eyefem.solve.heap"):
        assert heap.configure_heap() is False
    assert "EYEFEM_HEAP=lean: the heap's thresholds were not set" in caplog.text


@pytest.mark.skipif(not GLIBC, reason="malloc_trim is glibc's")
def test_the_heap_is_trimmed_after_a_compilation(monkeypatch):
    """configure_heap's lean heap trims the arenas after an XLA compilation of at least
    TRIM_AFTER_COMPILE_S (0 here, so that a jit of x * 3 counts), not after a cached
    call."""
    import jax

    assert heap.trim_after_compiles() is True
    trims = []
    monkeypatch.setattr(heap, "_trim_heap", lambda: trims.append(1))
    monkeypatch.setattr(heap, "TRIM_AFTER_COMPILE_S", 0.0)
    f = jax.jit(lambda x: x * 3.0 + 0.25)
    f(1.0)
    assert len(trims) == 1
    f(2.0)  # compiled already: no compilation, no trim
    assert len(trims) == 1
    monkeypatch.setattr(heap, "TRIM_AFTER_COMPILE_S", 1e9)
    jax.jit(lambda x: x * 5.0 - 0.5)(1.0)  # a compilation below the threshold
    assert len(trims) == 1
