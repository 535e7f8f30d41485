"""The surgical outcomes, each defined once as a function of the state.

A state's outcomes (:func:`outcomes`): IOP, cavity volume, axial length, buckle
indentation, suture force and the clinical optics (corneal power and astigmatism,
anterior chamber depth; eyefem.eye.optics); a buckle body adds its own (a band's tension
and shortening). The outcomes of an operation are changes from the pressurised
pre-operative eye (:func:`changes`: axial length, refraction, corneal power, anterior
chamber depth). Each is written once with jax.numpy (:func:`cavity_iop_mmhg`,
:func:`indentation`, :func:`suture_force`, :func:`eye_optics`, :func:`changes`), so the
reported value (numpy, :func:`outcomes`) and its adjoint gradient (:func:`outcome_function`,
eyefem.eye.design) come from the same functions.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from eyefem.eye import optics
from eyefem.eye.parts import SurgeryParts, buckle_coords_at
from eyefem.eye.sutures import ray_face_intersection
from eyefem.fem.bars import bilinear
from eyefem.fem.cavity import cavity_pressures
from eyefem.fem.mesh import hex_geometry, quad_shape
from eyefem.fem.units import KPA, MMHG


BAND_QUADRATURE = 6
"""Gauss points per face direction of the area weights of :func:`band_area_weights`: a
band's edge is sampled at 1/6 of an element, not at the nodes."""


@functools.partial(jax.tree_util.register_dataclass, data_fields=["ids", "weights"],
                   meta_fields=["area_mm2"])
@dataclasses.dataclass(frozen=True)
class BandWeights:
    """Area weights of nodes over a band of a surface: ids (k,), weights (k,) summing to 1,
    and the band's reference area, mm^2."""

    ids: np.ndarray
    weights: np.ndarray
    area_mm2: float


def band_area_weights(parts: SurgeryParts, beside: bool,
                      n_gauss: int = BAND_QUADRATURE) -> BandWeights:
    """Area weights of the outer scleral nodes over a band of the outer sclera: under the
    buckle's central half (``beside`` False: |a| < w/4) or 1.5-3 mm beside its edges (True:
    w/2 + 1.5 < |a| < w/2 + 3), a the across coordinate of
    eyefem.eye.parts.buckle_coords_at and w the buckle's width (mm). The bands are bounded
    at Gauss points (n_gauss^2 per reference face), not at nodes. Weight of node i: the
    integral over the band of its bilinear shape function, normalised to sum 1. ValueError
    where the band holds no Gauss point."""
    mesh, b = parts.eye.mesh, parts.buckle
    faces = mesh.face_set("eye/sclera_outer")
    g, w = np.polynomial.legendre.leggauss(n_gauss)
    xi = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    wg = np.outer(w, w).ravel()
    N, dN = quad_shape(xi)  # (G, 4), (G, 4, 2)
    Xf = mesh.nodes[faces]  # (F, 4, 3)
    xg = np.einsum("gk,fkd->fgd", N, Xf)
    dA = np.linalg.norm(np.cross(np.einsum("gk,fkd->fgd", dN[..., 0], Xf),
                                 np.einsum("gk,fkd->fgd", dN[..., 1], Xf)), axis=-1) * wg
    a, ok = buckle_coords_at(parts, xg.reshape(-1, 3))
    a, ok = np.abs(a).reshape(dA.shape), ok.reshape(dA.shape)
    inside = ok & ((a > b.width / 2 + 1.5) & (a < b.width / 2 + 3.0) if beside
                   else a < b.width / 4)
    if not inside.any():
        where = "beside" if beside else "under"
        raise ValueError(f"indentation: no part of the outer sclera lies {where} the buckle "
                         f"(width {b.width} mm); refine the mesh")
    nodal = np.einsum("fg,gk->fk", dA * inside, N)
    ids, inv = np.unique(faces, return_inverse=True)
    wn = np.bincount(inv.ravel(), nodal.ravel(), minlength=len(ids))
    keep = wn > 0
    return BandWeights(ids[keep], wn[keep] / wn.sum(), float(wn.sum()))


@functools.partial(jax.tree_util.register_dataclass, data_fields=["ids", "weights"],
                   meta_fields=[])
