"""Closed-loop sorting tests a user writes: a pytest plugin (entry point ``pytest11``: ``vcyto``).

Installed with vcyto, it gives every test in the environment these fixtures:

- ``vcyto_scenario``: the paper's device (``sim.model.scenario.Scenario()``); override the fixture for another;
- ``vcyto_plant``: ``vcyto_plant(model)`` builds a plant of a registered model once per test session and hands
  out fresh ones (``reset`` makes them so);
- ``sort_run``: ``sort_run(controller, cells=... | count=..., mix=..., rate=..., model="rom", ...)`` runs the closed
  loop (``vcyto.run_stream``) with your controller and returns a ``SortRun``.

and these assertions (plain functions: ``from vcyto.testing import assert_outlets``):

- ``assert_outlets(run, melanoma="upper", RBC="lower")``: every cell of each named type left by that outlet;
- ``assert_targets_sorted(run)``: every target left by the upper outlet, every non-target by the lower one;
- ``assert_purity(run, at_least=0.95)``, ``assert_yield(run, at_least=0.8)``;
- ``assert_no_missed_deadlines(run)``: no answer came after its deadline (``--realtime`` runs).

Each failure message names the cells and what became of them. Importing this module loads only pytest; vcyto
and the plant load when a fixture is used.
"""

from __future__ import annotations

from dataclasses import dataclass

import pytest


@dataclass(frozen=True)
class SortRun:
    """The summary of one closed-loop run (``run_stream``'s dict), with what a test asks of it."""

    summary: dict

    @property
    def cells(self) -> list[dict]:
        return self.summary["cells"]

    @property
    def statistics(self) -> dict:
        return self.summary["statistics"]

    @property
    def purity(self) -> float | None:
        return self.statistics["purity"]

    @property
    def sort_yield(self) -> float | None:
        return self.statistics["yield"]

    def outlets(self, cell_type: str) -> list[str]:
        """The outlet of each cell of ``cell_type``, in arrival order."""
        return [cell["outlet"] for cell in self.cells if cell["type"] == cell_type]


def _describe(cells) -> str:
    shown = ", ".join(f"cell {c['key']} ({c['type']}, detected {c['detected_class']}, decision {c['decision']}): "
                      f"{c['outlet']}" for c in cells[:10])
    return shown + (f" and {len(cells) - 10} more" if len(cells) > 10 else "")


def _complete(run: SortRun) -> None:
    status = run.summary.get("status", "complete")
    assert status == "complete", f"the run is {status}: {run.summary.get('reason')}"


def assert_outlets(run: SortRun, **outlets: str) -> None:
    """Every cell of each named type left by the named outlet (``melanoma="upper"``)."""
    _complete(run)
    for cell_type, outlet in outlets.items():
        cells = [c for c in run.cells if c["type"] == cell_type]
        assert cells, f"the run had no {cell_type} cell"
        wrong = [c for c in cells if c["outlet"] != outlet]
        assert not wrong, f"{len(wrong)} of {len(cells)} {cell_type} cells did not leave by the {outlet} outlet: " \
                          f"{_describe(wrong)}"


def assert_targets_sorted(run: SortRun) -> None:
    """Every target (true class II) left by the upper outlet and every non-target by the lower one."""
    _complete(run)
    wrong = [c for c in run.cells if c["outlet"] != ("upper" if c["true_class"] == "II" else "lower")]
    assert not wrong, f"{len(wrong)} of {len(run.cells)} cells left by the wrong outlet: {_describe(wrong)}"


def assert_purity(run: SortRun, at_least: float) -> None:
    _complete(run)
    purity = run.purity
    assert purity is not None, "nothing left by the upper outlet: the purity is undefined"
    assert purity >= at_least, f"purity {purity:.4f} < {at_least} ({run.statistics['outlets']})"


def assert_yield(run: SortRun, at_least: float) -> None:
    _complete(run)
    value = run.sort_yield
    assert value is not None, "the sample had no target: the yield is undefined"
    assert value >= at_least, f"yield {value:.4f} < {at_least} ({run.statistics['outcomes']})"


def assert_no_missed_deadlines(run: SortRun) -> None:
    missed = [c for c in run.cells if c["decision"] == "missed"]
    control = run.summary.get("control", {})
    assert not missed, (f"{len(missed)} decisions came after their deadline ({control.get('deadline_budget_ms')} ms "
                        f"budget; latency {control.get('latency_ms')}): {_describe(missed)}")


@pytest.fixture
def vcyto_scenario():
    """The paper's device; override this fixture in your conftest.py for another scenario."""
    from sim.model.scenario import Scenario
    return Scenario()


@pytest.fixture(scope="session")
def _vcyto_plants():
    return {}


@pytest.fixture
def vcyto_plant(vcyto_scenario, _vcyto_plants):
    """``vcyto_plant(model="rom")``: a plant of a registered model on ``vcyto_scenario``, built once a session."""
    def plant(model: str = "rom"):
        key = (model, vcyto_scenario)
        if key not in _vcyto_plants:
            from sim.model.arrivals import Arrivals
            from vcyto.stream import StreamSettings, make_plant
            _vcyto_plants[key] = make_plant(vcyto_scenario, StreamSettings(Arrivals(cells=("RBC",)), model=model))
        return _vcyto_plants[key]
    return plant


@pytest.fixture
def sort_run(vcyto_scenario, vcyto_plant):
    """``sort_run(controller, cells=("RBC", "melanoma"), model="rom", **options)``: one closed-loop run.

    ``controller``: your controller object, or a class/factory taking the controller settings (None: the
    built-in one). Options: ``cells`` or ``count`` with ``mix``; ``rate`` (cells/s), ``arrivals`` ("regular" or
    "poisson"), ``min_spacing`` (s), ``seed``, ``realtime`` (a real-time factor, or None for lock-step), and any
    field of ``ControllerSettings`` (``lead``, ``pulse``, ``mode``, ...)."""
    def run(controller=None, cells=("RBC", "melanoma"), count: int = 0, mix=(), rate: float = 500.0,
            arrivals: str = "regular", min_spacing: float = 0.5e-3, model: str = "rom", seed: int = 0,
            realtime: float | None = None, **controller_options) -> SortRun:
        from controller.sorter import ControllerSettings
        from sim.model.arrivals import Arrivals
        from vcyto.control import Timing
        from vcyto.stream import StreamSettings, run_stream
        settings = StreamSettings(Arrivals(cells=() if count else tuple(cells), count=count, mix=tuple(mix),
                                           rate=rate, process=arrivals, min_spacing=min_spacing),
                                  controller=ControllerSettings(**controller_options), model=model, seed=seed)
        if controller is not None and not isinstance(controller, type) and not hasattr(controller, "on_event"):
            controller = controller(settings.controller)          # a factory
        timing = Timing(realtime=True, factor=realtime) if realtime is not None else Timing()
        return SortRun(run_stream(vcyto_scenario, settings, plant=vcyto_plant(model), controller=controller,
                                  timing=timing))
    return run
