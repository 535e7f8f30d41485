"""What the surgery problem is built from (the eye, the buckle, the case parameters), and
the geometric queries on it: where the buckle sits on the sclera and how snug it fits; the
drained volume as the cavity's param (:func:`drained`, every buckle's stages).

:class:`SurgeryParts` is immutable: a stage that moves a deformable buckle's reference
returns new parts (:meth:`SurgeryParts.refitted`), it never changes the old ones.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import jax.numpy as jnp
import numpy as np

from eyefem.eye.buckles import Buckle, suture_anchor_frame


@dataclasses.dataclass(frozen=True)
class SurgeryParts:
    """The eye, the buckle and the case parameters of one surgery model.

    Attributes:
      eye: the eye model (eyefem.eye.eyemodel.EyeModel) whose mesh includes a deformable
        buckle's elements.
      buckle: the buckle's kind and position.
      p: the case parameters (eyefem.eye.surgery.SURGERY_FIELDS).
      sclera_nodes: (n,) ids of the outer scleral nodes.
      frame: suture anchor frame (centres, across, normals, along), each (n_sutures, 3).
      d_per_mm: radial motion of a rigid buckle per mm of tightening, mm/mm.
      extra_dof: the dof of the rigid buckle's own radial motion.
      band: node ids of a deformable band or tire (eyefem.eye.band.BandInfo), or None.
      sponge: whether a deformable sponge is sewn on (node set "sponge").
      scale: radial scale of the buckle's fit (1: on the unloaded eye; a deformable buckle
        refitted on the pressurised eye gets its snug scale).
    """

    eye: Any
    buckle: Buckle
    p: Mapping
    sclera_nodes: np.ndarray
    frame: tuple
    d_per_mm: float
    extra_dof: int
    band: Any = None
    sponge: bool = False
    scale: float = 1.0

    def refitted(self, mesh, scale: float) -> "SurgeryParts":
        """New parts on ``mesh`` (a deformable buckle's reference moved snug) at ``scale``."""
        return dataclasses.replace(self, eye=dataclasses.replace(self.eye, mesh=mesh),
                                   scale=scale)


def drained(drain_volume) -> dict:
    """The cavity's params (eyefem.fem.cavity.FluidCavity) of a volume drained when the
    buckle is placed: its injected volume dv = -drain_volume, mm^3 (= uL; numpy or JAX)."""
    return {"dv": -drain_volume}


def snug_scale(parts: SurgeryParts, q, node=None):
    """Radial scale of a buckle fitted snug on the eye at state q (n_dof,): the largest
    |x| / |X| of the outer scleral nodes under it (jax or numpy). ``node``: evaluate at
    that node instead (the maximiser, for a derivative; may be traced). See :func:`snug_node`."""
    mesh = parts.eye.mesh
    s = snug_node(parts, q) if node is None else node
    x = jnp.asarray(mesh.nodes)[s] + q[: 3 * mesh.n_nodes].reshape(-1, 3)[s]
    return jnp.linalg.norm(x) / jnp.linalg.norm(jnp.asarray(mesh.nodes)[s])


def snug_node(parts: SurgeryParts, q) -> int:
    """The outer scleral node under the buckle that the snug buckle touches (numpy q)."""
    mesh = parts.eye.mesh
    s = parts.sclera_nodes[buckle_zone(parts)]
    x = mesh.nodes[s] + np.asarray(q)[: 3 * mesh.n_nodes].reshape(-1, 3)[s]
    return int(s[np.argmax(np.linalg.norm(x, axis=1) / np.linalg.norm(mesh.nodes[s], axis=1))])


def buckle_coords(parts: SurgeryParts):
    """Across (a) and along coordinates (mm) of the outer scleral nodes relative to the
    buckle centre line, and a mask of nodes within the buckle's length."""
    return buckle_coords_at(parts, parts.eye.mesh.nodes[parts.sclera_nodes])


def buckle_coords_at(parts: SurgeryParts, X, half_length: float = 2.0):
    """The across coordinate a (k,) (mm from the buckle's centre line) of reference points
    X (k, 3) on the sclera, and a mask (k,) of those within the buckle's length (a
    segmental buckle: ``half_length`` mm either side of its centre, on the buckle's side
    of the globe; encircling: all)."""
    eye, b = parts.eye, parts.buckle
    g = eye.geometry
    th = np.arccos(np.clip(X[:, 2] / np.linalg.norm(X, axis=1), -1, 1))
    if b.encircling:
        return g.scleral_radius * (th - b.centre_angle(g)), np.ones(len(X), bool)
    cen, acr, nrm, _ = suture_anchor_frame(b, g, 1)
    v = X - cen[0]
    # the far side of the globe has small across and along coordinates too: keep the
    # hemisphere about the buckle's centre (X . n > 0)
    near = X @ nrm[0] > 0.0
    return v @ acr[0], near & (np.abs(v @ np.cross(nrm[0], acr[0])) < half_length)


def buckle_zone(parts: SurgeryParts):
    """Mask of the outer scleral nodes under the buckle (a segmental one: within 5 mm of
    its centre along it)."""
    a, ok = buckle_coords_at(parts, parts.eye.mesh.nodes[parts.sclera_nodes], half_length=5.0)
    return ok & (np.abs(a) < parts.buckle.width / 2)
