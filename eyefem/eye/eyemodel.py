"""Parametric eye model: a structured hexahedral globe, lens and Zinn's zonule.

Coordinates: mm, the optical axis is z (cornea at +z), the globe centre at the origin,
the optic nerve leaves the posterior pole 15 degrees nasally (toward +x).

The wall is a cubed sphere (no degenerate pole elements) with 4 element layers,
mapped along each ray from the centre onto the eye's outer surface (the scleral
sphere of radius R joined to the steeper corneal sphere at the limbus) and its
thickness profile. Layers from inside: retina, choroid, sclera, sclera; in front of
the ora serrata the two inner layers are ciliary body, in the cornea all four layers
are cornea; the ring of elements that the limbus crosses is limbus. The optic nerve is
a stub of hexahedra extruded from the posterior outer surface; the lens is a solid
ellipsoid (a cube mapped onto a ball) held by zonule bars between its equator and the
ciliary body. The vitreous/aqueous is one liquid cavity bounded by the wall's inner
surface and the lens surface.

Defaults (literature values; EyeGeometry's docstring names each):
axial length 24 mm, scleral radius 11.5 mm, anterior corneal radius 7.8 mm, central
corneal thickness 0.55 mm, sclera 0.5 mm at the limbus, 0.4 mm at the equator,
1.0 mm at the posterior pole, retina and choroid 0.2 mm each (0.25 at the pole), lens
4 mm thick and 9 mm across, optic nerve 3 mm across (disc 1.8 mm), ora serrata 6 mm
behind the limbus.
"""

from __future__ import annotations

import dataclasses
import logging
import re

import numpy as np

from eyefem.eye.sutures import ray_face_intersection
from eyefem.fem.bars import Bars, end_patches
from eyefem.fem.generators import spherical_shell
from eyefem.fem.mesh import Mesh, boundary_faces, hex_shape, merge
from eyefem.fem.terms import NodeSprings

log = logging.getLogger(__name__)

TISSUES = ("cornea", "limbus", "sclera", "ciliary_body", "choroid", "retina", "optic_nerve", "lens")

LEVELS = {"coarse": (10, 4), "half": (11, 4), "medium": (14, 4), "default": (22, 6),
          "fine": (32, 8), "finer": (44, 12), "finest": (54, 14), "ultrafine": (70, 18),
          "graded_half": (15, 4), "graded": (30, 8), "graded_fine": (45, 12)}
"""Mesh density levels: (cubed-sphere elements per patch edge, lens elements per edge).

These levels refine in-plane only: each keeps 4 element layers through the wall (retina,
choroid, two of sclera); "half", "fine", "finer", "finest" (about 73,000 hexahedra) and
"ultrafine" (about 122,000, run on a GPU machine) serve the mesh convergence study
(docs/convergence.md); the last three run outside CI. "half", "default" and "finer" nest: each halves the last one's
elements in-plane (ratio 2), so the wall's nodes of one are nodes of the next. The lens
needs an even count (its equator holds the zonule's nodes). A level name with the suffix "x2" (``mediumx2``, ``defaultx2``...)
splits every one of the 4 layers in two (8 through the wall), the same in-plane: the
through-thickness check of the study (:func:`level_spec`).

The "graded..." levels (GRADED_LEVELS) place their cubed-sphere nodes by the polar-angle map
:func:`graded_polar_angle`: elements BAND_REFINEMENT times shorter along the meridians in
the band zone BAND_ZONE_DEG, where encircling buckles sit, longer elsewhere
(docs/convergence.md, "A mesh graded toward the buckle")."""

THROUGH_SPLIT = "x2"

LENS_SPRING_PER_NODE = 1e-3
"""Stiffness of the lens's springs per node, N/mm, without EyeGeometry.lens_support (the
recorded results' model)."""

GRADED_LEVELS = ("graded_half", "graded", "graded_fine")
"""Levels whose nodes are graded toward the band zone (:func:`graded_polar_angle`)."""

GRADED_FAMILY = re.compile(r"graded(c?)(\d+)")
"""Level names "graded<N>": graded like GRADED_LEVELS, N elements per patch edge; and
"gradedc<N>": the same with the cornea refined too (CORNEA_ZONE_DEG, CORNEA_REFINEMENT)."""

