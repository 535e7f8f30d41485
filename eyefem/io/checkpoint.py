"""Stage checkpoints: resume an interrupted load path after its last completed stage.

A checkpoint holds data only, never code: ``checkpoint-<hash>.npz`` (numpy arrays, read
with ``allow_pickle=False``) and ``checkpoint.json`` (format, eyefem version, the case
fingerprint, the stage index, the step history rows, the VTU entries, the names and tree
structure of the arrays and the npz's sha256). It holds the state at the end of the last
completed stage and the state at the start of every completed stage (to replay their
``before`` hooks, which rebuild the model: closing the cavity, fitting the buckle...).
Both files are written atomically after every completed stage, the npz first, so that
the pair on disk always matches. A checkpoint of another case, another eyefem version
or another format, or one whose arrays do not match its manifest, is refused; a pickle
(``checkpoint.pkl`` of older versions) is never opened.
"""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path

import numpy as np

from eyefem.io.manifest import code_version
from eyefem.io.output import atomic_path, write_text

FILENAME = "checkpoint.json"
FORMAT = 3
"""The layout of the saved state (3: the suture terms' param "tied"); another is refused."""


class CheckpointError(RuntimeError):
    """The checkpoint is missing, unreadable or belongs to another case."""


def fingerprint(*parts) -> str:
    """A short hash of anything with a stable repr (the case parameters, dof count)."""
    return hashlib.sha256(repr(parts).encode()).hexdigest()[:16]


def flatten(tree, prefix: str, arrays: dict) -> dict:
    """Describe a pytree of nested dicts / lists / tuples / None with array or scalar
    leaves as JSON, moving the leaves into ``arrays`` (name -> np.ndarray) under names
    starting with ``prefix``. Returns the JSON structure; ``unflatten`` inverts it."""
    if tree is None:
        return {"none": True}
    if isinstance(tree, dict):
        if not all(isinstance(k, str) for k in tree):
            raise TypeError(f"checkpoint: {prefix}: dict keys must be strings, got {list(tree)}")
        return {"dict": {k: flatten(v, f"{prefix}/{k}", arrays) for k, v in tree.items()}}
    if isinstance(tree, (list, tuple)):
        if hasattr(tree, "_fields"):
            raise TypeError(f"checkpoint: {prefix}: named tuples are not supported")
        kind = "list" if isinstance(tree, list) else "tuple"
        return {kind: [flatten(v, f"{prefix}/{i}", arrays) for i, v in enumerate(tree)]}
    arr = np.asarray(tree)
    if arr.dtype == object:
        raise TypeError(f"checkpoint: {prefix}: leaf of type {type(tree).__name__} is not an "
                        "array or number")
    arrays[prefix] = arr
    return {"array": prefix}


def unflatten(node: dict, arrays) -> object:
    """Rebuild the pytree that ``flatten`` described (leaves as numpy arrays)."""
    if not isinstance(node, dict) or len(node) != 1:
        raise ValueError(f"malformed tree node {node!r}")
    (kind, val), = node.items()
    if kind == "none":
        return None
    if kind == "dict":
        return {k: unflatten(v, arrays) for k, v in val.items()}
    if kind in ("list", "tuple"):
        items = [unflatten(v, arrays) for v in val]
        return items if kind == "list" else tuple(items)
    if kind == "array":
        return np.asarray(arrays[val])
    raise ValueError(f"unknown tree node kind '{kind}'")


def _plain(v):
    if isinstance(v, np.generic):
        return v.item()
    raise TypeError(f"{type(v).__name__} is not JSON")


def save(out_dir: Path, *, key: str, stage: int, q, theta, starts, rows, vtu_entries):
    """Write the checkpoint after completed stage index ``stage``.

    Args: q (n_dof,) state; theta the design pytree; starts [(q, theta)] at the start of
    every completed stage; rows the history rows; vtu_entries [(time, file)]."""
    out_dir = Path(out_dir)
    arrays: dict[str, np.ndarray] = {}
    tree = {"q": flatten(q, "q", arrays), "theta": flatten(theta, "theta", arrays),
            "starts": [[flatten(a, f"starts/{i}/q", arrays),
                        flatten(b, f"starts/{i}/theta", arrays)]
                       for i, (a, b) in enumerate(starts)]}
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    blob = buf.getvalue()
    digest = hashlib.sha256(blob).hexdigest()
    npz = out_dir / f"checkpoint-{digest[:16]}.npz"
    with atomic_path(npz) as tmp:
        tmp.write_bytes(blob)
    meta = {"format": FORMAT, "code_version": code_version(), "key": key, "stage": stage,
            "npz": npz.name, "npz_sha256": digest, "tree": tree, "rows": list(rows),
            "vtu_entries": [list(e) for e in vtu_entries]}
    write_text(out_dir / FILENAME, json.dumps(meta, default=_plain) + "\n")
    for old in out_dir.glob("checkpoint-*.npz"):
        if old.name != npz.name:
            old.unlink(missing_ok=True)


def load(out_dir: Path, key: str) -> dict:
    """Read the checkpoint of ``out_dir``; checks that it belongs to the case ``key`` and
    this eyefem version. Returns dict(stage, q, theta, starts, rows, vtu_entries)."""
    out_dir = Path(out_dir)
    path = out_dir / FILENAME
    again = "run without --resume (or use another --out)"
    if not path.exists():
        old = " (a checkpoint.pkl of an older eyefem is never read)" if (
            out_dir / "checkpoint.pkl").exists() else ""
        raise CheckpointError(f"{path}: no checkpoint (no stage of this run completed){old}; "
                              "run without --resume")
    try:
        meta = json.loads(path.read_text())
        if not isinstance(meta, dict):
            raise TypeError("not a JSON object")
    except (OSError, ValueError, TypeError) as exc:
        raise CheckpointError(f"{path}: unreadable checkpoint ({exc}); {again}") from None
    if meta.get("format") != FORMAT:
        raise CheckpointError(f"{path}: checkpoint format {meta.get('format')!r}, expected "
                              f"{FORMAT}; {again}")
    if meta.get("code_version") != code_version():
        raise CheckpointError(f"{path}: checkpoint written by eyefem "
                              f"{meta.get('code_version')!r}, this is {code_version()}; {again}")
    if meta.get("key") != key:
        raise CheckpointError(f"{path}: the checkpoint belongs to another case or parameter "
                              f"set; {again}")
    npz = out_dir / str(meta.get("npz", ""))
    if Path(str(meta.get("npz", ""))).name != meta.get("npz") or not npz.is_file():
        raise CheckpointError(f"{path}: its arrays file '{meta.get('npz')}' is missing; {again}")
    blob = npz.read_bytes()
    if hashlib.sha256(blob).hexdigest() != meta.get("npz_sha256"):
        raise CheckpointError(f"{npz}: does not match {path} (sha256 differs); {again}")
    try:
        with np.load(npz, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
        tree = meta["tree"]
        return {"stage": int(meta["stage"]), "q": unflatten(tree["q"], arrays),
                "theta": unflatten(tree["theta"], arrays),
                "starts": [(unflatten(a, arrays), unflatten(b, arrays))
                           for a, b in tree["starts"]],
                "rows": list(meta["rows"]),
                "vtu_entries": [(float(t), str(f)) for t, f in meta["vtu_entries"]]}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CheckpointError(f"{path}: unreadable checkpoint ({exc}); {again}") from None
