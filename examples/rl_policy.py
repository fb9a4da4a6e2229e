"""Learn a sorting policy on the cheap plant (``rom``) with the cross-entropy method; check it on ``auto``.

The environment is ``vcyto/Sort-v0`` (``vcyto.rl``; docs/gymnasium.md) at 1,000 events/s: Poisson arrivals offered
at 1,111/s through the inlet's 0.1 ms dead time, RBC:0.9, melanoma:0.1, where coincidences are frequent and
aborts matter. The policy is a rule of five numbers, numpy only:

- an event whose fluorescence reaches ``gate`` is a candidate: pass it if an earlier type-I event (the
  detector's class) is predicted to arrive within [sort_low, sort_high] ms of it (the other's arrival minus this
  one's), else sort it;
- any other event: abort the nearest abortable pending sort if its target is predicted within
  [abort_low, abort_high] ms of this cell (the target's arrival minus this one's), else pass.

The built-in controller's purity mode is this rule with the detector's gate (0.5) and its calibrated envelope
widened by the timing error (sort window [-0.253, 0.246] ms, abort window [-0.246, 0.253] ms). The search starts
from the detector's gate and wide windows ([-0.5, 0.5] ms) and maximises the shaped reward (+1 a target sorted,
-30 a non-target sorted or caught on the divider) on training episodes of ``rom``; the figures are counted on
held-out episodes, the built-in controller running the same samples (the same stream seeds) through
``vcyto.run_stream``. The learned rule is then run on ``auto`` (``rom`` with FE-IB windows around close cells),
beside the built-in controller.

    python examples/rl_policy.py            # the figures of docs/gymnasium.md (~10 min on a quiet machine)
    python examples/rl_policy.py --quick    # a short search, rom only (the test; ~1 min)
"""

from __future__ import annotations

import argparse
import json
import sys

import gymnasium
import numpy as np

import vcyto.rl as rl
from sim.fast.linalg import SolverError
from sim.method.fluid import NumericalBlowUp
from vcyto.stream import StreamStopped, run_stream

FLUORESCENCE = rl.EVENT_FIELDS.index("fluorescence")
RECENT_AT, RECENT_WIDTH = len(rl.EVENT_FIELDS), len(rl.RECENT_FIELDS)
PENDING_AT, PENDING_WIDTH = RECENT_AT + rl.RECENT * RECENT_WIDTH, len(rl.PENDING_FIELDS)
NAMES = ("gate", "sort_low_ms", "sort_high_ms", "abort_low_ms", "abort_high_ms")
BUILT_IN = (0.5, -0.2532, 0.2457, -0.2457, 0.2532)    # the built-in purity mode's rule, for comparison
START = (0.5, -0.5, 0.5, -0.5, 0.5)                 # where the search starts: the detector's gate, wide windows
SPREAD = (0.2, 0.2, 0.2, 0.2, 0.2)
RATE = 1000.0 / (1 - 1000.0 * 0.1e-3)             # offered: 1,000 admitted events/s through the 0.1 ms dead time
CONTAMINANT_COST = 30.0       # the shaped reward: a non-target sorted (or caught on the divider) costs 30 targets


def window_policy(theta):
    """The action for an observation under the rule ``theta`` = (gate, sort_low, sort_high, abort_low,
    abort_high), windows in ms (module docstring)."""
    gate, sort_low, sort_high, abort_low, abort_high = (float(value) for value in theta)

    def act(observation) -> int:
        values = observation.tolist()
        if values[FLUORESCENCE] >= gate:
            for row in range(RECENT_AT, PENDING_AT, RECENT_WIDTH):
                present, type_ii, offset, _ = values[row:row + RECENT_WIDTH]
                if present and not type_ii and sort_low <= offset <= sort_high:
                    return rl.PASS
            return rl.SORT
        for row in range(PENDING_AT, len(values), PENDING_WIDTH):
            present, offset, abortable = values[row:row + PENDING_WIDTH]
            if present and abortable:           # the nearest abortable sort: the one the abort action takes back
                return rl.ABORT if abort_low <= offset <= abort_high else rl.PASS
        return rl.PASS
    return act


def episode(env, act, seed: int):
    """Run one episode of ``act`` from ``reset(seed=seed)``; (total reward, the final step's info)."""
    observation, _ = env.reset(seed=seed)
    total, ended = 0.0, False
    while not ended:
        observation, reward, terminated, truncated, info = env.step(act(observation))
        total, ended = total + reward, terminated or truncated
    return total, info


def cross_entropy(env, seeds, iterations: int, population: int, elite: int, rng) -> tuple[np.ndarray, list]:
    """The cross-entropy method over the rule's five numbers: sample ``population`` rules from a Gaussian, keep the
    ``elite`` best by their summed reward on the episodes ``seeds`` (the same episodes for every candidate), refit
    the Gaussian to them; the final mean and the best score of each iteration."""
    mean, spread = np.array(START), np.array(SPREAD)
    history = []
    for _ in range(iterations):
        candidates = mean + spread * rng.standard_normal((population, len(mean)))
        scores = np.array([sum(episode(env, window_policy(theta), seed)[0] for seed in seeds)
                           for theta in candidates])
        best = candidates[np.argsort(scores)[-elite:]]
        mean, spread = best.mean(axis=0), best.std(axis=0) + 0.005
        history.append(float(scores.max()))
    return mean, history


