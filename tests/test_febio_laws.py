"""FEBio's further hyperelastic laws (eyefem.fem.materials.FEBIO_LAWS, FebioLaw; the element
eyefem.fem.solid_compressible.SolidFebioLaw; the reader eyefem.io.febio_read): each law's
residual and tangent against finite differences, uniaxial tension of a cube against the
closed form of the law written here in principal stretches (numpy, from FEBio's sources),
the spectral function of the Ogden and Hencky laws at repeated eigenvalues, and the
reader's materials, fibres, material axes and refusals.
"""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.special import expi

from eyefem.fem import generators
from eyefem.fem.materials import FEBIO_LAWS, FebioLaw, spectral_sum
from eyefem.fem.mesh import Mesh
from eyefem.fem.solid_compressible import SolidFebioLaw
from eyefem.io.febio import FebError
from eyefem.io.febio_read import _rotate_e1_onto, build_stages, read_feb
from eyefem.solve.model import Model, node_dofs
from eyefem.solve.solver import Stage, solve

ORTHO = (1.0, 2.0, 1.5, 0.4, 0.5, 0.6, 0.3, 0.2, 0.25)  # E1-3, G12, G23, G31, v12, v23, v31
LAWS = {  # FEBio type -> (constants in FEBIO_LAWS' order, k or 0)
    "ogden": ((0.6, 0.2, 0, 0, 0, 0, 6.8, -2.0, 1, 1, 1, 1), 20.0),
    "ogden unconstrained": ((2.0, 0.6, 0, 0, 0, 0, 0, 3.0, 1, 1, 1, 1, 1), 0.0),
    "isotropic elastic": ((3.0, 0.3), 0.0),
    "isotropic hencky": ((3.0, 0.3), 0.0),
    "holmes-mow": ((3.0, 0.2, 0.5), 0.0),
    "uncoupled holmes-mow": ((0.5, 2.0), 20.0),
    "arruda-boyce": ((1.0, 6.0), 20.0),
    "veronda-westmann": ((0.1, 3.0), 20.0),
    "yeoh": ((0.5, -0.07, 0.01, 0, 0, 0), 20.0),
    "mooney-rivlin": ((0.5, 0.2), 20.0),
    "neo-hookean": ((3.0, 0.3), 0.0),
    "coupled mooney-rivlin": ((0.5, 0.2, 6.0), 0.0),
    "trans iso mooney-rivlin": ((0.5, 0.1, 0.3, 5.0, 8.0, 1.08), 20.0),
    "trans iso veronda-westmann": ((0.2, 1.5, 0.3, 5.0, 8.0, 1.08), 20.0),
    "fiber-exp-linear": ((0.3, 5.0, 8.0, 1.08), 0.0),
    "uncoupled fiber-exp-linear": ((0.0, 5.0, 8.0, 1.08), 20.0),
    "orthotropic elastic": (ORTHO, 0.0),
    "fung orthotropic": (ORTHO + (2.0,), 20.0),
    "fung-ortho-compressible": (ORTHO + (2.0, 6.0), 0.0),
}


def _law(kind, consts=None, k=None):
    c, kk = LAWS[kind]
    return FebioLaw("m", kind, ((kind, consts or c),), FEBIO_LAWS[kind][1],
                    kk if k is None else k)


def _directions(law, n_el):
    """Unit fibre (along (1, 1, 0.5)) or material axes (rotated about z) of each point."""
    t = 0.4
    axes = np.array([[np.cos(t), np.sin(t), 0], [-np.sin(t), np.cos(t), 0], [0, 0, 1.0]])
    fib = np.array([1.0, 1.0, 0.5]) / 1.5
    rows = []
    for _, _, nd in law.structure():
        rows += [fib] if nd == 1 else list(axes) if nd == 3 else []
    if not rows:
        return None
    return np.broadcast_to(np.array(rows), (n_el, 8, len(rows), 3))


def _element(law):
    rng = np.random.default_rng(3)
    box = generators.box(1.0, 1.2, 0.8, 1, 1, 1)
    X = box.nodes[box.hexes[0]] + 0.08 * rng.standard_normal((8, 3))
    mesh = Mesh(X, np.arange(8)[None], np.array([0]), ("m",))
    return SolidFebioLaw("m", mesh, law, np.array([0]), _directions(law, 1))


