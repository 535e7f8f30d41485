"""Run folders: a manifest (``run.json``), a lock, the folder's ownership, and clearing
the outputs of an older run.

``run.json`` in an output folder says which program and case made the results there,
whether the run finished, and the sha256 of every file it wrote::

    {"program": "eyefem", "format": 1, "code_version": "0.1.0", "case_hash": "3f2a...",
     "name": "uniaxial", "mesh": {"nodes": 27, "elements": 8}, "status": "complete",
     "started": "2026-11-26T06:30:00+00:00", "finished": "2026-11-26T06:30:04+00:00",
     "files": {"uniaxial_history.csv": "9c1e...", "vtu/uniaxial_0001.vtu": "..."}}

``status`` is ``running`` while solving, then ``complete``, ``failed`` (with ``reason``)
or ``interrupted``. Results are reused (``eyefem compare --reuse``) only from a complete
run of the same case hash and code version whose listed files all still have their
hashes.

Ownership (:func:`claim`): a run writes only into a folder that is new, empty, or holds
the ``run.json`` of an eyefem run; any other folder is refused unless ``force`` adopts it
(after listing the files that clearing would remove), and so is a folder inside the
installed package or the source tree's code. A new run first removes the files the
older run listed in its manifest (:func:`clear_outputs`): regular files inside the
folder only, never through a symbolic link. A lock file (``.eyefem.lock``, holding the
pid) refuses a second run into the same folder at the same time; the lock of a process
that no longer exists is taken over.
"""

from __future__ import annotations

import contextlib
import datetime
import hashlib
import importlib.metadata
import json
import logging
import os
import stat
from pathlib import Path

from eyefem.io.output import write_text

log = logging.getLogger(__name__)

FILENAME = "run.json"
LOCK = ".eyefem.lock"
PROGRAM = "eyefem"
FORMAT = 1
OUTPUT_PATTERNS = ("summary.json", "stages.csv", "*_history.csv", "*.pvd", "*.png",
                   "checkpoint.json", "checkpoint-*.npz", "checkpoint.pkl", "stability.json",
                   "stability.vtu", FILENAME)
"""Files an eyefem run writes under fixed names: what ``force`` lists and removes when it
adopts a folder, and what a new run clears after an older one whose manifest lists no
files (and the ``vtu/`` folder's ``*.vtu``)."""
RECORDED_PATTERNS = OUTPUT_PATTERNS + ("*.csv", "*.xdmf", "*.h5", "vtu/*.vtu")
"""Where the files a run writes are looked for when its manifest is updated (only those
written by the run itself are listed: :func:`record_files`)."""
_SCRATCH = (LOCK, ".eyefem-write-test-")
"""Names (prefixes) of eyefem's own scratch files, ignored when a folder's emptiness is judged."""


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
    elif bad := changed_files(out_dir, m):
        why = (f"{len(bad)} of its files changed since the run wrote them "
               f"({', '.join(bad[:3])}: sha256 differs or missing)")
    elif not isinstance(m.get("files"), dict):
        why = "its run.json lists no files and hashes to check them against"
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


def is_eyefem_run(m: dict | None) -> bool:
    """Whether a parsed ``run.json`` is an eyefem run's (its ``program``, or the keys of
    the manifests written before it had one)."""
    if not isinstance(m, dict):
        return False
    return m.get("program") == PROGRAM or (
        m.get("format") == FORMAT and {"case_hash", "code_version", "status"} <= m.keys())


def _code_folders() -> list[Path]:
    """The installed package's folder and, in a source checkout, the tree's code folders."""
    pkg = Path(__file__).resolve().parents[1]
    out = [pkg]
    root = pkg.parent
    if (root / "pyproject.toml").is_file():
        out += [root / d for d in (".git", "optimize", "tests", "benchmarks", ".ci")]
    return out


def protected(out_dir: Path) -> Path | None:
    """The code folder (package or source tree) that ``out_dir`` lies in, or None."""
    target = Path(out_dir).resolve()
    for d in _code_folders():
        if target == d or d in target.parents:
            return d
    return None


def _entries(out_dir: Path, inputs=()) -> list[str]:
    """Names in ``out_dir`` other than eyefem's scratch files and the caller's ``inputs``."""
    return sorted(n for n in os.listdir(out_dir)
                  if not n.startswith(_SCRATCH) and n not in inputs)


def _pattern_files(out_dir: Path) -> list[Path]:
    """Regular files (never symbolic links) of :data:`OUTPUT_PATTERNS` and ``vtu/*.vtu``
    in ``out_dir``; a ``vtu`` that is a link is not entered."""
    out_dir = Path(out_dir)
    found = [p for pat in OUTPUT_PATTERNS for p in out_dir.glob(pat) if _regular(p)]
    vtu = out_dir / "vtu"
    if vtu.is_dir() and not vtu.is_symlink():
        found += [p for p in sorted(vtu.glob("*.vtu")) if _regular(p)]
    return sorted(set(found))


def _regular(path: Path) -> bool:
    """A regular file, not a symbolic link (lstat: a link is never followed)."""
    try:
        return stat.S_ISREG(os.lstat(path).st_mode)
    except OSError:
        return False