GRADED_N_RANGE = (12, 64)
"""Accepted N of the "graded<N>" levels (64: about 100,000 hexahedra)."""

BAND_ZONE_DEG = (55.0, 130.0)
"""Polar angles (deg from the corneal apex) of the graded levels' refined zone: the buckle
centre 12 mm (position A, 90 deg) to 15 mm (position B, 105 deg) behind the limbus, with
its sutures' bites (+-4.5 mm) and the wall's bending beside them."""

BAND_REFINEMENT = 2.2
"""Ratio of the meridional element length outside the band zone to that inside it."""

BAND_TRANSITION_DEG = 5.0
"""Width (deg) of the smooth (tanh) transitions of the element density at the zone's edges."""

CORNEA_ZONE_DEG = 40.0
"""Polar angle (deg from the corneal apex) below which the "gradedc<N>" levels refine the
wall: the cornea (to about 33 deg), its limbus and the corneal fit zone of the refraction."""

CORNEA_REFINEMENT = 1.4
"""Ratio of the meridional element length outside both refined zones to that in the cornea
zone of the "gradedc<N>" levels: at N = 26 the cornea has the default level's density."""


def graded_polar_angle(theta_ref, zone_deg=BAND_ZONE_DEG, refinement=BAND_REFINEMENT,
                       transition_deg=BAND_TRANSITION_DEG, cornea_refinement=1.0,
                       cornea_deg=CORNEA_ZONE_DEG):
    """Polar angles (n,) rad of nodes at reference polar angles theta_ref (n,) rad.

    The map theta(theta_ref) of [0, pi] onto itself is monotone and smooth, with
    d theta / d theta_ref proportional to 1 / rho(theta), the element density
    rho = 1 + (refinement - 1) b(theta), b a smooth box (tanh edges) over the zone: a node
    spacing even in theta_ref becomes `refinement` times denser inside the zone than
    outside. With cornea_refinement > 1 the density is also that much higher below the polar
    angle cornea_deg (deg; a smooth step): rho is the larger of the two zones' densities.
    Nested reference meshes stay nested."""
    lo, hi = np.radians(zone_deg)
    w = np.radians(transition_deg)
    grid = np.linspace(0.0, np.pi, 20001)
    rho = 1.0 + (refinement - 1.0) * 0.5 * (np.tanh((grid - lo) / w) - np.tanh((grid - hi) / w))
    cornea = 0.5 * (1.0 - np.tanh((grid - np.radians(cornea_deg)) / w))
    rho = np.maximum(rho, 1.0 + (cornea_refinement - 1.0) * cornea)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (rho[1:] + rho[:-1]) * np.diff(grid))])
    return np.interp(theta_ref, np.pi * cum / cum[-1], grid)


def _graded_family_spec(base: str):
    """(n, lens elements) of a "graded<N>" name, None for other names."""
    m = GRADED_FAMILY.fullmatch(base)
    if m is None:
        return None
    n = int(m.group(2))
    lo, hi = GRADED_N_RANGE
    if not lo <= n <= hi:
        raise ValueError(f"eye mesh level '{base}': {n} elements per patch edge; choose "
                         f"{lo} to {hi} (graded36: the default level's elements outside the "
                         "band zone, 0.32 mm inside it; gradedc26: the default's in the "
                         "cornea)")
    # the lens: an even count (its equator holds the zonules), as the named graded levels
    return n, max(4, 2 * round(n / 7.5))


def level_spec(level: str) -> tuple[int, int, int]:
    """(elements per patch edge, lens elements per edge, sub-layers per wall layer) of a
    mesh level name: a key of LEVELS, "graded<N>" (N elements per patch edge, graded like
    GRADED_LEVELS), or either with the suffix "x2" (8 wall layers)."""
    base, split = level, 1
    if isinstance(level, str) and level.endswith(THROUGH_SPLIT):
        base, split = level[:-len(THROUGH_SPLIT)], 2
    family = _graded_family_spec(base) if isinstance(base, str) else None
    if family is not None:
        return family + (split,)
    if base not in LEVELS:
        raise ValueError(f"eye mesh level '{level}'; choose one of {sorted(LEVELS)}, "
                         f"'graded<N>' (N elements per patch edge, {GRADED_N_RANGE[0]} to "
                         f"{GRADED_N_RANGE[1]}, graded toward the band zone), 'gradedc<N>' "
                         "(the same with the cornea refined too), or one of them "
                         f"with the suffix '{THROUGH_SPLIT}' (8 wall layers instead of 4)")
    return LEVELS[base] + (split,)


