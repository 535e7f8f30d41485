"""Automatic suture generation: ray-face intersection and bite positions by hand."""

import numpy as np
import pytest

from eyefem.eye.sutures import generate_sutures, ray_face_intersection, suture_bar_ends
from eyefem.fem.bars import bilinear


def _sphere_patch(radius, n=24, half_angle=0.6):
    """Quads on a sphere around +z (outward normals), nodes (k, 3), faces (m, 4)."""
    a = np.linspace(-half_angle, half_angle, n + 1)
    u, v = np.meshgrid(a, a, indexing="ij")
    d = np.stack([np.tan(u), np.tan(v), np.ones_like(u)], -1)
    xyz = radius * (d / np.linalg.norm(d, axis=-1, keepdims=True)).reshape(-1, 3)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    faces = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 4)
    return xyz, faces


def test_ray_hits_bilinear_face_inside():
    xyz = np.array([[0, 0, 0], [2, 0, 0], [2, 2, 0.4], [0, 2, 0]], float)
    faces = np.array([[0, 1, 2, 3]])
    hit = ray_face_intersection(xyz, faces, [1.5, 0.5, 5.0], [0, 0, -1])
    assert hit is not None
    f, xi, t = hit
    p = bilinear(xi) @ xyz[faces[f]]
    np.testing.assert_allclose(p[:2], [1.5, 0.5], atol=1e-12)
    # bilinear surface z = 0.1 * x * y on this face
    assert p[2] == pytest.approx(0.1 * 1.5 * 0.5, abs=1e-12)
    assert t == pytest.approx(5.0 - p[2])
    assert ray_face_intersection(xyz, faces, [5.0, 5.0, 5.0], [0, 0, -1]) is None


def test_bites_on_sphere_at_hand_computed_positions():
    """Sutures across a strip over the pole of a 12 mm sphere: bites at +-w/2 along x."""
    R = 12.0
    xyz, faces = _sphere_patch(R)
    top = R + 0.8
    cen = np.array([[0.0, 0.0, top], [0.0, 2.0, np.sqrt(top**2 - 4)]])
    nrm = cen / np.linalg.norm(cen, axis=1, keepdims=True)
    across = np.array([[1.0, 0, 0], [1.0, 0, 0]])
    lay = generate_sutures(xyz, faces, cen, across, nrm, width=9.0, n_bars=3)
    pa, pb = lay.bite_a.positions(xyz), lay.bite_b.positions(xyz)
    # the bites lie on the ray from the centre through centre -+ w/2 across
    for k in range(2):
        for p, s in ((pa[k], -1), (pb[k], 1)):
            d = cen[k] + s * 4.5 * across[k]
            d /= np.linalg.norm(d)
            assert np.linalg.norm(np.cross(p / np.linalg.norm(p), d)) < 1e-9
            assert np.linalg.norm(p) == pytest.approx(R, rel=2e-3)  # on the faceted sphere
    assert lay.n_bars == 3 and lay.over_xyz.shape == (2, 2, 3)
    L = lay.lengths(xyz)
    assert np.all(L > 9.0) and np.all(L < 12.0)
    na, xa, nb, xb, which = suture_bar_ends(lay, over_node_ids=np.arange(4).reshape(2, 2) + 1000)
    assert na.shape == (6, 4) and which.tolist() == [0, 0, 0, 1, 1, 1]
    # varying the width moves the bites smoothly inside their faces
    lay2 = generate_sutures(xyz, faces, cen, across, nrm, width=9.01, n_bars=3)
    assert np.linalg.norm(lay2.bite_b.positions(xyz) - pb, axis=1).max() < 0.01


def test_suture_angle_rotates_bites():
    xyz, faces = _sphere_patch(12.0)
    cen, nrm = np.array([[0, 0, 12.8]]), np.array([[0, 0, 1.0]])
    lay = generate_sutures(xyz, faces, cen, [[1.0, 0, 0]], nrm, width=8.0, angle_deg=30.0)
    d = lay.bite_b.positions(xyz)[0] - lay.bite_a.positions(xyz)[0]
    assert np.degrees(np.arctan2(d[1], d[0])) == pytest.approx(30.0, abs=0.5)


