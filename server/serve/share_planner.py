"""Moving CPU shares between a host's sessions to where CPU buys what nothing else can.

A session under ``--quality auto`` that misses its frame rate trades picture for rate on
its own: its controller steps the render scale, method and encoded size down. Once at its
cheapest setting (its ``at_floor``), or under ``--quality fixed``, it has nothing left to
trade, and only CPU time buys it frames. The planner gives such a session's cgroup more
weight; the sessions that can still trade keep theirs, so under contention the kernel
moves CPU time to the stuck one, and the others' controllers answer the CPU they lose with
a smaller picture at their full rate (the ``framerate`` preference: the rate is worth the
most). When a boosted session holds its rate again the boost decays back to its base, so
the host's other sessions get their picture back.

The weights stay relative: the base is ``shares_for`` (the target's cost), a boost
multiplies it by at most ``MAX_BOOST``; it grows each period the session misses, by what the
missing rate asks (``target / fps``) but at most ``STEP``, and decays by ``DECAY`` a period
once the session clearly holds (``CLEAR_FRACTION`` of its target) or can trade again. A
weight moves only when it changes by ``MIN_CHANGE`` or more, and no boost grows within
``STEADY_S`` of the session's (or its worker's) start. Sans-IO: the supervisor feeds it the
sessions' status every ``PERIOD_S`` and writes the weights it returns.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

PERIOD_S = 5.0
MAX_BOOST = 4.0
STEP = 1.5  # a boost grows by at most this factor a period
DECAY = 0.8  # a held session's boost shrinks by this factor a period
HOLD_FRACTION = 0.9  # the controller's bar: under it, a window misses the target
CLEAR_FRACTION = 0.97  # a boost decays only above this share of the target
MIN_CHANGE = 0.1
STEADY_S = 30.0  # no boost this soon after a (worker) start


@dataclass(frozen=True)
class ShareInput:
    """One running session as the planner sees it."""

    group: str  # its cgroup (the key of the result)
    label: str  # for the log: "session 2 (game2)"
    base: int  # shares_for its target
    boost: float  # the factor in place (1: none)
    up: bool  # streaming (a starting or stalled session is left as it is)
    fps: float | None  # published over the monitor's window
    target_fps: float
    can_trade: bool  # auto and not at its floor: it holds its rate with its picture
    # Seconds since its process started or its worker last restarted: a session short of
    # its rate while it starts is short of its worker, not of CPU, and a boost would only
    # hand its start-up (imports, kernels) the others' CPU.
    steady_s: float = math.inf


@dataclass(frozen=True)
class ShareChange:
    group: str
    boost: float
    shares: int
    reason: str


def _short_by(row: ShareInput) -> float | None:
    """target / fps for a session short of its rate with nothing left to trade, else None."""
    if not row.up or row.can_trade or row.fps is None or not math.isfinite(row.fps):
        return None
    if row.steady_s < STEADY_S:
        return None
    if row.target_fps <= 0 or row.fps >= HOLD_FRACTION * row.target_fps:
        return None
    return row.target_fps / max(row.fps, 1e-3)


def _holds(row: ShareInput) -> bool:
    """Clearly at its rate (a margin above the miss bar, so a boost that just brought it
    there is not taken away at once), or able to trade picture for rate again."""
    if row.can_trade:
        return True
    return (
        row.fps is not None
        and math.isfinite(row.fps)
        and row.fps >= CLEAR_FRACTION * row.target_fps
    )


def plan(rows: Iterable[ShareInput]) -> list[ShareChange]:
    """The weights to write this period (only those that move), each with its reason."""
    from server.ops.cpu_shares import MAX_SHARES, MIN_SHARES

    changes: list[ShareChange] = []
    for row in rows:
        if not row.up:
            continue
        short = _short_by(row)
        if row.steady_s < STEADY_S and row.boost > 1.0:
            boost = 1.0
            why = "(re)starting: back to its base weight until it runs steadily"
        elif short is not None:
            # Grows while it misses: what the weight buys depends on the others' weights.
            boost = min(MAX_BOOST, row.boost * min(STEP, short))
            why = (
                f"{row.fps:.1f} of {row.target_fps:g} fps at its lowest setting: "
                "only CPU buys it frames"
            )
        elif _holds(row) and row.boost > 1.0:
            boost = row.boost * DECAY
            boost = 1.0 if boost < 1.0 + MIN_CHANGE else boost
            why = "holds its rate again: its weight returns toward its base"
        else:
            continue
        if boost != 1.0 and abs(boost - row.boost) < MIN_CHANGE * row.boost:
            continue
        shares = max(MIN_SHARES, min(MAX_SHARES, round(row.base * boost)))
        changes.append(ShareChange(row.group, boost, shares, f"{row.label}: {why}"))
    return changes
