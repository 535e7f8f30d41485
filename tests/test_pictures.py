"""Pictures (eyefem.io.pictures) and run progress (eyefem.io.progress) on tiny inputs.

A spherical shell of 6 x 3^2 x 1 hexahedra (no node layer on the plane y = 0) stands in for the eye: the plot functions
write PNGs, draw the buckle and the sutures they are given, colour up to the true
maximum (an extend arrow only where vmax clips it) and carry the titles passed.
"""

import logging

import numpy as np
import pytest

from eyefem.fem.generators import spherical_shell
from eyefem.io.pictures import (
    Zoom,
    boundary_quads,
    plane_basis,
    plot_outside,
    plot_section,
    section_polygons,
    section_segments,
)
from eyefem.io.progress import Heartbeat, Progress

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def shell():
    """(mesh, deformed positions (n, 3), element values (e,), buckle surface, sutures)."""
    mesh = spherical_shell(10.0, 1.0, 3, 1)
    x = mesh.nodes * 1.02
    values = np.linspace(0.0, 7.5, mesh.n_elem)  # true maximum 7.5
    u = np.linspace(0, 2 * np.pi, 33)
    a = np.array([-2.0, 2.0])
    U, A = np.meshgrid(u, a, indexing="ij")  # a band around z at z = A, radius 11.2
    pts = np.stack([11.2 * np.cos(U), 11.2 * np.sin(U), A], -1).reshape(-1, 3)
    idx = np.arange(len(pts)).reshape(len(u), 2)
    tris = np.concatenate([np.stack([idx[:-1, 0], idx[1:, 0], idx[1:, 1]], 1),
                           np.stack([idx[:-1, 0], idx[1:, 1], idx[:-1, 1]], 1)])
    sut_pts = np.array([[11.0, 0.0, -4.0], [11.3, 0.0, -2.0], [0.0, 11.0, 4.0],
                        [0.0, 11.3, 2.0]])
    sutures = (sut_pts, np.array([[0, 1], [2, 3]]), np.array([0.4, 0.3]))
    return mesh, x, values, (pts, tris), sutures


def test_section_segments_of_a_square_are_its_cut():
    """A unit square in the plane z = 0 spanning x in [-1, 1] cut by the plane x = 0:
    one segment from y = 0 to y = 1 (either split triangle may hold it)."""
    pts = np.array([[-1.0, 0, 0], [1.0, 0, 0], [1.0, 1.0, 0], [-1.0, 1.0, 0]])
    seg = section_segments(pts, np.array([[0, 1, 2, 3]]), (1.0, 0, 0))
    ys = np.sort(np.unique(np.round(seg[:, :, 1], 12)))
    assert np.allclose(seg[:, :, 0], 0.0)
    assert ys[0] == 0.0 and ys[-1] == 1.0
    assert np.allclose(plane_basis((0.0, 1.0, 0.0)), [[1, 0, 0], [0, 0, 1]])


def test_section_draws_buckle_sutures_and_true_maximum(shell, tmp_path):
    mesh, x, values, buckle, sutures = shell
    title = "Case T: a test band\nstage 'suture': IOP 15.0 mmHg"
    drawn = plot_section(tmp_path / "s.png", x, mesh.hexes, values, reference=mesh.nodes,
                         buckle=buckle, sutures=sutures, title=title,
                         zoom=Zoom((10.2, 0.0, 0.0), 5.0, 10.2, 10.7, "indentation\n0.50 mm"))
    assert (tmp_path / "s.png").read_bytes()[:8] == PNG
    assert drawn.title == title
    assert drawn.n_buckle > 0  # the band's cut: a segment at x = +-11.2 on each side
    assert drawn.n_sutures == 1  # only the suture in the plane y = 0
    cut = section_polygons(x, mesh.hexes, (0.0, 1.0, 0.0))[1]
    assert len(cut) >= 12  # the section: a ring of elements
    assert drawn.data_max == values[cut].max()  # the true maximum of the cut elements
    assert drawn.vmin == 0.0 and drawn.vmax == drawn.data_max and drawn.extend == "neither"


def test_clipped_scale_has_an_extend_arrow(shell, tmp_path):
    mesh, x, values, *_ = shell
    drawn = plot_outside(tmp_path / "o.png", x, mesh.hexes, values, vmax=3.0, title="clipped")
    assert (tmp_path / "o.png").read_bytes()[:8] == PNG
    assert drawn.vmax == 3.0 and drawn.extend == "max"
    owner = boundary_quads(mesh.hexes)[1]
    assert drawn.data_max == pytest.approx(values[owner].max())


