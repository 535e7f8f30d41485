"""Stage checkpoints: an interrupted load path resumes after its last completed stage."""

import numpy as np
import pytest

from eyefem.fem import generators
from eyefem.fem.materials import MooneyRivlin
from eyefem.fem.terms import NodeSprings
from eyefem.io import checkpoint
from eyefem.solve.problem import Setup
from eyefem.run.runner import run_setup
from eyefem.solve.model import node_dofs, solid_model
from eyefem.solve.solver import Stage


class Interrupted(Exception):
    pass


def _setup(stop_in_stage=None):
    """A block stretched in three stages; stage 2's hook swaps in springs on every node,
    so a resume after stage 2 that did not replay the hook would give another answer."""
    mesh = generators.box(1.0, 1.0, 1.0, 2, 2, 2, material="m")
    springs = NodeSprings("springs", mesh.node_set("x1"), k=1e-3)
    model = solid_model(mesh, {"m": MooneyRivlin.from_terms("m", {"c10": 0.5})}, (springs,))
    x0 = node_dofs(mesh.node_set("x0"))
    x1 = node_dofs(mesh.node_set("x1"))[0::3]
    dofs = np.concatenate([x0, x1])

    def stiffen(model, q, theta):
        stiff = NodeSprings("springs", mesh.node_set("all"), k=1e-3)
        return model.with_terms([stiff if t.name == "springs" else t for t in model.terms]), q, theta

    def probe(model, q, theta):
        if stop_in_stage is not None and len(calls) == stop_in_stage:
            raise Interrupted
        calls.append(1)
        return {"ux": float(q[x1].mean())}

    calls = []
    stages = [Stage("one", 2, (dofs, np.r_[np.zeros(len(x0)), np.full(len(x1), 0.1)])),
              Stage("two", 2, (dofs, np.r_[np.zeros(len(x0)), np.full(len(x1), 0.2)]),
                    before=stiffen),
              Stage("three", 2, (dofs, np.r_[np.zeros(len(x0)), np.full(len(x1), 0.3)]))]
    return Setup("block", model, stages, probe, lambda rows, out, plots: {"rows": len(rows)})


def test_resume_after_interruption_matches_an_uninterrupted_run(tmp_path):
    full = run_setup(_setup(), tmp_path / "full", vtu=True, plots=False, key="k")
    with pytest.raises(Interrupted):  # interrupted at the first step of stage three
        run_setup(_setup(stop_in_stage=4), tmp_path / "cut", vtu=True, plots=False, key="k")
    ck = checkpoint.load(tmp_path / "cut", checkpoint.fingerprint("k", "block", full.solution.model.n_dof, 3))
    assert ck["stage"] == 1 and len(ck["rows"]) == 4
    res = run_setup(_setup(), tmp_path / "cut", vtu=True, plots=False, key="k", resume=True)
    assert [r["stage"] for r in res.rows] == [r["stage"] for r in full.rows]
    np.testing.assert_allclose(res.solution.q, full.solution.q, rtol=1e-9, atol=1e-12)
    n_all = len(res.solution.model.mesh.node_set("all"))
    assert len(res.solution.model.term("springs").nodes) == n_all  # the hook was replayed
    assert len(list((tmp_path / "cut" / "vtu").glob("*.vtu"))) == 7  # undeformed + 6 steps
    files = sorted(p.name for p in (tmp_path / "cut").glob("checkpoint*"))
    assert len(files) == 2 and "checkpoint.json" in files  # and one checkpoint-<hash>.npz
    assert not list((tmp_path / "cut").glob("*.pkl"))


def test_resume_refuses_a_checkpoint_of_another_case(tmp_path):
    run_setup(_setup(), tmp_path, vtu=False, plots=False, key="case A")
    with pytest.raises(checkpoint.CheckpointError, match="another case"):
        run_setup(_setup(), tmp_path, vtu=False, plots=False, key="case B", resume=True)
    with pytest.raises(checkpoint.CheckpointError, match="no checkpoint"):
        run_setup(_setup(), tmp_path / "empty", vtu=False, plots=False, key="case A", resume=True)