LEVEL_HELP = (f"eye mesh level: {', '.join(LEVELS)}, graded<N> (N elements per patch edge, "
              f"{GRADED_N_RANGE[0]}-{GRADED_N_RANGE[1]}, graded toward the band zone), or "
              "gradedc<N> (the same with the cornea refined too); the suffix 'x2' (e.g. "
              "'defaultx2': 8 wall layers instead of 4)")
"""What a case file's ``mesh`` field takes (the help of its schema)."""

LEVEL_EXPECTED = (f"one of {list(LEVELS)}, graded<N> or gradedc<N> (N {GRADED_N_RANGE[0]}-"
                  f"{GRADED_N_RANGE[1]}), or one with the suffix 'x2'")
"""What a case file's ``mesh`` field expects, for its error message."""

SURGICAL_LEVEL = "fine"
"""The surgical cases' eye mesh (the surgery schema's default): the uniform level with 32
elements per patch edge, 25,166 hexahedra, the coarsest level of the mesh study within
its bounds (5 % for the IOP rise, indentation, axial length and refraction changes, 10 %
for the largest suture force) with the case files' model (docs/convergence.md, "Results:
the case files' model"). The uniform level named "default" (11,862 hexahedra, the seed's
model size) stays for the calibration, the nested study and the cases that name it."""


def is_graded(level: str) -> bool:
    """True for the levels graded toward the band zone (GRADED_LEVELS, "graded<N>",
    "gradedc<N>")."""
    base = level.removesuffix(THROUGH_SPLIT)
    return base in GRADED_LEVELS or GRADED_FAMILY.fullmatch(base) is not None


def cornea_refinement(level: str) -> float:
    """The cornea zone's refinement of a level: CORNEA_REFINEMENT for "gradedc<N>", else 1."""
    m = GRADED_FAMILY.fullmatch(level.removesuffix(THROUGH_SPLIT))
    return CORNEA_REFINEMENT if m is not None and m.group(1) == "c" else 1.0


def is_level(level) -> bool:
    """True for a mesh level name :func:`level_spec` accepts."""
    try:
        level_spec(level)
    except (ValueError, TypeError, AttributeError):
        return False
    return True


