"""Stage checkpoints: resume an interrupted load path after its last completed stage.

A checkpoint (``checkpoint.pkl`` in the output directory, written atomically after
every completed stage) holds the state at the end of the last completed stage, the
state at the start of every completed stage (to replay their ``before`` hooks, which
rebuild the model: closing the cavity, fitting the buckle...), the rows of the step
history and the VTU entries written so far, and a fingerprint of the case so that a
checkpoint is never applied to a different model.
"""

from __future__ import annotations

import hashlib
import pickle
from pathlib import Path

import jax
import numpy as np

from eyefem.io.output import atomic_path

FILENAME = "checkpoint.pkl"
VERSION = 1


class CheckpointError(RuntimeError):
    """The checkpoint is missing, unreadable or belongs to another case."""


def fingerprint(*parts) -> str:
    """A short hash of anything with a stable repr (the case parameters, dof count)."""
    return hashlib.sha256(repr(parts).encode()).hexdigest()[:16]


def _numpy(tree):
    return jax.tree_util.tree_map(np.asarray, tree)


def save(out_dir: Path, *, key: str, stage: int, q, theta, starts, rows, vtu_entries):
    """Write the checkpoint after completed stage index ``stage``."""
    data = {"version": VERSION, "key": key, "stage": stage, "q": np.asarray(q),
            "theta": _numpy(theta), "starts": [(np.asarray(a), _numpy(b)) for a, b in starts],
            "rows": list(rows), "vtu_entries": list(vtu_entries)}
    with atomic_path(Path(out_dir) / FILENAME) as tmp:
        with open(tmp, "wb") as f:
            pickle.dump(data, f, protocol=pickle.HIGHEST_PROTOCOL)


def load(out_dir: Path, key: str) -> dict:
    """Read the checkpoint of ``out_dir``; checks that it belongs to the case ``key``."""
    path = Path(out_dir) / FILENAME
    if not path.exists():
        raise CheckpointError(f"{path}: no checkpoint (no stage of this run completed); "
                              "run without --resume")
    try:
        with open(path, "rb") as f:
            data = pickle.load(f)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means unusable
        raise CheckpointError(f"{path}: unreadable checkpoint ({exc}); run without --resume") from None
    if data.get("version") != VERSION:
        raise CheckpointError(f"{path}: checkpoint version {data.get('version')}, expected "
                              f"{VERSION}; run without --resume")
    if data["key"] != key:
        raise CheckpointError(f"{path}: the checkpoint belongs to another case or parameter set; "
                              "run without --resume (or use another --out)")
    return data