@pytest.mark.parametrize("kind", sorted(LAWS))
def test_residual_and_tangent_against_finite_differences(kind):
    """The element's residual is the derivative of its energy, its tangent the derivative
    of its residual (central differences; the fibre stretched beyond lam_max)."""
    law = _law(kind)
    term = _element(law)
    p, d = term.params, term.data
    fib = np.array([1.0, 1.0, 0.5]) / 1.5  # stretched 12 % along the fibre: in tension
    X = term.mesh.nodes
    u = (0.05 * np.random.default_rng(11).standard_normal((8, 3))
         + 0.12 * (X @ fib)[:, None] * fib).ravel()
    e_jit = jax.jit(lambda x: term.local_energy(x[None], p, d)[0])
    gh_jit = jax.jit(lambda x: term.local_grad_hess(x[None], p, d))
    energy = lambda x: float(e_jit(jnp.asarray(x)))  # noqa: E731
    grad = lambda x: np.asarray(gh_jit(jnp.asarray(x))[0][0])  # noqa: E731
    g, H = (np.asarray(a)[0] for a in gh_jit(jnp.asarray(u)))
    h = 1e-6
    basis = np.eye(24)
    g_fd = np.array([(energy(u + h * b) - energy(u - h * b)) / (2 * h) for b in basis])
    assert np.abs(g_fd - g).max() < 1e-6 * np.abs(g).max()
    H_fd = np.stack([(grad(u + h * b) - grad(u - h * b)) / (2 * h) for b in basis], axis=1)
    assert np.abs(H_fd - H).max() < 1e-6 * np.abs(H).max()
    assert np.abs(H - H.T).max() < 1e-10 * np.abs(H).max()
    # stress free and finite in the reference state (repeated eigenvalues for Ogden)
    g0, H0 = (np.asarray(a)[0] for a in gh_jit(jnp.zeros(24)))
    assert np.abs(g0).max() <= 1e-12 * max(np.abs(H0).max(), 1.0) and np.isfinite(H0).all()


def test_spectral_sum_at_repeated_eigenvalues():
    """tr C^p's Hessian at C = I and along a stretch with two equal eigenvalues against
    the closed forms (p (p - 1) on the diagonal: d2/dC_00^2 of sum lam^p)."""
    f = lambda C: spectral_sum(C, 1.7, 0)  # noqa: E731
    H = np.asarray(jax.hessian(f)(jnp.eye(3))).reshape(9, 9)
    assert H[0, 0] == pytest.approx(1.7 * 0.7, rel=1e-12)
    # off-diagonal C_01 = C_10 = s: eigenvalues 1 +- s; d2/ds2 of (1+s)^p + (1-s)^p = 2p(p-1)
    g = lambda s: f(jnp.eye(3) + s * jnp.array([[0, 1, 0], [1, 0, 0], [0, 0, 0.0]]))  # noqa
    assert float(jax.grad(jax.grad(g))(0.0)) == pytest.approx(2 * 1.7 * 0.7, rel=1e-12)
    C = jnp.diag(jnp.array([1.3, 0.9, 0.9]))
    assert float(f(C)) == pytest.approx(1.3 ** 1.7 + 2 * 0.9 ** 1.7, rel=1e-14)
    assert np.allclose(jax.grad(f)(C), np.diag([1.7 * 1.3 ** 0.7, 1.7 * 0.9 ** 0.7,
                                                1.7 * 0.9 ** 0.7]), rtol=1e-12)


# ------------------------------------------------------------- closed forms, principal stretches
def _lame(E, v):
    return v * E / ((1 + v) * (1 - 2 * v)), E / (2 * (1 + v))


def _fiber(lt, c3, c4, c5, lam1):
    if lt < 1:
        return 0.0
    c3 = c3 or c5 / c4 * np.exp(-c4 * (lam1 - 1))
    w = lambda x: c3 * np.exp(-c4) * (expi(c4 * x) - expi(c4)) - c3 * np.log(x)  # noqa: E731
    if lt <= lam1:
        return w(lt)
    c6 = c3 * (np.exp(c4 * (lam1 - 1)) - 1) - c5 * lam1
    return c5 * (lt - lam1) + c6 * np.log(lt / lam1) + w(lam1)


