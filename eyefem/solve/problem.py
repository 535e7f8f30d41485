"""The problem contract: what a problem builder (the surgery, a verification problem, an
imported mesh or FEBio deck) hands to the runner (:func:`eyefem.run.runner.run_setup`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from eyefem.solve.loadpath import Stage
from eyefem.solve.model import Model


@dataclasses.dataclass(frozen=True)
class Setup:
    """What a problem builder returns.

    Attributes:
      name: base name of the output files.
      model: the model.
      stages: the load path.
      probe: ``f(model, q, theta) -> dict`` of scalars recorded at every step.
      finish: ``f(rows, out_dir, plots) -> dict`` summary (theory comparison, plots).
      q0: optional initial state, shape (n_dofs,).
      parts: what the problem was built from, for outputs and planning (the surgery:
        eyefem.eye.parts.SurgeryParts), or None.
    """

    name: str
    model: Model
    stages: list[Stage]
    probe: Callable[[Model, np.ndarray, Any], dict]
    finish: Callable[[list[dict], Path, bool], dict]
    q0: np.ndarray | None = None
    parts: Any = None
