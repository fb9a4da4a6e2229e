import pytest

from sim.fluid import NavierStokes
from sim.scenario import UM, Scenario


@pytest.fixture(scope="session")
def paper_scenario():
    return Scenario()


@pytest.fixture(scope="session")
def paper_solver(paper_scenario):
    """The paper's device at the paper's resolution (54,243 DOFs), built once per test session."""
    return NavierStokes(paper_scenario)


@pytest.fixture(scope="session")
def coarse_scenario():
    return Scenario().with_numerics(mesh_h=5 * UM)


@pytest.fixture(scope="session")
def rom_plant(paper_scenario, paper_solver):
    """The rom plant of the paper's device (its flows from the session's paper solver)."""
    from sim.rom import RomFlows, RomPlant
    return RomPlant(paper_scenario, flows=RomFlows.of(paper_scenario, fluid=paper_solver))
