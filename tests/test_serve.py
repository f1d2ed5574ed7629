"""``upcast serve``: N sessions in their own processes; one failing leaves the others alone.

The slow tests run 4 small sessions (160x90 -> 320x180 at 15 fps, so 4 fit on
a 2-core CI machine next to the relay) and read each session's published
frame count from ``/sessions`` (the session counts the frames it hands to the
relay). A session's rate is frames over a window of several seconds.

Tolerance for "the others keep their rate": at least 85% of their rate before
the kill, over a window that contains the whole restart. A restart starts a
new Python interpreter that imports torch (about a core-second, twice that
for a whole session), on a machine with 2 cores shared by 4 sessions and the
relay; frame counts are read every 0.5 s (+-1 frame in ~100). A real stall
of a neighbour (shared state, a lock, a blocked relay) would show as a much
larger drop or zero.
"""

from __future__ import annotations

import asyncio
import io
import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from server.ops.cpu_shares import shares_for
from server.serve.config import ConfigFileError, load_overrides, session_configs
from server.serve.control_client import request_control
from server.session.session_control import SessionControl
from server.stack.local import SessionConfig, session_files
from server.stream_config import StreamConfig
from tests.serve_harness import ROOT, SMALL, Served, serve

CLI = [sys.executable, "-m", "server.cli"]
WINDOW_S = 8.0
FRAME_TAP_PORT = 5270  # session i's frame tap: 5270 + i - 1
TOLERANCE = 0.85


def _frames(served: Served) -> dict[str, tuple[float, int]]:
    """Each session's (time it counted, frames it published)."""
    return {r["broadcast"]: (r["frames_at"], int(r["frames"])) for r in served.sessions()}


def _rates(served: Served, window_s: float) -> dict[str, float]:
    """Frames per second each session published over the next ``window_s``."""
    f0 = _frames(served)
    time.sleep(window_s)
    f1 = _frames(served)
    return {
        b: (f1[b][1] - f0[b][1]) / (f1[b][0] - f0[b][0]) if f1[b][0] > f0[b][0] else 0.0
        for b in f0
        if b in f1
    }


# -- config --------------------------------------------------------------------------------


def test_config_errors_name_the_session_and_the_field(tmp_path: Path) -> None:
    path = tmp_path / "sessions.json"
    path.write_text(
        json.dumps(
            [{"scene": "default"}, {"render_size": "banana", "fsp": 30}, {"upscaler": "nope"}]
        )
    )
    with pytest.raises(ConfigFileError) as err:
        load_overrides(path)
    text = str(err.value)
    assert "session 2:" in text and "render_size" in text and "fsp" in text
    assert "session 3:" in text and "upscaler" in text
    assert "session 1:" not in text


def test_toml_overrides_apply_per_session(tmp_path: Path) -> None:
    path = tmp_path / "sessions.toml"
    path.write_text('[[sessions]]\nfps = 20\n\n[[sessions]]\nbroadcast = "arena"\nseed = 3\n')
    overrides = load_overrides(path)
    configs = session_configs(SessionConfig(), StreamConfig(), overrides, 3, "game")
    assert [s.broadcast for _, s in configs] == ["game-1", "arena", "game-3"]
    assert [c.fps for c, _ in configs] == [20, 60, 60]
    assert configs[1][0].seed == 3


def test_config_errors_across_sessions_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "sessions.json"
    entries = [{"render_size": "1920x1080"}, {"broadcast": "x"}, {"broadcast": "x"}]
    path.write_text(json.dumps({"sessions": entries}))
    with pytest.raises(ConfigFileError) as err:
        session_configs(SessionConfig(), StreamConfig(), load_overrides(path), 3, "game")
    assert "session 1:" in str(err.value) and "larger than display_size" in str(err.value)
    assert "broadcast names must differ between sessions: x" in str(err.value)
    with pytest.raises(ConfigFileError, match="6 sessions, --sessions 2"):
        session_configs(SessionConfig(), StreamConfig(), load_overrides(path) * 2, 2, "game")