def w_principal(kind, c, k, s):
    """W (MPa) at principal stretches s (3,), axes and fibre along x, y, z (FEBio's
    definitions: the sources named in eyefem.fem.materials.FEBIO_LAWS)."""
    J = s.prod()
    sb = s * J ** (-1 / 3)
    i1, i2 = (sb ** 2).sum(), (sb[0] * sb[1]) ** 2 + (sb[1] * sb[2]) ** 2 + (sb[0] * sb[2]) ** 2
    U = 0.5 * k * np.log(J) ** 2
    if kind == "ogden":
        return U + sum(c[j] / c[6 + j] ** 2 * ((sb ** c[6 + j]).sum() - 3) for j in range(6))
    if kind == "ogden unconstrained":
        return 0.5 * c[0] * (J - 1) ** 2 + sum(c[1 + j] / c[7 + j] ** 2 * (
            (s ** c[7 + j]).sum() - 3 - c[7 + j] * np.log(J)) for j in range(6))
    if kind == "isotropic elastic":
        lam, mu = _lame(*c)
        E = 0.5 * (s ** 2 - 1)
        return 0.5 * lam * E.sum() ** 2 + mu * (E ** 2).sum()
    if kind == "holmes-mow":
        lam, mu = _lame(c[0], c[1])
        ha = lam + 2 * mu
        I1, I2 = (s ** 2).sum(), (s[0] * s[1]) ** 2 + (s[1] * s[2]) ** 2 + (s[0] * s[2]) ** 2
        eq = np.exp(c[2] * ((2 * mu - lam) * (I1 - 3) + lam * (I2 - 3)) / ha) / J ** (2 * c[2])
        return ha / (4 * c[2]) * (eq - 1)
    if kind == "trans iso mooney-rivlin":
        return U + c[0] * (i1 - 3) + c[1] * (i2 - 3) + _fiber(sb[0], *c[2:])
    if kind == "orthotropic elastic":
        E1, E2, E3, G12, G23, G31, v12, v23, v31 = c
        mu = np.array([G12 + G31 - G23, G12 - G31 + G23, -G12 + G31 + G23])
        comp = np.array([[1 / E1, -v12 / E1, -v31 / E3], [-v12 / E1, 1 / E2, -v23 / E2],
                         [-v31 / E3, -v23 / E2, 1 / E3]])
        lam = np.linalg.inv(comp) - 2 * np.diag(mu)
        E = 0.5 * (s ** 2 - 1)
        return mu @ E ** 2 + 0.5 * E @ lam @ E
    raise KeyError(kind)


def principal_stress(kind, c, k, s, h=1e-6):
    """Cauchy stresses (3,) s_i / J dW/ds_i (central differences)."""
    dW = np.array([(w_principal(kind, c, k, s + h * e) - w_principal(kind, c, k, s - h * e))
                   / (2 * h) for e in np.eye(3)])
    return s * dW / s.prod()


@pytest.mark.parametrize("kind, lam", [
    ("ogden", 1.3), ("ogden", 0.8), ("ogden unconstrained", 1.25), ("isotropic elastic", 1.2),
    ("holmes-mow", 1.3), ("trans iso mooney-rivlin", 1.05), ("trans iso mooney-rivlin", 1.15),
    ("trans iso mooney-rivlin", 0.85),
    ("orthotropic elastic", 1.1)])
def test_uniaxial_tension_of_a_cube(kind, lam):
    """A unit cube of 2 x 2 x 2 hexahedra, symmetry planes x = y = z = 0, x = 1 moved to
    lam: homogeneous, the lateral stretches where the closed form's lateral stresses vanish
    and the axial reaction its sigma_xx times the deformed face's area (1e-7)."""
    c, k = LAWS[kind]
    law = _law(kind)
    mesh = generators.box(1.0, 1.0, 1.0, 2, 2, 2, material="m")
    rows = []
    for _, _, nd in law.structure():
        rows += [np.eye(3)[0]] if nd == 1 else list(np.eye(3)) if nd == 3 else []
    fib = np.broadcast_to(np.array(rows), (mesh.n_elem, 8, len(rows), 3)) if rows else None
    model = Model(mesh, (SolidFebioLaw("m", mesh, law, np.arange(mesh.n_elem), fib),),
                  3 * mesh.n_nodes)
    held = [node_dofs(mesh.node_set(s), a) for s, a in (("x0", "x"), ("y0", "y"), ("z0", "z"))]
    pull = node_dofs(mesh.node_set("x1"), "x")
    dofs = np.concatenate(held + [pull])
    vals = np.r_[np.zeros(sum(len(h) for h in held)), np.full(len(pull), lam - 1.0)]
    q = np.asarray(solve(model, [Stage("pull", 4, (dofs, vals))]).q)
    u = q.reshape(-1, 3)
    sy, sz = 1 + u[mesh.node_set("y1"), 1], 1 + u[mesh.node_set("z1"), 2]
    assert np.ptp(sy) < 1e-10 and np.ptp(sz) < 1e-10
    force = float(model.gradient(q, model.theta0())[pull].sum())
    if kind == "orthotropic elastic":  # two lateral stretches
        from scipy.optimize import fsolve
        ly, lz = fsolve(lambda m: principal_stress(kind, c, k, np.array([lam, *m]))[1:],
                        [0.95, 0.95], xtol=1e-14)
    else:
        ly = lz = brentq(lambda m: principal_stress(kind, c, k, np.array([lam, m, m]))[1],
                         0.5, 1.5, xtol=1e-15)
    assert sy.mean() == pytest.approx(ly, abs=1e-7) and sz.mean() == pytest.approx(lz, abs=1e-7)
    f_ref = principal_stress(kind, c, k, np.array([lam, ly, lz]))[0] * ly * lz
    assert force == pytest.approx(f_ref, rel=1e-6)


