"""Structured mesh generators: counts, volumes, quality, sets and face orientation."""

import numpy as np
import pytest

from eyefem.fem import generators
from eyefem.fem.mesh import boundary_faces, hex_geometry, open_edges, quad_gauss_points, quad_shape


def volume(m):
    return hex_geometry(m.nodes, m.hexes)[1].sum()


def face_normals(nodes, faces):
    """Unit right-hand normals (n, 3) and centroids (n, 3) of quads."""
    x = nodes[faces]
    n = np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 1])
    return n / np.linalg.norm(n, axis=1, keepdims=True), x.mean(axis=1)


def flux_x_dot_n(nodes, faces):
    """sum over faces of integral x . n dA (2x2 Gauss, bilinear quads); = 3 V for a closed
    outward surface around V."""
    xg, wg = quad_gauss_points()
    n, dn = quad_shape(xg)  # (4g, 4a), (4g, 4a, 2)
    xe = nodes[faces]  # (F, 4, 3)
    x = np.einsum("ga,fai->fgi", n, xe)
    t = np.einsum("gaj,fai->fgij", dn, xe)
    nda = np.cross(t[..., 0], t[..., 1])
    return np.einsum("fgi,fgi,g->", x, nda, wg)


def same_faces(a, b):
    return {tuple(sorted(f)) for f in a.tolist()} == {tuple(sorted(f)) for f in b.tolist()}


# --- box ----------------------------------------------------------------------------------

def test_box_counts_volume_sets_normals():
    o = np.array([1.0, -2.0, 0.5])
    L = np.array([2.0, 1.5, 0.7])
    m = generators.box(*L, 4, 3, 2, origin=o, material="steel")
    assert m.n_elem == 24 and m.n_nodes == 5 * 4 * 3
    assert m.materials == ("steel",)
    assert volume(m) == pytest.approx(L.prod(), rel=1e-12)
    assert np.allclose(m.jacobian_ratio(), 1.0)
    assert np.allclose(m.nodes.min(0), o) and np.allclose(m.nodes.max(0), o + L)
    counts = {"x": 3 * 2, "y": 4 * 2, "z": 4 * 3}
    for ax, name in enumerate("xyz"):
        for side, val in ((0, o[ax]), (1, o[ax] + L[ax])):
            key = f"{name}{side}"
            ns = m.node_set(key)
            assert np.allclose(m.nodes[ns, ax], val)
            assert len(ns) == np.isclose(m.nodes[:, ax], val).sum()
            f = m.face_set(key)
            assert len(f) == counts[name]
            assert np.all(np.isin(f, ns))
            nrm, _ = face_normals(m.nodes, f)
            want = np.eye(3)[ax] * (1 if side else -1)
            assert np.allclose(nrm, want)
    assert same_faces(m.face_set("boundary"), boundary_faces(m.hexes))
    assert len(open_edges(m.face_set("boundary"))) == 0
    assert flux_x_dot_n(m.nodes, m.face_set("boundary")) == pytest.approx(3 * L.prod())


@pytest.mark.parametrize("args", [(1, 1, 1, 0, 1, 1), (1, 0, 1, 1, 1, 1), (-1, 1, 1, 1, 1, 1)])
def test_box_rejects_bad_input(args):
    with pytest.raises(ValueError):
        generators.box(*args)


# --- quarter disk -------------------------------------------------------------------------

def test_quarter_disk_seed_size():
    m = generators.quarter_disk(10.0, 0.1, 52, 50, 1)
    assert m.n_elem == 25**2 + 50 * 52 == 3225
    assert generators.quarter_disk(10.0, 0.1, 20, 50, 2).n_elem == 3250
    assert m.jacobian_ratio().min() > 0.3