@dataclasses.dataclass(frozen=True)
class SurfacePoint:
    """A point of a mesh surface as a fixed combination of node positions: ids (k,) and
    weights (k,), the bilinear shape functions of the face it lies in at its place."""

    ids: np.ndarray
    weights: np.ndarray

    def at(self, x):
        """Its position (3,) for node positions x (n_nodes, 3) (numpy or JAX)."""
        return self.weights @ x[self.ids]


def axis_point(mesh, anterior: bool) -> SurfacePoint:
    """Where the optical axis (z, through the origin) leaves the eye's outer surface
    (face set "eye/outer"): the corneal apex (``anterior``) or the outer posterior pole.
    A node on a mesh with an even number of elements per patch edge; on an odd one the
    axis crosses a face's middle, and the point interpolates its four nodes."""
    faces = mesh.face_set("eye/outer")
    hit = ray_face_intersection(mesh.nodes, faces, np.zeros(3),
                                np.array([0.0, 0.0, 1.0 if anterior else -1.0]))
    if hit is None:
        raise ValueError("eye outcomes: the optical axis misses the eye's outer surface")
    return SurfacePoint(faces[hit[0]].copy(), np.asarray(bilinear(hit[1]), float))


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["under", "beside", "apex", "pole", "cornea"],
                   meta_fields=["cornea_zone_mm", "lens_pole", "n_nodes"])
@dataclasses.dataclass(frozen=True)
class OutcomeNodes:
    """The node ids the geometric outcomes read (fixed for one eye mesh).

    Attributes: under, beside: area weights of the outer scleral nodes over the band under
    the buckle's central half and over those 1.5-3 mm beside it (:func:`band_area_weights`);
    apex, pole: corneal apex and outer posterior pole on the optical axis
    (:func:`axis_point`); cornea: the anterior corneal nodes
    of the fit zone (cornea_zone_mm across); lens_pole: the lens's anterior pole; n_nodes:
    nodes of the mesh (the displacement block of q).
    """

    under: BandWeights
    beside: BandWeights
    apex: SurfacePoint
    pole: SurfacePoint
    cornea: np.ndarray
    cornea_zone_mm: float
    lens_pole: int
    n_nodes: int


def outcome_nodes(parts: SurgeryParts) -> OutcomeNodes:
    """The outcome node sets of the parts' eye and buckle. The indentation reads the
    buckle's cross-section (encircling: all around; segmental: within 2 mm of the sponge
    centre, on its side of the globe); ValueError where the mesh has no scleral face under
    or beside the buckle."""
    mesh = parts.eye.mesh
    under, beside = band_area_weights(parts, False), band_area_weights(parts, True)
    cornea, zone = optics.cornea_zone(mesh)
    return OutcomeNodes(under, beside, axis_point(mesh, True), axis_point(mesh, False),
                        cornea, zone,
                        optics.lens_anterior_pole(mesh), int(mesh.n_nodes))


def positions(X, q, ids):
    """Current positions (k, 3) of the nodes ids: reference X (n_nodes, 3) + displacement."""
    return X[ids] + q[: 3 * len(X)].reshape(-1, 3)[ids]


def indentation(X, q, nodes: OutcomeNodes):
    """Buckle indentation height, mm: the mean outer radius of the sclera beside the buckle
    minus that under its central half, each mean weighted by area
    (:func:`band_area_weights`: the bands' edges fall between the nodes, so the outcome
    does not jump with which nodes a band holds on a given mesh)."""
    r = lambda bw: jnp.linalg.norm(positions(X, q, bw.ids), axis=1) @ bw.weights  # noqa: E731
    return r(nodes.beside) - r(nodes.under)


def cavity_pressure(q, params, data, dofs):
    """The closed cavity's pressure, MPa (JAX): its first cavity's, from its volume law
    (params, data, dofs: the FluidCavity's). The IOP of every outcome and of the
    timeline's carried steps (eyefem.eye.simulators.TimelineSimulator, which also moves
    the regulation's history on with it)."""
    return cavity_pressures(q, params, data, dofs)[0][0]


