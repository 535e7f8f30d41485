"""Bad mesh files (issue 76: inputs stay inputs; meshes checked like case files): Abaqus
*INCLUDE only below the including file's folder, regular files, bounded depth and size,
no cycle or fan-out; GENERATE ranges bounded before they are expanded; duplicate node and
element numbers refused; non-finite coordinates, folders, link loops and binary gmsh files
named with the fix. Each error is one MeshFileError line (exit 2 through the CLI) naming
the file, line and keyword, and never quoting a file it was not meant to read."""

import os
from pathlib import Path

import meshio
import numpy as np
import pytest

from eyefem.cli.main import main as cli_main
from eyefem.io.meshfile import (MAX_INCLUDE_DEPTH, MAX_MESH_BYTES, MeshFileError,
                                read_hex_mesh)

N = 2  # hexahedra per edge of the unit block


def _grid():
    g = np.linspace(0.0, 1.0, N + 1)
    pts = np.array([[x, y, z] for z in g for y in g for x in g])
    idx = lambda i, j, k: (k * (N + 1) + j) * (N + 1) + i  # noqa: E731
    hexes = [[idx(i, j, k), idx(i + 1, j, k), idx(i + 1, j + 1, k), idx(i, j + 1, k),
              idx(i, j, k + 1), idx(i + 1, j, k + 1), idx(i + 1, j + 1, k + 1),
              idx(i, j + 1, k + 1)] for k in range(N) for j in range(N) for i in range(N)]
    return pts, np.array(hexes)


def _inp_text(extra=""):
    """A unit block of N^3 C3D8 elements (element set 'solid'), node sets z0 and z1."""
    pts, hexes = _grid()
    out = ["*Node"] + [f"{n + 1}, {x:.17g}, {y:.17g}, {z:.17g}" for n, (x, y, z) in enumerate(pts)]
    out += ["*Element, type=C3D8, elset=solid"]
    out += [", ".join(str(v) for v in [e + 1, *(h + 1)]) for e, h in enumerate(hexes)]
    for name, z in (("z0", 0.0), ("z1", 1.0)):
        out += [f"*Nset, nset={name}", ", ".join(str(n + 1) for n in np.nonzero(pts[:, 2] == z)[0])]
    return "\n".join(out) + "\n" + extra


def _msh(path):
    """The block as an ASCII gmsh 2.2 file (volume 'solid')."""
    pts, hexes = _grid()
    meshio.write(path, meshio.Mesh(pts, [("hexahedron", hexes)],
                                   cell_data={"gmsh:physical": [np.ones(len(hexes), int)],
                                              "gmsh:geometrical": [np.ones(len(hexes), int)]},
                                   field_data={"solid": np.array([1, 3])}),
                 file_format="gmsh22", binary=False)
    return path


def _passwd_lines():
    """Lines of /etc/passwd that must never appear in a message."""
    try:
        return [ln for ln in Path("/etc/passwd").read_text().splitlines() if len(ln) > 8]
    except OSError:
        return ["root:x:0:0"]


def _refused(path, *words, **kw):
    """The one-line message of reading ``path``, checked for ``words`` and for no line of
    /etc/passwd."""
    with pytest.raises(MeshFileError) as info:
        read_hex_mesh(path, **kw)
    msg = str(info.value)
    assert "\n" not in msg
    for w in words:
        assert w in msg, (w, msg)
    assert not any(line in msg for line in _passwd_lines())
    assert "root:" not in msg
    return msg


def _run_case(tmp_path, mesh_name, capsys):
    case = tmp_path / "c.toml"
    case.write_text('[case]\nproblem = "user_mesh"\n[parameters]\n'
                    f'mesh_file = "{mesh_name}"\nsteps = 1\nfixed = ["z0"]\ndisplaced = "z1"\n'
                    "displacement = [0.0, 0.0, 0.05]\n[materials.solid]\nc10 = 0.1\n")
    code = cli_main(["-q", "run", str(case), "--out", str(tmp_path / "out"), "--no-vtu"])
    captured = capsys.readouterr()
    return code, captured.err + captured.out


def test_the_good_block_reads(tmp_path):
    (tmp_path / "b.inp").write_text(_inp_text())
    assert read_hex_mesh(tmp_path / "b.inp").n_elem == N**3
    assert read_hex_mesh(_msh(tmp_path / "b.msh")).n_elem == N**3


# 1. *INCLUDE: below the including file's folder, regular files, bounded, no cycle/fan-out

@pytest.mark.parametrize("target", ["../" * 20 + "etc/passwd", "/etc/passwd", "/dev/zero"])
def test_include_outside_the_folder_is_refused_unread(tmp_path, target):
    (tmp_path / "m.inp").write_text(f"*INCLUDE, INPUT={target}\n" + _inp_text())
    _refused(tmp_path / "m.inp", "m.inp:1: *INCLUDE, INPUT=", "outside the folder of m.inp",
             "EYEFEM_ALLOW_INCLUDE=DIR", "allow_include=")


