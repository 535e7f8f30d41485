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
class Whole:
    """The whole model behind a Setup that solves a reduced one (the mirror half of the
    eye): the runner writes the results of the whole (VTU frames with its mesh, fields and
    reactions; the stability checks) at the whole state lifted from the solved one.

    Attributes:
      model: the whole model at the start (``n_dof`` unknowns).
      stages: the whole model's stages, by the solved stages' names (their prescribed
        dofs, on the whole, give the reactions; their active terms the NaN fields).
      q0: the whole's initial state (n_dof,) or None (zero).
      lift: ``f(model, q, theta) -> (model, q, theta)``: the whole model in effect with a
        solved model (after the stages' hooks), the whole state (n_dof,) of a solved state
        and the whole's design of a solved design.
      solved: what the solved model is, for summary.json and run.json (e.g. "mirror half
        y > 0").
      residual: ``f(g) -> g_whole``: the whole's residual (n_dof,) at a lifted state from
        the solved model's residual there (the reactions, without the whole's kernels), or
        None (the whole model's gradient at the lifted state).
    """

    model: Model
    stages: list[Stage]
    q0: np.ndarray | None
    lift: Callable[[Model, np.ndarray, Any], tuple[Model, np.ndarray, Any]]
    solved: str = "reduced"
    residual: Callable[[np.ndarray], np.ndarray] | None = None


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
      whole: the whole model when ``model`` is a reduced one (:class:`Whole`: the
        results are written on the whole), or None.
    """

    name: str
    model: Model
    stages: list[Stage]
    probe: Callable[[Model, np.ndarray, Any], dict]
    finish: Callable[[list[dict], Path, bool], dict]
    q0: np.ndarray | None = None
    parts: Any = None
    whole: Whole | None = None
