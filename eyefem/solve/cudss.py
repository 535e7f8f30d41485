"""cuDSS, NVIDIA's sparse direct solver, as the factorisation backend ``"cudss"`` (a GPU).

With ``--device gpu`` the element kernels run on the GPU and, where this backend is
available, so do the Newton step's factorisation and back-solves: the tangent's upper
triangle (CSR) is copied to the device, factorised there as a real symmetric indefinite
matrix (LDL^T with pivoting) and every right-hand side is solved there.

It needs CuPy (the device arrays) and cuDSS's library ``libcudss.so.0`` (the wheel
``nvidia-cudss-cu13``, or a CUDA install; ``EYEFEM_CUDSS_LIB`` names the file), read
through ctypes. Where either is missing, or no GPU is there, the backend is not in
``available_backends()`` and nothing changes.

As with Pardiso, one analysis (reordering, symbolic factorisation) is kept per sparsity
pattern and each Newton iteration only refactorises numerically; a factorisation kept
for an adjoint solve is refactorised when used after another one of its pattern.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import os
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from eyefem.solve.errors import LinearSolveError

log = logging.getLogger(__name__)

LIBRARY = "libcudss.so.0"
"""The file name of the cuDSS library this binding was written for (cuDSS 0.7)."""

# cudss.h (0.7) enumerations
_R_64F, _R_32I = 1, 10  # cudaDataType_t
_MTYPE_SYMMETRIC, _MVIEW_UPPER, _BASE_ZERO, _COL_MAJOR = 1, 2, 0, 0
_PHASE_ANALYSIS, _PHASE_FACTORIZATION, _PHASE_SOLVE = 3, 4, 1008
_DATA_INFO = 0
_STATUS = ("success", "not initialised", "allocation failed", "invalid value",
           "not supported", "execution failed", "internal error")
_MAX_PATTERNS = 8


class CuDSSUnavailable(RuntimeError):
    """cuDSS cannot be used here (no CuPy, no GPU or no libcudss)."""


def _library_candidates() -> list[str]:
    out = [os.environ["EYEFEM_CUDSS_LIB"]] if os.environ.get("EYEFEM_CUDSS_LIB") else []
    try:
        import nvidia  # the namespace package of NVIDIA's wheels

        for root in nvidia.__path__:
            out += [str(p) for p in sorted(Path(root).glob(f"cu*/lib/{LIBRARY}"))]
            out += [str(p) for p in sorted(Path(root).glob(f"cudss/lib/{LIBRARY}"))]
    except ImportError:
        pass
    return out + [LIBRARY]


@functools.lru_cache(maxsize=1)
def _runtime():
    """(ctypes library, cupy, handle, config), loaded once; CuDSSUnavailable says why not."""
    try:
        import cupy
    except ImportError:
        raise CuDSSUnavailable("CuPy is not installed (pip install cupy-cuda13x)") from None
    try:
        if cupy.cuda.runtime.getDeviceCount() < 1:
            raise CuDSSUnavailable("no GPU")
    except cupy.cuda.runtime.CUDARuntimeError as exc:
        raise CuDSSUnavailable(f"no usable GPU ({exc})") from None
    errors = []
    for name in _library_candidates():
        try:
            lib = ctypes.CDLL(name)
            break
        except OSError as exc:
            errors.append(f"{name}: {exc}")
    else:
        raise CuDSSUnavailable(f"{LIBRARY} not found (pip install nvidia-cudss-cu13, or set "
                               f"EYEFEM_CUDSS_LIB): {'; '.join(errors)}")
    for fn in ("cudssCreate", "cudssConfigCreate", "cudssDataCreate", "cudssMatrixCreateCsr",
               "cudssMatrixCreateDn", "cudssExecute", "cudssMatrixSetValues",
               "cudssMatrixDestroy", "cudssDataDestroy", "cudssDataGet"):
        getattr(lib, fn).restype = ctypes.c_int
    lib.cudssMatrixCreateCsr.argtypes = [
        ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64, ctypes.c_void_p,
        ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int, ctypes.c_int,
        ctypes.c_int, ctypes.c_int, ctypes.c_int]
    lib.cudssMatrixCreateDn.argtypes = [
        ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64, ctypes.c_void_p,
        ctypes.c_int, ctypes.c_int]
    lib.cudssExecute.argtypes = [ctypes.c_void_p, ctypes.c_int] + [ctypes.c_void_p] * 5
    lib.cudssDataGet.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int,
                                 ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p]
    handle, config = ctypes.c_void_p(), ctypes.c_void_p()
    _check(lib.cudssCreate(ctypes.byref(handle)), "cudssCreate")
    _check(lib.cudssConfigCreate(ctypes.byref(config)), "cudssConfigCreate")
    return lib, cupy, handle, config


def _check(status: int, what: str) -> None:
    if status != 0:
        word = _STATUS[status] if 0 <= status < len(_STATUS) else f"status {status}"
        raise LinearSolveError(f"cuDSS {what} failed: {word}")


@functools.lru_cache(maxsize=1)
def available() -> bool:
    """Whether the cudss backend can run here (loads CuPy and cuDSS on the first call)."""
    try:
        _runtime()
    except CuDSSUnavailable as exc:
        log.debug("cuDSS backend unavailable: %s", exc)
        return False
    return True


_BY_PATTERN: dict = {}


class _Pattern:
    """cuDSS's data for one sparsity pattern: the CSR arrays on the device, the matrix
    descriptor and the analysis; ``owner`` is the factorisation its factors hold."""

    def __init__(self, U: sp.csr_matrix):
        lib, cupy, handle, config = _runtime()
        self.n = U.shape[0]
        self.indptr = cupy.asarray(U.indptr.astype(np.int32))
        self.indices = cupy.asarray(U.indices.astype(np.int32))
        self.values = cupy.asarray(U.data)
        self.matrix, self.data = ctypes.c_void_p(), ctypes.c_void_p()
        _check(lib.cudssDataCreate(handle, ctypes.byref(self.data)), "cudssDataCreate")
        _check(lib.cudssMatrixCreateCsr(
            ctypes.byref(self.matrix), self.n, self.n, U.nnz, self.indptr.data.ptr, None,
            self.indices.data.ptr, self.values.data.ptr, _R_32I, _R_64F, _MTYPE_SYMMETRIC,
            _MVIEW_UPPER, _BASE_ZERO), "cudssMatrixCreateCsr")
        self.owner = None
        self.analysed = self.freed = False

    def execute(self, phase: int, x=None, b=None) -> None:
        lib, cupy, handle, config = _runtime()
        if x is None:  # analysis and factorisation read no right-hand side
            x = b = cupy.zeros((self.n, 1))
        mats = []
        for arr in (x, b):
            m = ctypes.c_void_p()
            _check(lib.cudssMatrixCreateDn(ctypes.byref(m), self.n, arr.shape[1], self.n,
                                           arr.data.ptr, _R_64F, _COL_MAJOR),
                   "cudssMatrixCreateDn")
            mats.append(m)
        try:
            _check(lib.cudssExecute(handle, phase, config, self.data, self.matrix, mats[0],
                                    mats[1]), f"execute (phase {phase})")
            cupy.cuda.runtime.deviceSynchronize()
        finally:
            for m in mats:
                lib.cudssMatrixDestroy(m)

    def factorize(self, values: np.ndarray, owner: int) -> None:
        lib, cupy, handle, config = _runtime()
        self.values.set(values)
        if not self.analysed:
            self.execute(_PHASE_ANALYSIS)
            self.analysed = True
        self.execute(_PHASE_FACTORIZATION)
        info = ctypes.c_int(0)
        written = ctypes.c_size_t(0)
        _check(lib.cudssDataGet(handle, self.data, _DATA_INFO, ctypes.byref(info),
                                ctypes.sizeof(info), ctypes.byref(written)), "cudssDataGet")
        if info.value != 0:
            raise LinearSolveError(f"cuDSS factorisation: info {info.value} (a zero pivot: "
                                   "singular tangent; check that rigid-body motions are "
                                   "constrained)")
        self.owner = owner

    def free(self) -> None:
        lib, _, handle, _ = _runtime()
        lib.cudssMatrixDestroy(self.matrix)
        lib.cudssDataDestroy(handle, self.data)
        self.freed, self.owner = True, None


class CuDSS:
    """A factorisation of a symmetric sparse matrix on the GPU; ``solve(b)`` with b (n,)
    or (n, k) on the host returns x of the same shape on the host."""

    def __init__(self, A):
        self.U = sp.triu(A, format="csr")
        self.U.sort_indices()
        self.pattern = self._pattern()
        self.pattern.factorize(self.U.data, id(self))

    def _pattern(self) -> _Pattern:
        """This matrix's pattern entry (made, and the oldest beyond a few freed, if new)."""
        U = self.U
        key = (U.shape[0], U.nnz, hash(U.indptr.tobytes()), hash(U.indices.tobytes()))
        pattern = _BY_PATTERN.pop(key, None)
        if pattern is None:
            if len(_BY_PATTERN) >= _MAX_PATTERNS:
                _BY_PATTERN.pop(next(iter(_BY_PATTERN))).free()
            pattern = _Pattern(U)
        _BY_PATTERN[key] = pattern  # the most recent last
        return pattern

    def solve(self, b):
        _, cupy, _, _ = _runtime()
        if self.pattern.freed:  # evicted since (a factorisation kept for an adjoint)
            self.pattern = self._pattern()
        p = self.pattern
        if p.owner != id(self):  # another factorisation of this pattern came since
            p.factorize(self.U.data, id(self))
        rhs = cupy.asarray(np.asfortranarray(np.asarray(b, np.float64).reshape(p.n, -1)))
        x = cupy.zeros_like(rhs)
        p.execute(_PHASE_SOLVE, x, rhs)
        return cupy.asnumpy(x).reshape(np.shape(b))