def test_the_command_refuses_a_bad_config_file_at_start(tmp_path: Path) -> None:
    path = tmp_path / "bad.json"
    path.write_text(json.dumps([{}, {"fps": -1}]))
    done = subprocess.run(
        [*CLI, "serve", "--relay", "http://127.0.0.1:9/", "--config", str(path), "--port", "5220"],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2
    assert "session 2:" in done.stderr and "fps" in done.stderr


# -- four sessions --------------------------------------------------------------------------


def _by_broadcast(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    return {r["broadcast"]: r for r in rows}


def _assert_kept_rate(before: dict[str, float], after: dict[str, float], others: list[str]) -> None:
    print(f"fps before: {before}\nfps after:  {after}")  # shown with pytest -s / on failure
    for b in others:
        assert after[b] >= TOLERANCE * before[b], (
            f"{b} fell from {before[b]:.1f} to {after[b]:.1f} fps ({before=}, {after=})"
        )


@pytest.fixture(scope="module")
def four() -> Any:
    with serve(
        5230, "--sessions", "4", "--frame-tap-port", str(FRAME_TAP_PORT), *SMALL, up_timeout_s=180
    ) as served:
        yield served


@pytest.mark.slow
def test_four_sessions_publish_and_are_listed(four: Served) -> None:
    rows = four.sessions()
    assert [r["broadcast"] for r in rows] == ["game-1", "game-2", "game-3", "game-4"]
    assert len({r["pid"] for r in rows}) == 4 and len({r["worker_pid"] for r in rows}) == 4
    assert len({r["name"] for r in rows}) == 4
    assert len({r["metrics_port"] for r in rows}) == 4
    rates = _rates(four, 4.0)
    assert all(rate > 10 for rate in rates.values()), rates  # 15 fps target
    status, body = four.get("/metrics")
    assert status == 200 and body.count(b"upcast_serve_session_up{") == 4
    assert four.get("/healthz")[0] == 200
    assert four.get("/nope")[0] == 404
    # Each session in a cgroup of its own, weighted by its target (fps x display pixels),
    # where this host lets cgroups be written; else /sessions says why not.
    cpu = four.answer()["cpu_shares"]
    if cpu["enforced"]:
        again = four.sessions()
        # At its base weight, or moved by the share planner, which says why.
        base = shares_for(15.0, 320 * 180)
        assert all(r["cpu_shares"] >= base for r in again), again
        assert all(r["cpu_shares"] == base or r["cpu_shares_reason"] for r in again), again
        assert all((r["cpu_seconds"] or 0) > 0 for r in again), again
    else:
        assert cpu["reason"] and all(r["cpu_shares"] is None for r in rows)
    # Every process of a session has its own metrics: the session, then its game and worker.
    for row in rows:
        port = int(row["metrics_port"])
        for offset, metric in (
            (0, b"upcast_fps{"),
            (1, b"upcast_game_frames_rendered_total"),
            (2, b"upcast_worker_frames_upscaled_total"),
        ):
            with urllib.request.urlopen(f"http://127.0.0.1:{port + offset}/metrics") as r:
                assert metric in r.read(), (row["broadcast"], offset)


@pytest.mark.slow
def test_each_session_taps_its_own_encoded_frames(four: Served) -> None:
    """--frame-tap-port: session i answers its encoded frames' thumbnails on port + i - 1
    (what deploy/smoke.sh compares the browser's canvas with)."""
    for i in range(4):
        with urllib.request.urlopen(f"http://127.0.0.1:{FRAME_TAP_PORT + i}/frames") as r:
            summary = json.loads(r.read())
        assert summary["count"] > 1 and summary["factor"] == 4, summary
        first, last = (_tapped(FRAME_TAP_PORT + i, summary[end]) for end in ("first", "last"))
        assert last.shape == (180 // 4, 320 // 4, 3) and last.dtype == np.float32
        assert 5.0 < float(last.mean()) < 250.0  # a rendered scene, not black or blank
        assert not np.array_equal(first, last)  # the camera moves: frames by id, not one


def _tapped(port: int, frame_id: int) -> Any:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/frames/{frame_id}") as r:
        return np.load(io.BytesIO(r.read()), allow_pickle=False)


@pytest.mark.slow
def test_killing_one_worker_leaves_the_other_sessions_at_their_rate(four: Served) -> None:
    before = _rates(four, WINDOW_S)
    victim = _by_broadcast(four.sessions())["game-2"]
    os.kill(int(victim["worker_pid"]), signal.SIGKILL)
    after = _rates(four, WINDOW_S)  # the window holds the whole worker restart
    rows = four.wait(
        lambda rows: _by_broadcast(rows)["game-2"]["worker_restarts"] == 1,
        30,
        "the worker restart",
    )
    assert _by_broadcast(rows)["game-2"]["pid"] == victim["pid"]  # the session stayed
    _assert_kept_rate(before, after, ["game-1", "game-3", "game-4"])
    recovered = _rates(four, 4.0)
    assert recovered["game-2"] >= TOLERANCE * before["game-2"], (before, recovered)


@pytest.mark.slow
def test_killing_a_whole_session_restarts_it_and_nobody_else_notices(four: Served) -> None:
    before = _rates(four, WINDOW_S)
    victim = _by_broadcast(four.sessions())["game-3"]
    os.kill(int(victim["pid"]), signal.SIGKILL)
    after = _rates(four, WINDOW_S)
    rows = four.wait(
        lambda rows: (
            (r := _by_broadcast(rows)["game-3"])["restarts"] == 1
            and r["state"] == "up"
            and r["frames"] > 0
        ),
        90,
        "the session restart",
    )
    restarted = _by_broadcast(rows)["game-3"]
    assert restarted["pid"] != victim["pid"] and restarted["name"] != victim["name"]
    _assert_kept_rate(before, after, ["game-1", "game-2", "game-4"])
    # What the killed process left behind (its game, worker, rings, sockets) is gone.
    for pid in (victim["worker_pid"], victim["game_pid"]):
        assert not Path(f"/proc/{pid}").exists() or _is_zombie(int(pid))
    assert not [p for p in session_files(victim["name"]) if p.exists()]
    assert _rates(four, 4.0)["game-3"] > 10


@pytest.mark.slow
def test_a_restarted_relay_gets_every_session_back(four: Served) -> None:
    """Runs last in this module: every session loses its relay connection."""
    relay = four.answer()["relay"]
    os.kill(int(relay["pid"]), signal.SIGKILL)
    deadline = time.monotonic() + 60
    while four.answer()["relay"]["restarts"] != 1:
        assert time.monotonic() < deadline, "the relay was not restarted"
        time.sleep(0.5)
    # Every session publishes on the new relay again (it lists their broadcasts)...
    names = {row["broadcast"] for row in four.sessions()}
    while not names <= set(_relay_broadcasts(four)):
        assert time.monotonic() < deadline, "the sessions did not come back to the new relay"
        time.sleep(0.5)
    # ...and answers a control request there, which only a session publishing there can.
    for row in four.sessions():
        record = asyncio.run(
            request_control(
                four.player_url(row["broadcast"]),
                row["broadcast"],
                SessionControl(upscaler="bilinear"),
                timeout_s=30,
            )
        )
        assert record.last_control is not None and record.last_control.accepted, record


def _relay_broadcasts(served: Served) -> list[str]:
    try:
        url = f"http://127.0.0.1:{served.port}/stats"
        with urllib.request.urlopen(url, timeout=5) as r:
            broadcasts: list[str] = json.loads(r.read())["broadcasts"]
            return broadcasts
    except OSError:  # the new relay is not listening yet
        return []


def _is_zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ", 1)[1].startswith("Z")
    except OSError:
        return True
