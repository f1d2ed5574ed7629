"""Admission in ``upcast serve``: no session starts while a running one is at its floor.

The verdicts (server/serve/admission.py) on rows like ``/sessions``', then the
supervisor's use of them with stand-in session processes whose status files the test
writes: sessions start in order, the next refused (or queued until the floor clears)
with the reason in ``/sessions``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import pytest

from server.serve.admission import CLEAR_S, SETTLE_S, Admission
from server.serve.supervisor import ServedSession, Supervisor
from server.stack.local import SessionConfig
from server.stream_config import StreamConfig


def row(name: str, **kw: Any) -> dict[str, Any]:
    base = {"broadcast": name, "state": "up", "quality": "auto", "quality_at_floor": False,
            "fps": 30.0, "target_fps": 30.0, "up_for_s": 60.0}  # fmt: skip
    return {**base, **kw}


def test_verdicts() -> None:
    refuse, queue, admit = Admission("refuse"), Admission("queue"), Admission("admit")
    floor = [row("game-1"), row("game-2", quality_at_floor=True, fps=14.2)]
    verdict = refuse.decide(floor, 0.0)
    assert verdict.action == "refuse"
    assert verdict.reason == (
        "the host cannot hold another session: game-2 publishes 14.2 of 30 fps at the "
        "cheapest setting it may run"
    )
    assert queue.decide(floor, 0.0).action == "queue"
    assert admit.decide(floor, 0.0).action == "start"
    # A session holding a frame rate its controller lowered holds less than it was asked.
    slowed = [row("game-1", frame_rate=30.0), row("game-2", frame_rate=15.0, fps=14.9)]
    verdict = refuse.decide(slowed, 0.0)
    assert verdict.action == "refuse"
    assert verdict.reason == (
        "the host cannot hold another session: game-2 runs at 15 of 30 fps: nothing cheaper "
        "held its target"
    )
    assert refuse.decide([row("game-1", frame_rate=30.0)], 0.0).action == "start"
    # A session that has not settled yet says nothing about the host: wait for it.
    assert refuse.decide([row("game-1", up_for_s=SETTLE_S - 1)], 0.0).action == "wait"
    assert refuse.decide([row("game-1", state="starting", up_for_s=None)], 0.0).action == "wait"
    # Fixed sessions report no floor: nobody waits for them, nobody is refused by them.
    fixed = [row("game-1", quality="fixed", quality_at_floor=None, up_for_s=0.0)]
    assert refuse.decide(fixed, 0.0).action == "start"
    assert refuse.decide([], 0.0).action == "start"
    # Garbage in a status row is "not known", never a crash.
    odd = [row("game-1", fps="x", target_fps=None, up_for_s=float("nan"), quality_at_floor=1)]
    assert refuse.decide(odd, 0.0).action == "wait"
    with pytest.raises(ValueError, match="admission must be one of"):
        Admission("maybe")  # type: ignore[arg-type]


class FakeProcess:
    """Stands in for a session process: alive until ended."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        return self.returncode


class Host:
    """A supervisor over stand-in sessions; the test writes their status files."""

    def __init__(self, tmp_path: Path, policy: str, quality: str = "auto", n: int = 3) -> None:
        self.sessions = [
            ServedSession(
                index=i,
                config=SessionConfig(),
                stream=StreamConfig(broadcast=f"game-{i}", quality=quality),
                metrics_port=0,
                status_path=tmp_path / f"session-{i}.json",
            )
            for i in range(1, n + 1)
        ]
        self.supervisor = Supervisor(
            self.sessions,
            relay_url="http://127.0.0.1:9/",
            admission=Admission(policy),  # type: ignore[arg-type]
        )
        self.started: list[int] = []
        self.supervisor._start = self._start  # type: ignore[method-assign]

    def _start(self, s: ServedSession) -> None:
        s.proc = FakeProcess(1000 + s.index)  # type: ignore[assignment]
        s.started_at = time.monotonic()
        self.started.append(s.index)

    def report(
        self, index: int, *, at_floor: bool, fps: float = 30.0, up_for: float = 60.0
    ) -> None:
        s = self.sessions[index - 1]
        s.started_at = time.monotonic() - up_for
        s.status_path.write_text(json.dumps({
            "state": "up", "updated": time.time(), "quality": s.stream.quality,
            "quality_at_floor": at_floor, "fps": fps, "frames": 100,
        }))  # fmt: skip

    def states(self) -> list[str]:
        return [r["state"] for r in self.supervisor.snapshot()]


def test_sessions_start_in_turn_and_the_next_is_refused_at_the_floor(tmp_path: Path) -> None:
    host = Host(tmp_path, "refuse")
    host.supervisor.start_all()
    assert host.started == [1] and host.states()[1:] == ["waiting", "waiting"]
    host.report(1, at_floor=False, up_for=SETTLE_S / 2)
    host.supervisor.check()
    assert host.started == [1]  # game-1 is still settling
    host.report(1, at_floor=False)
    host.supervisor.check()
    assert host.started == [1, 2]
    host.report(2, at_floor=True, fps=17.5)
    host.supervisor.check()
    assert host.started == [1, 2]
    rows = host.supervisor.snapshot()
    assert [r["state"] for r in rows] == ["up", "up", "refused"]
    assert "game-2 publishes 17.5 of" in rows[2]["admission_reason"]
    assert host.supervisor.all_up()  # every session it let start is up
    # Refused stays refused: the floor clearing later does not start it.
    host.report(2, at_floor=False)
    host.supervisor.check()
    assert host.started == [1, 2] and host.states()[2] == "refused"


def test_a_queued_session_starts_once_the_floor_has_cleared(tmp_path: Path) -> None:
    host = Host(tmp_path, "queue", n=2)
    host.supervisor.start_all()
    host.report(1, at_floor=True, fps=12.0)
    host.supervisor.check()
    assert host.states() == ["up", "queued"]
    host.report(1, at_floor=False)
    host.supervisor.check()
    assert host.started == [1]  # the floor must stay clear CLEAR_S first
    host.supervisor.admission._floor_clear_since = time.monotonic() - CLEAR_S - 0.1
    host.supervisor.check()
    assert host.started == [1, 2]
    assert host.supervisor.snapshot()[1]["admission_reason"] is None


def test_fixed_sessions_and_admit_start_without_waiting(tmp_path: Path) -> None:
    fixed = Host(tmp_path / "a", "refuse", quality="fixed")
    (tmp_path / "a").mkdir()
    fixed.supervisor.start_all()
    assert fixed.started == [1, 2, 3]
    admit = Host(tmp_path / "b", "admit")
    (tmp_path / "b").mkdir()
    admit.supervisor.start_all()
    assert admit.started == [1, 2, 3]
