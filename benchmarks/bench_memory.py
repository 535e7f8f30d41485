"""Where a surgical run's memory goes: the resident memory by phase and what holds it.

Builds a surgery case on a mesh level, solves its first stage (pressurisation) and the
first ``--steps`` load steps of the tightening stage (the solver as ``eyefem run`` runs
it, with the case file's ``[solver]`` options: predictors, line search, contact look-ahead,
Woodbury cavity terms), writes one VTU frame, and prints:

- the process's peak resident memory in each phase (Linux's high-water mark, reset at
  each phase through /proc/self/clear_refs, so a phase's peak is its own; elsewhere a
  sampling thread), and the resident memory at its end;
- Pardiso's own report of each factorisation (iparm(15) peak of the symbolic analysis,
  iparm(16) permanent, iparm(17) the factors, KB), how many Pardiso instances held
  factors at once and how much they held together;
- the sizes of the sparse tangent (nnz, bytes) and of the local blocks of one assembly;
- JAX's live buffers (``jax.live_arrays()``) at each phase's end;
- with ``--tracemalloc``, the peak of Python's and numpy's own allocations in each
  phase (slower: run it apart from the timed runs).

    python benchmarks/bench_memory.py                        # case 1 on coarse
    python benchmarks/bench_memory.py --mesh default
    python benchmarks/bench_memory.py --mesh default --tracemalloc --json mem.json

Test-free: it checks nothing, it measures (docs/performance.md, "Memory").
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import tempfile
import threading
import time
import weakref
from pathlib import Path

T0 = time.perf_counter()
MB = 1024.0 * 1024.0


def _status_kb(field: str) -> float | None:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(field + ":"):
                    return float(line.split()[1])
    except OSError:
        pass
    return None


def rss_mb() -> float:
    kb = _status_kb("VmRSS")
    if kb is None:  # not Linux: the peak so far is all there is
        kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        kb /= 1024.0 if sys.platform == "darwin" else 1.0
    return kb / 1024.0


def reset_hwm() -> bool:
    """Reset the kernel's peak resident memory of this process (Linux >= 4.0)."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


class Phases:
    """The peak and final resident memory of each phase (and its wall time)."""

    def __init__(self, trace: bool):
        self.rows, self.name, self.sampled, self.trace = [], None, 0.0, trace
        self.hwm = reset_hwm()
        self._stop = threading.Event()
        threading.Thread(target=self._sample, daemon=True).start()

    def _sample(self):  # a phase's peak where the kernel's cannot be reset
        while not self._stop.wait(0.02):
            self.sampled = max(self.sampled, rss_mb())

    def start(self, name: str):
        self.end()
        self.name, self.tic, self.sampled = name, time.perf_counter(), rss_mb()
        if self.hwm:
            reset_hwm()
        if self.trace:
            import tracemalloc
            tracemalloc.reset_peak()

    def end(self, **extra):
        if self.name is None:
            return
        row = {"phase": self.name, "s": round(time.perf_counter() - self.tic, 2),
               "peak_rss_MB": round(max(self.sampled, (_status_kb("VmHWM") or 0) / 1024.0
                                        if self.hwm else 0.0), 1),
               "end_rss_MB": round(rss_mb(), 1), **live_jax()}
        if self.trace:
            import tracemalloc
            cur, peak = tracemalloc.get_traced_memory()
            row.update(traced_MB=round(cur / MB, 1), traced_peak_MB=round(peak / MB, 1))
        row.update(extra)
        self.rows.append(row)
        self.name = None


def live_jax() -> dict:
    import jax

    arrays = jax.live_arrays()
    return {"jax_live_arrays": len(arrays),
            "jax_live_MB": round(sum(a.nbytes for a in arrays) / MB, 1)}


