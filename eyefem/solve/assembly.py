"""Assembly of local gradients and Hessians into the reduced sparse Newton system.

The reduced system keeps the free primal dofs (displacements not prescribed) and the
multipliers. A CSR pattern and a slot map (local entry -> CSR data position) are built
once per set of prescribed dofs; each Newton iteration only runs ``np.bincount``.
Multipliers local to one item (Q1P0 element pressures) are condensed element by
element: the displacement block is assembled as K + d b b^T (see linsolve).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp

from eyefem.fem.terms import Term
from eyefem.solve.linsolve import SaddlePointSolver
from eyefem.solve.model import Model

SHIFT_BETA = 1e4
"""Augmentation strength whose diagonal a Levenberg-Marquardt shift is relative to (the
shift levels of the Newton solver were set with beta = 1e4)."""


@dataclasses.dataclass
class _TermPattern:
    prim: np.ndarray  # (k_p,) local positions of primal dofs
    mult: int | None  # local position of the multiplier
    k_slots: np.ndarray  # (n * k_p * k_p,) CSR data slot (nnz: a dropped entry)
    b_slots: np.ndarray | None
    b_valid: np.ndarray | None


@dataclasses.dataclass(frozen=True, eq=False)
class LocalBlocks:
    """One term's local blocks at a state (host arrays, n items of k local dofs).

    g (n, k) local gradients; H (n, k_p, k_p) primal Hessians with the multiplier condensed
    (H_pp + d b b^T), or (n, k, k) for a dynamic term or a Gauss-Newton Hessian; b (n, k_p)
    and d (n,) the multiplier column and its weight (None without multipliers); low_rank
    the term's rank-one parts (alpha, v (n_p,)) on the free primal dofs."""

    term: Term
    g: np.ndarray
    H: np.ndarray
    b: np.ndarray | None
    d: np.ndarray | None
    low_rank: tuple


PATTERN_CHUNK = 2000
"""Items per chunk while the CSR pattern and the slot maps are built (:class:`Assembler`):
the keys of one chunk's local entries are alive at a time, not every term's at once."""


def _chunk_keys(rd, lo, hi, n):
    """Keys row * n + col (int64, (hi - lo) * k * k) of the local entries of items lo:hi
    (rd (items, k): reduced dof indices, -1 where not free), -1 where either is not free."""
    r = rd[lo:hi, :, None].astype(np.int64)
    c = rd[lo:hi, None, :]
    key = r * n + c
    key[(r < 0) | (c < 0)] = -1
    return key.ravel()


def _sorted_unique(a):
    """The sorted distinct values of a 1-D array a (sorted in place; numpy 2's np.unique
    hashes first, about ten times slower here)."""
    a.sort()
    return a[np.concatenate([[True], a[1:] != a[:-1]])] if len(a) else a