def test_include_through_a_link_out_of_the_folder_is_refused(tmp_path):
    (tmp_path / "sub").mkdir()
    os.symlink("/etc/passwd", tmp_path / "sub" / "part.inp")
    (tmp_path / "m.inp").write_text("*INCLUDE, INPUT=sub/part.inp\n" + _inp_text())
    _refused(tmp_path / "m.inp", "m.inp:1: *INCLUDE, INPUT=sub/part.inp: outside the folder")


def test_include_of_passwd_through_the_cli_exits_2_without_its_content(tmp_path, capsys):
    (tmp_path / "m.inp").write_text("*INCLUDE, INPUT=/etc/passwd\n" + _inp_text())
    code, text = _run_case(tmp_path, "m.inp", capsys)
    assert code == 2
    assert "m.inp:1: *INCLUDE, INPUT=/etc/passwd: outside the folder" in text
    assert "Traceback" not in text and "root:" not in text
    assert not any(line in text for line in _passwd_lines())


def test_allowed_include_folder_is_read(tmp_path):
    (tmp_path / "lib").mkdir()
    (tmp_path / "lib" / "block.inp").write_text(_inp_text())
    (tmp_path / "case").mkdir()
    (tmp_path / "case" / "m.inp").write_text("*INCLUDE, INPUT=../lib/block.inp\n")
    _refused(tmp_path / "case" / "m.inp", "outside the folder")
    mesh = read_hex_mesh(tmp_path / "case" / "m.inp", allow_include=[tmp_path / "lib"])
    assert mesh.n_elem == N**3


@pytest.mark.parametrize("kind", ["dir", "fifo", "devzero_link"])
def test_include_of_no_regular_file_is_refused(tmp_path, kind):
    sub = tmp_path / "sub"
    sub.mkdir()
    if kind == "fifo":
        os.mkfifo(sub / "part.inp")
    elif kind == "devzero_link":  # allowed folder, but a character device
        os.symlink("/dev/zero", sub / "part.inp")
    else:
        (sub / "part.inp").mkdir()
    (tmp_path / "m.inp").write_text("*INCLUDE, INPUT=sub/part.inp\n" + _inp_text())
    words = {"dir": "is a directory", "fifo": "a FIFO (named pipe), not a regular file",
             "devzero_link": "a character device, not a regular file"}[kind]
    _refused(tmp_path / "m.inp", "m.inp:1: *INCLUDE, INPUT=sub/part.inp: ", words,
             "give an Abaqus .inp text file", allow_include=["/dev"])


def test_include_cycle_is_refused(tmp_path):
    (tmp_path / "a.inp").write_text("*INCLUDE, INPUT=b.inp\n")
    (tmp_path / "b.inp").write_text("** b\n*INCLUDE, INPUT=a.inp\n")
    _refused(tmp_path / "a.inp", "b.inp:2: *INCLUDE, INPUT=a.inp: an include cycle "
             "(a.inp -> b.inp -> a.inp); remove the *INCLUDE that closes it")


def test_include_fan_out_bomb_is_refused_at_the_first_repeat(tmp_path):
    """Ten files each including the next ten times: 10^9 reads of the last one, refused at
    its second *INCLUDE."""
    for i in range(10):
        (tmp_path / f"f{i}.inp").write_text(
            f"*INCLUDE, INPUT=f{i + 1}.inp\n" * 10 if i < 9 else _inp_text())
    _refused(tmp_path / "f0.inp", "f8.inp:2: *INCLUDE, INPUT=f9.inp: f9.inp is already "
             "included (at ", "f8.inp:1)", "each file is included once", "include bomb")


def test_include_depth_is_bounded_and_can_be_raised(tmp_path, monkeypatch):
    depth = MAX_INCLUDE_DEPTH + 1
    for i in range(depth):
        (tmp_path / f"d{i}.inp").write_text(f"*INCLUDE, INPUT=d{i + 1}.inp\n")
    (tmp_path / f"d{depth}.inp").write_text(_inp_text())
    _refused(tmp_path / "d0.inp", f"d{depth - 1}.inp:1: *INCLUDE, INPUT=d{depth}.inp: ",
             f"nested more than {MAX_INCLUDE_DEPTH} levels deep", "EYEFEM_MAX_INCLUDE_DEPTH=N")
    assert read_hex_mesh(tmp_path / "d0.inp", max_include_depth=depth).n_elem == N**3
    monkeypatch.setenv("EYEFEM_MAX_INCLUDE_DEPTH", str(depth))
    assert read_hex_mesh(tmp_path / "d0.inp").n_elem == N**3