def test_spherical_fibre_is_febios_quaternion_rotation():
    """FESphericalVectorGenerator: v rotated by quatd(e1, a) (FEBio's RotateVector, ported
    here) for a = (X - centre) / |X - centre|; parallel and opposite a leave v as it is."""
    def febio(a, v):
        a = a / np.linalg.norm(a)
        e1 = np.array([1.0, 0, 0])
        n = np.cross(e1, a)
        n = n / np.linalg.norm(n) if np.linalg.norm(n) > 0 else n
        d = e1 @ a
        w, (x, y, z) = np.sqrt((1 + d) / 2), n * np.sqrt((1 - d) / 2)
        if w == 0 or not (x or y or z):
            return v
        qw = v @ [x, y, z]
        qx, qy, qz = (v[0] * w - v[1] * z + v[2] * y, v[1] * w - v[2] * x + v[0] * z,
                      v[2] * w - v[0] * y + v[1] * x)
        return np.array([w * qx + x * qw + y * qz - z * qy, w * qy + y * qw + z * qx - x * qz,
                         w * qz + z * qw + x * qy - y * qx])
    rng = np.random.default_rng(5)
    r = np.r_[rng.standard_normal((6, 3)), [[2.0, 0, 0], [-1.0, 0, 0]]]
    v = np.array([0.3, -0.5, 0.8])
    got = _rotate_e1_onto(r, v)
    assert np.allclose(got, [febio(a, v) for a in r], atol=1e-13)


# ----------------------------------------------------------------------------- the reader
DECK = """<?xml version="1.0"?>
<febio_spec version="4.0">
  <Module type="solid"/>
  <Control><analysis>STATIC</analysis><time_steps>2</time_steps><step_size>0.5</step_size>
  </Control>
  <Material>
    MATERIAL
  </Material>
  <Mesh>
    <Nodes name="all">
      <node id="1">0,0,0</node><node id="2">1,0,0</node><node id="3">1,1,0</node>
      <node id="4">0,1,0</node><node id="5">0,0,1</node><node id="6">1,0,1</node>
      <node id="7">1,1,1</node><node id="8">0,1,1</node>
    </Nodes>
    <Elements type="hex8" name="Part1"><elem id="1">1,2,3,4,5,6,7,8</elem></Elements>
    <NodeSet name="x0">1,4,5,8</NodeSet><NodeSet name="y0">1,2,5,6</NodeSet>
    <NodeSet name="z0">1,2,3,4</NodeSet><NodeSet name="x1">2,3,6,7</NodeSet>
  </Mesh>
  <MeshDomains><SolidDomain name="Part1" mat="m"/></MeshDomains>
  MESHDATA
  <Boundary>
    <bc name="a" node_set="x0" type="zero displacement"><x_dof>1</x_dof><y_dof>0</y_dof>
      <z_dof>0</z_dof></bc>
    <bc name="b" node_set="y0" type="zero displacement"><x_dof>0</x_dof><y_dof>1</y_dof>
      <z_dof>0</z_dof></bc>
    <bc name="c" node_set="z0" type="zero displacement"><x_dof>0</x_dof><y_dof>0</y_dof>
      <z_dof>1</z_dof></bc>
    <bc name="d" node_set="x1" type="prescribed displacement"><dof>x</dof>
      <value lc="1">0.2</value><relative>0</relative></bc>
  </Boundary>
  <LoadData><load_controller id="1" type="loadcurve"><interpolate>LINEAR</interpolate>
    <points><pt>0,0</pt><pt>1,1</pt></points></load_controller></LoadData>
</febio_spec>
"""

