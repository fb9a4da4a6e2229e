import json

import numpy as np
import pytest
from guard import vcyto_inline

from sim.method.taylorhood import TaylorHood
from sim.model.mesh import MESH_H_SLACK, MeshSize, channel_mesh
from sim.model.scenario import UM, Scenario


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
    assert np.max(np.diff(cmesh.y)) <= h_um * UM * (1 + MESH_H_SLACK)
    assert np.max(np.diff(cmesh.x)) <= h_um * UM * (1 + MESH_H_SLACK)


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


@pytest.mark.parametrize("h_um", [3.33, 3.333, 3.3333, 10 / 3])
def test_a_size_written_to_a_few_digits_names_the_papers_mesh(h_um):
    """3.33 um lies 0.1 % below 10/3 um: it builds the paper's 90 x 66 squares, not one with an extra column."""
    size = MeshSize.of(Scenario().channel, h_um * UM)
    assert size.squares == (90, 66) and size.dofs == 54_243 and size.uniform
    assert size.largest == pytest.approx(10 / 3 * UM, rel=1e-12)


def test_sizes_that_name_the_same_spacing_build_the_same_mesh():
    channel = Scenario().channel
    assert MeshSize.of(channel, 2.2222 * UM).squares == MeshSize.of(channel, 2.2222222223 * UM).squares
    assert MeshSize.of(channel, 1.67 * UM).squares == MeshSize.of(channel, 5 / 3 * UM).squares == (180, 132)
    # 0.2 % slack only: a size 1 % below a uniform one is not rounded up to it
    assert MeshSize.of(channel, 3.3 * UM).squares != (90, 66)


@pytest.mark.parametrize("h_um", [20 / 3, 3.33, 7.0, 2.2222])
def test_the_mesh_a_size_states_is_the_mesh_it_builds(h_um):
    channel = Scenario().channel
    size = MeshSize.of(channel, h_um * UM)
    space = TaylorHood(channel_mesh(channel, h_um * UM))
    assert space.cmesh.squares == size.squares and space.dofs == size.dofs
    spacings = np.concatenate([np.diff(space.cmesh.x), np.diff(space.cmesh.y)])
    assert spacings.max() == pytest.approx(size.largest, rel=1e-12)
    assert size.uniform == bool(np.ptp(spacings) < 1e-9 * spacings.max())


def test_the_note_says_which_mesh_was_built():
    channel = Scenario().channel
    assert MeshSize.of(channel, 2.5 * UM).note() is None                     # uniform, exactly as asked
    snapped = MeshSize.of(channel, 3.33 * UM).note()
    assert "90 x 66 squares" in snapped and "54,243 DOFs" in snapped and "3.33333 um" in snapped
    graded = MeshSize.of(channel, 2.2222 * UM).note()
    assert "graded" in graded and "2.5 um or 2 um" in graded


@pytest.mark.parametrize("asked, dofs, squares", [("3.33um", 54_243, "90 x 66"), ("1.67um", 215_403, "180 x 132")])
def test_mesh_h_on_the_command_line_runs_the_mesh_it_states(asked, dofs, squares):
    status, out, err = vcyto_inline(["scenario", "--mesh-h", asked, "--json"])
    assert status == 0
    mesh_h = json.loads(out)["numerics"]["mesh_h"]
    size = MeshSize.of(Scenario().channel, mesh_h)
    assert size.dofs == dofs and not size.snapped              # the run's h is the built mesh's spacing
    assert f"{dofs:,} DOFs" in err and squares in err           # and the note says so