def cavity_iop_mmhg(q, params, data, dofs):
    """The closed cavity's pressure (:func:`cavity_pressure`), mmHg (JAX)."""
    return cavity_pressure(q, params, data, dofs) / MMHG


def most_loaded_bar(sutures, q, params) -> int:
    """The suture bar with the largest axial force at state q (n_dof,) (numpy): the bar
    whose force :func:`suture_force` reports."""
    return int(np.argmax(sutures.forces(q, params)))


def suture_force(sutures, q, params, data, dofs, largest):
    """The axial force (N) of suture bar ``largest`` (JAX) once it is tied, 0 before (its
    force times its param "tied": untied, its rest length is the reference one and its
    force means nothing): the most loaded bar's, with ``largest`` = argmax of
    ``sutures.forces`` at the state (the bar is chosen at the state by
    :func:`most_loaded_bar`, its force differentiated); ``sutures``: the term (its methods
    only), params, data and dofs its own."""
    return tied_force(sutures.axial_forces(q[dofs], params, data), params, largest)


def tied_force(forces, params, largest):
    """The force (N) of bar ``largest`` of a suture term's axial ``forces`` (n,) once it is
    tied, 0 before (its params' "tied"; numpy or JAX): :func:`suture_force`'s rule."""
    return forces[largest] * params["tied"][largest]


def eye_optics(X, q, nodes: OutcomeNodes) -> dict:
    """Axial length (mm), corneal power and astigmatism (D), anterior chamber depth (mm)."""
    x = X + q[: 3 * len(X)].reshape(-1, 3)
    apex = nodes.apex.at(x)
    return {"axial_length_mm": jnp.linalg.norm(apex - nodes.pole.at(x)),
            "corneal_power_D": optics.corneal_power_d(x, nodes.cornea),
            "corneal_astigmatism_D": optics.corneal_astigmatism_d(x, nodes.cornea),
            "anterior_chamber_depth_mm": optics.anterior_chamber_depth(apex,
                                                                     x[nodes.lens_pole])}


def changes(now: dict, preop: dict) -> dict:
    """The outcomes of an operation from the optics (:func:`eye_optics`) of a state and of
    the pressurised pre-operative eye: axial length change (mm), refraction change (D;
    negative: myopic), corneal power change (D), anterior chamber depth change (mm)."""
    d_axial = now["axial_length_mm"] - preop["axial_length_mm"]
    d_power = now["corneal_power_D"] - preop["corneal_power_D"]
    return {"axial_length_change_mm": d_axial,
            "refraction_change_D": optics.refraction_change_d(d_axial, d_power),
            "corneal_power_change_D": d_power,
            "anterior_chamber_depth_change_mm": (now["anterior_chamber_depth_mm"]
                                                 - preop["anterior_chamber_depth_mm"])}


STRESS_PATCH_MM = 1.0
"""Radius of the patch of sclera over which the peak scleral stress is averaged, mm (about
the wall's thickness: a fixed physical size, so that the peak converges under refinement
where a single element's stress at a bite or at the buckle's edge does not)."""


def stress_patches(mesh, radius: float = STRESS_PATCH_MM) -> sparse.csr_matrix:
    """Volume-weighted averaging matrix (n_sclera, n_elem): row i averages the element
    values of the scleral elements whose reference centroids lie within ``radius`` mm of
    scleral element i's centroid (itself included). ValueError where the mesh has no
    material 'sclera'."""
    if "sclera" not in mesh.materials:
        raise ValueError(f"peak scleral stress: the mesh has no material 'sclera' "
                         f"({list(mesh.materials)})")
    sid = np.nonzero(mesh.material_ids == list(mesh.materials).index("sclera"))[0]
    centroids = mesh.nodes[mesh.hexes[sid]].mean(axis=1)
    vol = hex_geometry(mesh.nodes, mesh.hexes[sid])[1].sum(axis=1)
    rows = cKDTree(centroids).query_ball_point(centroids, radius)
    r = np.repeat(np.arange(len(sid)), [len(k) for k in rows])
    c = np.concatenate(rows)
    w = vol[c]
    W = sparse.csr_matrix((w, (r, sid[c])), shape=(len(sid), mesh.n_elem))
    return sparse.diags(1.0 / np.asarray(W.sum(axis=1)).ravel()) @ W