def test_bad_suture_input():
    xyz, faces = _sphere_patch(12.0, half_angle=0.2)
    with pytest.raises(ValueError, match="misses the scleral surface"):
        generate_sutures(xyz, faces, [[0, 0, 12.8]], [[1.0, 0, 0]], [[0, 0, 1.0]], width=20.0)
    with pytest.raises(ValueError, match="width = -1"):
        generate_sutures(xyz, faces, [[0, 0, 12.8]], [[1.0, 0, 0]], [[0, 0, 1.0]], width=-1.0)


def _bites(xyz, faces, width, turn=0.0):
    """Bites of four sutures across a band along y at the top of the sphere patch, the
    frame turned by ``turn`` radians about z: (layout, projected points (8, 3))."""
    c, s = np.cos(turn), np.sin(turn)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    y = np.linspace(-1.5, 1.5, 4)
    cen = np.stack([0.3 * np.ones(4), y, 10.0 * np.ones(4)], -1) @ rot.T
    acr = np.tile([1.0, 0.0, 0.0], (4, 1)) @ rot.T
    nrm = cen / np.linalg.norm(cen, axis=1, keepdims=True)
    acr = acr - (acr * nrm).sum(1, keepdims=True) * nrm
    acr /= np.linalg.norm(acr, axis=1, keepdims=True)
    lay = generate_sutures(xyz, faces, cen, acr, nrm, width=width, angle_deg=7.0)
    a_rot = np.cos(np.radians(7.0)) * acr + np.sin(np.radians(7.0)) * np.cross(nrm, acr)
    return lay, np.concatenate([cen - 0.5 * width * a_rot, cen + 0.5 * width * a_rot]), a_rot


def test_bite_derivative_through_jax_matches_central_differences_of_the_layout():
    """radial_bites (the bites as a JAX function of the points they project, its JVP the
    implicit derivative within each face): its value is the layout's xi, and its derivative
    along d width and d turn against central differences of generate_sutures, bite by
    bite, where the bite stays in its face over +-h: to 1e-7 (the differences'
    truncation, h = 1e-4)."""
    import jax
    import jax.numpy as jnp

    from eyefem.eye.sutures import radial_bites

    xyz, faces = _sphere_patch(10.0)
    w, h = 3.0, 1e-4
    lay, p, a_rot = _bites(xyz, faces, w)
    bites = [lay.bite_a, lay.bite_b]
    nodes = np.concatenate([b.nodes for b in bites])
    xi0 = np.concatenate([b.xi for b in bites])
    sgn = np.repeat([-1.0, 1.0], 4)[:, None]
    start = np.clip(xi0 + 0.05, -1, 1)  # Newton from a nearby design's bites
    xi, _ = jax.jvp(lambda p: radial_bites(p, xyz[nodes], start), (jnp.asarray(p),),
                    (jnp.zeros_like(p),))
    np.testing.assert_allclose(xi, xi0, atol=1e-9)
    for var, dp in {"width": 0.5 * sgn * np.tile(a_rot, (2, 1)),
                    "turn": np.cross([0.0, 0.0, 1.0], p)}.items():
        _, dxi = jax.jvp(lambda p: radial_bites(p, xyz[nodes], xi0), (jnp.asarray(p),),
                         (jnp.asarray(dp),))
        dxi = np.asarray(dxi)
        pm = [_bites(xyz, faces, w + e)[0] if var == "width" else _bites(xyz, faces, w, e)[0]
              for e in (h, -h)]
        xis = [np.concatenate([q.bite_a.xi, q.bite_b.xi]) for q in pm]
        same = [np.all(np.concatenate([q.bite_a.nodes, q.bite_b.nodes]) == nodes, axis=1)
                for q in pm]
        ok = same[0] & same[1]
        assert ok.sum() >= 6, var
        np.testing.assert_allclose(dxi[ok], ((xis[0] - xis[1]) / (2 * h))[ok], atol=1e-7)
        assert np.abs(dxi).max() > 1e-2  # the bites do move
