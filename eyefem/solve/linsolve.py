"""Sparse linear solves for the Newton tangent.

The tangent of the mixed formulation is a saddle-point system

    [ K   B ] [ x ]   [ f ]
    [ B^T 0 ] [ y ] = [ g ]

(K: displacement block, B: one column per element multiplier). It is solved by
augmented-Lagrangian (Uzawa) iterations on the condensed matrix K + B D B^T, which
has K's sparsity pattern; D is chosen per multiplier so that every iteration
reduces the constraint error by about ``1/beta``. Rank-k updates of K (fluid
cavities) are added by the Woodbury identity, reusing the same factorisation.

Factorisation backends are pluggable: ``"pardiso"`` (MKL through pypardiso, the
default when installed), ``"cudss"`` (NVIDIA's cuDSS on a GPU, the default with
``--device gpu`` where installed; eyefem.solve.cudss) and ``"superlu"`` (scipy, always
there). Every solve checks its own residual.

Length: one saddle-point solver with its backends (Pardiso, SuperLU), the Schur
complement CG and the low-rank updates it shares; about 420 lines.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import weakref

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from eyefem.solve.errors import LinearSolveError, NegativeCurvature

__all__ = ["LinearSolveError", "NegativeCurvature", "SPD", "SaddlePointSolver",
           "available_backends", "default_backend", "factorize", "positive_definite"]

log = logging.getLogger(__name__)


def available_backends() -> list[str]:
    """Backends that can be used on this machine."""
    from eyefem.solve.cudss import available as cudss_available

    out = []
    try:
        import pypardiso  # noqa: F401
        out.append("pardiso")
    except ImportError:
        pass
    if cudss_available():
        out.append("cudss")
    out.append("superlu")
    return out


def default_backend() -> str:
    """cuDSS where the element kernels run on a GPU (``--device gpu``, or JAX's own
    default where none was chosen) and it is available; else Pardiso where installed;
    else SuperLU."""
    import jax

    have = available_backends()
    if "cudss" in have:
        device = jax.config.jax_default_device
        if (device.platform if device is not None else jax.default_backend()) == "gpu":
            return "cudss"
    return next(b for b in have if b != "cudss")


class _SuperLU:
    # MMD on A^T A: on the 1,536-hexahedron shell (5,784 free dofs) it fills 21x and
    # factorises in 2.6 s where MMD on A^T + A filled 67x and took 27 s (2-core VM,
    # benchmarks/bench_core.py --sizes 8:4 --no-path --backend superlu).
    def __init__(self, A):
        try:
            self.lu = spla.splu(A.tocsc(), permc_spec="MMD_ATA",
                                options={"SymmetricMode": True})
        except RuntimeError as exc:
            raise LinearSolveError(f"SuperLU factorisation failed: {exc} (singular tangent: "
                                   "check that rigid-body motions are constrained)") from exc

    def solve(self, b):
        return self.lu.solve(b)


_PARDISO_BY_PATTERN: dict = {}

PARDISO_PATTERNS = 8
"""At most this many sparsity patterns keep a Pardiso instance: a new pattern frees the
one factorised longest ago (:meth:`_Pardiso._analyse`), so the patterns a solve alternates
stay analysed while a planner's designs (bites on other faces) add new ones."""

PARDISO_MEMORY_FRACTION = 0.25
"""The patterns' Pardiso instances together keep at most this share of the machine's
physical memory (their factors, as Pardiso estimates them after the symbolic analysis);
beyond it the oldest are freed. On a large mesh the patterns that contact re-pairing
makes would otherwise hold several factorisations of gigabytes each."""


