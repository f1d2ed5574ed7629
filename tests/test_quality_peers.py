"""The arbiter between a host's sessions: who waits for cores, and the others hold."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from server.serve.admission import Admission
from server.session.quality.model import Setting
from server.session.quality.peers import (
    HOST_FILE_ENV,
    STALE_S,
    HostPeers,
    PeerRow,
    PeerWait,
    parse_peer_wait,
    write_host_file,
)
from tests.quality_sim import SimulatedHost
from tests.test_admission import Host
from tests.test_quality_controller import controller


def _file(rows: list[dict[str, object]], at: float = 1000.0) -> str:
    return json.dumps({"written_at": at, "sessions": rows})


def test_the_lowest_waiting_rate_of_the_others_is_read() -> None:
    text = _file([
        {"index": 1, "waiting_rate": 0.333, "cores_short": 0.2},  # our own: not a peer
        {"index": 2, "waiting_rate": 0.667, "cores_short": 0.1},
        {"index": 3, "waiting_rate": 0.5, "cores_short": 0.3},
        {"index": 5, "waiting_rate": 0.5, "cores_short": 0.25},  # as low, short of less
        {"index": 4, "waiting_rate": None, "cores_short": None},  # not waiting
    ])  # fmt: skip
    assert parse_peer_wait(text, own_index=1, now_wall=1001.0) == PeerWait(0.5, 0.25)
    assert parse_peer_wait(text, own_index=3, now_wall=1001.0) == PeerWait(0.333, 0.2)


@pytest.mark.parametrize(
    "text",
    [
        "",
        "{",
        "[]",
        json.dumps({"written_at": 1000.0}),
        json.dumps({"written_at": "soon", "sessions": []}),
        json.dumps({"written_at": 1000.0, "sessions": {"index": 2}}),
        _file([{"index": 2, "waiting_rate": True}]),
        _file([{"index": 2, "waiting_rate": float("nan")}]),
        _file([{"index": 2, "waiting_rate": 0.0}]),
        _file([{"index": 2, "waiting_rate": 1.5}]),
        _file([{"index": 2, "waiting_rate": "0.5"}]),
        _file([{"index": 2, "waiting_rate": 0.5, "cores_short": -0.1}]),
        _file([{"index": 2, "waiting_rate": 0.5, "cores_short": float("inf")}]),
        _file(["not a row", 7]),
        _file([{"index": 2, "waiting_rate": 0.5}], at=1000.0 - STALE_S - 1),  # stale
        _file([{"index": 2, "waiting_rate": 0.5}], at=1010.0),  # from the future
    ],
)
def test_a_malformed_or_stale_host_file_says_nothing(text: str) -> None:
    assert parse_peer_wait(text, own_index=1, now_wall=1000.0) is None


def test_written_then_read_through_the_environment(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "host.json"
    write_host_file(path, [PeerRow(1, None), PeerRow(2, 0.5, 0.2)])
    monkeypatch.setenv(HOST_FILE_ENV, str(path))
    monkeypatch.setenv(HOST_FILE_ENV + "_INDEX", "1")
    assert HostPeers.from_environment().waiting() == PeerWait(0.5, 0.2)
    monkeypatch.setenv(HOST_FILE_ENV + "_INDEX", "2")
    assert HostPeers.from_environment().waiting() is None
    monkeypatch.delenv(HOST_FILE_ENV)
    assert HostPeers.from_environment().waiting() is None  # a session on its own
    assert HostPeers(tmp_path / "gone.json", 1).waiting() is None


def test_the_supervisor_names_the_sessions_waiting_for_cores(tmp_path: Path) -> None:
    host = Host(tmp_path, "admit", n=3)
    host.supervisor.start_all()
    for i, (short, fraction) in enumerate([(None, 1.0), (0.3, 1 / 3), (0.1, 2 / 3)], 1):
        rate = fraction * host.sessions[i - 1].config.fps
        host.sessions[i - 1].status_path.write_text(json.dumps({
            "state": "up", "updated": time.time(), "quality": "auto", "fps": rate,
            "frame_rate": rate, "quality_cores_short": short,
        }))  # fmt: skip
    host.supervisor.check()
    text = host.supervisor.host_path.read_text()
    rows = {r["index"]: r["waiting_rate"] for r in json.loads(text)["sessions"]}
    assert rows == {1: None, 2: pytest.approx(1 / 3), 3: pytest.approx(2 / 3)}
    assert parse_peer_wait(text, 1, time.time()) == PeerWait(pytest.approx(1 / 3), 0.3)
    # A session that ended says nothing any more.
    host.sessions[1].proc.returncode = 1  # type: ignore[union-attr]
    host.supervisor.admission = Admission("admit")
    host.supervisor._tell_peers()
    rows = {r["index"] for r in json.loads(host.supervisor.host_path.read_text())["sessions"]}
    assert rows == {1, 3}


def _mean_fps(host: SimulatedHost, i: int, start: float, end: float) -> float:
    values = host.fps_between(i, start, end)
    return sum(values) / len(values)


def test_a_session_waiting_below_its_rate_gets_the_cores_another_holds() -> None:
    """Session 0 holds 30 fps on a picture above its cheapest; session 1 runs at 10 fps and
    could run faster with a few more cores. Alone, each controller keeps what it has;
    told of the other (as under serve), session 0 steps its picture down for it, and
    session 1's rate comes up."""

    def run(peers: bool) -> SimulatedHost:
        holder = controller()
        waiter = controller(Setting("bilinear", 2.667, rate=1 / 3))
        host = SimulatedHost(cores=1.3, controllers=[holder, waiter], peers=peers)
        host.run(60.0)
        return host

    alone = run(False)
    assert alone.controllers[1].setting.rate == pytest.approx(1 / 3), alone.log
    assert alone.controllers[1].state.waiting_for_cores
    assert (alone.controllers[1].state.cores_short or 0.0) > 0
    told = run(True)
    assert told.controllers[1].setting.rate >= 2 / 3 - 1e-6, told.log
    assert _mean_fps(told, 1, 30.0, 60.0) >= 0.9 * 20.0, told.log
    # The holder kept its own rate; it paid in picture, by stepping down.
    assert _mean_fps(told, 0, 30.0, 60.0) >= 0.9 * 30.0, told.log
    assert told.controllers[0].setting.rate == 1.0
    yields = [line for _, i, line in told.log if i == 0 and "waits for cores" in line]
    assert yields and all(line.startswith("quality down") for line in yields), told.log
    # The promise: while a session waits at a lower rate, no other steps up.
    waiting_at = {t for t, w in told.waiting if w[1]}
    ups = [t for t, i, line in told.log if i == 0 and line.startswith("quality up")]
    assert not waiting_at.intersection(ups), told.log


