"""Stability of a converged state (eyefem.solve.stability): a pretensioned and a compressed
string against their closed forms, and the constrained eigenproblem of an incompressible
(Q1P0) block against dense linear algebra on the null space of the constraints."""

import json
import logging
from pathlib import Path

import meshio
import numpy as np
import pytest
import scipy.linalg
import scipy.sparse

from eyefem.cli.main import main as cli_main
from eyefem.fem.bars import Bars
from eyefem.fem.generators import box
from eyefem.fem.materials import MooneyRivlin
from eyefem.run.runner import stage_stability
from eyefem.solve.assembly import Assembler
from eyefem.solve.model import Model, node_dofs, solid_model
from eyefem.solve.solver import NewtonOptions, Stage
from eyefem.solve.stability import StabilityError, lowest_modes

N_BARS, LENGTH, EA = 8, 2.0, 3.0  # a string of 8 bars, 2 mm each, EA = 3 N


def _string(shortening):
    """A straight string of N_BARS equal bars along x, ends held, every bar's rest length
    (1 - shortening) times its length: in equilibrium at q = 0 with the axial force
    N = EA shortening in every bar (a tension for shortening > 0)."""
    X = np.zeros((N_BARS + 1, 3))
    X[:, 0] = LENGTH * np.arange(N_BARS + 1)
    ends = np.arange(N_BARS)
    bars = Bars("string", np.repeat(ends[:, None], 4, 1), np.repeat(ends[:, None] + 1, 4, 1),
                np.zeros((N_BARS, 2)), np.zeros((N_BARS, 2)), X, EA=EA)
    model = Model(None, (bars,), 3 * len(X))
    theta = {"string": {**bars.params, "shortening": np.full(N_BARS, shortening)}}
    held = np.zeros(model.n_dof, bool)
    held[node_dofs([0, N_BARS])] = True
    return model, theta, held


def _chain(c, j):
    """Eigenvalue j of c tridiag(-1, 2, -1) on the N_BARS - 1 inner nodes."""
    return c * (2.0 - 2.0 * np.cos(j * np.pi / N_BARS))


def test_pretensioned_string_closed_form():
    """Transverse modes of a string in tension N: (N / L) (2 - 2 cos(j pi / n)), twice each
    (y and z), below the axial ones (EA / L) (...), and the mode of j = 1 a half sine."""
    s = 0.05
    model, theta, held = _string(s)
    modes = lowest_modes(model, np.zeros(model.n_dof), theta, held, k=5)
    tension = EA * s
    expect = [_chain(tension / LENGTH, 1)] * 2 + [_chain(tension / LENGTH, 2)] * 2 + \
        [_chain(tension / LENGTH, 3)]
    np.testing.assert_allclose(modes.values, expect, rtol=1e-9)
    assert modes.stable and np.all(modes.residuals < 1e-8)
    u = modes.shapes[0].reshape(-1, 3)
    assert np.allclose(u[:, 0], 0.0, atol=1e-10)  # transverse
    sine = np.sin(np.pi * np.arange(N_BARS + 1) / N_BARS)
    amp = np.linalg.norm(u[:, 1:], axis=1)
    np.testing.assert_allclose(amp, sine / np.linalg.norm(sine), atol=1e-8)


def test_compressed_string_is_unstable():
    """A string in compression (rest length above its length) has the transverse
    eigenvalues of the tension case with the opposite sign: the lowest in magnitude is
    -(|N| / L) (2 - 2 cos(pi / n)), and the state is reported unstable."""
    s = -0.01
    model, theta, held = _string(s)
    modes = lowest_modes(model, np.zeros(model.n_dof), theta, held, k=2)
    np.testing.assert_allclose(modes.values, [_chain(EA * s / LENGTH, 1)] * 2, rtol=1e-9)
    assert not modes.stable


@pytest.fixture(scope="module")
def block():
    """A 3 x 2 x 2 Q1P0 neo-Hookean block, face x0 held, face x1 pulled 20% along x and
    sheared, the inner nodes perturbed: a strained state (not an equilibrium; the
    eigenproblem of the tangent is defined at any state)."""
    mesh = box(3.0, 2.0, 2.0, 3, 2, 2)
    model = solid_model(mesh, {"default": MooneyRivlin("default", [[0, 0.01], [0.05, 0]])})
    held = np.zeros(model.n_dof, bool)
    ends = np.concatenate([mesh.node_sets["x0"], mesh.node_sets["x1"]])
    held[node_dofs(ends)] = True
    q = np.zeros(model.n_dof)
    u = 0.02 * np.random.default_rng(1).standard_normal((mesh.n_nodes, 3))
    u[mesh.node_sets["x0"]] = 0.0
    u[mesh.node_sets["x1"]] = [0.6, 0.2, 0.0]
    q[: 3 * mesh.n_nodes] = u.ravel()
    return model, q, model.theta0(), held


def _dense_constrained(model, q, theta, held):
    """Eigenvalues of K on the null space of B^T, by dense linear algebra."""
    asm = Assembler(model, held)
    _, K, B, D, low_rank = asm.assemble(q, theta)
    Kd = (K - B @ scipy.sparse.diags(D) @ B.T).toarray()
    for alpha, v in low_rank:
        Kd = Kd + alpha * np.outer(v, v)
    Z = scipy.linalg.null_space(B.toarray().T)
    return np.linalg.eigvalsh(Z.T @ Kd @ Z)