@dataclasses.dataclass(frozen=True)
class EyeGeometry:
    """Dimensions of the eye, mm (defaults from the literature).

    Attributes:
      axial_length: corneal apex to the outer posterior pole (24).
      scleral_radius: outer radius of the scleral sphere R (11.5).
      cornea_radius: anterior corneal radius of curvature (7.8).
      cornea_thickness: central corneal thickness (0.55).
      limbus_thickness: wall at the limbus (0.6; sclera 0.5 + cornea periphery).
      sclera_limbus, sclera_equator, sclera_pole: scleral thickness (0.5, 0.4, 1.0).
      ciliary_thickness: ciliary body (0.5).
      choroid_thickness, retina_thickness: at the equator (0.2, 0.2); x 1.25 at the pole.
      ora_serrata: arc length from the limbus to the ora serrata (6).
      lens_diameter, lens_thickness: (9, 4); lens_centre_depth: from the corneal apex (5.6).
      nerve_diameter: optic nerve (3), nerve_length: stub (3), nerve_angle_deg: from the
        posterior pole toward +x (15); disc_diameter: optic disc (1.8).
      zonule_area: cross-section per zonule bar with point insertions, mm^2 (0.01).
      zonule_insertion_radius: None: each zonule bar pulls on one point of the ciliary
        body with the cross-section zonule_area (the model of the recorded results); a
        radius, mm: the bars share the zonule's total cross-section zonule_total_area and
        spread their pull over discs of that radius of the ciliary body's inner surface, so
        that the zonule is the same on every mesh level. Point insertions are not: their
        number follows the lens mesh and a point pull deflects the soft ciliary body by an
        amount that grows as the elements shrink, which made the graded levels' eyes up to
        2.4 % more rigid than the uniform ones (docs/convergence.md, "The zonule").
      zonule_total_area: the zonule's total cross-section with spread insertions, mm^2
        (0.24: the default level's 24 bars of 0.01).
      limbus_width: arc width of the limbus ring, mm, centred on the corneoscleral
        junction: the elements whose centroid lies within it are limbus, a tissue of the
        same size on every mesh level (1.5: the anatomical limbus, a transition zone about
        1.5 mm wide, Hogan et al. 1971, "Histology of the Human Eye"); None: the elements
        the junction passes through (one element wide, so the ring narrows as the mesh is
        refined and the model changes with the mesh).
      lens_support: None: springs of LENS_SPRING_PER_NODE (1e-3 N/mm) on every lens node
        tie the floating lens to its place (the model of the recorded results): their sum,
        0.125 N/mm on the coarse and half levels, 0.343 on the default and gradedc26, 0.729
        on fine and 2.2 on finer, follows the lens mesh, and it carries a tenth of what
        the zonule carries when a band pulls the anterior segment forward, so the lens's
        motion and the anterior chamber depth change follow the mesh
        (docs/convergence.md, "The lens's support"); a stiffness, N/mm: the springs' sum,
        shared by the lens's nodes, the same on every level.
      tissue_mixing: False: each wall element is wholly one tissue, by its centroid (the
        tissues' boundaries are staircases of the mesh, which move by up to an element as
        it is refined); True: an element that a boundary of the limbus ring, the cornea,
        the ciliary body or the optic disc cuts stores the mixture of the tissues'
        energies in the proportions of its volume (TISSUE_SAMPLES^3 points per element;
        eyefem.fem.solid.element_coeffs), so the tissues have their own size and place on
        every mesh level; needs limbus_width. The outputs still label every element with
        its centroid's tissue.
    """

    axial_length: float = 24.0
    scleral_radius: float = 11.5
    cornea_radius: float = 7.8
    cornea_thickness: float = 0.55
    limbus_thickness: float = 0.6
    sclera_limbus: float = 0.5
    sclera_equator: float = 0.4
    sclera_pole: float = 1.0
    ciliary_thickness: float = 0.5
    choroid_thickness: float = 0.2
    retina_thickness: float = 0.2
    ora_serrata: float = 6.0
    lens_diameter: float = 9.0
    lens_thickness: float = 4.0
    lens_centre_depth: float = 5.6
    nerve_diameter: float = 3.0
    nerve_length: float = 3.0
    nerve_angle_deg: float = 15.0
    disc_diameter: float = 1.8
    zonule_area: float = 0.01
    zonule_insertion_radius: float | None = None
    zonule_total_area: float = 0.24
    limbus_width: float | None = 1.5
    tissue_mixing: bool = False
    lens_support: float | None = None

    def __post_init__(self):
        if not isinstance(self.tissue_mixing, (bool, np.bool_)):
            raise ValueError(f"eye geometry: tissue_mixing = {self.tissue_mixing!r}; must be "
                             "true or false")
        if self.tissue_mixing and self.limbus_width is None:
            raise ValueError("eye geometry: tissue_mixing needs a limbus ring of fixed width "
                             "(limbus_width, e.g. 1.5 mm); the one-element ring has no "
                             "boundary to mix across")
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "tissue_mixing" or (
                    v is None and f.name in ("limbus_width", "zonule_insertion_radius",
                                             "lens_support")):
                continue
            if not (np.isfinite(v) and v > 0):
                unit = "N/mm" if f.name == "lens_support" else "mm"
                raise ValueError(f"eye geometry: {f.name} = {v} {unit}; must be a positive "
                                 "number")
        if not self.scleral_radius < self.axial_length - self.scleral_radius:
            raise ValueError(f"eye geometry: axial_length {self.axial_length} must exceed twice "
                             f"the scleral radius {self.scleral_radius} (the cornea protrudes)")

    @property
    def apex_z(self) -> float:
        return self.axial_length - self.scleral_radius

    @property
    def cornea_centre_z(self) -> float:
        return self.apex_z - self.cornea_radius

    @property
    def limbus_angle(self) -> float:
        """Polar angle of the limbus (where the corneal and scleral spheres meet), rad."""
        R, c, rc = self.scleral_radius, self.cornea_centre_z, self.cornea_radius
        z = (R**2 - rc**2 + c**2) / (2 * c)
        if not abs(z) < R:
            raise ValueError("eye geometry: the corneal and scleral spheres do not intersect; "
                             "check axial_length, scleral_radius and cornea_radius")
        return float(np.arccos(z / R))

    def outer_radius(self, d):
        """Distance (n,) from the centre to the outer surface along unit directions d (n, 3)."""
        R, c, rc = self.scleral_radius, self.cornea_centre_z, self.cornea_radius
        dc = d[:, 2] * c
        disc = dc**2 - c**2 + rc**2
        s = np.where(disc > 0, dc + np.sqrt(np.maximum(disc, 0.0)), 0.0)
        return np.maximum(R, s)

    def profile(self, theta):
        """Wall thickness T (n,) and inner-layer fraction f (n,) at polar angles theta (rad)."""
        tl = self.limbus_angle
        ora = tl + self.ora_serrata / self.scleral_radius
        ret_c = self.retina_thickness + self.choroid_thickness
        pts = np.array([
            (0.0, self.cornea_thickness, 0.5),
            (tl, self.limbus_thickness, 0.5),
            (tl + 0.07, self.sclera_limbus + self.ciliary_thickness,
             self.ciliary_thickness / (self.sclera_limbus + self.ciliary_thickness)),
            (ora, self.sclera_limbus * 0.9 + 0.75 * ret_c, 0.75 * ret_c / (self.sclera_limbus * 0.9
                                                                          + 0.75 * ret_c)),
            (np.pi / 2, self.sclera_equator + ret_c, ret_c / (self.sclera_equator + ret_c)),
            (np.pi, self.sclera_pole + 1.25 * ret_c, 1.25 * ret_c / (self.sclera_pole + 1.25 * ret_c)),
        ])
        return np.interp(theta, pts[:, 0], pts[:, 1]), np.interp(theta, pts[:, 0], pts[:, 2])


