"""The whole model exported to FEBio 4 (eyefem.io.febio.write_feb): every stage a <step>,
bars and node springs as FEBio's linear springs, a closed cavity as FEBio's volume
constraint, the encircling buckle as rigid segments in sliding contact; what FEBio cannot
be given is listed in the deck's header. The tests need no FEBio binary (FEBio's runs of
the deck are recorded: benchmarks/febio_surgery.json); the decks are read back with
eyefem's own reader."""

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from eyefem.fem import generators
from eyefem.fem.bars import Bars
from eyefem.fem.materials import mooney_rivlin
from eyefem.fem.terms import NodeSprings
from eyefem.io.febio import write_feb
from eyefem.io.febio_read import FebError, build_stages, deck_pieces, read_feb
from eyefem.solve.problem import Setup
from eyefem.solve.model import node_dofs, solid_model
from eyefem.solve.solver import Stage, solve

ROOT = Path(__file__).resolve().parents[1]


def _linked_block():
    """A 2 x 1 x 1 mm block (3 x 2 x 2 hexahedra) clamped at x0, two bars (EA 0.3 N)
    between nodes of its x1 face, whose nodes node springs (0.02 N/mm) hold; stage 1 pulls
    z1 up 0.05 mm, stage 2 to 0.1 mm."""
    mat = mooney_rivlin("rubber", 0.25, 0.05)
    mesh = generators.box(2.0, 1.0, 1.0, 3, 2, 2, material=mat.name)
    x1 = mesh.node_set("x1")
    a, b = x1[:2], x1[-2:]
    bars = Bars("ties", np.repeat(a[:, None], 4, 1), np.repeat(b[:, None], 4, 1),
                np.zeros((2, 2)), np.zeros((2, 2)), mesh.nodes, EA=0.3)
    springs = NodeSprings("hold", x1, k=0.02)
    model = solid_model(mesh, {mat.name: mat}, (bars, springs))
    clamp = node_dofs(mesh.node_set("x0"), "xyz")
    lift = node_dofs(np.setdiff1d(mesh.node_set("z1"), mesh.node_set("x0")), "z")
    dofs = np.r_[clamp, lift]

    def stage(name, h):
        return Stage(name, 2, (dofs, np.r_[np.zeros(len(clamp)), np.full(len(lift), h)]))
    return Setup("linked", model, [stage("up", 0.05), stage("more", 0.1)],
                 lambda *a: {}, lambda *a: {})


def test_steps_bars_and_springs_round_trip_to_the_same_solution(tmp_path):
    """Two stages become two <step>s; the bars become linear springs with E = EA / L0 and
    each node spring three springs to fixed ground nodes GROUND_ARM away along x, y, z
    (FEBio's E (l - L0): the same energies, the node springs' to O(|u| / GROUND_ARM)).
    Read back and solved by eyefem, the deck gives the native solution."""
    setup = _linked_block()
    deck = tmp_path / "linked.feb"
    assert write_feb(setup, deck) == []
    pieces = deck_pieces(deck)
    n = setup.model.mesh.n_nodes
    assert pieces["steps"] == ["up", "more"]
    n_held = len(setup.model.mesh.node_set("x1"))
    assert pieces["nodes"] == n + 3 * n_held  # + three ground nodes per held node
    assert pieces["springs"] == {"linear spring": 2 + 3 * n_held}
    mesh, mats, loads = read_feb(deck)
    model, stages = build_stages(mesh, mats, loads)
    assert [s.n_steps for s in stages] == [2, 2]
    native = np.asarray(solve(setup.model, setup.stages).q)[: 3 * n]
    back = np.asarray(solve(model, stages).q)[: 3 * n]
    assert np.max(np.abs(native)) > 0.05
    # mm: the deck's k = 1000 (c10 + c01) with laugon = 1 is read back as exactly
    # incompressible, so the two solutions are the same model
    assert np.max(np.abs(back - native)) <= 1e-8


@pytest.fixture(scope="module")
def surgery_deck(tmp_path_factory):
    from eyefem.catalog import problems, schemas
    from eyefem.io.casefile import load_case, with_parameters

    case = load_case(ROOT / "cases/surgery/case1.toml", schemas())
    # the pieces are compared with the whole model's
    case = with_parameters(case, mesh="coarse", symmetry="none")
    setup = problems()[case.problem][1](case.parameters, case.materials)
    deck = tmp_path_factory.mktemp("feb") / "case1.feb"
    warnings = write_feb(setup, deck)
    return setup, deck, warnings


def test_a_mirror_half_exports_the_whole_eye(surgery_deck, tmp_path, capsys):
    """A case solved as the mirror half (case1.toml: symmetry = 'mirror') gives FEBio the
    whole eye through `eyefem export-feb`: the same deck as the case solved whole, and the
    command names the whole mesh's size."""
    from eyefem.cli.main import main

    _, whole_deck, whole_warnings = surgery_deck
    deck = tmp_path / "case1.feb"  # the name the whole deck has (its log file is named after it)
    assert main(["export-feb", str(ROOT / "cases/surgery/case1.toml"), "--mesh", "coarse",
                 "-o", str(deck)]) == 0
    out = capsys.readouterr().out
    assert "3 stage(s) as steps (3153 mesh nodes, 2470 elements)" in out  # not the half's
    assert out.count("not exported or approximated") == len(whole_warnings)
    assert deck.read_text() == whole_deck.read_text()


