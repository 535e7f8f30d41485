"""Run a sweep on dask.distributed: every run a task, the table rewritten as runs finish.

:func:`run_sweep` plans the runs (eyefem.study.spec.plan), skips those whose folder
``runs/<index>_<hash8>/`` holds a record (row.json) of the same run hash with status
'ok' or 'did-not-converge' (the same case and code would give the same answer), submits
the rest to a Dask cluster (a LocalCluster of one-thread worker processes, or an
existing scheduler), and as each task finishes writes the table (results.parquet,
results.csv). While the runs go, a progress line (done / failed / running / queued, the
elapsed and the estimated time left) is emitted at most every ``progress_interval``
seconds, and at the start and the end. A run that fails is a row with its message; a worker
that dies has its task re-run by Dask's scheduler (up to ``allowed_failures`` deaths of
that task, then the row says so); an interrupted sweep keeps what finished, and the same
command continues it.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
import uuid
from collections.abc import Callable
from pathlib import Path

from eyefem.io import manifest
from eyefem.study import table
from eyefem.study.spec import PlannedRun, Sweep, plan
from eyefem.study.task import reused_record, run_case

log = logging.getLogger(__name__)

SKIP_STATUSES = ("ok", "did-not-converge")
"""Statuses of a recorded run that a restarted sweep keeps (a 'failed' run, which may
have failed for a passing reason such as a full disk, is run again)."""
ALLOWED_FAILURES = 3
"""Worker deaths a task may cause before the scheduler gives up on it (KilledWorker)."""
PROGRESS_INTERVAL = 5.0
"""Seconds between two progress lines of a sweep (at most one per interval)."""
MISSING_DEPENDENCY = ('eyefem sweep needs dask.distributed and pyarrow: '
                      'pip install "eyefem[sweep]"')


@dataclasses.dataclass
class SweepResult:
    """What a sweep did: its table rows, the folder, how many runs were computed now,
    skipped (complete before), failed, and the wall time (s)."""

    rows: list[dict]
    out_dir: Path
    computed: int
    skipped: int
    failed: int
    wall_s: float


def check_dependencies() -> None:
    """ImportError with the install command when dask.distributed or pyarrow is missing."""
    try:
        import distributed  # noqa: F401
        import pyarrow  # noqa: F401
    except ImportError:
        raise ImportError(MISSING_DEPENDENCY) from None


def quiet_dask_logs(level: int = logging.WARNING) -> None:
    """Set Dask's own loggers (distributed.*, INFO by default: every connection, worker
    start and close) to ``level``; for the entry points (CLI, notebooks)."""
    import distributed  # noqa: F401 - creates its loggers

    for name in list(logging.root.manager.loggerDict):
        if name.split(".")[0] == "distributed":
            logging.getLogger(name).setLevel(level)


def _fmt_s(s: float) -> str:
    if not math.isfinite(s):
        return "?"
    s = round(s)
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else (
        f"{s // 60}m{s % 60:02d}s" if s >= 60 else f"{s}s")


class SweepProgress:
    """The progress of a sweep's runs: one line at most every ``interval`` seconds.

    Args:
      total: the runs to compute (those not complete before).
      emit: where a line goes (a callable taking the text).
      interval: the least time between two lines, s (``force`` overrides it).
      clock: the time source, s (for tests).

    The time left is the elapsed time per finished run times the runs left (the runs
    finish at the pace of the cluster, several at a time); '?' before the first."""

    def __init__(self, total: int, emit: Callable[[str], None], interval: float = PROGRESS_INTERVAL,
                 clock: Callable[[], float] = time.monotonic):
        self.total, self.emit, self.interval, self.clock = total, emit, float(interval), clock
        self.t0 = clock()
        self.last = -math.inf

    def line(self, done: int, failed: int, running: int) -> str:
        """The progress text after ``done`` finished runs (``failed`` of them not ok)."""
        elapsed = self.clock() - self.t0
        left = self.total - done
        eta = 0.0 if not left else elapsed / done * left if done else math.nan
        return (f"sweep: {done}/{self.total} runs done ({failed} failed), {running} running, "
                f"{max(0, left - running)} queued; {_fmt_s(elapsed)} elapsed, ~{_fmt_s(eta)} left")

    def due(self) -> bool:
        """Whether ``interval`` has passed since the last line."""
        return self.clock() - self.last >= self.interval

    def update(self, done: int, failed: int, running: int, *, force: bool = False) -> bool:
        """Emit the line if ``interval`` has passed since the last one (or ``force``);
        returns whether it did."""
        if not force and not self.due():
            return False
        self.last = self.clock()
        self.emit(self.line(done, failed, running))
        return True


def _running(client, pending, fallback: int) -> int:
    """How many of the ``pending`` futures a worker is executing now: per worker, the
    tasks it is processing, at most its threads; ``fallback`` if the scheduler does not
    say."""
    keys = {f.key for f in pending}
    try:
        nthreads = client.nthreads()
        return sum(min(sum(k in keys for k in ks), nthreads.get(w, 1))
                   for w, ks in client.processing().items())
    except Exception:  # noqa: BLE001 - a busy or lost scheduler: the estimate will do
        return min(len(pending), fallback)


def local_client(n_workers: int | None = None):
    """A dask Client on a new LocalCluster: ``n_workers`` (default: the cores) worker
    processes of one thread each (JAX and the sparse solvers are not shared between
    threads of a run; a process per run keeps their caches apart)."""
    from distributed import Client, LocalCluster

    n = n_workers or os.cpu_count() or 1
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                           dashboard_address=":0")
    return Client(cluster)


def run_sweep(sweep: Sweep, *, out: str | Path | None = None, client=None,
              scheduler: str | None = None, workers: int | None = None,
              progress: Callable[[str], None] | None = None,
              progress_interval: float = PROGRESS_INTERVAL, device: str = "cpu") -> SweepResult:
    """Run the sweep's runs on a Dask cluster; returns the table and counts.

    Args:
      sweep: a validated sweep (eyefem.study.spec.load_sweep).
      out: output folder (default: the sweep's ``output``).
      client: a dask Client to use (kept open); else ``scheduler`` (an address of an
        existing cluster; its workers must see ``out``, a shared file system), else a new
        LocalCluster of ``workers`` processes (default: the cores), closed at the end.
      progress: where the progress lines go (default: this module's logger at INFO).
      progress_interval: the least time between two progress lines, s.
      device: where each run's element kernels run ("cpu" or "gpu", as ``eyefem --device``);
        a worker without a GPU fails its runs with a message.
    """
    check_dependencies()
    import jax
    from distributed import Client, wait

    tic = time.perf_counter()
    out_dir = manifest.check_writable(Path(out) if out is not None else sweep.output)
    runs, invalid = plan(sweep)
    overrides = {i: row for i, row in enumerate(sweep.rows)}
    records: dict[int, dict] = {}
    for i, row, msg in invalid:
        records[i] = {"index": i, "status": "failed", "error": f"invalid case: {msg}",
                      "wall_s": 0.0, "run_hash": "", "run_dir": ""}
    todo: list[PlannedRun] = []
    for r in runs:
        prev = reused_record(out_dir / "runs" / r.folder, r.run_hash, SKIP_STATUSES)
        if prev is not None:
            records[r.index] = prev
        else:
            todo.append(r)
    skipped = len(runs) - len(todo)
    log.info("sweep %s: %d runs (%d complete before, %d to run, %d invalid) -> %s",
             sweep.path, len(sweep.rows), skipped, len(todo), len(invalid), out_dir)

    def write_table():
        rows = table.rows(records, overrides, sweep.varied, sweep.outcomes)
        table.write(rows, out_dir)
        return rows

    rows = write_table()
    computed = 0
    if todo:
        own = client is None
        if own:
            client = Client(scheduler) if scheduler else local_client(workers)
        try:
            n_workers = max(1, len(client.scheduler_info().get("workers", {})))
            cache = jax.config.jax_compilation_cache_dir or None
            _allow_failures(client)
            futures = {}
            for r in todo:
                f = client.submit(run_case, r.case_text, str((out_dir / "runs" / r.folder).resolve()),
                                  run_hash=r.run_hash, index=r.index, gradients=sweep.gradients,
                                  outcomes=sweep.outcomes, fd_step=sweep.fd_step,
                                  jax_cache=cache, device=device, pure=False,
                                  key=f"eyefem-run-{r.index:04d}-{r.run_hash[:8]}-{uuid.uuid4().hex[:6]}")
                futures[f] = r
            log.info("sweep: %d runs submitted to %d workers (%s)", len(futures), n_workers,
                     client.scheduler.address)
            failed = 0
            meter = SweepProgress(len(futures), progress or log.info, progress_interval)
            pending = set(futures)
            meter.update(0, 0, _running(client, pending, n_workers), force=True)
            while pending:
                try:
                    done, pending = wait(pending, timeout=progress_interval,
                                         return_when="FIRST_COMPLETED")
                except TimeoutError:  # nothing finished: a progress line all the same
                    done = set()
                for f in sorted(done, key=lambda f: futures[f].index):
                    r = futures[f]
                    try:
                        rec = f.result()
                    except Exception as exc:  # noqa: BLE001 - KilledWorker, lost scheduler...
                        rec = {"index": r.index, "run_hash": r.run_hash, "status": "failed",
                               "error": f"{type(exc).__name__}: {exc}", "wall_s": math.nan,
                               "run_dir": str(out_dir / "runs" / r.folder)}
                    records[r.index] = rec
                    computed += 1
                    failed += rec["status"] != "ok"
                    log.debug("sweep: run %d %s in %s", r.index, rec["status"],
                              _fmt_s(rec.get("wall_s", math.nan)))
                    if rec["status"] != "ok":
                        log.warning("sweep: run %d %s: %s", r.index, rec["status"],
                                    str(rec.get("error", ""))[:500])
                if done:
                    rows = write_table()
                if meter.due() or not pending:  # ask the scheduler only for a line
                    meter.update(computed, failed, _running(client, pending, n_workers)
                                 if pending else 0, force=True)
        finally:
            if own:
                cluster = getattr(client, "cluster", None)
                client.close()
                if cluster is not None:
                    cluster.close()
    n_failed = sum(r["status"] != "ok" for r in rows)
    return SweepResult(rows, out_dir, computed, skipped, n_failed, time.perf_counter() - tic)


def _allow_failures(client) -> None:
    """Let a task survive ALLOWED_FAILURES deaths of its worker (the scheduler's
    ``allowed_failures``) on a cluster this sweep talks to."""
    def setter(dask_scheduler=None, n=ALLOWED_FAILURES):
        dask_scheduler.allowed_failures = max(dask_scheduler.allowed_failures, n)

    try:
        client.run_on_scheduler(setter)
    except Exception as exc:  # noqa: BLE001 - a scheduler that refuses keeps its own
        log.debug("sweep: could not set allowed_failures: %s", exc)


def best_designs(sweep: Sweep, rows: list[dict]) -> list[dict]:
    """The ``sweep.best['show']`` best ok rows by the [best] outcome and goal."""
    b = sweep.best
    name = b["outcome"] or next((c for c in (rows[0] if rows else {}) if c not in
                                 table.FIXED_COLUMNS and c not in sweep.varied
                                 and not c.startswith("d_")), None)
    ok = [r for r in rows if r["status"] == "ok" and isinstance(r.get(name), float)
          and math.isfinite(r[name])]
    if not name or not ok:
        return []

    def score(r):
        v = r[name]
        return v if b["goal"] == "min" else -v if b["goal"] == "max" else abs(v - b["target"])

    return sorted(ok, key=score)[: b["show"]]


def format_best(sweep: Sweep, rows: list[dict]) -> str:
    """A text table of the best designs (varied parameters, outcomes)."""
    best = best_designs(sweep, rows)
    if not best:
        return "no successful run to rank"
    b = {**sweep.best, "outcome": sweep.best["outcome"] or next(
        c for c in best[0] if c not in table.FIXED_COLUMNS and c not in sweep.varied)}
    goal = f"closest to {b['target']:g}" if b["goal"] == "target" else f"{b['goal']}imum"
    cols = ["index", *sweep.varied] + [c for c in best[0] if c not in table.FIXED_COLUMNS
                                        and c not in sweep.varied and not c.startswith("d_")]
    width = {c: max(len(c), 12) for c in cols}
    lines = [f"best designs by {b['outcome']} ({goal}):",
             "  " + "  ".join(f"{c:>{width[c]}}" for c in cols)]
    for r in best:
        cells = [f"{r[c]:>{width[c]}.6g}" if isinstance(r[c], float) else f"{r[c]!s:>{width[c]}}"
                 for c in cols]
        lines.append("  " + "  ".join(cells))
    return "\n".join(lines)