TISSUE_SAMPLES = 4
"""Points per element edge (a TISSUE_SAMPLES^3 midpoint grid in reference coordinates,
weighted by the volume each carries) at which EyeGeometry.tissue_mixing finds the
tissues' volume fractions."""


def _tissue_at(theta, off_axis, layer, g: "EyeGeometry"):
    """Tissue index (TISSUES) at points of polar angle theta (rad), arc distance off_axis
    from the optic nerve's axis (mm) and wall layer (0 retina .. 3 outer sclera), by the
    rules of :func:`build_eye` (arrays broadcast; limbus_width set)."""
    tl = g.limbus_angle
    ora = tl + g.ora_serrata / g.scleral_radius
    half = 0.5 * g.limbus_width / g.scleral_radius
    mat = np.where(layer >= 2, TISSUES.index("sclera"),
                   np.where(layer == 1, TISSUES.index("choroid"), TISSUES.index("retina")))
    mat = np.where((theta < ora) & (layer < 2), TISSUES.index("ciliary_body"), mat)
    mat = np.where((off_axis < g.disc_diameter / 2) & (layer < 2), TISSUES.index("optic_nerve"),
                   mat)
    mat = np.where(theta < tl - half, TISSUES.index("cornea"), mat)
    return np.where(np.abs(theta - tl) <= half, TISSUES.index("limbus"), mat)