class PardisoWatch:
    """Pardiso's reports and the factorisations alive at once (wraps eyefem.solve.linsolve)."""

    def __init__(self, linsolve):
        self.ls = linsolve
        self.objects = weakref.WeakSet()  # _Pardiso objects alive
        self.factorisations = 0
        self.analyses = 0
        self.instances = 0  # _Pardiso objects made (one per factorised tangent)
        self.reports = {}  # id(pypardiso solver) -> (permanent KB, factors KB)
        self.last = {}
        self.max_alive = (0, 0.0)  # (instances holding factors, their KB)
        self.max_report = {}
        cls = linsolve._Pardiso
        init, fact, analyse = cls.__init__, cls._factorize, cls._analyse
        new = linsolve._new_pardiso
        watch = self

        def _new(pypardiso, *args):
            solver = new(pypardiso, *args)
            solver.iparm[17] = -1  # iparm(18) < 0: report nnz(L) (changes nothing else)
            return solver
        linsolve._new_pardiso = _new

        def _init(obj, A):
            watch.objects.add(obj)
            watch.instances += 1
            init(obj, A)

        def _analyse(obj):
            watch.analyses += 1
            analyse(obj)

        def _factorize(obj):
            fact(obj)
            watch.factorisations += 1
            ip = obj.entry["solver"].iparm
            rep = {"n": int(obj.A.shape[0]), "nnz_upper": int(obj.A.nnz),
                   "peak_symbolic_KB": int(ip[14]), "permanent_KB": int(ip[15]),
                   "factors_KB": int(ip[16]), "nnz_L": int(ip[17])}
            watch.last = rep
            watch.reports[id(obj.entry["solver"])] = (rep["permanent_KB"], rep["factors_KB"])
            if rep["permanent_KB"] + rep["factors_KB"] > (watch.max_report.get("permanent_KB", 0)
                                                          + watch.max_report.get("factors_KB", 0)):
                watch.max_report = rep
            alive = watch.alive()
            if alive[1] > watch.max_alive[1] or alive[0] > watch.max_alive[0]:
                watch.max_alive = (max(alive[0], watch.max_alive[0]),
                                   max(alive[1], watch.max_alive[1]))

        cls.__init__, cls._factorize, cls._analyse = _init, _factorize, _analyse

    def alive(self):
        """(instances holding a symbolic analysis or factors, their KB) now: Pardiso's
        permanent memory, plus its factors where they are held (an owner)."""
        held = {}

        def add(e):
            perm, fact = self.reports.get(id(e["solver"]), (e.get("kb", 0.0), 0.0))
            held[id(e["solver"])] = perm + (fact if e.get("owner") is not None else 0.0)
        for e in list(self.ls._PARDISO_BY_PATTERN.values()):
            if not e.get("freed"):
                add(e)
        for obj in list(self.objects):
            e = obj.entry
            if not e.get("freed") and e.get("owner") is not None:
                add(e)
        return len(held), sum(held.values())


class AssemblyWatch:
    """Sizes of the tangent and the local blocks of the largest assembly."""

    def __init__(self, assembly):
        self.assemblies, self.sizes = 0, {}
        scatter = assembly.Assembler.scatter
        watch = self

        def _scatter(asm, n_dof, blocks, pressure_stiffness=True):
            held = []

            def seen():
                for b in blocks:
                    held.append(sum(a.nbytes for a in (b.g, b.H, b.b, b.d) if a is not None))
                    yield b
            out = scatter(asm, n_dof, seen(), pressure_stiffness)
            watch.assemblies += 1
            K, B = out[1], out[2]
            size = {"free_dofs": int(K.shape[0]), "K_nnz": int(K.nnz),
                    "K_MB": round((K.data.nbytes + K.indices.nbytes + K.indptr.nbytes) / MB, 1),
                    "B_MB": round(0.0 if B is None else (B.data.nbytes + B.indices.nbytes
                                                         + B.indptr.nbytes) / MB, 1),
                    "local_blocks_MB": round(sum(held) / MB, 1),
                    "largest_term_blocks_MB": round(max(held, default=0) / MB, 1),
                    "slot_maps_MB": round(sum(p.k_slots.nbytes for p in asm.patterns.values())
                                          / MB, 1)}
            if size["K_nnz"] >= watch.sizes.get("K_nnz", 0):
                watch.sizes = size
            return out

        assembly.Assembler.scatter = _scatter