def test_outside_draws_buckle_sutures_and_excludes(shell, tmp_path):
    mesh, x, values, buckle, sutures = shell
    hot = np.argsort(values)[-3:]  # the hottest elements, excluded from the scale
    drawn = plot_outside(tmp_path / "o.png", x, mesh.hexes, values, buckle=buckle,
                         sutures=sutures, exclude=hot, title="outside",
                         directions={"nasal +x": (1, 0, 0), "anterior +z": (0, 0, 1)})
    assert drawn.n_buckle == len(buckle[1])
    assert 1 <= drawn.n_sutures <= 2  # those on the side facing the viewer
    keep = np.setdiff1d(boundary_quads(mesh.hexes)[1], hot)
    assert drawn.vmax == pytest.approx(values[keep].max()) and drawn.extend == "neither"
    assert drawn.title == "outside"


def test_outside_with_every_suture_hidden_draws_without_warnings(shell, tmp_path):
    """No suture on the visible side: nothing is added for them (an empty collection
    made matplotlib autoscale from infinite limits and warn of an overflow)."""
    import warnings

    mesh, x, values, buckle, _ = shell
    view = np.array([np.cos(np.radians(10.0)) * np.cos(np.radians(-60.0)),
                     np.cos(np.radians(10.0)) * np.sin(np.radians(-60.0)),
                     np.sin(np.radians(10.0))])
    far = -11.0 * view  # the default view's far side
    sutures = (np.array([far, far * 1.03]), np.array([[0, 1]]), np.array([0.2]))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        drawn = plot_outside(tmp_path / "h.png", x, mesh.hexes, values, buckle=buckle,
                             sutures=sutures)
    assert drawn.n_sutures == 0 and (tmp_path / "h.png").read_bytes().startswith(PNG)


class _Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


class _Stage:
    def __init__(self, name, n_steps):
        self.name, self.n_steps = name, n_steps


def test_progress_lines_throttled_with_time_left(caplog):
    clock = _Clock()
    progress = Progress([_Stage("pressurise", 1), _Stage("tighten", 4)], interval=5.0,
                        clock=clock)
    with caplog.at_level(logging.INFO, logger="eyefem.io.progress"):
        clock.now = 10.0
        progress.step("pressurise", 1, 1.0)  # a stage's end is always logged
        clock.now = 11.0
        progress.step("tighten", 1, 0.25)  # 1 s after the last line: quiet
        clock.now = 20.0
        progress.beat()  # a step under way for 9 s: a heartbeat
        clock.now = 21.0
        progress.step("tighten", 2, 0.5)  # 1 s after the heartbeat: quiet
        clock.now = 25.5
        progress.beat()  # the step converged 4.5 s ago: quiet
        clock.now = 32.0
        progress.step("tighten", 3, 0.75)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 3, lines
    assert lines[0].startswith("progress: stage 1/2 pressurise, step 1/1, t = 1.000, 20% done")
    assert "about 40 s left" in lines[0]  # 10 s for 1 of 5 steps
    assert "stage 2/2 tighten, step 1/4" in lines[1] and "step 2 under way for 9 s" in lines[1]
    assert "step 3/4, t = 0.750, 80% done, 32 s elapsed, about 8 s left" in lines[2]
    assert "[" not in "".join(lines)  # numbers, not arrays


def test_heartbeat_says_what_is_under_way_until_there_is_news(caplog):
    """A planner's simulation reports only when it ends; the heartbeat fills the silence
    (one line per interval without news) and stays quiet after news."""
    clock, n = _Clock(), [0]
    beat = Heartbeat(lambda: f"simulation {n[0]}", interval=60.0, clock=clock)
    with caplog.at_level(logging.INFO, logger="eyefem.io.progress"):
        clock.now = 30.0
        beat.beat()  # 30 s of silence: quiet
        clock.now = 61.0
        beat.beat()
        clock.now = 100.0
        beat.beat()  # 39 s after the last line: quiet
        clock.now = 130.0
        n[0] = 1
        beat.news()
        clock.now = 185.0
        beat.beat()  # 55 s after the news: quiet
        clock.now = 190.0
        beat.beat()
    lines = [r.getMessage() for r in caplog.records]
    assert lines == ["simulation 0 under way for 1 min 01 s", "simulation 1 under way for 1 min 00 s"]
    with Heartbeat(lambda: "x", interval=0.01) as running:
        assert running._thread.is_alive()
    assert running._thread is None


def test_progress_heartbeat_thread_stops():
    progress = Progress([_Stage("a", 1)], interval=0.01)
    with progress:
        assert progress._thread is not None and progress._thread.is_alive()
    assert progress._thread is None


@pytest.mark.slow
def test_surgery_cases_write_their_pictures(coarse_comparison):
    """Every coarse case 1-6 of the session's comparison (about 10 minutes, shared) wrote
    the meridional section and the outside view (eyefem.eye.surgery.pictures)."""
    for name in ("section_von_mises.png", "outside_von_mises.png"):
        found = sorted(coarse_comparison.rglob(name))
        assert len(found) == 6, found
        assert all(p.read_bytes()[:8] == PNG for p in found)
