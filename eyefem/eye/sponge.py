"""A deformable radial sponge sewn onto the eye (seed 6.2: "sponge deformable").

The sponge (:func:`eyefem.eye.buckle_meshes.deformable_sponge`, neo-Hookean c10 = 0.1 MPa,
material "sponge") waits parked SPONGE_PARK mm off the sclera while the eye is
pressurised, is fitted snug on the pressurised eye (its stress-free reference moved
radially until its closest node is SPONGE_CLEARANCE mm off the sclera) when the cavity
closes, and is then held by its contact on the sclera, its sutures and springs on its
rigid motion (SPONGE_SPRING) while the sutures are tightened. Each suture is three
tension-only bars: bite A -> a point embedded in the sponge's outer half (where the ray
to the globe centre through the sclera 0.3 of the sponge's width from its centre line
meets it) -> the point on the other side -> bite B (as the deformable band's).
"""

from __future__ import annotations

import numpy as np

from eyefem.eye.buckle_meshes import deformable_sponge
from eyefem.eye.buckles import Buckle
from eyefem.eye.eyemodel import LEVELS, EyeGeometry, level_spec
from eyefem.eye.sutures import generate_sutures, suture_bars
from eyefem.fem.contact import SurfaceContact
from eyefem.fem.mesh import Mesh
from eyefem.fem.terms import OrbitSpring

SPONGE_PARK = 0.3
"""Gap between the sclera and the deformable sponge while it waits for stage 2, mm."""
SPONGE_CLEARANCE = 4e-3
"""Gap of the sponge fitted snug on the pressurised eye under its closest node, mm."""
SPONGE_SPRING = (0.1, 0.01)
"""Springs on the sponge's rigid motion: its best-fit rotation (N mm/rad) and its mean
translation across and along its axis (N/mm; eyefem.fem.terms.OrbitSpring with shift_axes),
not on its motion into the sclera nor on its deformation. On frictionless contact a
round sponge under a suture loop can roll and slide sideways almost freely (the loop's
length hardly changes): with springs of 1e-5 N/mm on every node it drifted 0.4 mm
across on the coarse eye and Newton crawled at 1/8 steps. Their force
(sponge_springs/force_N, logged) stands in for friction."""
SPONGE_SMOOTHING = 2e-3
"""Smoothing length of the sponge's contact on the sclera, mm (SurfaceContact smoothing)."""
SPONGE_DIVISIONS = {"coarse": (8, 10), "medium": (16, 16), "default": (16, 20)}
"""Elements around and along the deformable sponge per eye mesh level; another level takes
those of the finest of these whose elements per patch edge it has at least
(:func:`sponge_divisions`)."""


def sponge_divisions(level: str) -> tuple[int, int]:
    """(elements around, elements along) the deformable sponge on eye mesh ``level``."""
    if level in SPONGE_DIVISIONS:
        return SPONGE_DIVISIONS[level]
    n = level_spec(level)[0]
    fitting = [lv for lv in SPONGE_DIVISIONS if LEVELS[lv][0] <= n]
    return SPONGE_DIVISIONS[max(fitting or ["coarse"], key=lambda lv: LEVELS[lv][0])]


def sponge_mesh(buckle: Buckle, g: EyeGeometry, level: str, gap: float) -> Mesh:
    """The sponge with its lowest mantle line ``gap`` mm off the (unloaded) sclera."""
    n_circ, n_len = sponge_divisions(level)
    return deformable_sponge(buckle, g, g.scleral_radius + buckle.width / 2 + gap,
                             n_len=n_len, n_circ=n_circ)


def fit_sponge(mesh: Mesh, buckle: Buckle, g: EyeGeometry, level: str, scale: float,
               q, normals: str = "facet") -> Mesh:
    """The mesh with the sponge's reference moved snug onto the eye at state q: built on
    the sphere of radius scale R + SPONGE_CLEARANCE, then moved along its centre normal
    until its closest node lies SPONGE_CLEARANCE off the outer sclera (its faces, or
    their Nagata patches with normals = "nodal")."""
    nodes = mesh.nodes.copy()
    ids = mesh.node_set("sponge")
    gap0 = (scale - 1.0) * g.scleral_radius + SPONGE_CLEARANCE
    nodes[ids] = sponge_mesh(buckle, g, level, gap0).nodes
    th, ph = buckle.centre_angle(g), np.radians(buckle.meridian_deg)
    n0 = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
    q = np.asarray(q)
    for _ in range(3):
        m = mesh.replace(nodes=nodes)
        gap, node, _ = SurfaceContact("fit", m, "sponge/inner", "eye/sclera_outer",
                                      normals=normals).update(q, None)._gaps(q)
        if len(node) == 0:
            raise RuntimeError("fit_sponge: no sponge node finds the sclera under it")
        nodes[ids] += (SPONGE_CLEARANCE - gap.min()) * n0
    return mesh.replace(nodes=nodes)


def sponge_contact_term(mesh: Mesh, sclera_c10: float, normals: str = "facet") -> SurfaceContact:
    """Node-to-segment contact of the sponge's eye-facing nodes (slave) on the outer
    sclera (master; normals: SurfaceContact's); penalty from the sclera's Young's
    modulus."""
    return SurfaceContact("buckle", mesh, "sponge/inner", "eye/sclera_outer",
                          modulus=6 * sclera_c10, smoothing=SPONGE_SMOOTHING, normals=normals)


def sponge_suture_term(mesh: Mesh, buckle: Buckle, frame, p: dict):
    """Sutures over the deformable sponge (three tension-only bars each) and their layout."""
    cen, acr, nrm, _ = frame
    layout = generate_sutures(mesh.nodes, mesh.face_set("eye/sclera_outer"), cen, acr, nrm,
                              width=p["suture_width"], angle_deg=p["suture_angle_deg"], n_bars=3,
                              buckle_faces=mesh.face_set("sponge/outer"),
                              buckle_half_width=0.3 * buckle.width)
    return suture_bars("sutures", layout, mesh.nodes, mesh.face_set("eye/sclera_outer"),
                       EA=p["suture_EA"], bite_radius=p["bite_radius"],
                       bite_length=p["bite_length"]), layout


def sponge_spring_term(mesh: Mesh, buckle: Buckle, g: EyeGeometry) -> OrbitSpring:
    """Springs on the sponge's rigid motion (SPONGE_SPRING)."""
    th, ph = buckle.centre_angle(g), np.radians(buckle.meridian_deg)
    across = np.array([-np.sin(ph), np.cos(ph), 0.0])
    along = np.array([np.cos(th) * np.cos(ph), np.cos(th) * np.sin(ph), -np.sin(th)])
    ids = mesh.node_set("sponge")
    k_rot, k_trans = SPONGE_SPRING
    return OrbitSpring("sponge_springs", ids, mesh.nodes[ids], k_rot=(k_rot,) * 3,
                       k_trans=k_trans, shift_axes=(tuple(across), tuple(along)))