def tissue_fractions(nodes, hexes, layer, nerve_dir, g: "EyeGeometry", chunk: int = 8192):
    """Volume fractions (n_elem, len(TISSUES)) of the tissues in wall elements hexes
    (n_elem, 8) of layers layer (n_elem,), from TISSUE_SAMPLES^3 points per element each
    weighted by the volume it carries (det dX/dxi)."""
    s = TISSUE_SAMPLES
    t = -1.0 + (2.0 * np.arange(s) + 1.0) / s
    xi = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3)
    n_sh, dn_sh = hex_shape(xi)  # (p, 8), (p, 8, 3)
    out = np.zeros((len(hexes), len(TISSUES)))
    for lo in range(0, len(hexes), chunk):
        xe = nodes[hexes[lo:lo + chunk]]
        x = np.einsum("pa,eai->epi", n_sh, xe)
        w = np.linalg.det(np.einsum("eai,paj->epij", xe, dn_sh))
        r = np.linalg.norm(x, axis=-1)
        theta = np.arccos(np.clip(x[..., 2] / r, -1.0, 1.0))
        off = g.scleral_radius * np.arccos(np.clip(x @ nerve_dir / r, -1.0, 1.0))
        mat = _tissue_at(theta, off, layer[lo:lo + chunk, None], g)
        rows = np.repeat(np.arange(len(xe)), mat.shape[1])
        np.add.at(out[lo:lo + chunk], (rows, mat.ravel()), w.ravel())
    return out / out.sum(axis=1, keepdims=True)


def _ball(n):
    """A solid unit ball: an n^3 cube of hexahedra mapped onto the sphere (nodes, hexes)."""
    s = np.linspace(-1.0, 1.0, n + 1)
    X, Y, Z = np.meshgrid(s, s, s, indexing="ij")
    x, y, z = X.ravel(), Y.ravel(), Z.ravel()
    nodes = np.stack([x * np.sqrt(1 - y**2 / 2 - z**2 / 2 + y**2 * z**2 / 3),
                      y * np.sqrt(1 - z**2 / 2 - x**2 / 2 + z**2 * x**2 / 3),
                      z * np.sqrt(1 - x**2 / 2 - y**2 / 2 + x**2 * y**2 / 3)], 1)
    idx = np.arange((n + 1) ** 3).reshape(n + 1, n + 1, n + 1)
    a = idx[:-1, :-1, :-1]
    hexes = np.stack([a, idx[1:, :-1, :-1], idx[1:, 1:, :-1], idx[:-1, 1:, :-1],
                      idx[:-1, :-1, 1:], idx[1:, :-1, 1:], idx[1:, 1:, 1:], idx[:-1, 1:, 1:]],
                     -1).reshape(-1, 8)
    return nodes, hexes


@dataclasses.dataclass(frozen=True)
class EyeModel:
    """The eye mesh and what the surgery needs to know about it.

    Attributes:
      mesh: wall + nerve ("eye/...") and lens ("lens/...") in one mesh. Face sets:
        "eye/inner" (wall inside, normals into the liquid), "eye/outer" (outer surface),
        "eye/sclera_outer" (outer scleral faces, behind the limbus), "lens/surface".
        Node sets: "eye/apex", "eye/pole" (outer posterior pole), "eye/nerve_end".
      geometry: the EyeGeometry.
      zonule: (lens node ids (k,), ciliary faces (k, 4), xi (k, 2)) bar ends.
      level: mesh level name.
    """

    mesh: Mesh
    geometry: EyeGeometry
    zonule: tuple
    level: str

    def zonule_bar_EA(self, E: float) -> float:
        """Axial stiffness of one zonule bar, N: E (MPa) x zonule_area with point
        insertions, x zonule_total_area shared by the bars with spread ones (EyeGeometry)."""
        g = self.geometry
        if g.zonule_insertion_radius is None:
            return E * g.zonule_area
        return E * g.zonule_total_area / len(self.zonule[0])

    def zonule_bars(self, E: float, name: str = "zonule") -> Bars:
        """Zinn's zonule: one bar from each lens equator node radially out to the ciliary
        body's inner surface, Young's modulus E (MPa), with point or spread insertions
        (EyeGeometry.zonule_insertion_radius; eyefem.fem.bars.EndPatches)."""
        lens_eq, faces, xi = self.zonule
        nodes, radius = self.mesh.nodes, self.geometry.zonule_insertion_radius
        patch = None if radius is None else end_patches(
            nodes, self.mesh.face_set("eye/inner"), faces, xi, True, radius)
        return Bars(name, np.repeat(lens_eq[:, None], 4, 1), faces, np.zeros((len(lens_eq), 2)),
                    xi, nodes, EA=self.zonule_bar_EA(E), patch_b=patch)

    def lens_springs(self, name: str = "lens_springs") -> NodeSprings:
        """Springs tying the lens's nodes to their reference places: LENS_SPRING_PER_NODE
        each, or the geometry's ``lens_support`` (N/mm) shared by the nodes
        (EyeGeometry.lens_support). The lens floats in the liquid, held otherwise by the
        zonule alone, which is slack before the eye is pressurised."""
        nodes = self.mesh.node_set("lens")
        total = self.geometry.lens_support
        k = LENS_SPRING_PER_NODE if total is None else total / len(nodes)
        return NodeSprings(name, nodes, k=k)

    def quality(self) -> dict:
        """Element counts per tissue and the worst Jacobian ratio."""
        jr = self.mesh.jacobian_ratio()
        out = {"elements": int(self.mesh.n_elem), "nodes": int(self.mesh.n_nodes),
               "worst_jacobian_ratio": float(jr.min())}
        for i, m in enumerate(self.mesh.materials):
            out[f"elements_{m}"] = int(np.sum(self.mesh.material_ids == i))
        return out


