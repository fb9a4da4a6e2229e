"""`vcyto bench gym`: environment steps per second of the Gymnasium environment (``vcyto.rl``) on the ``rom``
plant, against the same sample run by the loop itself with the built-in controller (``run_stream``)."""

from __future__ import annotations

import statistics
import time

from sim.model.scenario import Scenario

TARGET_STEPS_PER_S = 1e4


def bench_gym(scenario: Scenario, count: int = 2000, rate: float = 1000.0 / 0.9, min_spacing: float = 0.1e-3,
              mix=(("RBC", 0.9), ("melanoma", 0.1)), repeats: int = 5, seed: int = 0,
              progress=lambda message: None, plant=None) -> dict:
    """Steps per second of ``gymnasium.make("vcyto/Sort-v0")`` (its wrappers included) on ``rom``: episodes of
    ``count`` cells offered at ``rate`` (Poisson, dead time ``min_spacing``), the gate's policy (sort what the
    detector classes II, pass the rest: an action read off the observation, so that the policy costs nothing),
    each episode ``reset(seed=seed)``, ``repeats`` times, the median. The reference: the same sample through
    ``run_stream`` with the built-in controller (detector events per second of loop wall time, set-up apart).
    The plant is built once, before the timing (``plant``: one already built). The process's CPU time is measured
    too: on a machine shared with other work the wall time includes waiting for a core."""
    import gymnasium

    from .. import rl
    from ..stream import run_stream

    progress("set-up: the rom plant (steady flows, sampling, kernels)")
    started = time.perf_counter()
    env = gymnasium.make(rl.ENV_ID, model="rom", count=count, rate=rate, mix=tuple(mix), min_spacing=min_spacing,
                         scenario=scenario, plant=plant)
    setup = time.perf_counter() - started
    core = env.unwrapped
    runs = []
    for repeat in range(repeats):
        progress(f"episode {repeat + 1} of {repeats}")
        observation, info = env.reset(seed=seed)
        steps, ended, started, cpu = 0, False, time.perf_counter(), time.process_time()
        while not ended:
            observation, _, terminated, truncated, info = env.step(1 if observation[3] else 0)
            steps, ended = steps + 1, terminated or truncated
        wall, cpu = time.perf_counter() - started, time.process_time() - cpu
        device = core.plant.time
        loop = run_stream(scenario, core.episode_settings, plant=core.plant)
        loop_wall = loop["wall_time_s"] - loop["setup_time_s"]
        runs.append({"steps": steps, "wall_s": wall, "cpu_s": cpu, "steps_per_s": steps / wall,
                     "steps_per_cpu_s": steps / cpu,
                     "device_time_s": device, "loop_events": loop["statistics"]["events"],
                     "loop_events_per_s": loop["statistics"]["events"] / loop_wall,
                     "purity": info["purity"], "yield": info["yield"]})
    env.close()
    median = statistics.median(run["steps_per_s"] for run in runs)
    return {"model": "rom", "count": count, "rate_per_s": rate, "min_spacing_ms": min_spacing * 1e3,
            "mix": [list(pair) for pair in mix], "seed": seed, "setup_s": setup, "runs": runs,
            "steps_per_episode": runs[-1]["steps"], "steps_per_s": median,
            "steps_per_cpu_s": statistics.median(run["steps_per_cpu_s"] for run in runs),
            "loop_events_per_s": statistics.median(run["loop_events_per_s"] for run in runs),
            "real_time_factor": runs[-1]["device_time_s"] * median / runs[-1]["steps"],
            "target_steps_per_s": TARGET_STEPS_PER_S, "target_met": median >= TARGET_STEPS_PER_S}


def gym_lines(result: dict) -> list[str]:
    runs = ", ".join(f"{run['steps_per_s']:,.0f}" for run in result["runs"])
    verdict = "met" if result["target_met"] else "NOT met"
    return [
        f"gymnasium: vcyto/Sort-v0 on rom, {result['count']:,} cells offered at {result['rate_per_s']:g}/s (Poisson, "
        f"min spacing {result['min_spacing_ms']:g} ms, {', '.join(f'{n}:{w:g}' for n, w in result['mix'])}), "
        f"{result['steps_per_episode']:,} steps an episode, seed {result['seed']}; set-up {result['setup_s']:.2f} s",
        f"  {result['steps_per_s']:,.0f} environment steps/s (median of {len(result['runs'])}: {runs}); "
        f"target >= {result['target_steps_per_s']:,.0f}: {verdict}",
        f"  {result['steps_per_cpu_s']:,.0f} steps per second of the process's CPU time (what a machine to itself "
        "would give; the wall figure falls on a shared one)",
        f"  device time {result['real_time_factor']:.1f}x real time; the loop itself with the built-in controller: "
        f"{result['loop_events_per_s']:,.0f} events/s",
    ]
