"""The benchmarks of `vcyto bench`, one module per family; each measures in one process, so that ratios are
meaningful on a noisy machine, and returns a JSON-ready dict with the lines that report it.

- ``fluid``: set-up and per-step cost of the fluid solver, per convection treatment; the bare back-solve.
- ``treatments``: how far imex, oseen and stokes steps differ from implicit ones (flow, paper scenario).
- ``membrane``: the paper's membrane method against the conserving one.
- ``tolerance``: time steps chosen by a tolerance against fixed steps on the paper scenarios.
- ``controller``: decision latency of the sorting controller.
- ``realtime``: real-time factor of the closed loop with the rom plant.
- ``auto``: the auto plant against feib on one stream, cell by cell.
- ``recording``: overhead of the MCAP + Rerun recording.
- ``process``: whole ``vcyto`` processes (separate processes, warm cache) against the whole-process targets.
- ``sort``: long rom sorting runs with recording (separate processes): cost per event, memory, file sizes.
- ``sweep``: one sweep on pools of several sizes: the speed-up.
"""