def test_nobody_gives_its_picture_for_a_claim_it_cannot_meet() -> None:
    """The session at 20 fps would need more cores than all the other's picture steps
    could free: the other keeps its picture (and may still step up into idle cores)."""

    def run(peers: bool) -> SimulatedHost:
        low = controller(Setting("bilinear", 2.667, rate=1 / 3))
        high = controller(Setting("bilinear", 2.667, rate=2 / 3))
        host = SimulatedHost(cores=1.5, controllers=[low, high], peers=peers)
        host.run(40.0)
        return host

    told, alone = run(True), run(False)
    assert told.controllers[0].state.waiting_for_cores, told.log
    assert not [line for _, _, line in told.log if "waits for cores" in line], told.log
    assert told.controllers[1].setting == alone.controllers[1].setting


def test_with_no_picture_left_to_give_a_session_meets_the_waiting_one_half_way() -> None:
    """Both at their cheapest picture, one at 30 fps and one at 15 that could run faster:
    the first steps down one rate (never below the other's), and both run 20 fps."""

    def run(peers: bool) -> SimulatedHost:
        cheapest = Setting("bilinear", 4.0, True, 3.0)
        first = controller(cheapest)
        second = controller(Setting("bilinear", 4.0, True, 3.0, rate=0.5))
        host = SimulatedHost(cores=0.9, controllers=[first, second], peers=peers)
        host.run(60.0)
        return host

    alone = run(False)
    assert [c.setting.rate for c in alone.controllers] == [1.0, 0.5], alone.log
    told = run(True)
    assert [c.setting.rate for c in told.controllers] == [pytest.approx(2 / 3)] * 2, told.log
    for i in (0, 1):
        assert _mean_fps(told, i, 30.0, 60.0) >= 0.9 * 20.0, told.log
    yields = [line for _, i, line in told.log if "waits for cores" in line]
    assert len(yields) == 1 and "at 20 fps" in yields[0], told.log
