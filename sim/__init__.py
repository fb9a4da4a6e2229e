"""The plant: the SAW cell sorter's channel flow, cells and reduced models (no I/O, no printing).

The plant contract (every plant: ``FeibPlant``, ``StreamlinePlant`` and the ``rom``, ``oneway`` and ``auto``
plants of ``vcyto.make_plant``): ``reset(arrivals) -> Observation`` with ``arrivals`` a list of
(time in s, cell type name); ``step(actuation) -> Observation`` advances one control period with the IDT
drive ``actuation`` (0 or 1); ``observe() -> Observation`` (what the optics see: ``CellView``s);
``truth() -> Truth`` (``CellTruth``s: fates, membranes; never shown to the controller); ``done``;
``control_period`` (s); ``sim.plants.contract`` states it (``Plant`` and its optional capabilities).
``check_plant(make_plant, arrivals)`` checks a factory of fresh plants against the contract.
Exports are imported on first use.
"""

import importlib as _importlib

_EXPORTS = {
    "Scenario": "sim.model.scenario", "ScenarioError": "sim.model.scenario", "Arrivals": "sim.model.arrivals",
    "schedule": "sim.model.arrivals", "Observation": "sim.plants.contract", "CellView": "sim.plants.contract",
    "Truth": "sim.plants.contract", "CellTruth": "sim.plants.contract", "Plant": "sim.plants.contract",
    "Schedule": "sim.plants.contract", "check_plant": "sim.plants.contract",
    "FeibPlant": "sim.plants.feib", "StreamlinePlant": "sim.plants.streamline",
}
__all__ = list(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        value = getattr(_importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'sim' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
