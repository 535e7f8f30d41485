"""Run folders: a manifest (``run.json``), a lock, and clearing the outputs of an older run.

``run.json`` in an output folder says which case made the results there and whether
the run finished::

    {"format": 1, "code_version": "0.1.0", "case_hash": "3f2a...", "name": "uniaxial",
     "mesh": {"nodes": 27, "elements": 8}, "status": "complete",
     "started": "2026-11-26T06:30:00+00:00", "finished": "2026-11-26T06:30:04+00:00"}

``status`` is ``running`` while solving, then ``complete``, ``failed`` (with ``reason``)
or ``interrupted``. Results are reused (``eyefem compare --reuse``) only from a complete
run of the same case hash and code version. A new run first removes what an older run
wrote there (only eyefem's own files, see :data:`OUTPUT_PATTERNS`); ``--resume`` keeps
them. A lock file (``.eyefem.lock``, holding the pid) refuses a second run into the
same folder at the same time; the lock of a process that no longer exists is taken over.
"""

from __future__ import annotations

import contextlib
import datetime
import hashlib
import importlib.metadata
import json
import logging
import os
import shutil
from pathlib import Path

from eyefem.io.output import write_text

log = logging.getLogger(__name__)

FILENAME = "run.json"
LOCK = ".eyefem.lock"
FORMAT = 1
OUTPUT_PATTERNS = ("summary.json", "stages.csv", "*_history.csv", "*.pvd", "*.png",
                   "checkpoint.json", "checkpoint-*.npz", "checkpoint.pkl", "stability.json",
                   "stability.vtu", FILENAME)
"""Files of an older run that a new run removes (and the ``vtu/`` folder's ``*.vtu``)."""


class OutputError(OSError):
    """The output folder cannot be used (a file, not writable, locked by another run)."""


def code_version() -> str:
    """The installed eyefem version (``importlib.metadata``), or ``unknown``."""
    try:
        return importlib.metadata.version("eyefem")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def _plain(obj):
    """JSON-able canonical form of case data (dicts, dataclasses, arrays, scalars)."""
    import dataclasses

    import numpy as np

    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {"__type__": type(obj).__name__,
                **{f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}}
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in sorted(obj.items(), key=lambda kv: str(kv[0]))}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        return repr(float(obj))  # exact; also nan/inf
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if obj is None or isinstance(obj, (bool, int, str)):
        return obj
    return repr(obj)


def case_key(problem: str, parameters: dict, materials: dict, solver) -> str:
    """A canonical text of the parsed case (problem, parameters with the mesh level,
    materials, solver options, and the sha256 of every file a parameter names by its
    absolute path: a user's mesh file): equal text <=> the same computation."""
    files = {v: hashlib.sha256(Path(v).read_bytes()).hexdigest()
             for v in parameters.values()
             if isinstance(v, str) and Path(v).is_absolute() and Path(v).is_file()}
    return json.dumps({"problem": problem, "parameters": _plain(parameters),
                       "materials": _plain(materials), "solver": _plain(solver),
                       **({"files": files} if files else {})}, sort_keys=True)


def case_hash(key: str) -> str:
    """sha256 (hex, 32 characters) of a case key."""
    return hashlib.sha256(key.encode()).hexdigest()[:32]


def now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def read(out_dir: Path) -> dict | None:
    """The manifest of ``out_dir`` or None (missing or unreadable)."""
    path = Path(out_dir) / FILENAME
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def write(out_dir: Path, manifest: dict) -> dict:
    """Write ``run.json`` atomically; returns the manifest."""
    write_text(Path(out_dir) / FILENAME, json.dumps(manifest, indent=2) + "\n")
    return manifest


def updated(out_dir: Path, manifest: dict, **changes) -> dict:
    """Write and return a copy of ``manifest`` with ``changes``."""
    return write(out_dir, {**manifest, **changes})


def reusable_summary(out_dir: Path, key: str) -> dict | None:
    """The summary of a complete run of the case ``key`` by this code version in
    ``out_dir``, or None (with the reason logged) when it has to be computed again."""
    out_dir = Path(out_dir)
    m = read(out_dir)
    why = None
    if m is None:
        why = "no run manifest (run.json)"
    elif m.get("status") != "complete":
        why = f"the run there is '{m.get('status')}'"
    elif m.get("case_hash") != case_hash(key):
        why = "the case changed since that run"
    elif m.get("code_version") != code_version():
        why = f"it was computed by eyefem {m.get('code_version')}, this is {code_version()}"
    else:
        try:
            return json.loads((out_dir / "summary.json").read_text())
        except (OSError, ValueError):
            why = "summary.json is missing or unreadable"
    log.info("%s: not reusing the results there (%s); computing", out_dir, why)
    return None


def check_writable(out_dir: Path) -> Path:
    """Create ``out_dir`` and check that files can be written there, before any solving.

    Raises OutputError naming the folder and the fix."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError(f"output folder '{out_dir}' is an existing file; give a folder "
                          "with --out (or [output] directory)")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        probe = out_dir / f".eyefem-write-test-{os.getpid()}"
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        raise OutputError(f"cannot write in the output folder '{out_dir}': "
                          f"{exc.strerror or exc}; choose another --out") from None
    return out_dir


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def acquire(out_dir: Path):
    """Take ``out_dir/.eyefem.lock`` (our pid); returns the function that releases it.

    Raises OutputError when a live process holds it; a lock of a dead pid is taken over."""
    path = Path(out_dir) / LOCK
    for _ in range(3):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                pid = int(path.read_text().strip() or "0")
            except (OSError, ValueError):
                pid = 0
            if pid > 0 and _alive(pid):
                raise OutputError(f"output folder '{out_dir}' is in use by another eyefem run "
                                  f"(pid {pid}, lock {path}); wait for it to end or choose "
                                  "another --out") from None
            log.warning("%s: taking over the stale lock of process %d (no longer running)",
                        out_dir, pid)
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
            continue
        with os.fdopen(fd, "w") as f:
            f.write(f"{os.getpid()}\n")
        break
    else:
        raise OutputError(f"output folder '{out_dir}': could not take the lock {path}")

    def release():
        with contextlib.suppress(FileNotFoundError):
            path.unlink()

    return release


@contextlib.contextmanager
def locked(out_dir: Path):
    """Hold the lock of ``out_dir`` while the block runs (see :func:`acquire`)."""
    release = acquire(out_dir)
    try:
        yield Path(out_dir) / LOCK
    finally:
        release()


def clear_outputs(out_dir: Path) -> list[Path]:
    """Remove the files an older eyefem run wrote in ``out_dir`` (only
    :data:`OUTPUT_PATTERNS` and ``vtu/*.vtu``); returns what was removed."""
    out_dir = Path(out_dir)
    gone = [p for pat in OUTPUT_PATTERNS for p in out_dir.glob(pat) if p.is_file()]
    vtu = out_dir / "vtu"
    if vtu.is_dir():
        gone += sorted(vtu.glob("*.vtu"))
    for p in gone:
        p.unlink()
    if vtu.is_dir() and not any(vtu.iterdir()):
        shutil.rmtree(vtu)
    if gone:
        log.info("%s: removed %d files of an older run", out_dir, len(gone))
    return gone