class Stop(Exception):
    pass


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="cases/surgery/case1.toml")
    ap.add_argument("--mesh", default="coarse", help="mesh level (default: coarse)")
    ap.add_argument("--steps", default="1",
                    help="load steps of the tightening stage to solve (default 1); 'all': "
                         "the whole load path, every stage (the run's own peak)")
    ap.add_argument("--tracemalloc", action="store_true",
                    help="also trace Python's and numpy's allocations (slower)")
    ap.add_argument("--keep-factors", action="store_true",
                    help="every pattern's Pardiso instance keeps its factors (before issue 75: "
                         "linsolve.RELEASE_OTHER_FACTORS = False)")
    ap.add_argument("--json", default=None, help="also write the figures to this file")
    args = ap.parse_args(argv)

    if args.tracemalloc:
        import tracemalloc
        tracemalloc.start(1)
    phases = Phases(args.tracemalloc)
    phases.start("import jax, eyefem")
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from eyefem.catalog import problems, schemas
    from eyefem.io.casefile import load_case, with_mesh
    from eyefem.io.output import SeriesWriter
    from eyefem.run.runner import write_step
    from eyefem.solve import assembly, linsolve
    from eyefem.solve.heap import configure_heap
    from eyefem.solve.solver import solve

    configure_heap()
    if args.keep_factors:
        linsolve.RELEASE_OTHER_FACTORS = False
    pardiso, asmw = PardisoWatch(linsolve), AssemblyWatch(assembly)
    phases.start("build the case (mesh, model)")
    case = load_case(args.case, schemas())
    case = with_mesh(case, args.mesh)
    setup = problems()[case.problem][1](case.parameters, case.materials)
    n_elem = setup.model.mesh.n_elem
    whole = args.steps == "all"
    stages = setup.stages if whole else setup.stages[:2]
    n_steps = 0 if whole else int(args.steps)
    kept = {}
    counts = {"iterations": 0}

    def on_step(rec, model, q, theta):
        counts["iterations"] += rec.iterations
        kept.update(model=model, q=q, theta=theta, stage=rec.stage, t=rec.t)
        if not whole and rec.stage == stages[1].name and rec.step >= n_steps:
            raise Stop

    def on_stage_end(i, model, q, theta, starts):
        phases.end(newton_iterations=counts["iterations"],
                   factorisations=pardiso.factorisations, **_alive(pardiso))
        counts["iterations"] = 0
        if i + 1 < len(stages):
            phases.start(f"{stages[i + 1].name}: " + ("the stage" if whole else
                                                       f"{n_steps} load step(s)"))
        pardiso.factorisations = 0

    phases.start(f"{stages[0].name} (compiles the kernels)")
    tic = time.perf_counter()
    try:
        solve(setup.model, stages, options=case.solver, on_step=on_step,
              on_stage_end=on_stage_end)
    except Stop:
        pass
    if phases.name is not None:
        phases.end(newton_iterations=counts["iterations"],
                   factorisations=pardiso.factorisations, **_alive(pardiso))
    solve_s = time.perf_counter() - tic
    phases.start("one VTU frame")
    with tempfile.TemporaryDirectory() as tmp:
        writer = SeriesWriter(Path(tmp), setup.name)
        write_step(writer, setup, kept["stage"], kept["t"], kept["model"], kept["q"], kept["theta"])
    phases.end()

    peak = max(r["peak_rss_MB"] for r in phases.rows)  # clear_refs resets ru_maxrss too
    out = {"case": args.case, "mesh": args.mesh, "hexahedra": n_elem,
           "tightening_steps": args.steps, "heap": os.environ.get("EYEFEM_HEAP", "glibc"),
           "release_other_factors": getattr(linsolve, "RELEASE_OTHER_FACTORS", None),
           "machine": f"{platform.machine()}, {os.cpu_count()} cores",
           "solve_s": round(solve_s, 1), "total_s": round(time.perf_counter() - T0, 1),
           "phases": phases.rows,
           "pardiso_largest": pardiso.max_report,
           "pardiso_most_alive": {"instances": pardiso.max_alive[0],
                                  "MB": round(pardiso.max_alive[1] / 1024.0, 1)},
           "pardiso_analyses": pardiso.analyses, "pardiso_objects": pardiso.instances,
           "assembly": {**asmw.sizes, "assemblies": asmw.assemblies},
           "peak_rss_MB (process, since start)": round(peak, 1)}
    print(json.dumps(out, indent=1))
    print(_table(out))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")


def _alive(pardiso) -> dict:
    n, kb = pardiso.alive()
    return {"pardiso_instances_end": n, "pardiso_MB_end": round(kb / 1024.0, 1),
            "pardiso_patterns": len(pardiso.ls._PARDISO_BY_PATTERN)}


def _table(out) -> str:
    lines = [f"{out['case']} on {out['mesh']} ({out['hexahedra']} hexahedra), "
             f"tightening steps: {out['tightening_steps']}; peak RSS "
             f"{out['peak_rss_MB (process, since start)']:.0f} MB; solve {out['solve_s']} s",
             "| phase | s | peak RSS, MB | RSS at end, MB | JAX live, MB | Newton its / factorisations"
             " | Pardiso at end: instances (patterns), MB |"
             + (" traced peak, MB |" if "traced_peak_MB" in out["phases"][-1] else ""),
             "|---|---:|---:|---:|---:|---:|---:|"
             + ("---:|" if "traced_peak_MB" in out["phases"][-1] else "")]
    for r in out["phases"]:
        lines.append(f"| {r['phase']} | {r['s']} | {r['peak_rss_MB']} | {r['end_rss_MB']} | "
                     f"{r['jax_live_MB']} | {r.get('newton_iterations', '-')} / "
                     f"{r.get('factorisations', '-')} | {r.get('pardiso_instances_end', '-')} "
                     f"({r.get('pardiso_patterns', '-')}), {r.get('pardiso_MB_end', '-')} |"
                     + (f" {r['traced_peak_MB']} |" if "traced_peak_MB" in r else ""))
    p, a = out["pardiso_largest"], out["assembly"]
    if p:
        lines.append(f"Pardiso (largest): n {p['n']}, nnz(upper) {p['nnz_upper']:,}, nnz(L) "
                     f"{p['nnz_L']:,}, peak symbolic {p['peak_symbolic_KB'] / 1024:.0f} MB, "
                     f"permanent {p['permanent_KB'] / 1024:.0f} MB, factors "
                     f"{p['factors_KB'] / 1024:.0f} MB; most alive at once: "
                     f"{out['pardiso_most_alive']['instances']} instances, "
                     f"{out['pardiso_most_alive']['MB']} MB")
    if a:
        lines.append(f"Tangent: {a['free_dofs']:,} free dofs, nnz {a['K_nnz']:,} ({a['K_MB']} MB, "
                     f"B {a['B_MB']} MB); local blocks {a['local_blocks_MB']} MB of one assembly "
                     f"(largest term {a['largest_term_blocks_MB']} MB); slot maps "
                     f"{a['slot_maps_MB']} MB")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
