"""A Gymnasium environment of the sorting loop: one step is one detector event awaiting its decision.

``import vcyto.rl`` registers ``vcyto/Sort-v0``; then ``gymnasium.make("vcyto/Sort-v0", model="rom", ...)``
(or, without the import, ``gymnasium.make("vcyto.rl:vcyto/Sort-v0", ...)``). Needs the optional extra ``rl``
(``pip install 'vcyto[rl]'``). docs/gymnasium.md describes the spaces, the rewards and how to train and check.

The environment is the closed loop itself (``vcyto.stream.Loop``), its controller a port whose answer is the
action: the loop runs until the detector completes an event, and stops there, lock-step, until the action
decides it (device time does not pass while a decision is outstanding). Any plant of the registry runs:
``rom`` to train, ``auto`` or ``feib`` to check a policy.

Observation (``SortEnv.observation_names``), what a controller could know at the event, float32:
- the event: fluorescence (a.u.), scatter / 100 (a.u.), velocity / the calibrated reference velocity, detected
  class (0: I, 1: II), look-ahead (its decision deadline minus its time, ms);
- the ``RECENT`` latest earlier events whose predicted arrivals lie within ``HORIZON`` of this one's, latest
  first: present (1/0), class, offset of its predicted arrival from this one's (ms), sorted (1 while its sort
  stands and its pulse is not over);
- the ``PENDING`` sorts whose pulses are not over, nearest arrival first: present, offset of its target's
  predicted arrival from this one's (ms), abortable (1 if its pulse has not started).
Action: 0 pass, 1 sort (the calibrated pulse: from the predicted arrival minus the lead, ``DeviceFacts``),
2 pass and abort the abortable pending sort nearest in arrival (``aborts=False``: 0 and 1 only).
Rewards (``REWARDS``): ``shaped`` (each cell as it leaves: +1 a target by the upper outlet, minus
``contaminant_cost`` a non-target anywhere but the lower outlet: the upper one, or caught on the divider between
them, ``wall``, where no outlet is certain), ``f1`` (at the end: the F1 score of purity and yield), ``purity_floor``
(at the end: the yield, minus ``floor_weight`` times the purity's shortfall below ``purity_floor``).
Purity and yield are counted as in the sort report (``vcyto.sortreport``): purity over the cells that left by
the upper outlet, yield over the targets offered (those the inlet turned away included).

Seeding: ``reset(seed=s)`` seeds the environment's generator, which draws each episode's stream seed (in the
reset's ``info["seed"]``): ``vcyto stream --seed`` that number runs the same sample with another controller.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import replace

import gymnasium
import numpy as np
from gymnasium import spaces

from controller.events import TYPE_II, Decision
from controller.protocol import DeviceFacts
from sim.model.arrivals import Arrivals
from sim.model.scenario import Scenario

from .control import Reply
from .outcomes import DEFAULT_OUTLET, SORTED_OUTLET
from .stream import Loop, StreamSettings, make_plant

ENV_ID = "vcyto/Sort-v0"
RECENT = 4                 # earlier events in the observation
PENDING = 4                # pending sorts in the observation
HORIZON = 1e-3             # s: earlier events whose predicted arrivals lie further away are left out
REWARDS = ("shaped", "f1", "purity_floor")
PASS, SORT, ABORT = range(3)
MIX = (("RBC", 0.9), ("melanoma", 0.1))
EVENT_FIELDS = ("fluorescence", "scatter", "velocity", "detected_class", "look_ahead_ms")
RECENT_FIELDS = ("present", "class", "offset_ms", "sorted")
PENDING_FIELDS = ("present", "offset_ms", "abortable")
LARGE = 1e3                # bound of the observation's unbounded quantities (a.u., ms)
_EVENT_BOUNDS = ((0.0, LARGE), (0.0, LARGE), (0.0, LARGE), (0.0, 1.0), (-LARGE, LARGE))
_RECENT_BOUNDS = ((0.0, 1.0), (0.0, 1.0), (-HORIZON * 1e3, HORIZON * 1e3), (0.0, 1.0))
_PENDING_BOUNDS = ((0.0, 1.0), (-LARGE, LARGE), (0.0, 1.0))
_ABSENT_RECENT = (0.0,) * len(RECENT_FIELDS)
_ABSENT_PENDING = (0.0,) * len(PENDING_FIELDS)


def observation_names() -> tuple[str, ...]:
    return (EVENT_FIELDS + tuple(f"recent{k}_{name}" for k in range(RECENT) for name in RECENT_FIELDS)
            + tuple(f"pending{k}_{name}" for k in range(PENDING) for name in PENDING_FIELDS))


def _bounds():
    rows = _EVENT_BOUNDS + _RECENT_BOUNDS * RECENT + _PENDING_BOUNDS * PENDING
    return (np.array([low for low, _ in rows], dtype=np.float32), np.array([high for _, high in rows],
                                                                           dtype=np.float32))


class ActionPort:
    """The loop's port to the environment: each event is answered with the decisions the action made
    (``answer``, set before the loop is told of the event)."""

    name = "gymnasium policy"

    def __init__(self):
        self.answer: tuple = ()
        self._replies: list[Reply] = []

    def start(self, facts: DeviceFacts) -> None:
        self.facts = facts

    def post(self, event, clock: float) -> None:
        self._replies.append(Reply(event.event_id, self.answer, 0.0))

    def replies(self, wait: float = 0.0) -> list[Reply]:
        replies, self._replies = self._replies, []
        return replies

    def drive(self, clock: float) -> None:
        return None

    def close(self) -> None:
        pass


def sorting_figures(sorted_targets: int, contaminants: int, targets_offered: int) -> tuple[float, float, float]:
    """(purity, yield, F1) from the targets and non-targets that left by the upper outlet and the targets offered
    (purity 1 when nothing was sorted, yield 1 when no target was offered: nothing was lost)."""
    upper = sorted_targets + contaminants
    purity = sorted_targets / upper if upper else 1.0
    yield_ = sorted_targets / targets_offered if targets_offered else 1.0
    f1 = 2 * purity * yield_ / (purity + yield_) if purity + yield_ > 0 else 0.0
    return purity, yield_, f1


class _Departures:
    """A sink of the loop (not paced) that keeps the cells that left, shown as the loop shows its steps to every
    sink (the sort report among them), until the environment takes them for its rewards."""

    paced = False
    needs_state = False           # reads the cells' truth only

    def __init__(self):
        self.cells: list = []

    def on_step(self, record):
        self.cells.extend(cell for cell in record.truth.cells if cell.fate != "in_channel")

    def take(self) -> list:
        cells, self.cells = self.cells, []
        return cells


class SortEnv(gymnasium.Env):
    """The sorting loop as a Gymnasium environment (module docstring).

    ``model``: a plant of the registry (``sim.plants.registry``), built once (``plant``: one already built). The sample
    of an episode: ``count`` cells of ``mix`` offered at ``rate`` cells/s (``process``, the inlet's dead time
    ``min_spacing``), or ``settings`` (a ``vcyto.stream.StreamSettings``: arrivals, detector, controller
    calibration, model; its seed is replaced by each episode's). ``reward``: one of ``REWARDS``.
    """

    metadata = {"render_modes": []}

    def __init__(self, model: str = "rom", count: int = 200, rate: float = 1000.0 / 0.9, mix=MIX,
                 min_spacing: float = 0.1e-3, process: str = "poisson", reward: str = "shaped",
                 contaminant_cost: float = 10.0, purity_floor: float = 0.99, floor_weight: float = 10.0,
                 aborts: bool = True, scenario: Scenario | None = None, settings: StreamSettings | None = None,
                 plant=None):
        if reward not in REWARDS:
            raise ValueError(f"reward must be one of {', '.join(REWARDS)} (got {reward!r})")
        for name, value in (("contaminant_cost", contaminant_cost), ("floor_weight", floor_weight)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0 (got {value!r})")
        if not (isinstance(purity_floor, (int, float)) and 0.0 <= purity_floor <= 1.0):
            raise ValueError(f"purity_floor must be a number in [0, 1] (got {purity_floor!r})")
        if settings is None:
            arrivals = Arrivals(count=count, mix=tuple(mix), rate=rate, process=process, min_spacing=min_spacing)
            settings = StreamSettings(arrivals, model=model)
        self.scenario = scenario or Scenario()
        self.settings = settings
        self.plant = plant or make_plant(self.scenario, settings)
        self.reward_kind, self.contaminant_cost = reward, float(contaminant_cost)
        self.purity_floor, self.floor_weight = float(purity_floor), float(floor_weight)
        self.observation_names = observation_names()
        self._low, self._high = _bounds()
        self.observation_space = spaces.Box(self._low, self._high, dtype=np.float32)
        self.action_space = spaces.Discrete(3 if aborts else 2)
        self._actions = range(self.action_space.n)
        self._target = {cell.name: cell.target for cell in self.scenario.cell_types}
        self.loop = None

    # ------------------------------------------------------------------ the Gymnasium API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.episode_settings = replace(self.settings, seed=int(self.np_random.integers(2**63 - 1)))
        self._port = ActionPort()
        self._left = _Departures()
        self.loop = loop = Loop(self.scenario, self.episode_settings, plant=self.plant, sinks=(self._left,),
                                controller=self._port)
        self._facts = loop.control.facts
        self._recent: deque = deque(maxlen=RECENT)      # (event id, class, predicted arrival) of earlier events
        self._sorts: dict = {}                          # event id -> (arrival, pulse on, pulse off) of standing sorts
        self._batch, self._next, self._ended = [], 0, False
        self._sorted_targets = self._contaminants = self._misrouted = 0
        sample = loop.sample
        self._targets_offered = sum(count for name, count in sample.offered.items() if self._target[name])
        self._alive = self._to_next_event()
        self._collect()                                 # cells that left before the first decision
        return self._observe(), {"seed": self.episode_settings.seed, "targets_offered": self._targets_offered}

    def step(self, action):
        if self.loop is None or self._ended:
            raise RuntimeError("call reset() before step(): " + ("the episode has ended" if self.loop else
                                                                 "no episode yet"))
        if action not in self._actions:
            raise ValueError(f"action must be one of {list(self._actions)} (got {action!r})")
        action = int(action)
        if self._alive:
            self._decide(self._batch[self._next], action)
            self._next += 1
            self._alive = self._to_next_event()
        reward = self._collect()
        if self._alive:
            return self._observe(), reward, False, False, {}
        return self._end(reward)

    @property
    def event(self):
        """The detector event awaiting its decision (``controller.events.DetectorEvent``; None once the episode
        has ended): what the observation describes, for a policy that wants more than the observation."""
        return self._batch[self._next] if self.loop is not None and self._alive else None

    def summary(self) -> dict:
        """The episode's sort report as ``vcyto stream`` writes it (``vcyto.stream.Loop.summary``)."""
        return self.loop.summary("complete" if self.plant.done else "truncated")

    # ------------------------------------------------------------------ the loop
    def _to_next_event(self) -> bool:
        """Run the loop until an event awaits its decision (True) or the run ends (False)."""
        loop = self.loop
        while self._next == len(self._batch):
            if self._batch:
                loop.conclude(self._batch)
                self._batch = []
            if not loop.proceed:
                loop.control.finish()
                loop.finish()
                return False
            self._batch, self._next = loop.advance(), 0
            if not self._batch:
                loop.conclude(self._batch)
        return True

    def _decide(self, event, action: int) -> None:
        facts, sorts = self._facts, self._sorts
        arrival = facts.arrival(event)
        if action == SORT:
            on = arrival - facts.lead
            answer = [Decision(event.event_id, "sort", arrival, on, on + facts.pulse)]
            sorts[event.event_id] = (arrival, on, on + facts.pulse)
        else:
            answer = [Decision(event.event_id, "pass", arrival)]
            if action == ABORT:
                nearest = min(((abs(standing[0] - arrival), key) for key, standing in sorts.items()
                               if standing[1] > event.time), default=None)
                if nearest is not None:
                    answer.append(Decision(nearest[1], "abort", sorts.pop(nearest[1])[0], reason="aborted by the "
                                                                                                 "policy"))
        self._port.answer = answer
        self.loop.control.deliver((event,), event.time)
        self._recent.appendleft((event.event_id, float(event.classification == TYPE_II), arrival))

    def _collect(self) -> float:
        """The shaped reward of the cells that left since the last call (and their count for the figures): a
        non-target that leaves by neither outlet (``wall``: caught on the divider; ``lost``) costs as much as one
        sorted, ``misrouted``; purity and yield count the outlets only, as the sort report does."""
        if self.reward_kind != "shaped" and self._alive:
            return 0.0
        reward = 0.0
        for cell in self._left.take():
            if cell.fate == "in_channel" or cell.fate == DEFAULT_OUTLET:
                continue
            if self._target[cell.type]:
                if cell.fate == SORTED_OUTLET:
                    self._sorted_targets += 1
                    reward += 1.0
                continue
            if cell.fate == SORTED_OUTLET:
                self._contaminants += 1
            else:
                self._misrouted += 1
            reward -= self.contaminant_cost
        return reward if self.reward_kind == "shaped" else 0.0

    def _end(self, reward: float):
        purity, yield_, f1 = sorting_figures(self._sorted_targets, self._contaminants, self._targets_offered)
        if self.reward_kind == "f1":
            reward = f1
        elif self.reward_kind == "purity_floor":
            reward = yield_ - self.floor_weight * max(0.0, self.purity_floor - purity)
        info = {"purity": purity, "yield": yield_, "f1": f1, "sorted_targets": self._sorted_targets,
                "contaminants": self._contaminants, "misrouted": self._misrouted,
                "targets_offered": self._targets_offered,
                "events": self.loop.detected, "seed": self.episode_settings.seed}
        self._ended = True
        return np.zeros(self.observation_space.shape, dtype=np.float32), reward, self.plant.done, \
            not self.plant.done, info

    # ------------------------------------------------------------------ what a controller could know
    def _observe(self) -> np.ndarray:
        if not self._alive:
            return np.zeros(self.observation_space.shape, dtype=np.float32)
        facts, event, sorts = self._facts, self._batch[self._next], self._sorts
        arrival = facts.arrival(event)
        values = [_clamp(event.fluorescence), _clamp(event.scatter / 100),
                  _clamp(event.velocity / facts.reference_velocity), float(event.classification == TYPE_II),
                  _clamp((arrival - facts.lead - event.time) * 1e3, -LARGE)]
        for key in [key for key, (_, _, off) in sorts.items() if off <= event.time]:
            del sorts[key]                              # pulses over: no longer pending
        recent = [(1.0, type_ii, (other - arrival) * 1e3, float(event_id in sorts))
                  for event_id, type_ii, other in self._recent if abs(other - arrival) <= HORIZON]
        for row in recent:
            values.extend(row)
        values.extend(_ABSENT_RECENT * (RECENT - len(recent)))
        pending = sorted((abs(other - arrival), other, on) for other, on, _ in sorts.values())[:PENDING]
        for _, other, on in pending:
            values.extend((1.0, _clamp((other - arrival) * 1e3, -LARGE), float(on > event.time)))
        values.extend(_ABSENT_PENDING * (PENDING - len(pending)))
        return np.array(values, dtype=np.float32)


def _clamp(value: float, low: float = 0.0, high: float = 1e3) -> float:
    return low if value < low else high if value > high else value   # NaN stays NaN: never from the loop


gymnasium.register(id=ENV_ID, entry_point="vcyto.rl:SortEnv")