TIMR = """<material id="1" name="m" type="trans iso Mooney-Rivlin"><k>20</k><c1>0.5</c1>
  <c2>0.1</c2><c3>0.3</c3><c4>5</c4><c5>8</c5><lam_max>1.08</lam_max>FIBER</material>"""


def _write(tmp_path, material, meshdata=""):
    f = tmp_path / "d.feb"
    f.write_text(DECK.replace("MATERIAL", material).replace("MESHDATA", meshdata))
    return f


@pytest.mark.parametrize("fiber, expect", [
    ('<fiber type="vector"><vector>0,2,0</vector></fiber>', lambda X: np.array([0, 1.0, 0])),
    ('<fiber type="local"><local>1,7</local></fiber>', lambda X: np.ones(3) / np.sqrt(3)),
    ('<fiber type="spherical"><center>-1,0,0</center><vector>1,0,0</vector></fiber>',
     lambda X: (X - [-1, 0, 0]) / np.linalg.norm(X - [-1, 0, 0])),
    ('<fiber type="user"/>', lambda X: np.array([0, 0, 1.0])),
])
def test_reader_fibres(tmp_path, fiber, expect):
    from eyefem.fem.mesh import hex_gauss_points, hex_shape
    md = ('<MeshData><ElementData type="fiber" elem_set="Part1"><e lid="1">0,0,3</e>'
          '</ElementData></MeshData>') if "user" in fiber else ""
    mesh, mats, loads = read_feb(_write(tmp_path, TIMR.replace("FIBER", fiber), md))
    law = mats["m"]
    assert isinstance(law, FebioLaw) and law.uncoupled and law.k == 20.0
    assert law.parts == (("trans iso mooney-rivlin", (0.5, 0.1, 0.3, 5.0, 8.0, 1.08)),)
    shape, _ = hex_shape(hex_gauss_points()[0])
    xg = shape @ mesh.nodes[mesh.hexes[0]]
    assert np.allclose(loads.fibers["m"][0, :, 0], [expect(x) for x in xg], atol=1e-14)
    model, stages = build_stages(mesh, mats, loads)
    assert [t.name for t in model.terms][:1] == ["solid:m"]
    assert np.isfinite(np.asarray(solve(model, stages).q)).all()


def test_reader_mixture_and_material_axes(tmp_path):
    mix = """<material id="1" name="m" type="uncoupled solid mixture"><k>10</k>
      <solid type="Mooney-Rivlin"><k>0</k><c1>0.2</c1><c2>0</c2></solid>
      <solid type="uncoupled fiber-exp-linear"><c3>0</c3><c4>43</c4><c5>3</c5>
        <lambda>1.07</lambda><fiber type="vector"><vector>0,0,1</vector></fiber></solid>
      </material>"""
    _, mats, loads = read_feb(_write(tmp_path, mix))
    assert mats["m"].parts == (("mooney-rivlin", (0.2, 0.0)),
                               ("uncoupled fiber-exp-linear", (0.0, 43.0, 3.0, 1.07)))
    assert mats["m"].k == 10.0 and np.allclose(loads.fibers["m"][0, 0, 0], [0, 0, 1])
    ortho = ("<material id=\"1\" name=\"m\" type=\"orthotropic elastic\">" + "".join(
        f"<{n}>{v}</{n}>" for n, v in zip(("E1", "E2", "E3", "G12", "G23", "G31", "v12", "v23",
                                           "v31"), ORTHO))
        + '<mat_axis type="vector"><a>0.866,0.5,0</a><d>-0.5,0.866,0</d></mat_axis></material>')
    _, mats, loads = read_feb(_write(tmp_path, ortho))
    axes = loads.fibers["m"][0, 3]  # a Gauss point's three axes (rows)
    a = np.array([0.866, 0.5, 0]) / np.linalg.norm([0.866, 0.5, 0])
    assert np.allclose(axes[0], a) and np.allclose(axes[2], [0, 0, 1])
    assert np.allclose(axes @ axes.T, np.eye(3), atol=1e-14)


