import numpy as np
import pytest

from sim.mesh import channel_mesh
from sim.scenario import UM, Scenario
from sim.taylorhood import TaylorHood


def test_paper_resolution_has_the_papers_dofs(paper_solver):
    space = paper_solver.space
    assert space.cmesh.squares == (90, 66)
    assert 2 * space.N == 48_146
    assert space.P == 6_097
    assert space.dofs == 54_243


@pytest.mark.parametrize("h_um", [20 / 3, 10 / 3, 5 / 3, 7.0])
def test_every_inlet_and_outlet_end_is_a_vertex(h_um):
    channel = Scenario().channel
    cmesh = channel_mesh(channel, h_um * UM)
    for boundary in channel.inlets + channel.outlets:
        for end in boundary.span:
            assert np.min(np.abs(cmesh.y - end)) < 1e-12
    assert np.max(np.diff(cmesh.y)) <= h_um * UM * (1 + 1e-9)
    assert np.max(np.diff(cmesh.x)) <= h_um * UM * (1 + 1e-9)


def _boundary_length(cmesh, name):
    facets = cmesh.boundary(name)
    ends = cmesh.mesh.p[:, cmesh.mesh.facets[:, facets]]
    return np.sum(np.linalg.norm(ends[:, 0] - ends[:, 1], axis=0))


@pytest.mark.parametrize("h_um", [20 / 3, 10 / 3])
def test_named_boundaries_have_the_devices_lengths(h_um):
    channel = Scenario().channel
    cmesh = channel_mesh(channel, h_um * UM)
    for boundary in channel.inlets + channel.outlets:
        assert _boundary_length(cmesh, boundary.name) == pytest.approx(boundary.span[1] - boundary.span[0], rel=1e-12)
    open_length = sum(b.span[1] - b.span[0] for b in channel.inlets + channel.outlets)
    perimeter = 2 * (channel.length + channel.height)
    assert _boundary_length(cmesh, "wall") == pytest.approx(perimeter - open_length, rel=1e-12)
    window = channel.saw_window.span
    assert abs(_boundary_length(cmesh, "saw_window") - (window[1] - window[0])) <= 2 * h_um * UM


def test_finer_mesh_by_one_parameter():
    coarse = TaylorHood(channel_mesh(Scenario().channel, 20 / 3 * UM))
    fine = TaylorHood(channel_mesh(Scenario().channel, 10 / 3 * UM))
    assert coarse.cmesh.squares == (45, 35)          # graded so inlets stay aligned
    assert fine.dofs > 3.5 * coarse.dofs
