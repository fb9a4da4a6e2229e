"""The Gymnasium environment (``vcyto.rl``): Gymnasium's own checker, seeding, the loop itself behind the
actions (the built-in controller's decisions given as actions sort exactly as the built-in controller does),
the rewards against the sort report's counts, the example's learned policy and the benchmark's counts."""

import importlib.util
import math
import warnings
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from controller.sorter import SortController
from vcyto import rl
from vcyto.bench.gym import bench_gym, gym_lines
from vcyto.stream import run_stream

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "rl_policy.py"


@pytest.fixture
def env(paper_scenario, rom_plant):
    return rl.SortEnv(count=200, scenario=paper_scenario, plant=rom_plant)


def gate_policy(observation) -> int:
    """Sort what the detector classes II, pass the rest."""
    return rl.SORT if observation[rl.EVENT_FIELDS.index("detected_class")] else rl.PASS


def play(env, act, seed):
    """(observations, rewards, the final info) of one episode of ``act`` from ``reset(seed=seed)``."""
    observation, info = env.reset(seed=seed)
    observations, rewards, ended = [observation], [], False
    while not ended:
        observation, reward, terminated, truncated, info = env.step(act(observation))
        observations.append(observation)
        rewards.append(reward)
        ended = terminated or truncated
    return np.array(observations), rewards, info


def test_gymnasium_make_and_check_env_pass_on_rom(paper_scenario, rom_plant):
    made = gymnasium.make("vcyto/Sort-v0", count=60, scenario=paper_scenario, plant=rom_plant)
    assert isinstance(made.unwrapped, rl.SortEnv) and made.action_space.n == 3
    assert made.observation_space.shape == (len(rl.observation_names()),)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(made.unwrapped)
    assert not [w for w in caught if "WARN:" in str(w.message)], [str(w.message) for w in caught]   # the checker's
    # the module-path form (which imports vcyto.rl first) makes the same environment
    assert isinstance(gymnasium.make("vcyto.rl:vcyto/Sort-v0", count=5, scenario=paper_scenario,
                                     plant=rom_plant).unwrapped, rl.SortEnv)


def test_the_same_seed_gives_the_same_episode(env):
    def trace(seed):
        env.action_space.seed(3)
        return play(env, lambda observation: int(env.action_space.sample()), seed)

    first, again, other = trace(5), trace(5), trace(6)
    assert np.array_equal(first[0], again[0]) and first[1] == again[1] and first[2] == again[2]
    assert len(first[0]) > 100 and first[2]["seed"] != other[2]["seed"]
    assert len(first[0]) != len(other[0]) or not np.array_equal(first[0], other[0])
    # a reset without a seed continues the generator: another sample
    _, info = env.reset()
    assert info["seed"] not in (first[2]["seed"], other[2]["seed"])


def test_the_built_in_controllers_decisions_as_actions_sort_as_the_built_in_controller(paper_scenario, rom_plant):
    env = rl.SortEnv(count=400, scenario=paper_scenario, plant=rom_plant)
    env.reset(seed=11)
    built_in = SortController(env.settings.controller)
    ended, aborted_earlier = False, 0
    while not ended:
        event = env.event
        answer = built_in.on_event(event, event.time)
        own = [d for d in answer if d.event_id == event.event_id][0]
        others = [d for d in answer if d.event_id != event.event_id]
        assert len(others) <= 1 and all(d.action == "abort" for d in others)
        aborted_earlier += len(others)
        action = rl.SORT if own.action == "sort" else rl.ABORT if others else rl.PASS
        _, _, terminated, truncated, info = env.step(action)
        ended = terminated or truncated
    assert terminated and env.event is None
    with pytest.raises(RuntimeError, match="ended"):
        env.step(rl.PASS)
    ours = env.summary()
    theirs = run_stream(paper_scenario, env.episode_settings, plant=rom_plant)
    assert aborted_earlier > 0 and theirs["statistics"]["aborts"] > aborted_earlier   # both kinds of abort ran
    assert [cell["outlet"] for cell in ours["cells"]] == [cell["outlet"] for cell in theirs["cells"]]
    assert ([cell["decision"] == "sort" for cell in ours["cells"]]
            == [cell["decision"] == "sort" for cell in theirs["cells"]])
    assert ours["statistics"]["events"] == theirs["statistics"]["events"] == env.loop.detected
    assert ours["controller_name"] == rl.ActionPort.name and theirs["controller_name"] == "built-in"