def test_mesh_size_is_bounded_and_can_be_raised(tmp_path, monkeypatch):
    assert MAX_MESH_BYTES == 512 * 2**20
    (tmp_path / "part.inp").write_text(_inp_text())
    (tmp_path / "m.inp").write_text("** main\n*INCLUDE, INPUT=part.inp\n")
    _refused(tmp_path / "m.inp", "m.inp:2: *INCLUDE, INPUT=part.inp: ", "would exceed 100 bytes",
             "EYEFEM_MAX_MESH_BYTES=BYTES", max_bytes=100)
    monkeypatch.setenv("EYEFEM_MAX_MESH_BYTES", "100")
    _refused(tmp_path / "m.inp", "would exceed 100 bytes")
    _refused(_msh(tmp_path / "b.msh"), "b.msh: the mesh file and its *INCLUDE files would "
             "exceed 100 bytes")
    monkeypatch.setenv("EYEFEM_MAX_MESH_BYTES", "lots")
    _refused(tmp_path / "m.inp", "EYEFEM_MAX_MESH_BYTES = 'lots' is not a positive integer")
    monkeypatch.setenv("EYEFEM_MAX_MESH_BYTES", str(10**6))
    assert read_hex_mesh(tmp_path / "m.inp").n_elem == N**3


# 2. GENERATE ranges bounded before allocating

@pytest.mark.parametrize("line, words", [
    ("*NSET, NSET=big, GENERATE\n1, 300000000",
     "*NSET, GENERATE '1, 300000000': 300000000 node numbers, more than the 27 nodes "
     "defined above this line"),
    ("*ELSET, ELSET=big, GENERATE\n1, 300000000, 1",
     "*ELSET, GENERATE '1, 300000000, 1': 300000000 element numbers, more than the 8 "
     "elements defined above this line"),
    ("*NSET, NSET=back, GENERATE\n27, 1",
     "*NSET, GENERATE '27, 1': a reversed range (LAST 1 below FIRST 27); write it as 1, 27"),
    ("*ELSET, ELSET=flat, GENERATE\n1, 8, 0",
     "*ELSET, GENERATE '1, 8, 0': step 0; a GENERATE step must be at least 1"),
    ("*NSET, NSET=neg, GENERATE\n1, 8, -1", "step -1; a GENERATE step must be at least 1"),
    ("*NSET, NSET=odd, GENERATE\n1, x", "'x' is not an integer; a GENERATE line is FIRST, LAST"),
])
def test_generate_ranges_are_bounded(tmp_path, line, words):
    (tmp_path / "g.inp").write_text(_inp_text(line + "\n"))
    n_lines = len(_inp_text().splitlines())
    _refused(tmp_path / "g.inp", f"g.inp:{n_lines + 2}: ", words)


def test_generate_within_the_mesh_is_read(tmp_path):
    (tmp_path / "g.inp").write_text(_inp_text("*NSET, NSET=odd, GENERATE\n1, 27, 2\n"
                                              "*ELSET, ELSET=two, GENERATE\n1, 2\n"))
    mesh = read_hex_mesh(tmp_path / "g.inp")
    assert len(mesh.node_sets["odd"]) == 14 and mesh.element_sets["two"].tolist() == [0, 1]


# 3. Duplicate node and element numbers

def test_duplicate_abaqus_node_is_refused(tmp_path, capsys):
    text = _inp_text().replace("*Element", "*Node\n5, 0.5, 0.5, 0.25\n*Element")
    (tmp_path / "d.inp").write_text(text)
    line = text.splitlines().index("5, 0.5, 0.5, 0.25") + 1
    _refused(tmp_path / "d.inp", f"d.inp:{line}: node 5 is defined twice (first at ",
             "d.inp:6)", "give each node its own number")
    code, out = _run_case(tmp_path, "d.inp", capsys)
    assert code == 2 and f"d.inp:{line}: node 5 is defined twice" in out
    assert "Traceback" not in out


def test_duplicate_abaqus_element_is_refused(tmp_path):
    lines = _inp_text().splitlines()
    k = lines.index("*Element, type=C3D8, elset=solid")
    lines.insert(k + 3, lines[k + 1])  # element 1 again
    (tmp_path / "d.inp").write_text("\n".join(lines) + "\n")
    _refused(tmp_path / "d.inp", f"d.inp:{k + 4}: element 1 is defined twice (first at ",
             f"d.inp:{k + 2})", "give each element its own number")