def peak_scleral_stress(model, q, theta, patches) -> float:
    """The largest von Mises stress of the sclera averaged over a patch (kPa):
    max_i (patches @ sigma_vm)_i with :func:`stress_patches` (the solid term's element
    stresses, averaged over each element's Gauss points)."""
    vm = model.terms[0].fields(np.asarray(q), theta["solid"])["von_mises"]
    return float((patches @ vm).max()) / KPA


SCLERA_STRENGTH_MPA = 9.4
"""The sclera's strength, MPa: the peak wall stress at which human globes ruptured, with
the cornea's and sclera's properties from uniaxial strip tests taken to rupture (Stitzel,
Duma, Cormier and Herring, "A nonlinear finite element model of the eye with experimental
validation for the prediction of globe rupture", Stapp Car Crash Journal 46, 2002, SAE
2002-22-0005: "globe rupture has previously been shown to occur at peak stresses of
9.4 MPa"). One figure for a tissue whose strips vary with age, region and strain rate
(in 36 donor scleras the stress rose 157-203 % from a strain rate of 8 to 200 %/min:
"Regional variation in the biomechanical properties of the human sclera"); a ratio near 1 means the model's wall is at the
load at which eyes tear, not a prediction of where."""

SUTURE_BREAK_N = 3.0
"""A tied scleral suture's breaking load, N: knots of 6-0 braided polyglactin (Vicryl)
broke at a mean 307.6 g (3.02 N; the strand itself at 623.5 g), J AAPOS 2017,
"Securing extraocular muscles in strabismus surgery: laboratory analysis of biomechanical
parameters related to the suture" (PubMed 28989101); a flange of 5-0 polypropylene pulled
out of human sclera at 3.0 +- 0.5 N (Yuan et al., Am J Ophthalmol, October 2021). No
figure for tied 5-0 polyester (Mersilene, Ethibond), the buckle's usual suture, was
found; 4-0 sutures' knots held 8.7-11.9 N (J Mater Sci Mater Med 18:2363, 2007), so 3 N
is a low (safe-side) figure for 5-0, about the load at which a bite pulls through."""


PLAUSIBILITY = ("scleral_stress_fraction_of_strength", "suture_force_fraction_of_break")
"""The plausibility outcomes (:func:`plausibility`)."""


def plausibility(scleral_stress_kpa: float, suture_force_n: float) -> dict:
    """The plausibility outcomes: the peak scleral stress (kPa) as a fraction of the
    sclera's strength (SCLERA_STRENGTH_MPA) and the largest suture force (N) as a
    fraction of a tied suture's breaking load (SUTURE_BREAK_N); above 1: a tissue or a
    suture the model loads beyond what it bears."""
    return {"scleral_stress_fraction_of_strength":
            float(scleral_stress_kpa) * KPA / SCLERA_STRENGTH_MPA,
            "suture_force_fraction_of_break": float(suture_force_n) / SUTURE_BREAK_N}


OUTER_SURFACE = "eye/outer"
"""The eye mesh's node set of its outer surface."""


