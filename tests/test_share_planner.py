"""Moving CPU shares (server/serve/share_planner.py): a session stuck at its lowest
setting and short of its rate gets weight; it goes back once the session holds."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import pytest

from server.frames.frame import Size
from server.ops.cpu_shares import shares_for
from server.serve.share_planner import (
    CLEAR_FRACTION,
    MAX_BOOST,
    MIN_CHANGE,
    STEADY_S,
    STEP,
    ShareInput,
    plan,
)
from tests.test_admission import Host

ROW = ShareInput(
    group="session-1",
    label="session 1 (game-1)",
    base=1024,
    boost=1.0,
    up=True,
    fps=30.0,
    target_fps=30.0,
    can_trade=True,
)


def _step(row: ShareInput) -> ShareInput:
    """One period: the row with the planner's boost applied, if it moved."""
    changes = {c.group: c for c in plan([row])}
    change = changes.get(row.group)
    return row if change is None else replace(row, boost=change.boost)


def test_a_session_that_can_trade_or_holds_keeps_its_weight() -> None:
    assert plan([ROW]) == []
    assert plan([replace(ROW, fps=10.0)]) == []  # auto, not at its floor: it trades picture
    assert plan([replace(ROW, can_trade=False, fps=29.0)]) == []  # at its floor but holding


def test_a_stuck_session_gains_weight_step_by_step_up_to_the_cap() -> None:
    row = replace(ROW, can_trade=False, fps=10.0)  # at its floor, a third of its rate
    first = plan([row])
    assert len(first) == 1
    assert first[0].boost == pytest.approx(STEP) and first[0].shares == round(1024 * STEP)
    assert "10.0 of 30 fps" in first[0].reason and "session 1 (game-1)" in first[0].reason
    boosts = []
    for _ in range(10):
        row = _step(row)
        boosts.append(row.boost)
    assert boosts == sorted(boosts) and boosts[-1] == MAX_BOOST
    assert plan([row]) == []  # at the cap: nothing to write


def test_a_small_shortfall_grows_the_weight_by_what_it_asks() -> None:
    row = replace(ROW, can_trade=False, fps=25.0)  # 30 / 25 = 1.2, under STEP
    (change,) = plan([row])
    assert change.boost == pytest.approx(1.2)


def test_the_boost_decays_once_the_session_holds_with_a_margin() -> None:
    row = replace(ROW, can_trade=False, fps=10.0, boost=3.0)
    # Just over the miss bar, under the clear bar: kept (a boost that brought it there
    # is not taken at once).
    assert plan([replace(row, fps=0.93 * 30)]) == []
    held = replace(row, fps=CLEAR_FRACTION * 30)
    history = []
    for _ in range(20):
        held = _step(held)
        history.append(held.boost)
    assert history == sorted(history, reverse=True) and history[-1] == 1.0
    (back,) = plan([replace(row, boost=1.0 + MIN_CHANGE / 2, fps=30.0)])
    assert back.boost == 1.0 and back.shares == 1024
    # Able to trade again (its controller left the floor): decays too.
    (change,) = plan([replace(row, can_trade=True)])
    assert change.boost < 3.0


def test_sessions_not_up_or_without_a_rate_are_left_alone() -> None:
    stuck = replace(ROW, can_trade=False)
    assert plan([replace(stuck, up=False, fps=1.0)]) == []
    for fps in (None, math.nan, math.inf):
        assert plan([replace(stuck, fps=fps, boost=2.0)]) == [], fps
    assert plan([replace(stuck, fps=0.0)])[0].boost == STEP  # up and drawing nothing


def test_each_session_is_planned_on_its_own_figures() -> None:
    rows = [
        replace(ROW, group="a", can_trade=False, fps=12.0),
        replace(ROW, group="b", fps=12.0),
        replace(ROW, group="c", can_trade=False, fps=30.0, boost=2.0, base=4096),
    ]
    changes = {c.group: c for c in plan(rows)}
    assert set(changes) == {"a", "c"}
    assert changes["a"].boost == pytest.approx(STEP)
    assert changes["c"].shares == round(4096 * 2.0 * 0.8)


class FakeShares:
    """Stands in for the cgroups: records the weights written."""

    available = True

    def __init__(self) -> None:
        self.paths: list[Path] = []
        self.written: dict[str, int] = {}

    def place(self, session: str, pid: int, shares: int) -> bool:
        self.written[session] = shares
        return True

    def set_shares(self, session: str, shares: int) -> bool:
        self.written[session] = shares
        return True

    def shares(self, session: str) -> int | None:
        return self.written.get(session)

    def cpu_seconds(self, session: str) -> float | None:
        return None

    def close(self) -> None:
        pass


def test_the_supervisor_moves_a_stuck_sessions_weight_and_says_why(tmp_path: Path) -> None:
    host = Host(tmp_path, "admit", n=2)
    cpu = FakeShares()
    host.supervisor.cpu = cpu  # type: ignore[assignment]
    host.supervisor.start_all()
    host.supervisor.check()
    assert host.started == [1, 2]
    for s in host.sessions:  # long past their start (the stand-in start sets no time)
        s.steady_since = -math.inf
    target = host.sessions[1].config.fps
    host.report(1, at_floor=False, fps=target)
    host.report(2, at_floor=True, fps=12.0)
    host.supervisor._shares_at = -math.inf  # the period is due
    host.supervisor.check()
    groups = sorted(cpu.written)
    assert len(groups) == 1 and groups[0].endswith("2")  # only the stuck one moved
    rows = host.supervisor.snapshot()
    assert rows[0]["cpu_shares_reason"] is None
    config = host.sessions[1].config
    display = Size.parse(config.display_size)
    base = shares_for(config.fps, display.width * display.height)
    assert rows[1]["cpu_shares"] == round(base * STEP)
    assert f"12.0 of {config.fps:g} fps at its lowest setting" in rows[1]["cpu_shares_reason"]
    # Not again before the period is over.
    before = dict(cpu.written)
    host.supervisor.check()
    assert cpu.written == before
    # Its worker restarts: back to its base until it runs steadily again.
    host.report(2, at_floor=True, fps=0.0)
    status = json.loads(host.sessions[1].status_path.read_text())
    host.sessions[1].status_path.write_text(json.dumps({**status, "worker_restarts": 1}))
    host.supervisor._shares_at = -math.inf
    host.supervisor.check()
    rows = host.supervisor.snapshot()
    assert rows[1]["cpu_shares"] == base and "starting" in rows[1]["cpu_shares_reason"]


def test_no_boost_while_a_session_or_its_worker_starts() -> None:
    """Short of its rate because its worker restarts, not for CPU: a boost would hand its
    start-up the others' CPU. A boost in place goes back to the base."""
    starting = replace(ROW, can_trade=False, fps=3.0, steady_s=STEADY_S - 1)
    assert plan([starting]) == []
    (back,) = plan([replace(starting, boost=2.5)])
    assert back.boost == 1.0 and back.shares == 1024 and "starting" in back.reason
    assert plan([replace(starting, steady_s=STEADY_S)])[0].boost == STEP