@pytest.mark.parametrize("reward", rl.REWARDS)
def test_the_rewards_follow_the_sort_reports_counts(paper_scenario, rom_plant, reward):
    env = rl.SortEnv(count=300, reward=reward, contaminant_cost=3.0, purity_floor=0.9999, floor_weight=2.0,
                     scenario=paper_scenario, plant=rom_plant)
    _, rewards, info = play(env, gate_policy, seed=2)
    stats = env.summary()["statistics"]
    # the counts are the sort report's: purity over the upper outlet, yield over the targets offered
    assert math.isclose(info["purity"], stats["purity"]) and math.isclose(info["yield"], stats["yield"])
    assert info["contaminants"] > 0 and info["sorted_targets"] > 0       # a stream dense enough to co-deflect
    purity, yield_ = info["purity"], info["yield"]
    if reward == "shaped":
        assert sum(rewards) == info["sorted_targets"] - 3.0 * (info["contaminants"] + info["misrouted"])
        assert sum(r != 0 for r in rewards) > 10                          # paid as the cells leave
    else:
        assert all(r == 0 for r in rewards[:-1])
        expected = (2 * purity * yield_ / (purity + yield_) if reward == "f1"
                    else yield_ - 2.0 * (0.9999 - purity))
        assert math.isclose(rewards[-1], expected)


def test_passing_everything_sorts_nothing(env):
    _, rewards, info = play(env, lambda observation: rl.PASS, seed=1)
    assert info["sorted_targets"] == info["contaminants"] == 0 and info["targets_offered"] > 0
    assert (info["purity"], info["yield"], sum(rewards)) == (1.0, 0.0, 0.0)
    assert env.summary()["statistics"]["outlets"].get("upper", 0) == 0


def test_bad_arguments_and_misuse_are_refused(paper_scenario, rom_plant):
    for options, word in (({"reward": "f2"}, "reward"), ({"contaminant_cost": math.nan}, "contaminant_cost"),
                          ({"purity_floor": 1.5}, "purity_floor"), ({"count": 0}, "count")):
        with pytest.raises(ValueError, match=word):
            rl.SortEnv(scenario=paper_scenario, plant=rom_plant, **options)
    env = rl.SortEnv(count=20, aborts=False, scenario=paper_scenario, plant=rom_plant)
    assert env.action_space.n == 2
    with pytest.raises(RuntimeError, match="reset"):
        env.step(0)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.step(rl.ABORT)


def test_the_examples_learned_policy_matches_the_built_in_controller(capsys):
    spec = importlib.util.spec_from_file_location("rl_policy", EXAMPLE)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    result = example.main(["--quick"])
    rows = {row["policy"]: row for row in result["rows"]}
    learned, built_in, always = rows["learned"], rows["built-in"], rows["always sort"]
    assert learned["events"] == built_in["events"] > 800
    assert learned["purity"] > always["purity"] + 0.5          # it learned to pass type-I cells
    assert learned["yield"] > 0.5                              # and to sort targets
    assert learned["f1"] >= built_in["f1"] - 0.03              # within 0.03 of the built-in controller's F1
    assert "learned  rule: gate" in capsys.readouterr().out


def test_bench_gym_counts_every_event_as_a_step(paper_scenario, rom_plant):
    result = bench_gym(paper_scenario, count=150, repeats=2, plant=rom_plant)
    for run in result["runs"]:
        assert run["steps"] == run["loop_events"] > 100 and run["cpu_s"] > 0
    rates = [run["steps_per_s"] for run in result["runs"]]
    assert min(rates) <= result["steps_per_s"] <= max(rates)
    assert "environment steps/s" in "\n".join(gym_lines(result))


@pytest.mark.slow
def test_the_environment_runs_on_feib(paper_scenario):
    """The same environment on the FE-IB plant (1-3 min): the gate's policy sorts a melanoma and passes an RBC."""
    from sim.model.arrivals import Arrivals
    from vcyto.stream import StreamSettings

    settings = StreamSettings(Arrivals(cells=("RBC", "melanoma"), rate=500.0), model="feib")
    env = rl.SortEnv(settings=settings, scenario=paper_scenario)
    observations, _, info = play(env, gate_policy, seed=0)
    assert len(observations) == 3 and info["events"] == 2
    assert (info["sorted_targets"], info["contaminants"], info["targets_offered"]) == (1, 0, 1)
    assert env.summary()["model"] == "feib"