@pytest.mark.parametrize("material, message", [
    (TIMR.replace("FIBER", "<active_contraction><ascl>1</ascl></active_contraction>"),
     "active contraction"),
    (TIMR.replace("FIBER", '<fiber type="cylindrical"/>'), 'fiber type="cylindrical"'),
    (TIMR.replace("FIBER", '<fiber type="user"/>'), "no <MeshData> ElementData"),
    (TIMR.replace("<k>20</k>", "").replace("FIBER", ""), "needs a bulk modulus k > 0"),
    ('<material id="1" name="m" type="Ogden"><k>10</k><c1>1</c1><m1>0</m1></material>',
     "exponents must not be 0"),
    ('<material id="1" name="m" type="Ogden"><k>10</k><c1 type="map">c1map</c1></material>',
     "a parameter map"),
    ('<material id="1" name="m" type="Ogden"><k lc="1">10</k><c1>1</c1></material>',
     "a load curve on this parameter"),
    ('<material id="1" name="m" type="solid mixture"><solid type="Shenoy"/></material>',
     'solid type="Shenoy"> is not supported'),
    ('<material id="1" name="m" type="Holmes-Mow"><E>1</E><v>0.6</v><beta>1</beta></material>',
     "-1 < v < 0.5"),
    ('<material id="1" name="m" type="solid mixture"><solid type="Mooney-Rivlin"><c1>1</c1>'
     '<k>10</k></solid></material>', "an uncoupled constituent of a (coupled) solid mixture"),
])
def test_reader_refusals_name_the_feature(tmp_path, material, message):
    with pytest.raises(FebError, match=re.escape(message)):
        read_feb(_write(tmp_path, material))


def test_mesh_data_other_than_fibres_is_refused_by_kind(tmp_path):
    md = ('<MeshData><ElementData type="mat_axis" elem_set="Part1"><e lid="1">'
          '<a>1,0,0</a><d>0,1,0</d></e></ElementData></MeshData>')
    with pytest.raises(FebError, match=re.escape('<MeshData><ElementData type="mat_axis">')):
        read_feb(_write(tmp_path, TIMR.replace("FIBER", ""), md))


def test_stiff_solids_are_warned_not_refused(tmp_path, caplog):
    """Steel (E = 200 GPa) is above the case files' range: read with a warning; a c1 above
    STIFF_SOLID_C1 (25 MPa written in Pa) is still refused."""
    steel = '<material id="1" name="m" type="neo-Hookean"><E>200000</E><v>0.3</v></material>'
    _, mats, _ = read_feb(_write(tmp_path, steel))
    assert "stiff solid" in caplog.text
    with pytest.raises(FebError, match="impossible"):
        read_feb(_write(tmp_path, steel.replace("200000", "2.5e8")))


def test_active_contraction_on_a_load_curve(tmp_path):
    """A neo-Hookean cube (symmetry planes, otherwise free) with FEBio's prescribed
    isotropic active contraction T0 = -0.2 x lc(t) (stress T0 b / J): the step's constants
    are T0 at the step's end, the start's at t = 0, and the cube settles where the
    homogeneous stretch l makes mu (l^2 - 1) + lam ln J + T0 l^2 = 0 (J = l^3)."""
    mat = """<material id="1" name="m" type="solid mixture">
      <solid type="neo-Hookean"><E>1</E><v>0.3</v></solid>
      <solid type="prescribed isotropic active contraction"><T0 lc="1">-0.2</T0></solid>
      </material>"""
    deck = re.sub(r'<bc name="d".*?</bc>', "", DECK.replace("MATERIAL", mat).replace(
        "MESHDATA", ""), flags=re.S)  # no pull: free but for the symmetry planes
    f = tmp_path / "a.feb"
    f.write_text(deck)
    mesh, mats, loads = read_feb(f)
    assert mats["m"].curves == ((2, "1"),)  # E, v, then T0
    assert loads.law_constants["m"] == pytest.approx([1.0, 0.3, 0.0])
    assert loads.steps[-1].params["solid:m"]["c"] == pytest.approx([1.0, 0.3, -0.2])
    model, stages = build_stages(mesh, mats, loads)
    q = np.asarray(solve(model, stages).q).reshape(-1, 3)
    lam, mu = _lame(1.0, 0.3)
    ref = brentq(lambda s: mu * (s * s - 1) + lam * np.log(s ** 3) - 0.2 * s * s, 0.5, 2.0,
                 xtol=1e-15)
    assert 1 + q[6] == pytest.approx([ref, ref, ref], abs=1e-9)  # node 7 at (1, 1, 1)