def azimuthal_shares(mesh, u, n_max: int = 4, band_deg: float = 15.0) -> np.ndarray:
    """How the radial displacement u (n_nodes, 3) of the eye's outer surface splits over
    the azimuthal wave numbers m = 0..n_max about the optical axis (z): shares (n_max + 2,)
    of its sum of squares, the last one what wave numbers above n_max and the bands too
    small to fit leave.

    The outer nodes are grouped in bands of polar angle (``band_deg`` wide, from the
    corneal apex); in each band the radial displacement (along the reference position
    from the globe's centre) is fitted by least squares with a0 + sum_m (a_m cos m phi +
    b_m sin m phi), phi = atan2(y, x). An axisymmetric field is all m = 0; an ovalisation
    of the globe m = 2."""
    ids = mesh.node_set(OUTER_SURFACE)
    X = mesh.nodes[ids]
    radial = X / np.linalg.norm(X, axis=1, keepdims=True)
    dr = np.einsum("ij,ij->i", np.asarray(u)[ids], radial)
    polar = np.degrees(np.arccos(np.clip(radial[:, 2], -1.0, 1.0)))
    phi = np.arctan2(X[:, 1], X[:, 0])
    ms = np.arange(1, n_max + 1)
    energy = np.zeros(n_max + 1)
    for lo in np.arange(0.0, 180.0, band_deg):
        sel = (polar >= lo) & (polar < lo + band_deg)
        if sel.sum() < 4 * (2 * n_max + 1):
            continue
        p = phi[sel][:, None]
        cols = [np.ones((sel.sum(), 1)), np.cos(ms * p), np.sin(ms * p)]
        A = np.hstack(cols)
        c = np.linalg.lstsq(A, dr[sel], rcond=None)[0]
        energy[0] += np.sum((A[:, 0] * c[0]) ** 2)
        for j in range(n_max):
            part = A[:, 1 + j] * c[1 + j] + A[:, 1 + n_max + j] * c[1 + n_max + j]
            energy[1 + j] += np.sum(part**2)
    total = float(np.sum(dr**2)) or 1.0
    shares = energy / total
    return np.append(shares, max(0.0, 1.0 - shares.sum()))


_compiled_iop_mmhg = jax.jit(cavity_iop_mmhg)
_compiled_optics = jax.jit(eye_optics)
_compiled_indentation = jax.jit(indentation)
"""The JAX outcomes compiled for :func:`outcomes` at a state on the host (one small XLA
program each; eager JAX compiles one per operation on a machine's first run)."""


def outcomes(parts: SurgeryParts, model, q, theta, patches=None) -> dict:
    """The outcomes every buckle reports at state q (n_dof,): IOP (mmHg), cavity volume
    (mm^3), axial length and its change from the unloaded eye (mm), indentation (mm),
    largest suture bar force (N; :func:`suture_force` of :func:`most_loaded_bar`: 0 until
    the sutures are tied, as :func:`outcome_function`'s), corneal power and astigmatism
    (D), anterior chamber depth (mm), the peak scleral von Mises stress over a patch (kPa; ``patches``: the
    :func:`stress_patches` of the mesh, built here when not given), and those two as
    fractions of the sclera's strength and of a suture's breaking load
    (:func:`plausibility`). A buckle body adds its own (BuckleBody.outcomes)."""
    X, nodes = model.mesh.nodes, outcome_nodes(parts)
    cav = model.term("cavity")
    _, V = cav.pressures(q, theta["cavity"])
    closed = theta["iop"]["p"] == 0.0  # close_cavity releases the surface load
    iop = (float(_compiled_iop_mmhg(q, theta["cavity"], cav.data, cav.dofs)) if closed
           else float(theta["iop"]["p"]) / MMHG)
    sut = model.term("sutures")
    force = float(tied_force(sut.forces(q, theta["sutures"]), theta["sutures"],
                             most_loaded_bar(sut, q, theta["sutures"])))
    now = {k: float(v) for k, v in _compiled_optics(X, q, nodes).items()}
    unloaded = _compiled_optics(X, np.zeros_like(q), nodes)["axial_length_mm"]
    stress = peak_scleral_stress(model, q, theta,
                                 stress_patches(model.mesh) if patches is None else patches)
    return {"iop_mmhg": iop, "volume_mm3": float(V[0]),
            "axial_length_mm": now["axial_length_mm"],
            "axial_length_change_unloaded_mm": now["axial_length_mm"] - float(unloaded),
            "indentation_mm": float(_compiled_indentation(X, q, nodes)),
            "max_suture_force_N": force, **{k: v for k, v in now.items()
                                            if k != "axial_length_mm"},
            "scleral_stress_kPa": stress, **plausibility(stress, force)}


OPTICS = ("axial_length_mm", "corneal_power_D", "corneal_astigmatism_D",
          "anterior_chamber_depth_mm")
"""The optics of a state (:func:`eye_optics`)."""
CHANGES = ("axial_length_change_mm", "refraction_change_D", "corneal_power_change_D",
           "anterior_chamber_depth_change_mm")
"""The changes of an operation (:func:`changes`), measured from the pre-operative eye."""