def test_surgery_exports_every_stage_and_its_pieces(surgery_deck):
    """Case 1 on the coarse mesh: three steps, the zonule's 16 bars and the lens's
    springs as linear springs (three per lens node), the buckle as 24 rigid segments each
    in sliding-elastic contact with the sclera in the two steps where the buckle acts (a
    step's contact: FEBio deactivates it at the step's end), the cavity as one volume
    constraint."""
    setup, deck, _ = surgery_deck
    model = setup.model
    pieces = deck_pieces(deck)
    assert pieces["steps"] == [s.name for s in setup.stages]
    lens = len(model.term("lens_springs").nodes)
    zonule = len(model.term("zonule").params["EA"])
    assert pieces["springs"] == {"linear spring": zonule + 3 * lens}
    assert pieces["elements"]["hex8"] == model.mesh.n_elem
    assert pieces["rigid_bodies"] == 24 and pieces["contacts"] == {"sliding-elastic": 48}
    root = ET.parse(deck).getroot()
    assert root.find("Contact") is None
    assert [len(st.findall("Contact/contact")) for st in root.iter("step")] == [0, 24, 24]
    assert pieces["constraints"] == {"volume": 1} and pieces["surface_loads"] == 1
    # nodes: the mesh's, three ground nodes per lens spring, the segments' facets (5 x 7)
    assert pieces["nodes"] == model.mesh.n_nodes + 3 * lens + 24 * 5 * 7


def test_surgery_deck_lists_what_febio_is_not_given(surgery_deck):
    """The sutures (tied in a later stage and tightened) and the orbit's springs cannot be
    written; the buckle's segments, the zonule's moved ends and the cavity's penalty are
    approximations: all are in the header and returned (the command prints them)."""
    _, deck, warnings = surgery_deck
    listed = deck_pieces(deck)["omissions"]
    assert listed == warnings
    text = " ".join(listed)
    for name in ("'sutures'", "'orbit'", "'zonule'", "buckle 'buckle'", "cavity 'cavity'"):
        assert name in text
    assert "FEBio 4.11 gives for eyefem's exported decks: docs/febio.md" in deck.read_text()[:400]


def test_surgery_deck_reads_back_into_the_same_pieces(surgery_deck):
    """eyefem's own reader takes the exported deck back: the mesh's nodes and hexahedra
    (plus the ground and segment nodes), the zonule's and the lens's springs, one
    RigidContact per rigid segment acting in the tighten and suture stages (written in
    both steps), the cavity as a FluidCavity acting in the tighten stage only (FEBio's
    step-level constraint), the IOP load and the three stages."""
    setup, deck, _ = surgery_deck
    model0 = setup.model
    mesh, mats, loads = read_feb(deck)
    model, stages = build_stages(mesh, mats, loads)
    lens = len(model0.term("lens_springs").nodes)
    assert mesh.n_elem == model0.mesh.n_elem
    assert mesh.n_nodes == model0.mesh.n_nodes + 3 * lens + 24 * 5 * 7
    kinds = [type(t).__name__ for t in model.terms]
    assert kinds.count("RigidContact") == 24 and kinds.count("FluidCavity") == 1
    springs = [t for t in model.terms if type(t).__name__ == "LinearSpring"]
    assert sum(len(t.dofs) for t in springs) == 3 * lens + len(
        model0.term("zonule").params["EA"])
    assert [s.name for s in stages] == [s.name for s in setup.stages]
    assert [s.n_steps for s in stages] == [s.n_steps for s in setup.stages]
    cavity = next(t.name for t in model.terms if type(t).__name__ == "FluidCavity")
    assert [s.active is None or cavity in s.active for s in stages] == [False, True, False]
    contact = next(t.name for t in model.terms if type(t).__name__ == "RigidContact")
    assert [s.active is None or contact in s.active for s in stages] == [False, True, True]
    assert all(c.steps == (1, 2) for c in loads.contacts)
    assert loads.contacts[0].d == pytest.approx((0.0, 0.795775674, 0.795775674), rel=1e-8)


def test_surgery_ring_is_fitted_snug_on_the_decks_own_pressurised_eye(surgery_deck):
    """The segments are placed where eyefem's tighten stage fits its ring snug, on the eye
    the deck itself pressurises (read back and solved: FEBio's step 1 to 1.6e-6 mm): at
    the pressurise step's end no scleral node is pressed into them by more than the
    facets' departure from the analytic ring (the fit on eyefem's own eye, with the
    orbit's springs, left 0.069 mm); the steps with contact use FEBio's full Newton."""
    _, deck, warnings = surgery_deck
    assert any("on the deck's own pressurised eye" in w for w in warnings)
    model, stages = build_stages(*read_feb(deck))
    sol = solve(model, stages[:1])
    pen = [t.update(sol.q, sol.theta[t.name]).report(sol.q, sol.theta[t.name])[
        "max_penetration_mm"] for t in model.terms if type(t).__name__ == "RigidContact"]
    assert len(pen) == 24 and max(pen) < 0.025
    root = ET.parse(deck).getroot()
    assert [st.findtext("Control/solver/qn_method/max_ups") for st in root.iter("step")] == [
        None, "0", "0"]


def test_stage_count_out_of_range_is_refused(tmp_path):
    setup = _linked_block()
    with pytest.raises(ValueError, match="stages = 3; 'linked' has 2 stage"):
        write_feb(setup, tmp_path / "x.feb", stages=3)
    write_feb(setup, tmp_path / "one.feb", stages=1)
    assert deck_pieces(tmp_path / "one.feb")["steps"] == []