def physical_memory_kb() -> float:
    """The machine's physical memory, KB (inf where the system does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 1024.0
    except (ValueError, OSError, AttributeError):
        return float("inf")


def _free_pattern(key) -> None:
    """Free the Pardiso instance (symbolic analysis and factors) of a pattern."""
    old = _PARDISO_BY_PATTERN.pop(key)
    old["solver"].free_memory(everything=True)
    old["freed"], old["owner"] = True, None


def free_shared_patterns() -> int:
    """Free every shared pattern's Pardiso instance (its symbolic analysis and factors; kept
    factorisations stay): for a caller whose next solves use other patterns (a planner's
    next design, its bites on other faces). A pattern used again is analysed again.
    Returns how many held an analysis."""
    n = sum(not e["freed"] for e in _PARDISO_BY_PATTERN.values())
    for key in list(_PARDISO_BY_PATTERN):
        _free_pattern(key)
    return n


RELEASE_OTHER_FACTORS = True
"""Before a pattern's instance factorises, the other patterns' shared instances free their
numeric factors (Pardiso phase 0) and keep only their symbolic analysis: at most one set of
factors of the shared instances is alive (kept ones, :meth:`_Pardiso.keep`, hold their
own). An old factorisation solved again is refactorised first (its owner is gone), to the
same digits. The stages of a surgical run factorise three or more patterns (each stage's
prescribed dofs, a sparse look-ahead's tangent, the whole saddle point): on the default
eye (11,862 hexahedra) each held 197 MB of factors beside its 60 MB analysis
(benchmarks/bench_memory.py; docs/performance.md, "Memory")."""


def _release_factors(entry) -> None:
    """Free the numeric factors of every shared pattern's instance but ``entry``'s."""
    for other in _PARDISO_BY_PATTERN.values():
        if other is not entry and not other["freed"] and other["owner"] is not None:
            other["solver"].free_memory(everything=False)
            other["owner"] = None


PARDISO_IPARM = {1: 1, 2: 2, 8: 0, 10: 8, 11: 0, 13: 0, 21: 1, 25: 2}
"""Pardiso settings (1-based iparm): 1 = 1 (these instead of the defaults), 2 = 2 (METIS
ordering), 8 = 0 (no automatic iterative refinement: with the defaults every back-solve
ran two refinement steps, 2.5x its cost, without a more accurate result; the callers
check residuals and refine where it matters), 10 = 8 (pivot perturbation 1e-8), 11 = 13
= 0 (no scaling or matching: symmetric), 21 = 1 (Bunch-Kaufman pivoting), 25 = 2
(parallel forward/backward solve). Measured on the 12k-hex shell tangent (2 cores):
one back-solve 0.053 s -> 0.016 s, same residual (7e-9)."""


REPRODUCIBLE = True
"""Ask MKL for run-to-run bitwise reproducible results (conditional numerical
reproducibility, branch AUTO) before the first Pardiso call, unless MKL_CBWR already
chose a branch. Pardiso's threaded factorisation is otherwise not reproducible, and the
coarse deformable-band case (whose suture stage has nearby equilibria of its faceted
contact) gave IOPs of 23.42 to 23.74 mmHg from one input in three runs on 2 cores; with
it, the same to all digits (docs/performance.md for its cost)."""

_MKL_CBWR_BRANCH, _MKL_CBWR_BRANCH_OFF, _MKL_CBWR_AUTO = 1, 1, 2


def mkl_cnr_branch(lib) -> int:
    """MKL's current reproducibility branch (1: off, 2: AUTO, 3: COMPATIBLE, ...)."""
    import ctypes

    get = lib.MKL_CBWR_Get
    get.restype, get.argtypes = ctypes.c_int, [ctypes.c_int]
    return int(get(_MKL_CBWR_BRANCH))


def _set_reproducible(lib) -> None:
    import ctypes

    if not REPRODUCIBLE or mkl_cnr_branch(lib) != _MKL_CBWR_BRANCH_OFF:
        return
    put = lib.MKL_CBWR_Set
    put.restype, put.argtypes = ctypes.c_int, [ctypes.c_int]
    status = put(_MKL_CBWR_AUTO)
    if status != 0:
        log.warning("MKL refused the reproducible branch (MKL_CBWR_Set status %d): Pardiso's "
                    "results may differ in the last digits from run to run", status)


_MKL_RUNTIME: dict = {}


def _new_pardiso(pypardiso, mtype: int = -2):
    """A Pardiso instance of matrix type ``mtype`` (-2 real symmetric indefinite, 2 real
    symmetric positive definite) with :data:`PARDISO_IPARM` on the reproducible branch.

    pypardiso looks for MKL's runtime library afresh for every instance
    (``ctypes.util.find_library``, which runs ldconfig and the C compiler, then a recursive
    glob of the environment: 0.3 s an instance on the 2-core machine). The library the first
    instance loaded is handed to the later ones through pypardiso's own setting
    ``PYPARDISO_MKL_RT`` for the time of the call, unless the environment sets it."""
    path = None if "PYPARDISO_MKL_RT" in os.environ else _MKL_RUNTIME.get("path")
    if path is None:
        solver = pypardiso.PyPardisoSolver(mtype=mtype)
        _MKL_RUNTIME.setdefault("path", solver.libmkl._name)
    else:
        os.environ["PYPARDISO_MKL_RT"] = path
        try:
            solver = pypardiso.PyPardisoSolver(mtype=mtype)
        finally:
            del os.environ["PYPARDISO_MKL_RT"]
    _set_reproducible(solver.libmkl)
    for i, v in PARDISO_IPARM.items():
        solver.iparm[i - 1] = v
    return solver


class _Pardiso:
    """MKL Pardiso on the upper triangle: real symmetric indefinite (mtype -2, Bunch-Kaufman
    pivoting) or, with ``mtype`` 2, symmetric positive definite (Cholesky, no pivoting; a
    matrix that is not positive definite fails with LinearSolveError).

    One Pardiso instance is kept per sparsity pattern, so the symbolic analysis
    (ordering, about a third of the factorisation time) is done once per pattern and
    every Newton iteration only refactorises numerically. If another factorisation of
    the same pattern has been made since, ``solve`` refactorises this one first, so an
    old factorisation (kept for an adjoint solve) stays valid. Pardiso may perturb tiny
    pivots; the saddle-point solver checks every residual.
    """

    def __init__(self, A, mtype: int = -2):
        import pypardiso

        self.A = sp.triu(A, format="csr")
        self.A.sort_indices()
        self.mtype = mtype
        key = (self.A.shape[0], self.A.nnz, hash(self.A.indptr.tobytes()),
               hash(self.A.indices.tobytes()), mtype)
        entry = _PARDISO_BY_PATTERN.get(key)
        if entry is None:
            entry = {"solver": _new_pardiso(pypardiso, mtype), "owner": None, "freed": True}
        self.key, self.entry = key, entry
        self._factorize()

    def _analyse(self):
        """Symbolic analysis of this pattern; evicts the oldest patterns beyond
        PARDISO_PATTERNS or beyond PARDISO_MEMORY_FRACTION of the machine's memory
        (patterns change with contact and suture layouts). An evicted pattern is
        analysed again when it is used."""
        while len(_PARDISO_BY_PATTERN) >= PARDISO_PATTERNS:
            _free_pattern(next(iter(_PARDISO_BY_PATTERN)))
        self._call(self.entry["solver"], 11)
        iparm = self.entry["solver"].iparm  # KB: permanent symbolic + numeric factors
        self.entry["kb"] = float(iparm[15]) + float(iparm[16])
        self.entry["freed"] = False
        if not self.entry.get("kept"):
            _PARDISO_BY_PATTERN.pop(self.key, None)
            budget = PARDISO_MEMORY_FRACTION * physical_memory_kb()
            while _PARDISO_BY_PATTERN and (self.entry["kb"] + sum(
                    e.get("kb", 0.0) for e in _PARDISO_BY_PATTERN.values()) > budget):
                _free_pattern(next(iter(_PARDISO_BY_PATTERN)))
            _PARDISO_BY_PATTERN[self.key] = self.entry

    def keep(self):
        """Keep this factorisation for later solves (the adjoint of a stage, solved after
        later stages have factorised the same pattern): it moves into an instance of its
        own, which no later factorisation overwrites and whose memory is freed when this
        object is collected; the pattern's shared instance starts afresh (one more
        symbolic analysis)."""
        import pypardiso

        if self.entry.get("kept"):
            return
        shared = self.entry
        mine = {**shared, "kept": True}
        shared.update(solver=_new_pardiso(pypardiso, self.mtype), owner=None, freed=True)
        self.entry = mine
        if mine["owner"] != id(self):  # overwritten since: factorised again, in its own
            self._factorize()
        weakref.finalize(self, mine["solver"].free_memory, True)

    def _call(self, solver, phase, b=None):
        import pypardiso

        solver.set_phase(phase)
        b = np.zeros((self.A.shape[0], 1)) if b is None else b
        try:
            return solver._call_pardiso(self.A, b)
        except pypardiso.pardiso_wrapper.PyPardisoError as exc:
            raise LinearSolveError(f"Pardiso failed (phase {phase}): {exc}") from exc

    def _factorize(self):
        if RELEASE_OTHER_FACTORS and not self.entry.get("kept"):
            _release_factors(self.entry)
        if _PARDISO_BY_PATTERN.get(self.key) is self.entry:  # the most recently used last
            _PARDISO_BY_PATTERN[self.key] = _PARDISO_BY_PATTERN.pop(self.key)
        if self.entry["freed"]:
            self._analyse()
        self.entry["owner"] = None
        self._call(self.entry["solver"], 22)
        if self.mtype == 2 and self.entry["solver"].iparm[22] > 0:  # negative pivots
            raise LinearSolveError(f"Pardiso: {int(self.entry['solver'].iparm[22])} negative "
                                   "pivots of a matrix factorised as positive definite")
        self.entry["owner"] = id(self)

    def solve(self, b):
        if self.entry["owner"] != id(self):
            self._factorize()
        x = self._call(self.entry["solver"], 33, np.asfortranarray(b.reshape(b.shape[0], -1)))
        return x.reshape(b.shape)  # b (n,) or (n, k): several right-hand sides at once


SPD = "+spd"
"""Suffix of a backend name (``"pardiso+spd"``; ``"+spd"`` alone: the default backend) that
asks :func:`factorize` for a symmetric positive definite factorisation where the backend
has one (Pardiso's Cholesky, mtype 2), with Pardiso's symmetric indefinite factorisation
(mtype -2) where the matrix is not positive definite. SuperLU and cuDSS ignore it."""


def positive_definite(backend: str | None) -> str:
    """``backend`` (None: the default) asking for a positive definite factorisation (SPD)."""
    return backend if backend and backend.endswith(SPD) else f"{backend or ''}{SPD}"


FACTORISATIONS = {"cholesky": 0, "indefinite": 0, "cholesky_failed": 0}
"""Numeric factorisations made through :func:`factorize` since start, by kind (Pardiso:
``cholesky`` mtype 2, ``indefinite`` mtype -2 and the other backends; a Cholesky that met
a matrix not positive definite counts in ``cholesky_failed`` and again as the indefinite
factorisation that replaced it). Read by the benchmarks (eyefem.solve.augmented)."""


def factorize(A: sp.spmatrix, backend: str | None = None, on_indefinite: str = "fallback"):
    """Factorise a square sparse matrix; returns an object with ``solve(b)``.

    ``backend`` with the suffix :data:`SPD` tries a positive definite factorisation first;
    where the matrix is not positive definite, ``on_indefinite`` = "fallback" factorises it
    as symmetric indefinite and "raise" raises NegativeCurvature."""
    backend = backend or ""
    spd = backend.endswith(SPD)
    backend = (backend[:-len(SPD)] if spd else backend) or default_backend()
    if backend == "pardiso":
        if spd:
            try:
                fact = _Pardiso(A, mtype=2)
                FACTORISATIONS["cholesky"] += 1
                return fact
            except LinearSolveError as exc:
                FACTORISATIONS["cholesky_failed"] += 1
                if on_indefinite == "raise":
                    raise NegativeCurvature(
                        f"the tangent is not positive definite ({exc})") from exc
                log.debug("Cholesky factorisation failed (%s): symmetric indefinite instead", exc)
        FACTORISATIONS["indefinite"] += 1
        return _Pardiso(A)
    FACTORISATIONS["indefinite"] += 1
    if backend == "superlu":
        return _SuperLU(A)
    if backend == "cudss":
        from eyefem.solve.cudss import CuDSS

        return CuDSS(A)
    raise ValueError(f"linear solver backend '{backend}': unknown; choose from {available_backends()}")


@dataclasses.dataclass
class SaddlePointSolver:
    """Factorised saddle-point tangent; ``solve(f, g)`` returns (x, y).

    Args:
      K: (n, n) sparse displacement block (may already include B D B^T, see ``augmented``).
      B: (n, m) sparse coupling to the multipliers (or None when there are none).
      D: (m,) augmentation weights used in K_aug = K + B D B^T.
      low_rank: list of (alpha, v (n,)) rank-one updates alpha v v^T of K.
      augmented: True if K already includes B D B^T (assembled element by element).
      backend: factorisation backend.
      tol: relative residual required of every solve.
      cg_rtol: the Schur-complement CG stops at this constraint residual, relative.
      shift: the displacement block is factorised as K_aug + shift |diag(K) + shift_aug
        diag(B D B^T)| (a Levenberg-Marquardt shift for modified Newton steps; 0: exact).
      shift_aug: the share of the augmentation's diagonal in the shift (1: the shift is
        relative to diag(K_aug); the assembler passes 1e4 / beta, so the shifted system,
        and hence the damped step, does not depend on the augmentation strength).
      reuse: a solver of the same K, B, D, shift whose factorisation (and low-rank
        solves) this one shares; ``low_rank`` then extends that solver's (see
        ``plus_low_rank``).
      extra: a sparse symmetric (n, n) term added to the factorised block after the
        shift (see ``plus_sparse``), or None.
      indefinite: "kkt" solves an indefinite system exactly (direct factorisation of the
        whole saddle point), "raise" raises NegativeCurvature.
      refine: at most this many refinement steps of a solve whose residual exceeds
        refine_above (well above the roundoff of a good factorisation, 1e-9..1e-8 on the
        12k shell, so that a sound solve costs nothing extra).
    """

    K: sp.spmatrix
    B: sp.spmatrix | None
    D: np.ndarray | None
    low_rank: list = dataclasses.field(default_factory=list)
    augmented: bool = True
    backend: str | None = None
    tol: float = 1e-9
    cg_rtol: float = 1e-12
    max_uzawa: int = 30
    shift: float = 0.0
    indefinite: str = "kkt"
    refine: int = 3
    refine_above: float = 1e-7
    shift_aug: float = 1.0
    reuse: "SaddlePointSolver | None" = None
    extra: sp.spmatrix | None = None

    def __post_init__(self):
        if self.reuse is not None:
            self.K_aug, self.fact = self.reuse.K_aug, self.reuse.fact
        else:
            K = self.K
            aug = None
            if self.B is not None:
                aug = np.asarray(self.B.multiply(self.B) @ self.D).ravel()  # diag(B D B^T)
                if not self.augmented:
                    K = K + self.B @ sp.diags(self.D) @ self.B.T
            if self.shift:
                d = K.diagonal() if aug is None else K.diagonal() - (1.0 - self.shift_aug) * aug
                K = K + self.shift * sp.diags(np.abs(d))
            if self.extra is not None:
                K = K + self.extra
            self.K_aug = sp.csr_matrix(K)
            self.fact = factorize(self.K_aug, self.backend,
                                  "raise" if self.indefinite == "raise" else "fallback")
        if self.low_rank:
            V = np.stack([v for _, v in self.low_rank], axis=1)  # (n, r)
            a = np.array([al for al, _ in self.low_rank])
            self.V, self.alpha = V, a
            done = len(self.reuse.low_rank) if self.reuse is not None else 0
            self.KiV = self.reuse.KiV if done else np.zeros((len(V), 0))
            if done < V.shape[1]:  # all new right-hand sides at once
                self.KiV = np.hstack([self.KiV, self.fact.solve(V[:, done:]).reshape(len(V), -1)])
            cap = np.diag(1.0 / a) + V.T @ self.KiV
            self.cap_inv = np.linalg.inv(cap)
        self.n_solves = 0

    def keep(self) -> "SaddlePointSolver":
        """Keep the factorisation out of the Pardiso instance its pattern shares (see
        ``_Pardiso.keep``; other backends hold their own already). Returns self."""
        keep = getattr(self.fact, "keep", None)
        if keep is not None:
            keep()
        return self

    def plus_low_rank(self, extra: list) -> "SaddlePointSolver":
        """This tangent plus further rank-one terms (alpha, v (n,)), on the same
        factorisation (Woodbury: one back-solve per new term, all at once)."""
        return dataclasses.replace(self, low_rank=list(self.low_rank) + list(extra), reuse=self)

    def plus_sparse(self, S: sp.spmatrix) -> "SaddlePointSolver":
        """This tangent plus a sparse symmetric (n, n) S, factorised anew (for many
        rank-one terms, whose dense Woodbury columns would not fit in memory); the
        shift is that of this tangent, and its own low-rank terms stay."""
        extra = S if self.extra is None else self.extra + S
        return dataclasses.replace(self, reuse=None, extra=extra)

    def _solve_aug(self, b):
        x = self.fact.solve(b)
        if self.low_rank:
            x = x - self.KiV @ (self.cap_inv @ (self.V.T @ x))
        return x

    def _schur_cg(self, f, g, rtol=None):
        """CG on the Schur complement; f (n,) or (n, k), g (m,) or (m, k): k right-hand
        sides iterated together (one back-solve with k columns per iteration), each with
        its own step lengths and stopping test (``rtol``, default ``cg_rtol``)."""
        rtol = self.cg_rtol if rtol is None else rtol
        if getattr(self, "_kkt", None) is not None:  # negative curvature met before
            return self._kkt_solve(f, g)
        B, D = self.B, self.D
        one = f.ndim == 1
        f, g = f.reshape(len(f), -1), g.reshape(len(g), -1)
        Dc = D[:, None]
        x = self._solve_aug(f + B @ (Dc * g))  # y = 0
        y = np.zeros((B.shape[1], f.shape[1]))
        r = B.T @ x - g  # r = rhs - S y of S y = B^T x0 - g
        z = Dc * r
        p = z.copy()
        rz = np.einsum("ij,ij->j", r, z)
        scale = np.maximum(np.maximum(np.linalg.norm(Dc * g, axis=0),
                                      np.linalg.norm(Dc * (B.T @ x), axis=0)), 1e-300)
        for it in range(self.max_uzawa + 1):
            act = np.sqrt(np.abs(rz)) > rtol * scale
            if not act.any():
                break
            if it == self.max_uzawa:
                log.debug("Schur CG: not converged in %d iterations (%.1e relative)",
                          it, float(np.max(np.sqrt(np.abs(rz)) / scale)))
                break
            w = self._solve_aug(B @ p[:, act])  # K_aug^-1 B p
            Sp = B.T @ w
            pSp = np.einsum("ij,ij->j", p[:, act], Sp)
            if np.any(pSp <= 0):
                if self.indefinite == "raise":
                    raise NegativeCurvature("negative curvature of the tangent")
                log.debug("Schur CG: negative curvature; direct solve of the saddle point")
                X, Y = self._kkt_solve(f, g)
                return (X[:, 0], Y[:, 0]) if one else (X, Y)
            alpha = rz[act] / pSp
            y[:, act] += alpha * p[:, act]
            x[:, act] -= alpha * w
            r[:, act] -= alpha * Sp
            z = Dc * r
            rz_new = np.einsum("ij,ij->j", r, z)
            p[:, act] = z[:, act] + (rz_new[act] / rz[act]) * p[:, act]
            rz[act] = rz_new[act]
        self.iterations = it
        return (x[:, 0], y[:, 0]) if one else (x, y)

    def _kkt_solve(self, f, g):
        """Direct solve of the whole saddle-point system [[K_aug, B], [B^T, -eps]] (symmetric
        indefinite factorisation; eps ~ 1e-12 of K's diagonal keeps the pivots defined),
        with the low-rank terms by Woodbury and two refinements against the exact system.
        Used when K_aug is indefinite (the Schur complement CG meets negative curvature)."""
        B = self.B
        n, m = B.shape
        if getattr(self, "_kkt", None) is None:
            eps = 1e-12 * float(np.abs(self.K_aug.diagonal()).mean())
            A = sp.bmat([[self.K_aug, B], [B.T, -eps * sp.eye(m)]], format="csr")
            self._kkt = factorize(A, (self.backend or "").removesuffix(SPD) or None)
            if self.low_rank:
                Vk = np.vstack([self.V, np.zeros((m, self.V.shape[1]))])
                self._kkt_KiV = self._kkt.solve(Vk).reshape(Vk.shape)
                self._kkt_cap = np.linalg.inv(np.diag(1.0 / self.alpha) + Vk.T @ self._kkt_KiV)

        def apply_inverse(r):
            z = self._kkt.solve(r)
            if self.low_rank:
                z = z - self._kkt_KiV @ (self._kkt_cap @ (self.V.T @ z[:n]))
            return z

        D = self.D.reshape(-1, *([1] * (g.ndim - 1)))
        rhs = np.concatenate([f + B @ (D * g), g])
        z = apply_inverse(rhs)
        for _ in range(2):
            x, y = z[:n], z[n:]
            kx = self.K_aug @ x
            if self.low_rank:
                kx = kx + self.V @ (self.alpha.reshape(-1, *([1] * (g.ndim - 1))) * (self.V.T @ x))
            res = rhs - np.concatenate([kx + B @ y, B.T @ x])
            z = z + apply_inverse(res)
        self.iterations = -1
        return z[:n], z[n:]

    def _apply_K(self, x):
        """(K + low rank) x, without the augmentation."""
        y = self.K_aug @ x
        if self.B is not None:
            y = y - self.B @ (self.D * (self.B.T @ x))
        if self.low_rank:
            y = y + self.V @ (self.alpha * (self.V.T @ x))
        return y

    def _solve_once(self, f, g, rtol=None):
        if self.B is None:
            return self._solve_aug(f), np.zeros((0,) + f.shape[1:])
        return self._schur_cg(f, g, rtol)

    def approximate_solve(self, f, g=None, rtol=None):
        """One pass of :meth:`solve` without its residual check and refinement, the Schur
        CG stopped at ``rtol`` relative (default ``cg_rtol``): the preconditioner of an
        outer refinement that computes its own residuals against the exact tangent
        (eyefem.solve.adjoint.adjoint_solve). f (n,) or (n, k), g (m,) or (m, k).
        Returns (x, y) like f and g."""
        self.n_solves += 1
        return self._solve_once(f, self._constraint_rhs(f, g), rtol)

    def _constraint_rhs(self, f, g):
        """g, or zeros (m,) / (m, k) like f's columns where g is None."""
        m = 0 if self.B is None else self.B.shape[1]
        return np.zeros((m,) + f.shape[1:]) if g is None else g

    def _residual(self, f, g, x, y):
        """Residuals (K x + B y - f, B^T x - g) and the first's norm relative to the size
        of the terms summed (the augmented K x bounds the roundoff)."""
        res = self._apply_K(x) - f
        cres = np.zeros(0)
        if self.B is not None:
            res = res + self.B @ y
            cres = self.B.T @ x - g
        scale = max(np.linalg.norm(f), np.linalg.norm(self.K_aug @ x),
                    np.linalg.norm(self.B @ y) if self.B is not None else 0.0, 1e-300)
        return res, cres, np.linalg.norm(res) / scale

    def solve(self, f, g=None):
        """Solve the saddle-point system; returns (x (n,), y (m,)), or (x (n, k), y (m, k))
        for k right-hand sides f (n, k), g (m, k) solved together.

        Conjugate gradients on the Schur complement S = B^T K_aug^-1 B of the augmented
        system, preconditioned by D (S is close to D^-1): one back-solve per iteration.
        Falls back to a direct symmetric-indefinite factorisation of the whole saddle-point
        system if S shows negative curvature (K_aug indefinite). A residual above
        ``refine_above`` (Pardiso's perturbed pivots on a badly conditioned tangent) is
        refined against the exact system, up to ``refine`` times, while that lowers it.
        """
        g = self._constraint_rhs(f, g)
        x, y = self.approximate_solve(f, g)
        if f.ndim == 1:
            return self._checked(f, g, x, y)
        cols = [self._checked(f[:, j], g[:, j], x[:, j], y[:, j]) for j in range(f.shape[1])]
        return np.stack([c[0] for c in cols], 1), np.stack([c[1] for c in cols], 1)

    def _checked(self, f, g, x, y):
        """(x, y) of one right-hand side, refined while its residual is above
        ``refine_above``; LinearSolveError if it stays above 1e-6."""
        res, cres, rel = self._residual(f, g, x, y)
        for _ in range(self.refine):
            if not rel > self.refine_above:
                break
            dx, dy = self._solve_once(-res, -cres)
            res2, cres2, rel2 = self._residual(f, g, x + dx, y + dy)
            if not rel2 < rel:
                break
            x, y, res, cres, rel = x + dx, y + dy, res2, cres2, rel2
        if not np.isfinite(rel) or rel > 1e-6:
            raise LinearSolveError(f"linear solve residual {rel:.2e} relative (backend "
                                   f"{(self.backend or '').removesuffix(SPD) or default_backend()}"
                                   "): "
                                   "the tangent is singular "
                                   "or badly conditioned")
        if rel > self.tol:
            log.debug("linear solve residual %.2e relative, constraint %.2e",
                      rel, np.linalg.norm(cres))
        return x, y
