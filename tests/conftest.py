import atexit
import os
import shutil
import tempfile

import pytest

from sim.method.fluid import NavierStokes
from sim.model.scenario import UM, Scenario
from vcyto import speedsettings

# the command-line tests' set-up cache goes to a directory of this session, never the user's (vcyto/cache.py)
os.environ["VCYTO_CACHE_DIR"] = tempfile.mkdtemp(prefix="vcyto-test-cache-")
atexit.register(shutil.rmtree, os.environ["VCYTO_CACHE_DIR"], True)
# the simulator's speed settings as the vcyto command reads them (KMP_BLOCKTIME=0 before MKL loads included)
speedsettings.install()


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
    from sim.plants.rom import RomFlows, RomPlant
    return RomPlant(paper_scenario, flows=RomFlows.of(paper_scenario, fluid=paper_solver))


@pytest.fixture
def cache(tmp_path):
    """A set-up cache of its own (``vcyto.cache.DiskCache`` in ``tmp_path``) installed for ``sim`` during the test."""
    from sim.fast import store
    from vcyto.cache import DiskCache
    disk = DiskCache(tmp_path / "cache")
    previous = store.install(disk)
    yield disk
    store.install(previous)