def tally(env, act, seeds) -> dict:
    """Purity, yield and F1 of ``act`` over the episodes ``seeds``, counted over all of them together; with
    ``act`` None, the built-in controller on the same samples (``run_stream``). A run the plant cannot finish (a
    numerical failure of an FE-IB window, which the plant names) is reported as failed, with its reason."""
    total = np.zeros(5, dtype=int)
    for seed in seeds:
        try:
            total += built_in_counts(env, seed) if act is None else policy_counts(env, act, seed)
        except (StreamStopped, NumericalBlowUp, SolverError) as failure:
            return {"status": "failed", "reason": str(failure), "seed": seed}
    sorted_targets, contaminants, misrouted, offered, events = (int(n) for n in total)
    purity, yield_, f1 = rl.sorting_figures(sorted_targets, contaminants, offered)
    return {"status": "complete", "events": events, "sorted_targets": sorted_targets, "contaminants": contaminants,
            "misrouted": misrouted, "targets_offered": offered, "purity": purity, "yield": yield_, "f1": f1}


def policy_counts(env, act, seed: int) -> tuple:
    """(targets sorted, non-targets sorted, non-targets that left by neither outlet, targets offered, events) of
    an episode of ``act``."""
    _, info = episode(env, act, seed)
    return (info["sorted_targets"], info["contaminants"], info["misrouted"], info["targets_offered"],
            info["events"])


def built_in_counts(env, seed: int) -> tuple:
    """The same counts of the built-in controller on the sample of ``reset(seed=seed)``."""
    _, info = env.reset(seed=seed)
    core = env.unwrapped
    result = run_stream(core.scenario, core.episode_settings, plant=core.plant)
    upper = [cell for cell in result["cells"] if cell["outlet"] == "upper"]
    right = sum(cell["true_class"] == "II" for cell in upper)
    misrouted = sum(cell["true_class"] == "I" and cell["outlet"] not in ("upper", "lower", "not_injected")
                    for cell in result["cells"])
    return right, len(upper) - right, misrouted, info["targets_offered"], result["statistics"]["events"]


def make(model: str, count: int, scenario=None):
    return gymnasium.make(rl.ENV_ID, model=model, count=count, rate=RATE, min_spacing=0.1e-3, reward="shaped",
                          contaminant_cost=CONTAMINANT_COST, scenario=scenario)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a short search and rom only (the test)")
    parser.add_argument("--auto-cells", type=int, default=100,
                        help="cells of the check on auto, per policy (default 100; 0: no check)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = parser.parse_args(argv)
    quick = args.quick
    train = make("rom", 400 if quick else 2000)
    train_seeds = range(1, 2 if quick else 4)
    theta, history = cross_entropy(train, train_seeds, iterations=4 if quick else 10, population=8 if quick else 20,
                                   elite=3 if quick else 5, rng=np.random.default_rng(0))
    test = make("rom", 1000 if quick else 2000)
    test_seeds = range(100, 101 if quick else 105)
    rows = {("rom", "learned"): tally(test, window_policy(theta), test_seeds),
            ("rom", "built-in"): tally(test, None, test_seeds),
            ("rom", "always sort"): tally(test, lambda observation: rl.SORT, test_seeds)}
    if args.auto_cells > 0 and not quick:
        check = make("auto", args.auto_cells, scenario=test.unwrapped.scenario)
        rows[("auto", "learned")] = tally(check, window_policy(theta), (200,))
        rows[("auto", "built-in")] = tally(check, None, (200,))
    result = {"learned": dict(zip(NAMES, map(float, theta))), "built_in": dict(zip(NAMES, BUILT_IN)),
              "search_best": history,
              "rows": [{"model": model, "policy": policy, **row} for (model, policy), row in rows.items()]}
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        for name, rule in (("learned", theta), ("built-in", BUILT_IN)):
            print("{:<8} rule: gate {:.3f}, sort window [{:+.4f}, {:+.4f}] ms, abort window [{:+.4f}, {:+.4f}] ms"
                  .format(name, *rule))
        print(f"{'model':<6} {'policy':<12} {'events':>7} {'sorted':>7} {'wrong':>6} {'wall':>5} {'purity':>8} "
              f"{'yield':>8} {'F1':>6}")
        for row in result["rows"]:
            if row["status"] != "complete":
                print(f"{row['model']:<6} {row['policy']:<12} failed: {row['reason']}")
                continue
            print(f"{row['model']:<6} {row['policy']:<12} {row['events']:>7} {row['sorted_targets']:>7} "
                  f"{row['contaminants']:>6} {row['misrouted']:>5} {100 * row['purity']:>7.2f}% "
                  f"{100 * row['yield']:>7.2f}% {row['f1']:>6.3f}")
    return result


if __name__ == "__main__":
    sys.exit(main() and 0)