def test_block_matches_dense_constrained_eigenvalues(block):
    model, q, theta, held = block
    dense = _dense_constrained(model, q, theta, held)
    k = 4
    modes = lowest_modes(model, q, theta, held, k=k)
    nearest = np.sort(dense[np.argsort(np.abs(dense))[:k]])
    np.testing.assert_allclose(modes.values, nearest, rtol=1e-7)
    mult = model.multiplier_dofs
    asm = Assembler(model, held)
    _, _, B, _, _ = asm.assemble(q, theta)
    for phi in modes.shapes:  # the modes keep every element's volume, to first order
        assert np.linalg.norm(B.T @ phi[asm.free_primal]) < 1e-8
        assert np.all(phi[mult] == 0) and np.all(phi[held] == 0)


def test_block_eigenvalues_do_not_depend_on_the_augmentation(block):
    model, q, theta, held = block
    a = lowest_modes(model, q, theta, held, k=3, beta=1e2)
    b = lowest_modes(model, q, theta, held, k=3, beta=1e6)
    np.testing.assert_allclose(a.values, b.values, rtol=1e-7)


def test_too_many_modes_is_refused(block):
    model, q, theta, held = block
    with pytest.raises(StabilityError, match="free dofs"):
        lowest_modes(model, q, theta, held, k=10_000)


def test_excluded_directions_match_dense_constrained_eigenvalues(block):
    """Modes held orthogonal to given directions R: the eigenvalues of K on the null space
    of [B, R]^T, and never below those without R (constraints only raise them)."""
    model, q, theta, held = block
    asm = Assembler(model, held)
    _, K, B, D, _ = asm.assemble(q, theta)
    R = np.zeros((model.n_dof, 2))
    R[asm.free_primal] = np.random.default_rng(2).standard_normal((asm.n_p, 2))
    Kd = (K - B @ scipy.sparse.diags(D) @ B.T).toarray()
    Z = scipy.linalg.null_space(np.hstack([B.toarray(), R[asm.free_primal]]).T)
    dense = np.linalg.eigvalsh(Z.T @ Kd @ Z)
    k = 3
    modes = lowest_modes(model, q, theta, held, k=k, exclude=R)
    np.testing.assert_allclose(modes.values, np.sort(dense[np.argsort(np.abs(dense))[:k]]),
                               rtol=1e-7)
    assert np.abs(R.T @ modes.shapes.T).max() < 1e-9
    free = lowest_modes(model, q, theta, held, k=k)
    assert np.all(modes.values >= free.values * (1 - 1e-9))


ROOT = Path(__file__).resolve().parents[1]


def test_stability_command_writes_the_modes_of_a_run(tmp_path, capsys):
    """``eyefem run --stability`` records every stage end as stable (a cube in tension);
    ``eyefem stability`` on the run: stability.json (ascending eigenvalues, all positive)
    and stability.vtu (the mode shapes, largest nodal value 1); an unknown stage is
    refused naming the stages."""
    case, out = ROOT / "cases" / "verification" / "uniaxial.toml", tmp_path / "run"
    assert cli_main(["-q", "run", str(case), "--no-vtu", "--stability", "--out", str(out)]) == 0
    checks = json.loads((out / "summary.json").read_text())["stability"]
    assert checks and all(c["stable"] and c["lowest_eigenvalue_N_per_mm"] > 0
                          for c in checks.values())
    assert cli_main(["-q", "stability", str(case), "--out", str(out), "--modes", "3"]) == 0
    result = json.loads((out / "stability.json").read_text())
    values = [m["eigenvalue_N_per_mm"] for m in result["modes"]]
    assert result["stable"] and len(values) == 3 and values == sorted(values) and values[0] > 0
    assert all(m["relative_residual"] < 1e-8 for m in result["modes"])
    vtu = meshio.read(out / "stability.vtu")
    for j in (1, 2, 3):
        assert np.linalg.norm(vtu.point_data[f"mode_{j}"], axis=1).max() == pytest.approx(1.0)
    capsys.readouterr()
    assert cli_main(["-q", "stability", str(case), "--out", str(out), "--stage", "nope"]) == 2
    assert "has no stage 'nope'; its stages:" in capsys.readouterr().err


def test_stability_of_a_case_not_run_says_to_run_it_first(tmp_path, capsys):
    case = ROOT / "cases" / "verification" / "uniaxial.toml"
    assert cli_main(["-q", "stability", str(case), "--out", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err
    assert "holds no run of this case (no checkpoint.json)" in err and "run the case first" in err


def test_an_unstable_stage_end_is_recorded_and_said(caplog):
    """A run's stage check on the compressed string (an equilibrium, unstable): the record
    says unstable with the closed-form lowest eigenvalue, and a warning says the stage's
    outcomes are not physical."""
    model, theta, held = _string(-0.01)
    stage = Stage("compress", 1, (np.nonzero(held)[0], np.zeros(int(held.sum()))))
    with caplog.at_level(logging.WARNING, logger="eyefem.run.runner"):
        rec = stage_stability(model, np.zeros(model.n_dof), theta, stage, NewtonOptions(), 2)
    assert rec["stable"] is False and rec["lowest_mode_rigid_share"] is None
    assert rec["lowest_eigenvalue_N_per_mm"] == pytest.approx(_chain(EA * -0.01 / LENGTH, 1),
                                                              rel=1e-9)
    assert "stage 'compress' ended in an unstable equilibrium" in caplog.text
    assert "not physical" in caplog.text
    model, theta, held = _string(0.05)
    assert stage_stability(model, np.zeros(model.n_dof), theta, stage, NewtonOptions(),
                           2)["stable"] is True
