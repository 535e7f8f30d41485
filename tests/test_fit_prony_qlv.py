"""benchmarks/fit_prony.py with Fung's quasi-linear (QLV) constants: the closed-form
reduced relaxation function of a box spectrum against its defining integral, the curve
written with its source and fitted, and what a window-limited fit does not identify.
The constants here are synthetic (no published set could be read: eyefem/eye/relaxation.py)."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import quad

PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "fit_prony.py"
_spec = importlib.util.spec_from_file_location("fit_prony", PATH)
fp = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fp)


def _box(t, C, tau1, tau2):
    """G(t) from its definition: [1 + C int_tau1^tau2 exp(-t/s) ds/s] / [1 + C ln(tau2/tau1)],
    integrated in ln s."""
    val, _ = quad(lambda u: np.exp(-t / np.exp(u)), np.log(tau1), np.log(tau2),
                  epsabs=1e-14, epsrel=1e-13, limit=200)
    return (1.0 + C * val) / (1.0 + C * np.log(tau2 / tau1))


@pytest.mark.parametrize("C, tau1, tau2", [(0.1, 0.1, 1000.0), (0.05, 1.0, 1e5),
                                           (0.3, 0.01, 300.0)])
def test_the_closed_form_is_the_box_spectrum(C, tau1, tau2):
    t = np.geomspace(1e-3, 1e6, 19)
    G = fp.qlv_curve(t, C, tau1, tau2)
    ref = np.array([_box(x, C, tau1, tau2) for x in t])
    np.testing.assert_allclose(G, ref, rtol=1e-9)
    # the limits: the instantaneous response and the equilibrium fraction
    assert fp.qlv_curve([1e-9 * tau1], C, tau1, tau2)[0] == pytest.approx(1.0, abs=1e-7)
    assert fp.qlv_curve([1e3 * tau2], C, tau1, tau2)[0] == pytest.approx(
        1.0 / (1.0 + C * np.log(tau2 / tau1)), rel=1e-12)
    assert np.all(np.diff(G) <= 0)  # relaxation only


@pytest.mark.parametrize("args, words", [((0.1, 10.0, 1.0), "need 0 < tau1 < tau2"),
                                         ((-0.1, 1.0, 10.0), "C = -0.1"),
                                         ((0.1, 0.0, 10.0), "need 0 < tau1 < tau2")])
def test_bad_qlv_constants_are_refused(args, words):
    with pytest.raises(ValueError, match=words):
        fp.qlv_curve([1.0], *args)
    with pytest.raises(ValueError, match="above 0"):
        fp.qlv_curve([0.0, 1.0], 0.1, 1.0, 10.0)


def test_qlv_constants_become_a_sourced_curve_and_a_prony_fit(tmp_path):
    """--qlv samples G over the window into a CSV whose header names the source and the
    constants, and fits it: one exponential per decade reproduces the box spectrum to 1 %
    of G (measured 0.5 %), the reported rms is the residual's, and the fitted relaxed
    fraction over a 1-1000 s window is not the QLV's equilibrium when tau2 lies beyond
    the window (0.77 against 0.63: the test does not identify slower relaxation)."""
    import json

    csv, out = tmp_path / "curve.csv", tmp_path / "fit.json"
    C, tau1, tau2 = 0.05, 1.0, 1e5
    assert fp.main(["--qlv", str(C), str(tau1), str(tau2), "--window", "1", "1000",
                    "--source", "synthetic constants (test)", "--write", str(csv),
                    "--out", str(out)]) == 0
    t, G, src = fp.read_curve(str(csv))
    assert src[0] == "synthetic constants (test)" and "C = 0.05" in src[1]
    assert t[0] == pytest.approx(1.0) and t[-1] == pytest.approx(1000.0) and len(t) == 61
    np.testing.assert_allclose(G, fp.qlv_curve(t, C, tau1, tau2), rtol=1e-15)
    res = json.loads(out.read_text())
    assert res["source"] == src
    g, tau = np.array(res["g"]), np.array(res["tau_s"])
    Gfit = res["G0"] * (1.0 - np.sum(g[:, None] * (1.0 - np.exp(-t / tau[:, None])), 0))
    assert np.abs(Gfit - G).max() < 0.01
    dof = len(t) - len(g) - 1
    assert res["rms"] == pytest.approx(np.sqrt(np.sum((Gfit - G) ** 2) / dof), rel=1e-9)
    g_eq = 1.0 / (1.0 + C * np.log(tau2 / tau1))
    assert res["g_inf"] > g_eq + 0.1


def test_qlv_needs_its_source_and_window(tmp_path):
    with pytest.raises(SystemExit):
        fp.main(["--qlv", "0.1", "1", "10", "--window", "1", "100", "--write",
                 str(tmp_path / "c.csv")])
    with pytest.raises(SystemExit):
        fp.main(["--qlv", "0.1", "1", "10", "--window", "100", "1", "--source", "x",
                 "--write", str(tmp_path / "c.csv")])
    with pytest.raises(ValueError, match="give the curve's source"):
        fp.write_curve(str(tmp_path / "c.csv"), [1.0], [1.0], [" "])
