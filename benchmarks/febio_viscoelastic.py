"""eyefem's quasi-linear viscoelastic element against FEBio's `uncoupled viscoelastic`
material on the same deck: a unit cube of an exactly incompressible Mooney-Rivlin tissue
stretched in x over a ramp and held while its stress relaxes.

    python benchmarks/febio_viscoelastic.py [--febio PATH/TO/febio4] [--out DIR] \
        [--record benchmarks/febio_viscoelastic.json]

The deck (one hex8, symmetry planes x = 0, y = 0, z = 0, the face x = 1 pulled to a
stretch of 1.2 over 2 time units, then held to 102) holds the law as FEBio writes it:
``uncoupled viscoelastic`` with ``g0`` = g_inf and ``g1``, ``g2`` = eyefem's g_i about an
``elastic`` Mooney-Rivlin with eyefem's c10, c01 (FEUncoupledViscoElasticMaterial: S = g0
Se + sum_i g_i H_i, H_i updated as eyefem's h_i / g_i), the three-field domain made exactly
incompressible by FEBio's augmented Lagrangian (``laugon``), fixed time steps (no
automatic stepper) in three <Step>s: 8 of 0.25 (the ramp), 20 of 0.5, 18 of 5. eyefem
runs the same path with :class:`eyefem.fem.viscoelastic.ViscoelasticQ1P0` (stages with the
same durations and times). With ``--febio`` FEBio runs the deck and the pulled face's
reaction (the sum of its nodes' Rx, N) is compared with eyefem's at every step;
``--record`` writes FEBio's forces, its version and command as JSON, which
tests/test_febio_viscoelastic.py compares eyefem with (FEBio is never needed by the tests).
Time is in the deck's unit (eyefem's timeline uses minutes).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

C10, C01 = 0.2, 0.05
"""The elastic (instantaneous) law, MPa."""
G, TAU = (0.3, 0.2), (1.0, 20.0)
"""Prony fractions g_i and time constants tau_i (the deck's time unit)."""
STRETCH = 1.2
"""The stretch of the cube along x at the end of the ramp."""
STEPS = ((8, 0.25), (20, 0.5), (18, 5.0))
"""FEBio's <Step>s as (time steps, step size): the ramp to t = 2, then the hold to 102."""

DECK = """<?xml version="1.0" encoding="ISO-8859-1"?>
<!-- eyefem benchmarks/febio_viscoelastic.py: quasi-linear viscoelastic cube, stretch STRETCH
     over a ramp to t = RAMP, held to t = END; c10 = C10, c01 = C01 MPa, g = GS, tau = TAUS -->
<febio_spec version="4.0">
  <Module type="solid"/>
  <Material>
    <material id="1" name="tissue" type="uncoupled viscoelastic">
      <k>BULK</k>
      <g0>GINF</g0>
      PRONY
      <elastic type="Mooney-Rivlin"><k>0</k><c1>C10</c1><c2>C01</c2></elastic>
    </material>
  </Material>
  <Mesh>
    <Nodes name="all">
      <node id="1">0,0,0</node><node id="2">1,0,0</node><node id="3">1,1,0</node>
      <node id="4">0,1,0</node><node id="5">0,0,1</node><node id="6">1,0,1</node>
      <node id="7">1,1,1</node><node id="8">0,1,1</node>
    </Nodes>
    <Elements type="hex8" name="cube"><elem id="1">1,2,3,4,5,6,7,8</elem></Elements>
    <NodeSet name="x0">1,4,5,8</NodeSet><NodeSet name="y0">1,2,5,6</NodeSet>
    <NodeSet name="z0">1,2,3,4</NodeSet><NodeSet name="x1">2,3,6,7</NodeSet>
  </Mesh>
  <MeshDomains>
    <SolidDomain name="cube" mat="tissue"><laugon>1</laugon><atol>1e-9</atol></SolidDomain>
  </MeshDomains>
  <Boundary>
    <bc name="sx" node_set="x0" type="zero displacement"><x_dof>1</x_dof><y_dof>0</y_dof>
      <z_dof>0</z_dof></bc>
    <bc name="sy" node_set="y0" type="zero displacement"><x_dof>0</x_dof><y_dof>1</y_dof>
      <z_dof>0</z_dof></bc>
    <bc name="sz" node_set="z0" type="zero displacement"><x_dof>0</x_dof><y_dof>0</y_dof>
      <z_dof>1</z_dof></bc>
    <bc name="pull" node_set="x1" type="prescribed displacement"><dof>x</dof>
      <value lc="1">DISP</value><relative>0</relative></bc>
  </Boundary>
  <LoadData><load_controller id="1" type="loadcurve"><interpolate>LINEAR</interpolate>
    <extend>CONSTANT</extend><points><pt>0,0</pt><pt>RAMP,1</pt></points></load_controller>
  </LoadData>
  <Output>
    <logfile><node_data data="Rx" node_set="x1" delim=","/></logfile>
  </Output>
  <Step>
STEPS
  </Step>
</febio_spec>
"""

STEP = """    <step id="{k}" name="s{k}"><Control><analysis>STATIC</analysis>
      <time_steps>{n}</time_steps><step_size>{dt}</step_size>
      <solver type="solid"><dtol>1e-10</dtol><etol>1e-12</etol><rtol>1e-12</rtol>
        <max_refs>25</max_refs><qn_method type="full Newton"/></solver>
    </Control></step>"""


def ramp_time() -> float:
    return STEPS[0][0] * STEPS[0][1]


def step_times() -> np.ndarray:
    """The end time of every FEBio time step, (n,)."""
    t, out = 0.0, []
    for n, dt in STEPS:
        for i in range(n):
            out.append(t + (i + 1) * dt)
        t += n * dt
    return np.array(out)


def deck_text(bulk: float = 1e3) -> str:
    """The FEBio 4 deck (module docstring); ``bulk`` is FEBio's k, MPa (the augmented
    Lagrangian makes the element exactly incompressible whatever k)."""
    g_inf = 1.0 - sum(G)
    prony = "".join(f"<g{i}>{g!r}</g{i}><t{i}>{t!r}</t{i}>"
                    for i, (g, t) in enumerate(zip(G, TAU), start=1))
    steps = "\n".join(STEP.format(k=k, n=n, dt=repr(dt))
                      for k, (n, dt) in enumerate(STEPS, start=1))
    end = float(step_times()[-1])
    subs = {"STRETCH": repr(STRETCH), "RAMP": repr(ramp_time()), "END": repr(end),
            "C10": repr(C10), "C01": repr(C01), "GS": repr(G), "TAUS": repr(TAU),
            "BULK": repr(bulk), "GINF": repr(g_inf), "PRONY": prony,
            "DISP": repr(STRETCH - 1.0), "STEPS": steps}
    text = DECK
    for key in sorted(subs, key=len, reverse=True):
        text = text.replace(key, subs[key])
    return text


def read_reactions(log: Path) -> dict[float, float]:
    """FEBio's Rx data records (in its log: ``Time = t``, ``Data = Rx``, then one
    ``node,value`` line per node; ``*`` before the keys in a separate logfile):
    {time: the sum of the face's Rx, N}."""
    out: dict[float, float] = {}
    t, rows = None, None
    for line in log.read_text().splitlines():
        s = line.strip().lstrip("*").strip()
        if s.startswith("Time ="):
            t, rows = float(s.split("=")[1]), None
        elif s.startswith("Data =") and t is not None:
            rows = [] if s.split("=")[1].strip() == "Rx" else None
        elif rows is not None:
            parts = s.replace(",", " ").split()
            try:
                rows.append(float(parts[1]))
            except (ValueError, IndexError):
                out[t], rows = float(sum(rows)), None
    if rows is not None and t is not None:
        out[t] = float(sum(rows))
    return out


def eyefem_forces() -> tuple[np.ndarray, np.ndarray]:
    """(times (n,), the pulled face's force (n,), N) of eyefem's ViscoelasticQ1P0 on the
    deck's path: the ramp and the holds as stages with FEBio's durations and time steps."""
    import jax
    jax.config.update("jax_enable_x64", True)
    from eyefem.fem import generators
    from eyefem.fem.materials import MooneyRivlin
    from eyefem.fem.viscoelastic import ViscoelasticQ1P0
    from eyefem.solve.loadpath import Stage, solve
    from eyefem.solve.model import Model, node_dofs
    from eyefem.solve.options import NewtonOptions

    mesh = generators.box(1.0, 1.0, 1.0, 1, 1, 1, material="t")
    law = MooneyRivlin.from_terms("t", {"c10": C10, "c01": C01})
    term = ViscoelasticQ1P0("solid", mesh, law.coeffs[None], 3 * mesh.n_nodes,
                            g=[list(G)], tau=[list(TAU)])
    model = Model(mesh, (term,), 3 * mesh.n_nodes + mesh.n_elem)
    held = np.concatenate([node_dofs(mesh.node_set(s), c)
                           for s, c in (("x0", "x"), ("y0", "y"), ("z0", "z"))])
    pull = node_dofs(mesh.node_set("x1"), "x")
    bc = (np.r_[held, pull], np.r_[np.zeros(len(held)), np.full(len(pull), STRETCH - 1.0)])
    stages = []
    for k, (n, dt) in enumerate(STEPS):
        times = tuple(dt * (i + 1) for i in range(n))
        stages.append(Stage(f"s{k + 1}", n, bc, duration=n * dt, times=times))
    out = []

    def on_step(rec, m, q, th):
        out.append((float(th["solid"]["time"] + th["solid"]["dt"]),
                    float(m.gradient(q, th)[pull].sum())))
    solve(model, stages, options=NewtonOptions(rtol=1e-12, atol=1e-14), on_step=on_step)
    a = np.array(out)
    return a[:, 0], a[:, 1]


def run_febio(exe: str, out: Path) -> tuple[dict[float, float], float, list[str], str]:
    out.mkdir(parents=True, exist_ok=True)
    deck = out / "viscoelastic_cube.feb"
    deck.write_text(deck_text())
    cmd = [exe, "-i", deck.name, "-noconfig", "-silent"]
    env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    t0 = time.perf_counter()
    done = subprocess.run(cmd, cwd=out, capture_output=True, text=True, env=env, timeout=600)
    wall = time.perf_counter() - t0
    log = deck.with_suffix(".log")
    if done.returncode != 0 or not log.exists():
        raise SystemExit(f"febio_viscoelastic: FEBio failed (exit {done.returncode}); see {log}")
    version = next((f"FEBio {ln.split()[1]}" for ln in log.read_text().splitlines()
                    if ln.strip().lower().startswith("version ")), "unknown")
    return read_reactions(log), wall, cmd, version


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--febio", help="FEBio 4 executable (without it: eyefem's side only)")
    ap.add_argument("--out", default="results/febio_viscoelastic", help="FEBio's run folder")
    ap.add_argument("--record", help="write FEBio's forces and eyefem's as JSON")
    args = ap.parse_args(argv)
    t, f = eyefem_forces()
    if not args.febio:
        for ti, fi in zip(t, f):
            print(f"t = {ti:8.3f}  eyefem {fi:.9g} N")
        return 0
    reactions, wall, cmd, version = run_febio(args.febio, Path(args.out))
    got = {round(k, 9): v for k, v in reactions.items()}
    fb = np.array([got.get(round(ti, 9), np.nan) for ti in t])
    missing = [ti for ti, v in zip(t, fb) if not np.isfinite(v)]
    if missing:
        found = sorted(reactions)[:5]
        raise SystemExit(f"febio_viscoelastic: FEBio's log has no reaction at t = {missing[:3]}"
                         f" (its times: {found} ...)")
    sign = -1.0 if np.dot(fb, f) < 0 else 1.0  # FEBio's Rx: the reaction on the face
    rel = np.abs(sign * fb - f) / np.max(np.abs(f))
    print(f"{'t':>9} {'eyefem, N':>14} {'FEBio, N':>14} {'rel. diff':>10}")
    for ti, a, b, r in zip(t, f, sign * fb, rel):
        print(f"{ti:9.3f} {a:14.9f} {b:14.9f} {r:10.2e}")
    print(f"largest difference {rel.max():.2e} of the peak force; FEBio {wall:.1f} s")
    if args.record:
        Path(args.record).write_text(json.dumps({
            "febio": version, "command": " ".join(cmd),
            "settings": "fixed time steps, full Newton, dtol 1e-10, etol 1e-12, rtol 1e-12, "
                        "laugon 1, atol 1e-9, OMP_NUM_THREADS 1",
            "febio_seconds": round(wall, 2), "reaction_sign": sign,
            "times": [round(float(x), 9) for x in t], "febio_force_N": [float(x) for x in sign * fb],
            "eyefem_force_N": [float(x) for x in f],
            "largest_relative_difference": float(rel.max())}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
