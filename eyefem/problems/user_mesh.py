"""A user's own hexahedral mesh (gmsh, Abaqus, VTU through meshio: eyefem.io.meshfile)
loaded by node sets held, moved or pressed: ``problem = "user_mesh"``.

One stage of ``steps`` load steps ramps the prescribed displacements and the follower
pressure from zero (exact on an open face set too: eyefem.fem.surface.pressure_term).
Materials are named by the mesh's volume groups (or "default"), each given in the case
file's ``[materials.NAME]``.
"""

from __future__ import annotations

import difflib

import numpy as np

from eyefem.fem.surface import pressure_term
from eyefem.io.casefile import REQUIRED, Field, positive
from eyefem.io.meshfile import read_hex_mesh
from eyefem.solve.problem import Setup
from eyefem.solve.model import node_dofs, solid_model
from eyefem.solve.solver import Stage

USER_MESH_FIELDS = [
    Field("mesh_file", str, REQUIRED, "hexahedral mesh file (gmsh .msh, Abaqus .inp, VTU), "
          "relative to the case file", path=True),
    Field("steps", int, 10, "load steps", positive, ">= 1"),
    Field("fixed", list, [], "node sets held in x, y and z"),
    Field("fixed_x", list, [], "node sets held in x (a symmetry plane x = const)"),
    Field("fixed_y", list, [], "node sets held in y"),
    Field("fixed_z", list, [], "node sets held in z"),
    Field("displaced", str, "", "a node set moved by 'displacement' (ramped from zero)"),
    Field("displacement", list, [0.0, 0.0, 0.0], "displacement (x, y, z) of 'displaced', mm",
          lambda v: len(v) == 3 and all(isinstance(c, (int, float)) for c in v),
          "three numbers"),
    Field("displaced_components", str, "xyz", "the components of 'displacement' prescribed "
          "(the others free), e.g. 'z'", lambda v: bool(v) and set(v) <= set("xyz"),
          "letters of xyz"),
    Field("pressure_surface", str, "", "a face set (surface group) under the pressure"),
    Field("pressure", float, 0.0, "follower pressure on 'pressure_surface', MPa (> 0 pushes "
          "into the solid)"),
]


def _named(name: str, sets: dict, kind: str, mesh_file) -> np.ndarray:
    if name not in sets:
        close = difflib.get_close_matches(name, list(sets), n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        raise ValueError(f"{kind} '{name}' is not in the mesh file {mesh_file}{hint}; it "
                         f"has: {', '.join(sorted(sets))}")
    return sets[name]


def user_mesh(p, materials):
    """The Setup of a user's mesh (module doc): parameters ``p`` (USER_MESH_FIELDS),
    materials name -> MooneyRivlin (every material of the mesh must be given)."""
    mesh = read_hex_mesh(p["mesh_file"])
    missing = [m for m in mesh.materials if m not in (materials or {})]
    if missing:
        raise ValueError(f"the mesh's materials {missing} have no [materials.NAME] table; give "
                         f"each, e.g. [materials.{missing[0]}] c10 = 0.1")
    mats = {m: materials[m] for m in mesh.materials}
    dofs, vals = [], []
    for comps, names in (("xyz", p["fixed"]), ("x", p["fixed_x"]), ("y", p["fixed_y"]),
                         ("z", p["fixed_z"])):
        for name in names:
            d = node_dofs(_named(str(name), mesh.node_sets, "node set", p["mesh_file"]), comps)
            dofs.append(d)
            vals.append(np.zeros(len(d)))
    if p["displaced"]:
        nodes = _named(p["displaced"], mesh.node_sets, "node set", p["mesh_file"])
        for k, c in enumerate("xyz"):
            if c not in p["displaced_components"]:
                continue
            d = node_dofs(nodes, c)
            dofs.append(d)
            vals.append(np.full(len(d), float(p["displacement"][k])))
    if not dofs:
        raise ValueError("nothing holds the mesh: name node sets in 'fixed' (or fixed_x, "
                         "fixed_y, fixed_z, displaced)")
    d, v = np.concatenate(dofs), np.concatenate(vals)
    d, first = np.unique(d, return_index=True)  # a node in two sets: its first prescription
    v = v[first]
    terms, params = (), {}
    if p["pressure_surface"]:
        _named(p["pressure_surface"], mesh.face_sets, "face set", p["mesh_file"])
        terms = (pressure_term("pressure", mesh, p["pressure_surface"], 0.0),)
        params = {"pressure": {"p": p["pressure"]}}
    model = solid_model(mesh, mats, terms)
    n = mesh.n_nodes

    def probe(model, q, theta):
        u = np.asarray(q[: 3 * n]).reshape(n, 3)
        return {"max_displacement_mm": float(np.max(np.linalg.norm(u, axis=1)))}

    def finish(rows, out_dir, plots):
        return {"mesh_file": p["mesh_file"], "nodes": n, "elements": mesh.n_elem,
                "materials": list(mesh.materials),
                "max_displacement_mm": rows[-1]["max_displacement_mm"] if rows else 0.0}

    return Setup("user_mesh", model, [Stage("load", p["steps"], (d, v), params=params)],
                 probe, finish)


PROBLEMS = {"user_mesh": (USER_MESH_FIELDS, user_mesh)}