def build_eye(geometry: EyeGeometry = EyeGeometry(), level: str = "default") -> EyeModel:
    """Mesh the eye at a density level (a key of LEVELS: "coarse" .. "finest", "graded<N>", or
    one of them with the suffix "x2": 8 wall layers instead of 4; :func:`level_spec`)."""
    g = geometry
    n, n_lens, split = level_spec(level)
    shell = spherical_shell(1.0, 1.0, n, 4 * split)
    X = shell.nodes
    r = np.linalg.norm(X, axis=1)
    d = X / r[:, None]
    if is_graded(level):
        th = graded_polar_angle(np.arccos(np.clip(d[:, 2], -1, 1)),
                                cornea_refinement=cornea_refinement(level))
        ph = np.arctan2(d[:, 1], d[:, 0])
        d = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], 1)
    level_k = np.rint((r - 1.0) * 4 * split).astype(int)  # 0 (inside) .. 4 split (outside)
    theta = np.arccos(np.clip(d[:, 2], -1, 1))
    ro = g.outer_radius(d)
    T, f = g.profile(theta)
    t = level_k / split  # 0 .. 4: the tissue interfaces at integers, sub-layers between
    frac = np.interp(t, np.arange(5), [0.0, 0.5, 1.0, 1.0, 1.0]) * f + \
        np.interp(t, np.arange(5), [0.0, 0.0, 0.0, 0.5, 1.0]) * (1 - f)
    nodes = d * (ro - T + frac * T)[:, None]
    hexes = shell.hexes
    # tissues: by element centroid angle and layer
    th_e = theta[hexes]
    layer = np.min(level_k[hexes], axis=1) // split  # 0 retina .. 3 outer sclera
    tl = g.limbus_angle
    ora = tl + g.ora_serrata / g.scleral_radius
    nerve_dir = np.array([np.sin(np.radians(180 - g.nerve_angle_deg)), 0.0,
                          np.cos(np.radians(180 - g.nerve_angle_deg))])
    cen = nodes[hexes].mean(axis=1)
    cdir = cen / np.linalg.norm(cen, axis=1, keepdims=True)
    off_axis = g.scleral_radius * np.arccos(np.clip(cdir @ nerve_dir, -1, 1))
    mat = np.where(layer >= 2, TISSUES.index("sclera"),
                   np.where(layer == 1, TISSUES.index("choroid"), TISSUES.index("retina")))
    mat = np.where((th_e.mean(1) < ora) & (layer < 2), TISSUES.index("ciliary_body"), mat)
    mat = np.where((off_axis < g.disc_diameter / 2) & (layer < 2), TISSUES.index("optic_nerve"), mat)
    if g.limbus_width is None:  # the ring of elements the junction passes through
        mat = np.where(th_e.max(1) <= tl, TISSUES.index("cornea"), mat)
        mat = np.where((th_e.min(1) < tl) & (th_e.max(1) > tl), TISSUES.index("limbus"), mat)
    else:  # a ring of fixed arc width, by the elements' centroids
        th_c = np.arccos(np.clip(cdir[:, 2], -1, 1))
        half = 0.5 * g.limbus_width / g.scleral_radius
        mat = np.where(th_c < tl - half, TISSUES.index("cornea"), mat)
        mat = np.where(np.abs(th_c - tl) <= half, TISSUES.index("limbus"), mat)
    inner, outer = shell.face_set("inner"), shell.face_set("outer")
    # optic nerve stub: extrude the outer faces within the nerve radius along nerve_dir
    fc = nodes[outer].mean(axis=1)
    fdir = fc / np.linalg.norm(fc, axis=1, keepdims=True)
    near = g.scleral_radius * np.arccos(np.clip(fdir @ nerve_dir, -1, 1)) < g.nerve_diameter / 2
    stub_faces = outer[near]
    base = np.unique(stub_faces)
    n_ext = 3
    new_nodes, stub_hexes, prev = [], [], {int(b): int(b) for b in base}
    next_id = len(nodes)
    end_nodes = []
    for k in range(1, n_ext + 1):
        cur = {}
        for b in base:
            cur[int(b)] = next_id
            new_nodes.append(nodes[b] + k * g.nerve_length / n_ext * nerve_dir)
            next_id += 1
        for fq in stub_faces:
            lo = [prev[int(v)] for v in fq]
            hi = [cur[int(v)] for v in fq]
            stub_hexes.append(lo + hi)
        prev = cur
        end_nodes = list(cur.values())
    n_wall_elem = len(hexes)
    nodes = np.concatenate([nodes, np.array(new_nodes)])
    hexes = np.concatenate([hexes, np.array(stub_hexes, np.int64)])
    mat = np.concatenate([mat, np.full(len(stub_hexes), TISSUES.index("optic_nerve"))])
    outer_all = boundary_faces(hexes)
    outer_all = outer_all[~np.all(np.isin(outer_all, np.unique(inner)), axis=1)]
    sclera_outer = outer[~near & (theta[outer].min(axis=1) >= tl)]
    apex = int(np.argmax(nodes[:, 2]))
    n_wall = len(level_k)
    pole = int(np.argmin(np.where(level_k == 4 * split, nodes[:n_wall, 2], np.inf)))
    fractions = None
    if g.tissue_mixing:  # the wall's elements by their volume; the nerve stub is nerve
        fractions = np.eye(len(TISSUES))[mat]
        fractions[:n_wall_elem] = tissue_fractions(nodes, hexes[:n_wall_elem], layer, nerve_dir, g)
    eye = Mesh(nodes, hexes, mat, TISSUES,
               {"apex": np.array([apex]), "pole": np.array([pole]),
                "nerve_end": np.array(end_nodes), "outer": np.unique(outer_all)},
               {"inner": inner, "outer": outer_all, "sclera_outer": sclera_outer},
               material_fractions=fractions)
    # lens
    ln, lh = _ball(n_lens)
    a, c = g.lens_diameter / 2, g.lens_thickness / 2
    lz = g.apex_z - g.lens_centre_depth
    ln = ln * np.array([a, a, c]) + np.array([0.0, 0.0, lz])
    lbf = boundary_faces(lh)
    eq = np.nonzero(np.abs(ln[:, 2] - lz) < 1e-9 * a)[0]
    eq = eq[np.hypot(ln[eq, 0], ln[eq, 1]) > a * (1 - 1e-9)]
    lens = Mesh(ln, lh, np.zeros(len(lh), int), ("lens",), {"equator": eq}, {"surface": lbf})
    mesh = merge(("eye", eye), ("lens", lens))
    # zonule: from each lens equator node radially out to the wall's inner surface
    lens_eq = mesh.node_set("lens/equator")
    wall_in = mesh.face_set("eye/inner")
    faces, xis = [], []
    for v in lens_eq:
        p = mesh.nodes[v]
        hit = ray_face_intersection(mesh.nodes, wall_in, p, np.array([p[0], p[1], 0.0]))
        if hit is None:
            raise ValueError(f"eye model: the zonule ray from lens node {v} misses the wall")
        faces.append(wall_in[hit[0]])
        xis.append(hit[1])
    eye_model = EyeModel(mesh, g, (lens_eq, np.array(faces), np.array(xis)), level)
    q = eye_model.quality()
    log.info("eye model (%s): %d elements, %d nodes, worst Jacobian ratio %.3f", level,
             q["elements"], q["nodes"], q["worst_jacobian_ratio"])
    return eye_model
