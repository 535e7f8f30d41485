"""A user's hexahedral mesh from a file (eyefem.io.meshfile, problem "user_mesh"): gmsh
physical groups as materials and sets, a homogeneous stretch against the closed form,
the case-file path relative to the case, and the errors for what cannot be used."""

import json

import meshio
import numpy as np
import pytest

from eyefem.catalog import schemas
from eyefem.cli.main import main as cli_main
from eyefem.fem.materials import mooney_rivlin
from eyefem.io.casefile import load_case
from eyefem.io.meshfile import MeshFileError, read_hex_mesh
from eyefem.problems.user_mesh import user_mesh
from eyefem.solve.solver import solve

N = 2  # hexahedra per edge of the unit block


def _block(path, split_materials=True, cell="hexahedron"):
    """A unit cube of N^3 hexahedra as gmsh 2.2: volumes 'soft' (x < 1/2) and 'hard', the
    six faces as surfaces x0, x1, y0, y1, z0, z1 (quads wound inward on purpose)."""
    g = np.linspace(0.0, 1.0, N + 1)
    pts = np.array([[x, y, z] for z in g for y in g for x in g])
    idx = lambda i, j, k: (k * (N + 1) + j) * (N + 1) + i  # noqa: E731
    hexes, mats = [], []
    for k in range(N):
        for j in range(N):
            for i in range(N):
                hexes.append([idx(i, j, k), idx(i + 1, j, k), idx(i + 1, j + 1, k),
                              idx(i, j + 1, k), idx(i, j, k + 1), idx(i + 1, j, k + 1),
                              idx(i + 1, j + 1, k + 1), idx(i, j + 1, k + 1)])
                mats.append(1 if (i < N // 2 or not split_materials) else 2)
    quads, tags = [], []
    for tag, (axis, side) in enumerate([(0, 0), (0, N), (1, 0), (1, N), (2, 0), (2, N)], 3):
        for a in range(N):
            for b in range(N):
                c = [[a, b], [a + 1, b], [a + 1, b + 1], [a, b + 1]]
                ijk = [[side, u, v] if axis == 0 else [u, side, v] if axis == 1 else [u, v, side]
                       for u, v in c]
                quads.append([idx(*t) for t in ijk])
                tags.append(tag)
    names = {"soft": [1, 3], "hard": [2, 3], "x0": [3, 2], "x1": [4, 2], "y0": [5, 2],
             "y1": [6, 2], "z0": [7, 2], "z1": [8, 2]}
    if not split_materials:
        names.pop("hard")
    cells = [(cell, np.array(hexes)[:, :4] if cell == "tetra" else np.array(hexes)),
             ("quad", np.array(quads))]
    data = [np.array(mats), np.array(tags)]
    meshio.write(path, meshio.Mesh(pts, cells, cell_data={"gmsh:physical": data,
                                                          "gmsh:geometrical": data},
                                   field_data={k: np.array(v) for k, v in names.items()}),
                 file_format="gmsh22", binary=False)
    return path


def test_physical_groups_become_materials_and_sets(tmp_path):
    mesh = read_hex_mesh(_block(tmp_path / "b.msh"))
    assert mesh.n_elem == N**3 and mesh.materials == ("soft", "hard")
    assert np.bincount(mesh.material_ids).tolist() == [N**3 // 2] * 2
    z1 = mesh.node_sets["z1"]
    assert np.allclose(mesh.nodes[z1, 2], 1.0) and len(z1) == (N + 1) ** 2
    faces = mesh.face_sets["z0"]  # outward (-z) although the file winds them inward
    x = mesh.nodes[faces]
    normal = np.cross(x[:, 1] - x[:, 0], x[:, 3] - x[:, 0])
    assert len(faces) == N**2 and np.all(normal[:, 2] < 0)


def test_a_stretched_block_follows_the_closed_form(tmp_path):
    """Uniaxial stretch 1.3 of an incompressible block on symmetry planes: every point
    moves to (x, y) / sqrt(1.3), 1.3 z, whatever the two materials."""
    p = {f.name: f.default for f in schemas()["user_mesh"]}
    p.update(mesh_file=str(_block(tmp_path / "b.msh")), steps=2, fixed_x=["x0"],
             fixed_y=["y0"], fixed_z=["z0"], displaced="z1", displacement=[0.0, 0.0, 0.3],
             displaced_components="z")
    setup = user_mesh(p, {"soft": mooney_rivlin("soft", 0.1, 0.0),
                          "hard": mooney_rivlin("hard", 1.0, 0.05)})
    sol = solve(setup.model, setup.stages)
    X = setup.model.mesh.nodes
    x = X + sol.q[: X.size].reshape(-1, 3)
    lam = 1.3
    np.testing.assert_allclose(x, X * [lam**-0.5, lam**-0.5, lam], atol=1e-9)


def test_case_file_runs_with_its_mesh_beside_it(tmp_path, capsys):
    _block(tmp_path / "block.msh")
    case = tmp_path / "c.toml"
    case.write_text('[case]\nproblem = "user_mesh"\n[parameters]\nmesh_file = "block.msh"\n'
                    'steps = 2\nfixed = ["z0"]\ndisplaced = "z1"\ndisplacement = [0.1, 0.0, 0.0]\n'
                    "[materials.soft]\nc10 = 0.1\n[materials.hard]\nc10 = 0.5\n")
    assert load_case(case, schemas()).parameters["mesh_file"] == str(tmp_path / "block.msh")
    out = tmp_path / "out"
    assert cli_main(["-q", "run", str(case), "--out", str(out), "--no-vtu"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["elements"] == N**3 and summary["materials"] == ["soft", "hard"]
    assert summary["max_displacement_mm"] == pytest.approx(0.1, rel=1e-9)


@pytest.mark.parametrize("edit, words", [
    (('mesh_file = "block.msh"', 'mesh_file = "nothere.msh"'), "no such file"),
    (('fixed = ["z0"]', 'fixed = ["z_0"]'), "node set 'z_0' is not in the mesh (did you mean"),
    (("[materials.hard]\nc10 = 0.5\n", ""), "materials ['hard'] have no [materials.NAME]"),
    (('fixed = ["z0"]\ndisplaced = "z1"', 'displaced = ""'), "nothing holds the mesh"),
])
def test_bad_user_mesh_cases_name_the_problem(tmp_path, capsys, edit, words):
    _block(tmp_path / "block.msh")
    text = ('[case]\nproblem = "user_mesh"\n[parameters]\nmesh_file = "block.msh"\n'
            'fixed = ["z0"]\ndisplaced = "z1"\n[materials.soft]\nc10 = 0.1\n'
            "[materials.hard]\nc10 = 0.5\n")
    assert edit[0] in text
    case = tmp_path / "c.toml"
    case.write_text(text.replace(edit[0], edit[1]))
    assert cli_main(["-q", "run", str(case), "--out", str(tmp_path / "out")]) == 2
    assert words in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_tetrahedra_are_refused_with_the_fix(tmp_path):
    with pytest.raises(MeshFileError, match="no hexahedra .*tetra.*8-node hexahedra"):
        read_hex_mesh(_block(tmp_path / "t.msh", cell="tetra"))
