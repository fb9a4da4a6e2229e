"""The plant models, listed once: the closed loop, the sweep, the trade-off and the command line read this list.

Each entry names a model, says in one line what it is, whether it can carry calibration cells (``vcyto
calibrate``), and builds a fresh plant for a scenario. A model's module is imported only when a plant of it
is built, so listing the models loads no numerics library.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ..model.scenario import Scenario
from .contract import Plant

STREAMLINE_CONTROL_PERIOD = 10e-6    # s; the streamline stand-in's period when none is given


@dataclass(frozen=True)
class PlantModel:
    """One plant model: its name, a one-line description, and whether ``vcyto calibrate`` offers it."""

    name: str
    summary: str
    calibrates: bool
    builder: Callable[..., Plant]

    def build(self, scenario: Scenario, control_period: float | None = None, flows=None, **options) -> Plant:
        """A fresh plant of this model; ``flows`` (``sim.plants.rom.RomFlows``) are reused by the models that blend
        steady flows, ``options`` go to the plant's constructor (e.g. ``window_mesh_h`` of ``auto``)."""
        return self.builder(scenario, control_period, flows, **options)


def _feib(scenario, control_period, flows, **options):
    from .feib import AdaptiveFeibPlant, FeibPlant
    kind = AdaptiveFeibPlant if scenario.numerics.tolerance > 0 else FeibPlant    # with a tolerance: event-driven
    return kind(scenario, control_period=control_period, **options)


def _auto(scenario, control_period, flows, **options):
    from .auto import AutoPlant
    return AutoPlant(scenario, control_period=control_period, **options)


def _oneway(scenario, control_period, flows, **options):
    from .oneway import OneWayPlant
    return OneWayPlant(scenario, control_period=control_period, flows=flows, **options)


def _rom(scenario, control_period, flows, **options):
    from .rom import RomPlant
    return RomPlant(scenario, control_period=control_period, flows=flows, **options)


def _streamline(scenario, control_period, flows, **options):
    from .streamline import StreamlinePlant
    return StreamlinePlant(scenario, control_period=control_period or STREAMLINE_CONTROL_PERIOD, **options)


REGISTRY: dict[str, PlantModel] = {model.name: model for model in (
    PlantModel("feib", "the full two-way coupled FE-IB model", True, _feib),
    PlantModel("auto", "rom, switching to feib windows while cells interact", True, _auto),
    PlantModel("oneway", "membranes deforming in the blended steady flows, no feedback on the fluid", True, _oneway),
    PlantModel("rom", "cells as finite-size bodies in the blended steady flows", True, _rom),
    PlantModel("streamline", "centroids carried by the blended steady flows (a stand-in)", False, _streamline),
)}
MODELS: tuple[str, ...] = tuple(REGISTRY)
CALIBRATION_MODELS: tuple[str, ...] = tuple(name for name, model in REGISTRY.items() if model.calibrates)


def build(model: str, scenario: Scenario, control_period: float | None = None, flows=None, **options) -> Plant:
    """A fresh plant of the model named ``model`` (one of ``MODELS``)."""
    if model not in REGISTRY:
        raise ValueError(f"model must be one of {', '.join(MODELS)} (got {model!r})")
    return REGISTRY[model].build(scenario, control_period, flows, **options)