def outcome_function(names, X, nodes: OutcomeNodes, sutures):
    """f(q, theta, carry, data) -> (k,) the named outcomes at state q (n_dof,) (JAX), or
    (1,) their weighted sum with data["weights"] (k,) (None: the values); the functions
    :func:`outcomes` reports, so that a value and its gradient come from one definition.

    Args:
      names: outcome names: iop_mmhg, indentation_mm, max_suture_force_N, the OPTICS and
        the CHANGES (from carry["optics"], the pre-operative eye's :func:`eye_optics`).
        max_suture_force_N is :func:`suture_force` (0 until the sutures are tied), as
        :func:`outcomes` reports it.
      X: (n_nodes, 3) reference node positions, mm; nodes: the mesh's OutcomeNodes.
      sutures: a suture term of the kind whose data f receives (its methods only).
    data: {"cavity": (data, dofs) of the FluidCavity, "sutures": (data, dofs),
    "largest": the most loaded suture bar (:func:`suture_force`), "weights"}.
    """
    names = tuple(names)
    known = ("iop_mmhg", "indentation_mm", "max_suture_force_N") + OPTICS + CHANGES
    unknown = [n for n in names if n not in known]
    if unknown:
        raise KeyError(f"unknown outcomes {unknown}; known: {list(known)}")
    optical = bool(set(names) & set(OPTICS + CHANGES))

    def outcome(name, q, theta, data, opt, ch):
        if name in CHANGES:
            return ch[name]
        if name in OPTICS:
            return opt[name]
        if name == "iop_mmhg":
            return cavity_iop_mmhg(q, theta["cavity"], *data["cavity"])
        if name == "indentation_mm":
            return indentation(X, q, nodes)
        return suture_force(sutures, q, theta["sutures"], *data["sutures"], data["largest"])

    def f(q, theta, carry, data):
        opt = eye_optics(X, q, nodes) if optical else None
        ch = changes(opt, carry["optics"]) if opt is not None else {}
        values = jnp.stack([outcome(n, q, theta, data, opt, ch) for n in names])
        w = data["weights"]
        return values if w is None else jnp.reshape(jnp.dot(w, values), (1,))

    return f


def outcome_data(model, q, theta, weights=None) -> dict:
    """The data of :func:`outcome_function` at a converged state q (n_dof,), theta of
    ``model``: its cavity's and sutures' data and dofs, the most loaded suture bar, and
    ``weights`` (k,) or None."""
    return outcome_data_of(model.term("cavity"), model.term("sutures"), q, theta, weights)


def outcome_data_of(cav, sut, q, theta, weights=None) -> dict:
    """:func:`outcome_data` of a cavity term ``cav`` and a suture term ``sut`` of the model
    whose state q (n_dof,) and params theta are given (the whole eye's, where a mirror half
    was solved)."""
    return {"cavity": (cav.data, cav.dofs), "sutures": (sut.data, sut.dofs),
            "largest": jnp.asarray(most_loaded_bar(sut, q, theta["sutures"])),
            "weights": None if weights is None else jnp.asarray(weights, jnp.float64)}


def stage_summary(rows) -> list[dict]:
    """The last row of every stage, with the changes since the end of the first stage (the
    pressurised pre-operative eye: :func:`changes`) and its volume change."""
    out, pre = [], None
    for i, r in enumerate(rows):
        if i + 1 < len(rows) and rows[i + 1]["stage"] == r["stage"]:
            continue
        pre = r if pre is None else pre
        out.append({"stage": r["stage"], "iop_mmhg": r["iop_mmhg"],
                    "indentation_mm": r["indentation_mm"],
                    "axial_length_mm": r["axial_length_mm"],
                    "volume_change_mm3": r["volume_mm3"] - pre["volume_mm3"],
                    "max_suture_force_N": r["max_suture_force_N"],
                    "corneal_astigmatism_D": r["corneal_astigmatism_D"],
                    "scleral_stress_kPa": r.get("scleral_stress_kPa"),
                    **{k: r[k] for k in PLAUSIBILITY if k in r},
                    **{k: float(v) for k, v in changes(r, pre).items()}})
    return out
