"""Time an 8-run sweep on a LocalCluster of 1 and of 2 workers; print the speed-up.

    python benchmarks/bench_sweep.py                  # 8 coarse surgery runs (case 1)
    python benchmarks/bench_sweep.py --problem uniaxial --n 6 --repeat 3

Each timing is a whole ``run_sweep``: cluster start, the runs, the table, cluster close.
JAX's persistent compilation cache is on (a temporary folder, warmed by one untimed run),
as it is for a user of ``eyefem sweep``, so the figures measure the solves and not XLA's
compilation. Everything is written in a temporary folder.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import statistics
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
UNIAXIAL = """[case]
problem = "uniaxial"
[parameters]
stretch = 1.5
n = {n}
steps = 4
[materials.rubber]
c10 = 25.0
c01 = 5.0
"""


def sweep_file(folder: Path, problem: str, n: int) -> Path:
    f = folder / "bench.toml"
    if problem == "uniaxial":
        (folder / "base.toml").write_text(UNIAXIAL.format(n=n))
        values = [1.2 + 0.1 * i for i in range(8)]
        f.write_text(f'[sweep]\ncase = "base.toml"\n[grid]\nparameters.stretch = {values}\n')
    else:
        case = (ROOT / "cases/surgery/case1.toml").as_posix()
        values = [3.0 + 1.0 * i for i in range(8)]
        f.write_text(f'[sweep]\ncase = "{case}"\noutcomes = ["iop_mmhg"]\n'
                     '[set]\nparameters.mesh = "coarse"\n'
                     f'[grid]\nparameters.tightening = {values}\n')
    return f


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problem", choices=("surgery", "uniaxial"), default="surgery")
    ap.add_argument("--n", type=int, default=6, help="uniaxial: elements per edge")
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    logging.basicConfig(level=logging.WARNING)
    from eyefem.study.spec import load_sweep
    from eyefem.study.sweep import quiet_dask_logs, run_sweep

    quiet_dask_logs()

    with tempfile.TemporaryDirectory(prefix="eyefem-bench-sweep-") as tmp:
        tmp = Path(tmp)
        jax.config.update("jax_compilation_cache_dir", str(tmp / "jax-cache"))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.1)
        sweep = load_sweep(sweep_file(tmp, args.problem, args.n))
        first = sweep.rows[:1]
        warm = run_sweep(dataclasses.replace(sweep, rows=first), out=tmp / "warm", workers=1)
        assert warm.failed == 0, warm.rows
        times: dict[int, list[float]] = {1: [], 2: []}
        for r in range(args.repeat):
            for w in (1, 2):
                res = run_sweep(sweep, out=tmp / f"w{w}-{r}", workers=w)
                assert res.failed == 0 and res.computed == 8, res.rows
                times[w].append(res.wall_s)
                runs = sorted(row["wall_s"] for row in res.rows)
                print(f"{w} worker(s), repeat {r}: {res.wall_s:.1f} s (runs {runs[0]:.1f} to "
                      f"{runs[-1]:.1f} s each)", flush=True)
        m1, m2 = statistics.median(times[1]), statistics.median(times[2])
        what = "coarse surgery case 1" if args.problem == "surgery" else f"uniaxial n={args.n}"
        print(f"8-run sweep ({what}): median {m1:.1f} s on 1 worker, {m2:.1f} s on 2 workers: "
              f"speed-up {m1 / m2:.2f}")


if __name__ == "__main__":
    main()
