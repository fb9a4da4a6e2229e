"""The plant contract (``sim.plants.contract``): its check catches what it should, and every plant passes it."""

import random
import subprocess
import sys

import pytest

from sim.model.scenario import UM, Scenario
from sim.plants import registry as plants
from sim.plants.contract import (
    CellTruth,
    CellView,
    HasDiagnostics,
    HasFields,
    Observation,
    Plant,
    ReportsTruthUpdates,
    StepsUntil,
    Truth,
    check_plant,
)
from sim.plants.registry import CALIBRATION_MODELS, MODELS

ARRIVALS = [(0.0, "RBC"), (30e-6, "melanoma")]


class CountingPlant:
    """A plant whose only cell moves 1 um per control period; ``jitter`` adds a draw from an unseeded source."""

    control_period = 10e-6

    def __init__(self, jitter=False):
        self.jitter = random.Random() if jitter else None

    def reset(self, arrivals):
        self.steps, self.arrivals = 0, list(arrivals)
        return self.observe()

    def step(self, actuation):
        self.steps += 1
        return self.observe()

    def observe(self):
        x = self.steps * 1e-6 + (self.jitter.random() * 1e-9 if self.jitter else 0.0)
        cells = tuple(CellView(key, x, 115e-6, 1e-11, 0.0) for key in range(len(self.arrivals)))
        return Observation(self.steps * self.control_period, cells)

    def truth(self):
        cells = tuple(CellTruth(key, name, 0.0, "in_channel", float("nan"), float("nan"), self.steps * 1e-6,
                                115e-6, 1.0) for key, (_, name) in enumerate(self.arrivals))
        return Truth(self.steps * self.control_period, cells, 0)

    @property
    def done(self):
        return False


def test_a_deterministic_plant_passes_and_is_a_plant():
    assert isinstance(CountingPlant(), Plant)
    assert check_plant(CountingPlant, ARRIVALS, steps=5) == []


def test_check_plant_flags_two_fresh_plants_that_differ():
    problems = check_plant(lambda: CountingPlant(jitter=True), ARRIVALS, steps=5)
    assert problems == ["not deterministic: two fresh plants with the same arrivals and drive gave different results"]


def test_check_plant_refuses_one_instance_handed_out_twice():
    plant = CountingPlant()
    assert check_plant(lambda: plant, ARRIVALS, steps=5) == [
        "make_plant returned the same plant twice: pass a factory of fresh plants"]


def test_check_plant_flags_a_plant_that_loses_a_cell():
    class Leaky(CountingPlant):
        def truth(self):
            full = super().truth()
            return Truth(full.time, full.cells[1:], full.waiting)
    problems = check_plant(Leaky, ARRIVALS, steps=5)
    assert len(problems) == 1 and problems[0].startswith("cells not conserved")


PLANT_CLASSES = {"feib": ("sim.plants.feib", "FeibPlant"), "streamline": ("sim.plants.streamline", "StreamlinePlant"),
                 "rom": ("sim.plants.rom", "RomPlant"), "oneway": ("sim.plants.oneway", "OneWayPlant"),
                 "auto": ("sim.plants.auto", "AutoPlant")}


@pytest.mark.parametrize("model", MODELS)
def test_reset_takes_the_arrivals_and_no_seed(model):
    """Plants are deterministic (the run's seed draws arrivals and detector noise outside them): ``reset``
    has no seed to ignore, in the contract and in every registry entry."""
    import importlib
    import inspect
    module, name = PLANT_CLASSES[model]
    plant_class = getattr(importlib.import_module(module), name)
    assert list(inspect.signature(plant_class.reset).parameters) == ["self", "arrivals"]
    assert list(inspect.signature(Plant.reset).parameters) == ["self", "arrivals"]


def test_the_contract_and_the_controller_load_no_numerics_library_and_no_other_part_of_sim():
    code = ("import sim.plants.contract, controller.detector, controller.sorter, controller.events, sys; "
            "print('skfem' in sys.modules, 'numba' in sys.modules, "
            "sorted(m for m in sys.modules if m == 'sim' or m.startswith('sim.')))")
    output = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert output.strip().split(maxsplit=2) == ["False", "False", "['sim', 'sim.plants', 'sim.plants.contract']"]


def test_the_controller_sighting_is_the_contract_cell_view():
    from controller.events import Sighting
    assert Sighting is CellView


@pytest.fixture(scope="module")
def coarse():
    """The paper's device on a 5 um mesh with dt = 10 us, its fluid solver and its gridded steady flows."""
    from sim.method.fluid import NavierStokes
    from sim.plants.rom import RomFlows
    scenario = Scenario().with_numerics(mesh_h=5 * UM, dt=10e-6)
    fluid = NavierStokes(scenario)
    return scenario, fluid, RomFlows.of(scenario, spacing=2 * UM, fluid=fluid)


def _registry_options(model, coarse):
    """Constructor options that keep each registry entry cheap on the coarse device (shared flows)."""
    scenario, fluid, flows = coarse
    if model == "streamline":
        from sim.method.fluid import NavierStokes
        return {"fluid": NavierStokes(scenario.with_numerics(convection="stokes"))}
    if model in ("rom", "oneway"):
        return {"flows": flows}
    if model == "auto":
        return {"grid_spacing": 2 * UM}
    return {}


STEPS = {"feib": 6, "auto": 30, "oneway": 15, "rom": 25, "streamline": 20}


@pytest.mark.parametrize("model", MODELS)
def test_every_registry_entry_conforms_on_fresh_instances(model, coarse):
    scenario = coarse[0]
    options = _registry_options(model, coarse)
    problems = check_plant(lambda: plants.build(model, scenario, **options), ARRIVALS, steps=STEPS[model])
    assert problems == []


def test_the_registry_lists_every_model_the_tests_build():
    assert set(STEPS) == set(MODELS) == set(PLANT_CLASSES) and set(CALIBRATION_MODELS) == set(MODELS) - {"streamline"}


def test_the_command_line_offers_the_registry():
    from vcyto.cli import build_parser
    parser = build_parser()
    subcommands = next(a for a in parser._actions if a.choices and "stream" in a.choices).choices
    stream_model = next(a for a in subcommands["stream"]._actions if a.dest == "model")
    calibrate_model = next(a for a in subcommands["calibrate"]._actions if a.dest == "model")
    assert tuple(stream_model.choices) == MODELS and tuple(calibrate_model.choices) == CALIBRATION_MODELS


def test_rom_and_feib_name_their_capabilities(coarse):
    scenario, _, flows = coarse
    rom = plants.build("rom", scenario, flows=flows)
    assert isinstance(rom, Plant) and isinstance(rom, StepsUntil) and isinstance(rom, ReportsTruthUpdates)
    assert not isinstance(rom, HasFields)
    feib = plants.build("feib", scenario)
    assert isinstance(feib, HasFields) and isinstance(feib, HasDiagnostics) and not isinstance(feib, StepsUntil)
