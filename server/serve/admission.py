"""Admission for ``upcast serve``: start a session only while the host can carry it.

A session under adaptive quality says when the host cannot hold its frame rate even
at the cheapest setting it may run (its controller's ``at_floor``, in its status file:
server/session/quality/controller.py). While any running session says so, one more
session would only take frames from all of them, so the next one is refused (policy
``refuse``, the default: it is not started and ``/sessions`` says why) or queued
(``queue``: it starts once no session has been at its floor for ``CLEAR_S``, say after
another session ended). ``admit`` starts every session at once, as before. A session
whose controller lowered its frame rate below its target (nothing cheaper held it,
``frame_rate`` in its row) refuses the next one the same way: it holds a rate, but not
the one it was asked for.

A session's floor is known only after its controller has judged a few windows, so
under ``refuse`` and ``queue`` the sessions start one after the other: the next waits
until every running auto session has been up ``SETTLE_S`` (its warm-up and the first
steps down). Sessions that run ``--quality fixed`` report no floor: they are never
waited for and never refuse anyone (nothing would be known).

Sans-IO: the supervisor passes its rows (what ``/sessions`` shows) and the time.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

Policy = Literal["refuse", "queue", "admit"]
POLICIES: tuple[Policy, ...] = ("refuse", "queue", "admit")

# The controller's warm-up (5 s), two missed checks and a settle (2 s) after a step
# down, twice: what a session needs before its floor says anything.
SETTLE_S = 15.0
# A queued session starts after this long without any session at its floor.
CLEAR_S = 5.0


@dataclass(frozen=True)
class Verdict:
    action: Literal["start", "wait", "refuse", "queue"]
    reason: str


class Admission:
    def __init__(self, policy: Policy = "refuse") -> None:
        if policy not in POLICIES:
            raise ValueError(f"admission must be one of {', '.join(POLICIES)}, got {policy!r}")
        self.policy = policy
        self._floor_clear_since: float | None = None

    def decide(self, running: Sequence[Mapping[str, Any]], now: float) -> Verdict:
        """Whether the next session may start, given the running sessions' rows
        (``state``, ``quality``, ``quality_at_floor``, ``up_for_s``, ``fps``,
        ``target_fps``, ``frame_rate``, ``broadcast``) at ``now`` (monotonic seconds)."""
        if self.policy == "admit":
            return Verdict("start", "admission off")
        auto = [r for r in running if r.get("quality") == "auto"]
        up = [r for r in auto if r.get("state") == "up"]
        floor = [r for r in up if r.get("quality_at_floor") is True]
        slowed = [r for r in up if _lowered_rate(r)]
        if floor or slowed:
            self._floor_clear_since = None
            r = (floor or slowed)[0]
            fps, target = _number(r.get("fps")), _number(r.get("target_fps"))
            if floor:
                what = f"publishes {fps:.1f} of {target:.0f} fps at the cheapest setting it may run"
            else:
                rate = _number(r.get("frame_rate"))
                what = f"runs at {rate:.3g} of {target:.0f} fps: nothing cheaper held its target"
            reason = f"the host cannot hold another session: {r.get('broadcast')} {what}"
            return Verdict("refuse" if self.policy == "refuse" else "queue", reason)
        settling = [r for r in auto if _number(r.get("up_for_s")) < SETTLE_S]  # not up: 0
        if settling:
            return Verdict("wait", f"{settling[0].get('broadcast')} is still settling")
        if self._floor_clear_since is None:
            self._floor_clear_since = now
        # A queued session waits out CLEAR_S without a floor; a first verdict need not.
        return Verdict("start", "no session is at its floor")

    def queue_may_start(self, now: float) -> bool:
        """A queued session starts only after CLEAR_S without any session at its floor."""
        since = self._floor_clear_since
        return since is not None and now - since >= CLEAR_S


def _lowered_rate(row: Mapping[str, Any]) -> bool:
    """The session runs below its target frame rate (its controller lowered it)."""
    rate, target = _number(row.get("frame_rate")), _number(row.get("target_fps"))
    return 0.0 < rate < target - 1e-6


def _number(value: object) -> float:
    """A row's number; 0 for a missing or malformed one (a session not reporting yet)."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        return 0.0
    return float(value)