def _pattern_of(rds, n):
    """The CSR pattern (indptr (n + 1,), indices) of the local entries of every term's
    reduced dofs ``rds`` (items, k) and, per term, each entry's slot (its position in
    ``indices``; len(indices) for an entry on a dof that is not free), in chunks of
    PATTERN_CHUNK items: the sorted distinct keys and each entry's position among them,
    as np.unique(keys, return_inverse=True) of all entries at once gave them, without
    every key and np.unique's sort of them alive together. Case 1's tightening stage on
    the default eye (11,862 hexahedra): Assembler() allocates 140 MB at its peak instead
    of 616 MB, in 10.4 s against 14.3 s (shared 2-core machine), the same pattern and
    slots (docs/performance.md, "Memory")."""
    parts = []
    for rd in rds:
        for lo in range(0, len(rd), PATTERN_CHUNK):
            key = _chunk_keys(rd, lo, lo + PATTERN_CHUNK, n)
            parts.append(_sorted_unique(key[key >= 0]))
    uniq = _sorted_unique(np.concatenate(parts)) if parts else np.zeros(0, np.int64)
    del parts
    itype = np.int32 if max(n, len(uniq)) < 2 ** 31 else np.int64
    indptr = np.zeros(n + 1, itype)
    np.cumsum(np.bincount(uniq // n, minlength=n), out=indptr[1:])
    indices = (uniq % n).astype(itype)
    slots = []
    for rd in rds:
        k = rd.shape[1]
        out = np.empty(len(rd) * k * k, itype)  # int32 halves the kept slot maps
        for lo in range(0, len(rd), PATTERN_CHUNK):
            key = _chunk_keys(rd, lo, lo + PATTERN_CHUNK, n)
            s = np.searchsorted(uniq, key)
            s[key < 0] = len(uniq)
            out[lo * k * k: lo * k * k + len(s)] = s
        slots.append(out)
    return indptr, indices, slots


class Assembler:
    """Scatter of all static terms of a model into K (free primal) and B (free primal x mult).

    Args:
      model: the model.
      prescribed: (n_dof,) bool, True for prescribed displacement dofs.
      beta: augmentation strength of the element-wise condensation (about 1/beta
        contraction per Uzawa iteration).
    """

    def __init__(self, model: Model, prescribed: np.ndarray, beta: float = 1e4):
        self.model = model
        self.beta = beta
        n = model.n_dof
        mult = np.zeros(n, bool)
        mult[model.multiplier_dofs] = True
        if np.any(prescribed & mult):
            raise ValueError("a Lagrange multiplier dof cannot be prescribed")
        self.prescribed = prescribed
        self.free_primal = np.nonzero(~prescribed & ~mult)[0]
        self.mult = np.nonzero(mult)[0]
        self.red = np.full(n, -1, np.int64)
        self.red[self.free_primal] = np.arange(len(self.free_primal))
        self.mred = np.full(n, -1, np.int64)
        self.mred[self.mult] = np.arange(len(self.mult))
        self.n_p, self.n_m = len(self.free_primal), len(self.mult)
        rds, brow, bcol = [], [], []
        pats, boffs = {}, 0
        staged = []
        for t in model.terms:
            if getattr(t, "dynamic", False):
                continue
            k = t.dofs.shape[1]
            ms = list(t.multiplier_slots)
            if len(ms) > 1:
                raise ValueError(f"term '{t.name}': at most one multiplier per item is supported")
            prim = np.array([i for i in range(k) if i not in ms], np.int64)
            rd = self.red[t.dofs[:, prim]]  # (n, kp)
            if self.n_p < 2 ** 31:  # halves the pattern's temporaries
                rd = rd.astype(np.int32)
            rds.append(rd)
            staged.append((t.name, prim, ms[0] if ms else None))
            if ms:
                bc = np.repeat(self.mred[t.dofs[:, ms[0]]], len(prim))
                br = rd.ravel()
                bvalid = np.nonzero(br >= 0)[0]
                brow.append(br[bvalid]); bcol.append(bc[bvalid])
                pats[t.name] = (bvalid, boffs)
                boffs += len(bvalid)
        self.indptr, self.indices, slots = _pattern_of(rds, self.n_p)
        del rds
        if brow:
            br, bc = np.concatenate(brow), np.concatenate(bcol)
            self.B_pattern = sp.csr_matrix((np.arange(len(br), dtype=np.float64) + 1, (br, bc)),
                                           shape=(self.n_p, self.n_m))
            order = np.asarray(self.B_pattern.data - 1, dtype=np.int64)  # data position -> entry
            binv = np.empty_like(order)
            binv[order] = np.arange(len(order))
        self.patterns: dict[str, _TermPattern] = {}
        for (name, prim, m), k_slots in zip(staged, slots):
            bs = bv = None
            if name in pats:
                bv, boff = pats[name]
                bs = binv[boff: boff + len(bv)]
            self.patterns[name] = _TermPattern(prim, m, k_slots, bs, bv)

    def assemble(self, q, theta, active=None, pressure_stiffness=True, gauss_newton=False,
                 beta=None, model: Model | None = None):
        """Residual (n_dof,) and the factorisation-ready tangent pieces at q; with
        ``pressure_stiffness`` False the tangent leaves out the Hessians of follower
        pressures (terms marked ``pressure_stiffness``; their low-rank parts stay); with
        ``gauss_newton`` the terms that have one use their Gauss-Newton Hessian
        (``Term.grad_hess_gauss_newton``: penalty contact without the surface curvature);
        ``beta`` overrides the augmentation strength (0: K without B D B^T, D = 0, for
        products with the exact tangent free of the augmentation's cancellation);
        ``model`` assembles another model of the same layout than the one the assembler
        holds (a load path's stages share one assembler: the adjoint of an earlier stage).
        The kernels' part is :meth:`local_blocks`, the rest :meth:`scatter` (one term's
        blocks alive at a time).

        Returns: (r, K (n_p, n_p) CSR including the condensation, B (n_p, n_m) or None,
        D (n_m,) or None, low_rank list of (alpha, v (n_p,))).
        """
        model = self.model if model is None else model
        return self.scatter(model.n_dof, self._blocks(model, q, theta, active, gauss_newton,
                                                      beta), pressure_stiffness)

    def local_blocks(self, q, theta, active=None, gauss_newton=False, beta=None,
                     model: Model | None = None) -> list[LocalBlocks]:
        """Every active term's local blocks at q (the element kernels of :meth:`assemble`,
        evaluated on the host's arrays; arguments as there)."""
        model = self.model if model is None else model
        return list(self._blocks(model, q, theta, active, gauss_newton, beta))

    def _blocks(self, model, q, theta, active, gauss_newton, beta):
        for t in model._active(active):
            b = d = None
            if gauss_newton and t.grad_hess_gauss_newton is not None:
                g, H = model.local_grad_hess_gauss_newton(t, q, theta)
            elif getattr(t, "dynamic", False):
                g, H = model.local_grad_hess(t, q, theta)
            else:
                g, H, b, d = model.local_grad_hess_condensed(
                    t, q, theta, self.beta if beta is None else beta)
            low_rank = tuple((al, np.asarray(v)[self.free_primal])
                             for al, v in t.low_rank(q, theta[t.name], t.data, t.dofs))
            yield LocalBlocks(t, g, H, b, d, low_rank)

    def scatter(self, n_dof: int, blocks, pressure_stiffness=True):
        """The residual and tangent pieces of :meth:`assemble` from the terms' local blocks
        (an iterable of LocalBlocks, e.g. :meth:`local_blocks`)."""
        r = np.zeros(n_dof)
        kdata = np.zeros(len(self.indices))
        bdata = np.zeros(self.B_pattern.nnz) if self.n_m else None
        D = np.zeros(self.n_m) if self.n_m else None
        extra = []
        low_rank = []
        for blk in blocks:
            t = blk.term
            if getattr(t, "dynamic", False):
                extra.append(self._coo(t, blk.H))
            else:
                p = self.patterns[t.name]
                if p.mult is not None:
                    D[self.mred[t.dofs[:, p.mult]]] = blk.d
                    bdata += np.bincount(p.b_slots, blk.b.ravel()[p.b_valid],
                                         minlength=len(bdata))
                if pressure_stiffness or not t.pressure_stiffness:
                    kdata += np.bincount(p.k_slots, blk.H.ravel(), minlength=len(kdata) + 1)[:-1]
            r += np.bincount(t.dofs.ravel(), blk.g.ravel(), minlength=n_dof)
            low_rank.extend(blk.low_rank)
        K = sp.csr_matrix((kdata, self.indices, self.indptr), shape=(self.n_p, self.n_p))
        for e in extra:
            K = K + e
        B = None
        if self.n_m:
            B = sp.csr_matrix((bdata, self.B_pattern.indices, self.B_pattern.indptr),
                              shape=(self.n_p, self.n_m))
        return r, K, B, D, low_rank

    def _coo(self, t: Term, H):
        """Sparse matrix of a dynamic (re-paired) term's local blocks on the free primal dofs."""
        return self.coo(t.dofs, H)

    def coo(self, dofs, H):
        """Sparse (n_p, n_p) matrix of local blocks H (n, k, k) on the global dofs (n, k);
        entries on prescribed dofs or multipliers are dropped."""
        rd = self.red[dofs]
        k = rd.shape[1]
        r = np.repeat(rd, k, axis=1).ravel()
        c = np.tile(rd, (1, k)).ravel()
        ok = (r >= 0) & (c >= 0)
        return sp.csr_matrix((H.ravel()[ok], (r[ok], c[ok])), shape=(self.n_p, self.n_p))

    def solver(self, K, B, D, low_rank, backend=None, **kw) -> SaddlePointSolver:
        """Factorise the assembled tangent (kw: SaddlePointSolver's shift, indefinite).
        A shift is relative to the diagonal of the tangent augmented at SHIFT_BETA, so that
        a damped step does not depend on ``beta``."""
        return SaddlePointSolver(K, B, D, low_rank, augmented=True, backend=backend,
                                 shift_aug=SHIFT_BETA / self.beta, **kw)

    def reduce(self, v):
        """Split a global vector (n_dof,) into (free primal (n_p,), multipliers (n_m,))."""
        return v[self.free_primal], v[self.mult]

    def expand(self, x, y):
        """Global vector (n_dof,) from free primal and multiplier parts (prescribed = 0);
        (n_dof, k) from parts (n_p, k), (n_m, k)."""
        out = np.zeros((self.model.n_dof,) + np.shape(x)[1:])
        out[self.free_primal] = x
        out[self.mult] = y
        return out