def test_duplicate_gmsh_node_and_element_tags_are_refused(tmp_path):
    lines = _msh(tmp_path / "b.msh").read_text().splitlines()
    k = lines.index("$Nodes")
    nodes = lines[:]
    nodes[k + 3] = "1 0.5 0.5 0.25"  # node 2's line now defines node 1 again
    (tmp_path / "n.msh").write_text("\n".join(nodes) + "\n")
    _refused(tmp_path / "n.msh", f"n.msh:{k + 4}: node tag 1 is defined twice (first at "
             f"line {k + 3})", "give each node its own tag")
    k = lines.index("$Elements")
    elems = lines[:]
    elems[k + 3] = "1" + elems[k + 3][elems[k + 3].index(" "):]
    (tmp_path / "e.msh").write_text("\n".join(elems) + "\n")
    _refused(tmp_path / "e.msh", f"e.msh:{k + 4}: element tag 1 is defined twice (first at "
             f"line {k + 3})")


# 4. Non-finite coordinates, folders, link loops, binary gmsh files

@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_non_finite_coordinates_are_named_by_file_line_and_node(tmp_path, value):
    lines = _inp_text().splitlines()
    line = next(i for i, t in enumerate(lines, 1) if t.startswith("14, "))
    lines[line - 1] = f"14, 0.5, {value}, 0.5"
    (tmp_path / "n.inp").write_text("\n".join(lines) + "\n")
    _refused(tmp_path / "n.inp", f"n.inp:{line}: node 14 has a non-finite coordinate {value}",
             "give finite x, y, z")
    msh = _msh(tmp_path / "b.msh").read_text().splitlines()
    k = msh.index("$Nodes") + 1 + 14
    msh[k] = f"14 0.5 {value} 0.5"
    (tmp_path / "n.msh").write_text("\n".join(msh) + "\n")
    _refused(tmp_path / "n.msh", f"n.msh:{k + 1}: node 14 has a non-finite coordinate {value}",
             "give finite coordinates")


def test_a_folder_as_the_mesh_file_is_named_a_folder(tmp_path):
    (tmp_path / "meshes").mkdir()
    _msh(tmp_path / "meshes" / "b.msh")
    _refused(tmp_path / "meshes", "meshes: is a directory (it holds b.msh); give a mesh file")


def test_a_symlink_loop_as_the_mesh_file_is_one_line(tmp_path):
    os.symlink("b.msh", tmp_path / "a.msh")
    os.symlink("a.msh", tmp_path / "b.msh")
    _refused(tmp_path / "a.msh", "a.msh: a symbolic link loop", "point it at a mesh file")


def test_binary_and_junk_msh_are_refused_with_the_fix(tmp_path):
    mesh = meshio.read(_msh(tmp_path / "a.msh"))
    meshio.write(tmp_path / "bin.msh", mesh, file_format="gmsh22", binary=True)
    _refused(tmp_path / "bin.msh", "bin.msh: a binary gmsh file", "save it as ASCII in gmsh")
    (tmp_path / "junk.msh").write_bytes(bytes(range(256)) * 4)
    _refused(tmp_path / "junk.msh", "junk.msh: not a gmsh .msh file",
             "export the mesh from gmsh as an ASCII .msh")


@pytest.mark.parametrize("kind", ["folder", "loop"])
def test_a_folder_or_a_link_loop_as_mesh_file_through_the_cli(tmp_path, capsys, kind):
    """The case file's own check of ``mesh_file`` names a folder as a folder and a link
    loop as a loop, in one line, exit 2, and leaves no output folder."""
    if kind == "folder":
        (tmp_path / "meshes").mkdir()
        name, words = "meshes", "is a folder"
    else:
        (tmp_path / "a.msh").symlink_to(tmp_path / "b.msh")
        (tmp_path / "b.msh").symlink_to(tmp_path / "a.msh")
        name, words = "a.msh", "a loop of symbolic links"
    code, err = _run_case(tmp_path, name, capsys)
    assert code == 2 and words in err and "mesh_file" in err and "Traceback" not in err
    assert err.count("\n") == 1 and not (tmp_path / "out").exists()


def test_allow_include_on_the_command_line(tmp_path, capsys, monkeypatch):
    """``eyefem run --allow-include DIR``: the include refused without it is read with it."""
    monkeypatch.setenv("EYEFEM_ALLOW_INCLUDE", "")  # restored after the test
    (tmp_path / "lib").mkdir()
    (tmp_path / "lib" / "block.inp").write_text(_inp_text())
    (tmp_path / "case").mkdir()
    (tmp_path / "case" / "m.inp").write_text("*INCLUDE, INPUT=../lib/block.inp\n")
    code, text = _run_case(tmp_path, "case/m.inp", capsys)
    assert code == 2 and "outside the folder" in text
    case = tmp_path / "c.toml"
    code = cli_main(["-q", "run", str(case), "--out", str(tmp_path / "out"), "--no-vtu",
                     "--allow-include", str(tmp_path / "lib")])
    assert code == 0 and (tmp_path / "out" / "summary.json").exists()