def claim(out_dir: Path, *, force: bool = False, inputs=()) -> Path:
    """Check that a run may write into ``out_dir`` (creating it) before anything is built.

    The folder must be new, empty (but for eyefem's scratch files and the caller's
    ``inputs``, e.g. a sweep run's case file) or hold an eyefem run's ``run.json``;
    ``force`` adopts any other folder after logging the files that clearing will remove.
    Refused always: a folder inside the package or the source tree's code, and a ``vtu``
    inside it that is a symbolic link (results would be written through it). Raises
    OutputError naming the folder and the fix."""
    out_dir = Path(out_dir)
    code = protected(out_dir)
    if code is not None:
        raise OutputError(f"output folder '{out_dir}' is inside eyefem's own code ({code}); "
                          "results never go there: give a folder outside it with --out")
    check_writable(out_dir)
    vtu = out_dir / "vtu"
    if vtu.is_symlink() or (vtu.exists() and not vtu.is_dir()):
        raise OutputError(f"output folder '{out_dir}': 'vtu' there is a symbolic link or a "
                          "file, and the run's VTU frames would be written through it; remove "
                          "it or give a new folder with --out")
    names = _entries(out_dir, inputs)
    m = read(out_dir)
    if not names or is_eyefem_run(m):
        return out_dir
    if force:
        gone = _pattern_files(out_dir)
        log.warning("%s: adopted with --force (no eyefem run.json there); a new run removes "
                    "%d files of eyefem's names there%s", out_dir, len(gone),
                    "".join(f"\n  {p.relative_to(out_dir)}" for p in gone))
        return out_dir
    shown = ", ".join(names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "")
    raise OutputError(f"output folder '{out_dir}' is not empty and no eyefem run wrote it "
                      f"(it holds {shown}, and no eyefem run.json); eyefem writes only into "
                      "a new, empty or eyefem run folder: give a new folder with --out "
                      "NEW_DIR, or add --force to adopt this one (its files of eyefem's "
                      "names, listed first, are then removed)")


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _listed(out_dir: Path, files) -> list[Path]:
    """The paths of a manifest's ``files`` that are safe to touch: relative, inside
    ``out_dir`` without ``..``, regular files (never links)."""
    out_dir = Path(out_dir)
    if not isinstance(files, dict):
        return []
    ok = []
    for rel in files:
        parts = Path(str(rel)).parts
        if not parts or Path(str(rel)).is_absolute() or ".." in parts:
            continue
        if len(parts) > 1 and (out_dir / parts[0]).is_symlink():
            continue
        p = out_dir / str(rel)
        if _regular(p):
            ok.append(p)
    return ok


class FileRecord:
    """The files a run has written, with their sha256, kept up to date cheaply: a file is
    hashed again only when its size or modification time changed.

    ``since_ns``: the run's start (time.time_ns()); a file is listed when it matches
    :data:`RECORDED_PATTERNS`, is a regular file written at or after it, or was listed by
    the run this one resumes (``kept``: rel path -> sha256)."""

    def __init__(self, out_dir: Path, since_ns: int, kept: dict | None = None):
        self.out_dir = Path(out_dir)
        self.since_ns = since_ns
        self.kept = {k: v for k, v in (kept or {}).items()
                     if isinstance(k, str) and isinstance(v, str)}
        self._cache: dict[str, tuple[int, int, str]] = {}

    def files(self) -> dict[str, str]:
        """rel path -> sha256 of every file of the run now on disk (run.json excluded)."""
        out = {}
        seen = set()
        for pat in RECORDED_PATTERNS:
            if pat.startswith("vtu/") and (self.out_dir / "vtu").is_symlink():
                continue
            for p in self.out_dir.glob(pat):
                rel = p.relative_to(self.out_dir).as_posix()
                if rel in seen or rel == FILENAME:
                    continue
                seen.add(rel)
                try:
                    st = os.lstat(p)
                except OSError:
                    continue
                if not stat.S_ISREG(st.st_mode):
                    continue
                if st.st_mtime_ns < self.since_ns and rel not in self.kept:
                    continue
                c = self._cache.get(rel)
                if c is None or c[:2] != (st.st_size, st.st_mtime_ns):
                    c = (st.st_size, st.st_mtime_ns, _sha256(p))
                    self._cache[rel] = c
                out[rel] = c[2]
        return dict(sorted(out.items()))


def changed_files(out_dir: Path, m: dict | None, names=None) -> list[str]:
    """The files a manifest lists (all, or those of ``names``) that are missing or whose
    sha256 differs: what an accident (a copy, an edit, a truncated disk) changed since
    the run wrote them. A manifest without ``files`` lists none."""
    out_dir = Path(out_dir)
    files = (m or {}).get("files")
    if not isinstance(files, dict):
        return []
    bad = []
    for rel, digest in files.items():
        if names is not None and rel not in names:
            continue
        p = out_dir / str(rel)
        if p not in _listed(out_dir, {rel: digest}) or _sha256(p) != digest:
            bad.append(str(rel))
    return bad


def clear_outputs(out_dir: Path, previous: dict | None = None) -> list[Path]:
    """Remove the files an older eyefem run wrote in ``out_dir``: those its manifest
    ``previous`` lists (regular files inside the folder, never through a link), or, for
    a manifest without a list (or a folder adopted with ``force``), the regular files of
    :data:`OUTPUT_PATTERNS` and ``vtu/*.vtu``. Returns what was removed."""
    out_dir = Path(out_dir)
    files = (previous or {}).get("files")
    gone = _listed(out_dir, files) if isinstance(files, dict) else _pattern_files(out_dir)
    gone += [p for p in (out_dir / FILENAME,) if _regular(p) and p not in gone]
    for p in gone:
        p.unlink()
    vtu = out_dir / "vtu"
    if vtu.is_dir() and not vtu.is_symlink() and not any(vtu.iterdir()):
        vtu.rmdir()
    if gone:
        log.info("%s: removed %d files of an older run", out_dir, len(gone))
    return gone
