"""Buckles as rigid triangle surfaces placed on the eye, and the sutures that hold them.

Encircling buckles (band, flat tire, ridged tire) are surfaces of revolution about the
optical axis whose meridional profile follows the sclera over the buckle width, the
ridged tire carrying a central ridge that protrudes toward the sclera. The ring shrinks
radially: every point moves toward the axis by d = shortening / (2 pi), so its
circumference shortens by exactly ``shortening`` (the limit of the seed's rigid-segments
method with infinitely many segments; no gaps or overlaps between segments). A shift s
along the meridian (posteriorly) is its second motion (buckle position, differentiable).

Segmental buckles are silicone sponges (cylinders, diameter 5 mm) lying on the sclera,
radial (axis along the meridian) or circumferential (axis along the parallel).

Placement: the buckle centre lies ``distance`` mm (arc length on the scleral sphere)
behind the limbus at meridian ``meridian_deg`` (segmental); :func:`buckle_bodies` takes
a radial scale so that the buckle is fitted snug on the pressurised eye.

Deformable (hexahedral) bands, tires and radial sponges: :mod:`eyefem.eye.buckle_meshes`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from eyefem.eye.eyemodel import EyeGeometry
from eyefem.fem.rigid import RigidBody, grid_triangles

KINDS = {
    # width across (mm), thickness (mm), ridge height (mm), ridge width (mm)
    "band": (2.5, 0.6, 0.0, 0.0),
    "tire_flat": (7.0, 1.25, 0.0, 0.0),
    "tire_ridged": (7.0, 1.25, 0.75, 3.0),
    "sponge_radial": (5.0, 5.0, 0.0, 0.0),
    "sponge_circumferential": (5.0, 5.0, 0.0, 0.0),
}
"""Buckle kinds: (width, thickness, ridge height, ridge width), mm."""

SPONGE_LENGTH = 10.0


@dataclasses.dataclass(frozen=True)
class Buckle:
    """A buckle and its placement.

    Attributes:
      kind: one of KINDS.
      distance: arc length from the limbus to the buckle centre line, mm (12).
      meridian_deg: meridian of a segmental buckle's centre, degrees from +x (0).
      n_segments: rigid segments of an encircling buckle (24).
    """

    kind: str = "tire_flat"
    distance: float = 12.0
    meridian_deg: float = 0.0
    n_segments: int = 24

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"buckle kind '{self.kind}'; choose one of {sorted(KINDS)}")
        if not 2.0 <= self.distance <= 20.0:
            raise ValueError(f"buckle distance from the limbus = {self.distance} mm; expected "
                             "2 to 20 mm (encircling buckles sit 10-14 mm behind the limbus)")
        if self.n_segments < 3:
            raise ValueError(f"buckle n_segments = {self.n_segments}; must be >= 3")

    @property
    def encircling(self) -> bool:
        return not self.kind.startswith("sponge")

    @property
    def width(self) -> float:
        return KINDS[self.kind][0]

    @property
    def thickness(self) -> float:
        return KINDS[self.kind][1]

    def centre_angle(self, g: EyeGeometry) -> float:
        """Polar angle of the buckle centre line, rad."""
        return g.limbus_angle + self.distance / g.scleral_radius


def _frame(theta, phi):
    """Outward normal n, meridian tangent m (posterior), parallel tangent e (3,) each."""
    n = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
    m = np.array([np.cos(theta) * np.cos(phi), np.cos(theta) * np.sin(phi), -np.sin(theta)])
    e = np.array([-np.sin(phi), np.cos(phi), 0.0])
    return n, m, e


def _orient(body_pts, tris, toward):
    """Flip triangles whose normals do not point along ``toward(centroids)``."""
    P = body_pts[tris]
    nrm = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    flip = np.einsum("ti,ti->t", nrm, toward(P.mean(1))) < 0
    tris = tris.copy()
    tris[flip] = tris[flip][:, ::-1]
    return tris


def buckle_bodies(buckle: Buckle, g: EyeGeometry, radial_scale: float = 1.0,
                  clearance: float = 0.0) -> list[RigidBody]:
    """Rigid bodies of the buckle's inner (eye-facing) surface, normals toward the eye.

    Args: radial_scale: the scleral radius is taken as scale * R (the pressurised eye);
      clearance: gap left between buckle and sclera, mm.
    """
    R = g.scleral_radius * radial_scale + clearance
    th = buckle.centre_angle(g)
    w, _, ridge, ridge_w = KINDS[buckle.kind]
    if buckle.encircling:
        a = np.linspace(-w / 2, w / 2, 29)
        # ridge with 0.5 mm cosine flanks; edges lifted 0.3 mm over their last 0.5 mm
        # (no sharp corner for contact nodes to chatter on)
        t = np.clip((np.abs(a) - (ridge_w / 2 - 0.5)) / 0.5, 0.0, 1.0)
        h = ridge * 0.5 * (1 + np.cos(np.pi * t)) if ridge > 0 else np.zeros_like(a)
        lift = 0.3 * np.clip((np.abs(a) - (w / 2 - 0.5)) / 0.5, 0.0, 1.0) ** 2
        tp = th + a / R  # polar angle of each profile point
        rad = R + ridge - h + lift  # the ridge (or the flat band) touches the sclera
        rho, z = rad * np.sin(tp), rad * np.cos(tp)
        n_phi = 8 * buckle.n_segments
        phi = np.linspace(0.0, 2 * np.pi, n_phi + 1)
        P = np.stack([rho[None, :] * np.cos(phi)[:, None], rho[None, :] * np.sin(phi)[:, None],
                      np.broadcast_to(z, (n_phi + 1, len(a)))], -1).reshape(-1, 3)
        tris = grid_triangles(n_phi, len(a) - 1, closed_u=True)
        keep = np.unique(tris)
        remap = np.full(len(P), -1)
        remap[keep] = np.arange(len(keep))
        P, tris = P[keep], remap[tris]
        tris = _orient(P, tris, lambda c: -np.column_stack([c[:, 0], c[:, 1], 0 * c[:, 2]]))
        _, m, _ = _frame(th, 0.0)
        return [RigidBody("ring", P, tris, direction=(-1.0, 0.0, 0.0), direction2=m, radial=True)]
    # sponge: a cylinder of radius w/2 touching the sclera along its length
    phi0 = np.radians(buckle.meridian_deg)
    n, m, e = _frame(th, phi0)
    axis = m if buckle.kind == "sponge_radial" else e
    across = e if buckle.kind == "sponge_radial" else m
    rs = w / 2
    centre = (R + rs) * n
    ang = np.linspace(-np.pi, np.pi, 49)
    s = np.linspace(-SPONGE_LENGTH / 2, SPONGE_LENGTH / 2, 11)
    A, S = np.meshgrid(ang, s, indexing="ij")
    P = (centre + rs * (np.cos(A).ravel()[:, None] * -n + np.sin(A).ravel()[:, None] * across)
         + S.ravel()[:, None] * axis)
    tris = grid_triangles(48, 10, closed_u=True)
    tris = _orient(P, tris, lambda c: c - (c @ axis)[:, None] * axis - centre
                   + (centre @ axis) * axis)
    return [RigidBody("sponge", P, tris, direction=-n, direction2=m)]


def suture_anchor_frame(buckle: Buckle, g: EyeGeometry, n_sutures: int):
    """Suture positions over the buckle: centres (k, 3) on the sclera under the buckle
    centre line, across directions (k, 3), outward normals (k, 3), body index (k,).

    Encircling: n_sutures evenly around; sponge: n_sutures spread over 60% of its length.
    """
    th = buckle.centre_angle(g)
    R = g.scleral_radius
    cen, acr, nrm, body = [], [], [], []
    if buckle.encircling:
        for phi in 2 * np.pi * (np.arange(n_sutures) + 0.5) / n_sutures:
            n, m, _ = _frame(th, phi)
            cen.append(R * n), acr.append(m), nrm.append(n), body.append(0)
        return np.array(cen), np.array(acr), np.array(nrm), np.array(body)
    n0, m0, e0 = _frame(th, np.radians(buckle.meridian_deg))
    axis, across = (m0, e0) if buckle.kind == "sponge_radial" else (e0, m0)
    for t in np.linspace(-0.3, 0.3, n_sutures) * SPONGE_LENGTH:
        p = R * n0 + t * axis
        n = p / np.linalg.norm(p)
        a = across - (across @ n) * n
        cen.append(R * n), acr.append(a / np.linalg.norm(a)), nrm.append(n), body.append(0)
    return np.array(cen), np.array(acr), np.array(nrm), np.array(body)
