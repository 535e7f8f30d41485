"""Where the element kernels run: the CPU (default) or a GPU.

The energies and their derivatives are plain JAX, so they run on any device JAX has;
the Newton step's sparse assembly stays on the host (the local gradients and Hessians
are copied back to it once per iteration), and its factorisation runs on the GPU where
cuDSS is installed (eyefem.solve.cudss), else on the host (PARDISO, SuperLU).
Choose the device before any JAX work (entry points do it from ``--device``):

    >>> from eyefem.solve.device import select_device
    >>> select_device("cpu")   # doctest: +SKIP
"""

from __future__ import annotations

DEVICES = ("cpu", "gpu")


class DeviceError(RuntimeError):
    """The device asked for is not available to JAX."""


def select_device(name: str) -> str:
    """Make ``name`` ("cpu" or "gpu") JAX's default device; return a description of it.

    "cpu" keeps JAX off any accelerator (results then do not depend on the machine's
    GPU); "gpu" needs a CUDA build of jaxlib (``pip install "jax[cuda12]"``) and a GPU,
    and raises DeviceError saying so if JAX finds none.
    """
    import jax

    if name not in DEVICES:
        raise DeviceError(f"device {name!r} is not one of {', '.join(DEVICES)}")
    if name == "cpu":
        jax.config.update("jax_platforms", "cpu")
        dev = jax.devices("cpu")[0]
        jax.config.update("jax_default_device", dev)
    else:
        try:
            dev = jax.devices("gpu")[0]
        except RuntimeError as exc:
            raise DeviceError(
                "--device gpu: JAX finds no GPU on this machine "
                f"({str(exc).splitlines()[0]}). Install a CUDA build of jaxlib "
                "(pip install \"jax[cuda12]\") on a machine with an NVIDIA GPU, or run "
                "with --device cpu (the default).") from None
        jax.config.update("jax_default_device", dev)
    return f"{dev.platform} ({getattr(dev, 'device_kind', dev.platform)})"


CACHE_VARIABLE = "EYEFEM_JAX_CACHE"
"""The environment variable naming the folder of :func:`keep_compiled_by_default` (``off``:
none)."""


def keep_compiled_by_default() -> str | None:
    """Keep XLA's compiled kernels on disk (:func:`keep_compiled`) in ``EYEFEM_JAX_CACHE``
    (default ``~/.cache/eyefem/jax``; ``off``, ``0``, ``none`` or empty: nothing), so that a
    later run of a model of the same sizes skips compilation (about 26 s of the README main
    command's 29). A folder the user gave JAX (JAX_COMPILATION_CACHE_DIR) is kept, with
    JAX's own threshold. Entry points (``eyefem``, ``python -m optimize.plan``, the
    calibration) call it before the first compilation; returns the folder in use, or None."""
    import os
    from pathlib import Path

    import jax

    cache = os.environ.get(CACHE_VARIABLE, str(Path.home() / ".cache" / "eyefem" / "jax"))
    if jax.config.jax_compilation_cache_dir:
        return jax.config.jax_compilation_cache_dir
    if cache.lower() in ("", "0", "off", "none"):
        return None
    keep_compiled(cache)
    return cache


def keep_compiled(cache_dir: str) -> None:
    """Keep every executable XLA compiles in the persistent cache ``cache_dir``, the small
    ones too (JAX's default keeps only those that took over a second): a later run of a
    model of the same sizes then compiles nothing (the figures: docs/performance.md). Call
    before the first compilation."""
    import jax

    jax.config.update("jax_compilation_cache_dir", cache_dir)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