@pytest.mark.parametrize("nr,nc,nt", [(3, 4, 1), (6, 8, 2), (5, 10, 3)])
def test_quarter_disk_sets_and_orientation(nr, nc, nt):
    R, h = 5.0, 0.4
    m = generators.quarter_disk(R, h, nr, nc, nt, material="rubber")
    X = m.nodes
    n2 = (nc // 2) ** 2 + nc * nr
    assert m.n_elem == n2 * nt
    assert m.n_nodes == ((nc // 2 + 1) ** 2 + (nc + 1) * nr) * (nt + 1)
    assert m.jacobian_ratio().min() > 0.3
    assert X[:, 0].min() == 0.0 and X[:, 1].min() == 0.0
    assert X[:, 2].min() == 0.0 and X[:, 2].max() == pytest.approx(h)
    r = np.hypot(X[:, 0], X[:, 1])
    assert r.max() == pytest.approx(R)
    # node sets lie where documented and are complete
    per_line = nc // 2 + nr + 1
    for key, ax in (("sym_x", 0), ("sym_y", 1)):
        ns = m.node_set(key)
        assert np.all(X[ns, ax] == 0.0) and len(ns) == per_line * (nt + 1)
    rim = m.node_set("rim")
    assert np.allclose(r[rim], R) and len(rim) == (nc + 1) * (nt + 1)
    pole = m.node_set("pole")
    assert np.all(r[pole] == 0.0) and len(pole) == nt + 1
    (pb,), (pt,) = m.node_set("pole_bottom"), m.node_set("pole_top")
    assert np.allclose(X[pb], 0.0) and np.allclose(X[pt], [0, 0, h])
    # face sets: bottom -z, top +z, rim radially outward
    for key, z, nz in (("bottom", 0.0, -1.0), ("top", h, 1.0)):
        f = m.face_set(key)
        assert len(f) == n2
        nrm, _ = face_normals(X, f)
        assert np.allclose(X[f, 2], z) and np.allclose(nrm, [0, 0, nz])
        # covers the quarter disk: polygonal area close to pi R^2 / 4
        assert len(open_edges(f)) == 2 * per_line - 2 + nc
    nrm, c = face_normals(X, m.face_set("rim"))
    assert len(nrm) == nc * nt
    radial = c[:, :2] / np.hypot(c[:, 0], c[:, 1])[:, None]
    assert np.all(np.einsum("fi,fi->f", nrm[:, :2], radial) > 0.99) and np.allclose(nrm[:, 2], 0)
    # conforming: the only boundary faces are bottom, top, rim and the two symmetry planes
    assert len(boundary_faces(m.hexes)) == 2 * n2 + nc * nt + 2 * (per_line - 1) * nt


def test_quarter_disk_volume_converges():
    R, h = 10.0, 0.1
    exact = np.pi * R**2 * h / 4
    errs = [abs(volume(generators.quarter_disk(R, h, nr, nc, 1)) / exact - 1)
            for nr, nc in ((4, 8), (8, 16), (16, 32))]
    assert errs[0] < 0.02 and errs[-1] < 1e-3
    assert errs[1] < 0.3 * errs[0] and errs[2] < 0.3 * errs[1]  # ~ O(1/n_circ^2)
    assert abs(volume(generators.quarter_disk(R, h, 52, 50, 1)) / exact - 1) < 1e-3


@pytest.mark.parametrize("core", [0.3, 0.7])
def test_quarter_disk_core_size(core):
    m = generators.quarter_disk(1.0, 0.1, 6, 10, 1, core=core)
    assert m.jacobian_ratio().min() > 0.3
    assert volume(m) == pytest.approx(np.pi * 0.1 / 4, rel=0.01)


def test_quarter_disk_rejects_odd_n_circ():
    with pytest.raises(ValueError, match="even"):
        generators.quarter_disk(1.0, 0.1, 4, 7, 1)


# --- spherical shell ----------------------------------------------------------------------

@pytest.mark.parametrize("n,nt", [(1, 1), (4, 1), (11, 2)])
def test_shell_counts_volume_quality(n, nt):
    ri, t = 11.0, 1.0
    m = generators.spherical_shell(ri, t, n, nt)
    assert m.n_elem == 6 * n * n * nt
    assert m.n_nodes == (6 * n * n + 2) * (nt + 1)
    assert m.jacobian_ratio().min() > 0.3
    if n == 11:
        assert m.n_elem == 1452
        exact = 4 / 3 * np.pi * ((ri + t) ** 3 - ri**3)
        assert volume(m) == pytest.approx(exact, rel=0.01)


def test_shell_volume_converges():
    ri, t = 11.0, 1.0
    exact = 4 / 3 * np.pi * ((ri + t) ** 3 - ri**3)
    errs = [abs(volume(generators.spherical_shell(ri, t, n, 1)) / exact - 1) for n in (4, 8, 16)]
    assert errs[1] < 0.3 * errs[0] and errs[2] < 0.3 * errs[1]  # O(1/n^2) chordal error
    assert errs[2] < 5e-3


def test_shell_surfaces_closed_oriented_and_enclosing():
    ri, t, n, nt = 11.0, 1.0, 11, 2
    m = generators.spherical_shell(ri, t, n, nt)
    X = m.nodes
    r = np.linalg.norm(X, axis=1)
    assert np.allclose(r[m.node_set("inner")], ri) and np.allclose(r[m.node_set("outer")], ri + t)
    assert len(m.node_set("inner")) == len(m.node_set("outer")) == 6 * n * n + 2
    assert len(m.node_set("all")) == m.n_nodes
    inner, outer = m.face_set("inner"), m.face_set("outer")
    assert len(inner) == len(outer) == 6 * n * n
    assert len(open_edges(inner)) == 0 and len(open_edges(outer)) == 0
    # conforming: no internal seams left open between the patches
    bf = boundary_faces(m.hexes)
    assert len(bf) == 2 * 6 * n * n and same_faces(bf, np.concatenate([inner, outer]))
    for f, sign, rad in ((inner, -1, ri), (outer, 1, ri + t)):
        assert np.allclose(r[f], rad)
        nrm, c = face_normals(X, f)
        radial = c / np.linalg.norm(c, axis=1, keepdims=True)
        assert np.all(sign * np.einsum("fi,fi->f", nrm, radial) > 0.95)
    # the inner surface (normals toward the centre) encloses the cavity
    v_cav = -flux_x_dot_n(X, inner) / 3
    assert v_cav == pytest.approx(4 / 3 * np.pi * ri**3, rel=0.01)
    assert flux_x_dot_n(X, outer) / 3 == pytest.approx(4 / 3 * np.pi * (ri + t) ** 3, rel=0.01)


def test_shell_benchmark_sizes():
    """The benchmark shells (benchmarks/bench_core.py; their generation time is measured
    there, not here)."""
    m = generators.spherical_shell(11.0, 1.0, 32, 2)
    assert m.n_elem == 12288
    assert len(open_edges(m.face_set("inner"))) == 0
    assert generators.spherical_shell(11.0, 1.0, 25, 3).n_elem == 11250


def test_shell_octant():
    ri, t, n, nt = 11.0, 1.0, 12, 2
    full = generators.spherical_shell(ri, t, n, nt)
    m = generators.spherical_shell(ri, t, n, nt, octant=True)
    X = m.nodes
    assert m.n_elem == full.n_elem // 8 == 3 * (n // 2) ** 2 * nt
    assert X.min() == 0.0
    assert m.jacobian_ratio().min() > 0.3
    assert volume(m) == pytest.approx(volume(full) / 8, rel=1e-10)
    r = np.linalg.norm(X, axis=1)
    assert np.allclose(r[m.node_set("inner")], ri) and np.allclose(r[m.node_set("outer")], ri + t)
    m2 = n // 2 + 1
    for ax, key in enumerate(("sym_x", "sym_y", "sym_z")):
        ns = m.node_set(key)
        assert np.all(X[ns, ax] == 0.0) and len(ns) == (2 * m2 - 1) * (nt + 1)
        nrm, _ = face_normals(X, m.face_set(key))
        assert len(nrm) == n * nt and np.allclose(nrm, -np.eye(3)[ax])
    inner = m.face_set("inner")
    nrm, c = face_normals(X, inner)
    assert np.all(np.einsum("fi,fi->f", nrm, c) < 0)
    # the inner surface is open only along the symmetry planes
    e = open_edges(inner)
    on_plane = np.any(X[e] == 0, axis=2)  # (n_edges, 2)
    assert len(e) == 3 * n and np.all(on_plane)
    assert len(boundary_faces(m.hexes)) == 2 * len(inner) + 3 * n * nt
    # cavity volume of the octant: the symmetry planes carry no x . n flux
    assert -flux_x_dot_n(X, inner) / 3 == pytest.approx(np.pi * ri**3 / 6, rel=0.01)


def test_shell_rejects_bad_input():
    with pytest.raises(ValueError, match="even"):
        generators.spherical_shell(1.0, 0.1, 5, 1, octant=True)
    with pytest.raises(ValueError):
        generators.spherical_shell(1.0, 0.0, 4, 1)
