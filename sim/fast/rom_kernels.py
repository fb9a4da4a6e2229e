"""Numba kernels of the reduced plant (``sim.plants.rom``): cells carried through gridded flows, many periods per call.

Fields are sampled on a uniform grid, shape (types, nx, ny, 4) or (types, nx, ny, 4 + 2 M) with channels
[u_off, v_off, du, dv, du_1, dv_1, ..., du_M, dv_M]: the IDT-off flow, the change to the IDT-on flow, and
M > 1 modes of the flow's response to the drive, which sum to that change. Mode k has its own level q_k,
following the actuation through an exact first-order lag of time constant tau_k (tau_k = 0: at once), and
the flow is the IDT-off flow plus sum_k q_k times mode k (``bilinear``); while every level is the same
(the drive has been steady long enough, most of a stream) that is the IDT-off flow plus q times the change,
four channels instead of 2 + 2 M. With one mode (no mode channels) it is the single lag of the blended
steady flows. A cell is an axis-aligned ellipse
(semi-axes a along x, b along y) whose centroid moves with the field of its type; walls are axis-aligned
segments the ellipse may touch but not cross (``hold_off``), except the face of a divider between two outlets:
a cell pressed on it with its centroid in the divider's span settles there (fate WALL), where the FE-IB
plant's centroid would leave through the wall (docs/physics.md, "rom").

Cell state lives in flat arrays indexed by key: position (n, 2), fate (n,) coded as below, exit time and
ordinate, time spent stalled against a wall. ``advance`` steps whole control periods, each ``substeps``
midpoint (RK2) steps with each mode's level following the actuation through its exact first-order lag,
injects the cells due, and returns early when the caller must look (see its docstring). Helpers are
inlined: a numba call that passes arrays costs a reference count per array, more than a substep.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

WAITING = -1
IN_CHANNEL = 0
WALL = 1
LOST = 2
OUTLET = 3                     # fate OUTLET + k: left through outlet k

# counters: int64 array of the plant's integer state (TRACED: rows in the trace, TRACE_EVERY: its cadence in
# periods, 0 = no trace)
STEP, NEXT, FIRST, ACTIVE, PHYSICS_STEPS, CONTACTS, LOGGED, TRACED, TRACE_EVERY = range(9)
# params: float64 array of the plant's constants
PERIOD, SUBSTEPS, LENGTH, HEIGHT, SPACING_X, SPACING_Y, STALL_SPEED, STALL_TIME = range(8)
# lags: float64 array (M, 4): each mode's decay over a substep and over half a substep, then two scratch columns
# why ``advance`` returned
LIMIT, CROSSING, UNTIL, DONE = range(4)


@njit(cache=True, error_model="numpy", inline="always")
def bilinear(fields, kind, x, y, levels, params):
    """The velocity (u, v) of field ``kind`` at mode levels ``levels`` (M,) at (x, y), clamped to the channel."""
    nx = fields.shape[1]
    ny = fields.shape[2]
    gx = min(max(x, 0.0), params[LENGTH]) / params[SPACING_X]
    gy = min(max(y, 0.0), params[HEIGHT]) / params[SPACING_Y]
    i = min(int(gx), nx - 2)
    j = min(int(gy), ny - 2)
    fx = gx - i
    fy = gy - j
    level = levels[0]
    modes = 0                      # 0: every level is the same, the four-channel blend
    for m in range(1, levels.shape[0]):
        if levels[m] != level:
            modes = levels.shape[0]
    u = 0.0
    v = 0.0
    for di, dj, w in ((0, 0, (1.0 - fx) * (1.0 - fy)), (1, 0, fx * (1.0 - fy)), (0, 1, (1.0 - fx) * fy),
                      (1, 1, fx * fy)):
        if modes == 0:
            cu = fields[kind, i + di, j + dj, 0] + level * fields[kind, i + di, j + dj, 2]
            cv = fields[kind, i + di, j + dj, 1] + level * fields[kind, i + di, j + dj, 3]
        else:
            cu = fields[kind, i + di, j + dj, 0]
            cv = fields[kind, i + di, j + dj, 1]
            for m in range(modes):
                cu += levels[m] * fields[kind, i + di, j + dj, 4 + 2 * m]
                cv += levels[m] * fields[kind, i + di, j + dj, 5 + 2 * m]
        u += w * cu
        v += w * cv
    return u, v


@njit(cache=True, error_model="numpy", inline="always")
def on_divider(x, y, a, length, dividers):
    """Whether an ellipse of semi-axis a along x centred at (x, y) is pressed on a divider's face: a wall
    segment x = length, y in (dividers[k, 0], dividers[k, 1]) between two outlets, with its centroid's
    ordinate in that span (where the FE-IB plant's centroid would leave through the wall: fate ``wall``)."""
    if x + a < length * (1.0 - 1e-9):
        return False
    for k in range(dividers.shape[0]):
        if dividers[k, 0] <= y <= dividers[k, 1]:
            return True
    return False


@njit(cache=True, error_model="numpy", inline="always")
def hold_off(x, y, a, b, segments):
    """Move the centroid (x, y) of an a x b ellipse so it crosses no wall segment; (x, y, touched).

    ``segments`` rows (x0, y0, x1, y1, nx, ny): an axis-aligned wall from (x0, y0) to (x1, y1) with inward
    unit normal (nx, ny). Beside a segment the centroid is kept at least the semi-axis along the normal
    from it; beyond an end, at least the ellipse's own extent from the end point (pushed radially in the
    ellipse's metric). Two passes settle corners where two walls meet.
    """
    touched = False
    if segments.shape[0] == 0 or (segments[0, 0] < x - a and x + a < segments[0, 2]
                                  and segments[0, 1] < y - b and y + b < segments[1, 1]):
        return x, y, touched            # clear of every wall (rows 0, 1: the lower and upper walls)
    for _ in range(2):
        for k in range(segments.shape[0]):
            x0, y0, x1, y1, nx, ny = segments[k]
            vertical = x0 == x1
            along = y if vertical else x
            low = y0 if vertical else x0
            high = y1 if vertical else x1
            if low <= along <= high:
                if vertical:
                    if (x - x0) * nx < a:
                        x = x0 + nx * a
                        touched = True
                elif (y - y0) * ny < b:
                    y = y0 + ny * b
                    touched = True
                continue
            end_x = x0 if vertical else (low if along < low else high)
            end_y = (low if along < low else high) if vertical else y0
            distance = math.sqrt(((x - end_x) / a) ** 2 + ((y - end_y) / b) ** 2)
            if 0.0 < distance < 1.0:
                x = end_x + (x - end_x) / distance
                y = end_y + (y - end_y) / distance
                touched = True
    return x, y, touched


@njit(cache=True, error_model="numpy")
def outlet_code(y, outlets):
    """The fate of a centroid crossing x = length at ordinate y: OUTLET + k for outlet span k, else WALL."""
    for k in range(outlets.shape[0]):
        if outlets[k, 0] <= y <= outlets[k, 1]:
            return OUTLET + k
    return WALL


@njit(cache=True, error_model="numpy", inline="always")
def _move(i, fields, params, segments, dividers, outlets, semi_axes, kind, position, fate, exit_time, exit_y,
          counters, start_time, step, level, level_half, touched):
    """One midpoint step of cell i; settles its fate when it leaves the channel or is pressed on a divider."""
    k = kind[i]
    a = semi_axes[k, 0]
    b = semi_axes[k, 1]
    x = position[i, 0]
    y = position[i, 1]
    u1, v1 = bilinear(fields, k, x, y, level, params)
    u2, v2 = bilinear(fields, k, x + 0.5 * step * u1, y + 0.5 * step * v1, level_half, params)
    new_x, new_y, contact = hold_off(x + step * u2, y + step * v2, a, b, segments)
    if contact:
        touched[i] = True
        counters[CONTACTS] += 1
    if not (math.isfinite(new_x) and math.isfinite(new_y)) or new_x < 0.0:
        fate[i] = LOST
        exit_time[i] = start_time + step
        counters[ACTIVE] -= 1
    elif contact and on_divider(new_x, new_y, a, params[LENGTH], dividers):
        fate[i] = WALL
        exit_time[i] = start_time + step
        exit_y[i] = new_y
        counters[ACTIVE] -= 1
    elif new_x >= params[LENGTH]:
        weight = (params[LENGTH] - x) / (new_x - x)
        exit_y[i] = y + weight * (new_y - y)
        exit_time[i] = start_time + weight * step
        fate[i] = outlet_code(exit_y[i], outlets)
        counters[ACTIVE] -= 1
    position[i, 0] = new_x
    position[i, 1] = new_y


@njit(cache=True, error_model="numpy", inline="always")
def _period(fields, params, segments, dividers, outlets, semi_axes, start, kind, arrival, born, position, fate,
            exit_time, exit_y, stalled, counters, level, lags, actuation, before, touched):
    """Advance one control period and inject the cells then due; ``level`` (M,) is updated in place."""
    period = params[PERIOD]
    substeps = int(params[SUBSTEPS])
    step = period / substeps
    modes = level.shape[0]
    level_half = lags[:, 2]
    level_new = lags[:, 3]
    first = counters[FIRST]
    last = counters[NEXT]
    for i in range(first, last):
        if counters[STEP] > 0 or before[i, 0] > -np.inf:   # cells injected at reset are first seen after
            before[i, 0] = position[i, 0]                     # the first period, as if injected in it
            before[i, 1] = position[i, 1]
        touched[i] = False
    t0 = counters[STEP] * period
    for sub in range(substeps):
        for m in range(modes):
            level_half[m] = actuation + (level[m] - actuation) * lags[m, 1]
            level_new[m] = actuation + (level[m] - actuation) * lags[m, 0]
        for i in range(first, last):
            if fate[i] == IN_CHANNEL:
                _move(i, fields, params, segments, dividers, outlets, semi_axes, kind, position, fate, exit_time,
                      exit_y, counters, t0 + sub * step, step, level, level_half, touched)
        # settle a lag once it is within 1e-12 of the drive: the tail would decay into subnormal numbers,
        # which make every later look-up ~100x slower
        for m in range(modes):
            level[m] = level_new[m] if abs(level_new[m] - actuation) > 1e-12 else actuation
        counters[PHYSICS_STEPS] += 1
    counters[STEP] += 1
    now = counters[STEP] * period
    for i in range(first, last):           # a cell held against a wall that no longer moves is stuck there
        if fate[i] != IN_CHANNEL:
            continue
        moved = math.sqrt((position[i, 0] - before[i, 0]) ** 2 + (position[i, 1] - before[i, 1]) ** 2)
        if touched[i] and moved < params[STALL_SPEED] * period:
            stalled[i] += period
            if stalled[i] >= params[STALL_TIME] * (1 - 1e-12):
                fate[i] = WALL
                exit_time[i] = now
                exit_y[i] = position[i, 1]
                counters[ACTIVE] -= 1
        else:
            stalled[i] = 0.0
    inject(start, kind, arrival, born, position, fate, counters, now, 0.5 * period, before)


@njit(cache=True, error_model="numpy", inline="always")
def inject(start, kind, arrival, born, position, fate, counters, now, tolerance, before):
    """Put the cells due by ``now`` (+ ``tolerance``) at their start points; drop settled cells from the window."""
    while counters[NEXT] < arrival.shape[0] and arrival[counters[NEXT]] <= now + tolerance:
        i = counters[NEXT]
        position[i, 0] = start[kind[i], 0]
        position[i, 1] = start[kind[i], 1]
        before[i, 0] = -np.inf             # a new cell "crosses" every watched line it starts beyond
        before[i, 1] = start[kind[i], 1]
        fate[i] = IN_CHANNEL
        born[i] = now
        counters[NEXT] += 1
        counters[ACTIVE] += 1
    while counters[FIRST] < counters[NEXT] and fate[counters[FIRST]] > IN_CHANNEL:
        counters[FIRST] += 1


@njit(cache=True, error_model="numpy", inline="always")
def _due(arrival, counters, period):
    """The index past the last cell that can be in the channel at the end of the next period."""
    due = counters[NEXT]
    horizon = (counters[STEP] + 1.5) * period
    while due < arrival.shape[0] and arrival[due] <= horizon:
        due += 1
    return due


@njit(cache=True, error_model="numpy", inline="always")
def _crosses(x_before, x_after, lines):
    """Whether x went forwards across one of the lines x = lines[k]."""
    for k in range(lines.shape[0]):
        if x_before < lines[k] <= x_after:
            return True
    return False


@njit(cache=True, error_model="numpy", nogil=True)
def advance(fields, params, segments, dividers, outlets, semi_axes, start, kind, arrival, born, position, fate,
            exit_time, exit_y, stalled, counters, level_state, lags, before, touched, log_step, log_key, log_positions,
            trace_step, trace_key, trace_positions, actuation, until, max_periods, stop_lines, record_lines):
    """Step up to ``max_periods`` control periods at a constant ``actuation``; (periods done, reason).

    Stops after the period that reaches time ``until`` (UNTIL), after which every cell has settled (DONE),
    in which a cell in the channel crossed one of the ``stop_lines`` x = w forwards or was injected beyond
    one (CROSSING), or at ``max_periods`` (LIMIT). Every period in which a cell crosses a stop or record line
    is logged: log_step[m] (the period's index), log_key[m], log_positions[m] = (x, y) one period before
    (x = -inf for a cell injected then) and after; counters[LOGGED] entries. The call also returns
    (LIMIT) before a period for which the log might have no room.

    The trace (``counters[TRACE_EVERY]`` > 0): at the end of every period whose index is a multiple of it, each
    cell in the channel is appended: trace_step[m] (the period's index), trace_key[m], trace_positions[m] = (x, y);
    counters[TRACED] entries, kept across calls until the caller resets the count. The call returns (LIMIT) before
    a period whose rows might not fit. It releases the GIL: the plant's arrays are its own.
    """
    periods = 0
    counters[LOGGED] = 0
    capacity = log_key.shape[0]
    watching = stop_lines.shape[0] + record_lines.shape[0] > 0
    every = counters[TRACE_EVERY]
    while periods < max_periods:
        first = counters[FIRST]
        if watching and capacity - counters[LOGGED] < _due(arrival, counters, params[PERIOD]) - first:
            return periods, LIMIT           # no room to log a crossing of every cell that may be in the channel
        if every > 0 and (counters[STEP] + 1) % every == 0 and \
                trace_key.shape[0] - counters[TRACED] < _due(arrival, counters, params[PERIOD]) - first:
            return periods, LIMIT           # no room to trace every cell that may be in the channel then
        _period(fields, params, segments, dividers, outlets, semi_axes, start, kind, arrival, born, position, fate,
                exit_time, exit_y, stalled, counters, level_state, lags, actuation, before, touched)
        periods += 1
        if every > 0 and counters[STEP] % every == 0:
            for i in range(counters[FIRST], counters[NEXT]):
                if fate[i] == IN_CHANNEL:
                    m = counters[TRACED]
                    trace_step[m] = counters[STEP]
                    trace_key[m] = i
                    trace_positions[m, 0] = position[i, 0]
                    trace_positions[m, 1] = position[i, 1]
                    counters[TRACED] += 1
        stop = False
        if watching:
            for i in range(first, counters[NEXT]):
                if fate[i] != IN_CHANNEL:
                    continue
                stopping = _crosses(before[i, 0], position[i, 0], stop_lines)
                if stopping or _crosses(before[i, 0], position[i, 0], record_lines):
                    m = counters[LOGGED]
                    log_step[m] = counters[STEP]
                    log_key[m] = i
                    log_positions[m, 0] = before[i, 0]
                    log_positions[m, 1] = before[i, 1]
                    log_positions[m, 2] = position[i, 0]
                    log_positions[m, 3] = position[i, 1]
                    counters[LOGGED] += 1
                    stop = stop or stopping
        if stop:
            return periods, CROSSING
        if counters[STEP] * params[PERIOD] >= until:
            return periods, UNTIL
        if counters[NEXT] == arrival.shape[0] and counters[ACTIVE] == 0:
            return periods, DONE
    return periods, LIMIT
