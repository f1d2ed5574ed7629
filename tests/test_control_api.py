"""The control API: every control request gets exactly one result, on the status track.

Unit tests drive InputRouter and GameBroadcast directly; the slow test runs a
served session and ``upcast control`` against it over a real relay.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from server.moq import events as ev
from server.serve.control_client import request_control
from server.serve.control_schema import DEFAULT_PATH, render
from server.session.input_router import InputRouter
from server.session.session_control import ControlResult, StatusRecord
from server.worker.control import ControlServer, SetCachePolicy, SetUpscaler, parse_message
from tests.moq_pipe import Pipe
from tests.serve_harness import ROOT, SMALL, serve
from tests.test_session_broadcast import Harness


def _router(results: list[ControlResult], worker: Path | None = None) -> InputRouter:
    return InputRouter(
        game_input=None,
        worker_control=worker,
        request_keyframe=lambda: None,
        on_control_result=results.append,
    )


def test_the_committed_schema_is_current() -> None:
    assert DEFAULT_PATH.read_text() == render(), (
        "docs/control.schema.json is stale: run python -m server.serve.control_schema"
    )
    schema = json.loads(render())
    assert {"ControlMessage", "StatusRecord", "ControlResult"} <= set(schema["$defs"])


def test_refusals_say_why_and_carry_the_seq() -> None:
    results: list[ControlResult] = []
    router = _router(results, worker=Path("/nonexistent.ctl"))
    router.handle("g/input/a", b'{"type":"control","upscaler":"no_such","seq":7}')
    router.handle("g/input/a", b'{"type":"control","cache_policy":"reuse","seq":8}')
    # One part refused refuses the whole request: the switch is not applied either.
    router.handle(
        "g/input/a", b'{"type":"control","upscaler":"bicubic","cache_policy":"budget","seq":9}'
    )
    router.handle("g/input/a", b'{"type":"control","scale":99,"seq":10}')  # out of range
    router.handle("g/input/a", b'{"type":"control","seq":11}')  # asks for nothing
    router.handle("g/input/a", b'{"type":"look","dx":"x","seq":12}')  # not control: no result
    assert [(r.seq, r.accepted) for r in results] == [(n, False) for n in (7, 8, 9, 10, 11)]
    reasons = [r.reason or "" for r in results]
    assert "unknown 'no_such'" in reasons[0] and "bilinear" in reasons[0]
    assert "unknown cache policy 'reuse'" in reasons[1] and "budget" in reasons[1]
    assert reasons[2] == "cache_policy: upscaler 'bicubic' has no layer cache"
    assert "scale" in reasons[3]
    assert "empty control request" in reasons[4]
    assert all(r.source == "g/input/a" for r in results)


def test_scale_alone_is_accepted_at_once() -> None:
    results: list[ControlResult] = []
    scales: list[float] = []
    router = _router(results)
    router.on_scale_request = scales.append
    router.handle("g/input/a", b'{"type":"control","scale":1.5,"seq":3}')
    assert scales == [1.5]
    assert [(r.seq, r.accepted, r.requested) for r in results] == [(3, True, {"scale": 1.5})]


def test_encode_scale_reaches_the_encoder_and_is_refused_where_the_size_is_fixed() -> None:
    results: list[ControlResult] = []
    router = _router(results)
    # A router without the session's encoder hook (no size to change) says so.
    router.handle("g/input/a", b'{"type":"control","encode_scale":2,"seq":1}')
    scales: list[float] = []
    router.on_encode_scale = scales.append
    router.handle("g/input/a", b'{"type":"control","encode_scale":2,"seq":2}')
    router.handle("g/input/a", b'{"type":"control","encode_scale":0.5,"seq":3}')  # upscaling
    router.handle("g/input/a", b'{"type":"control","encode_scale":"NaN","seq":4}')
    assert scales == [2.0]
    assert [(r.seq, r.accepted) for r in results] == [(1, False), (2, True), (3, False), (4, False)]
    assert results[0].reason == "encode_scale: this session's encoder size is fixed"
    assert results[1].requested == {"encode_scale": 2.0}
    assert all("encode_scale" in (r.reason or "") for r in results[2:])
    # The session's own choice (adaptive quality) takes the same path.
    assert router.apply_setting("quality-auto", encode_scale=1.5) is not None
    assert scales == [2.0, 1.5] and results[-1].source == "quality-auto"


def test_frame_generation_goes_to_the_game_and_into_the_stream_state(tmp_path: Path) -> None:
    import socket

    game = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    game.bind(str(tmp_path / "game.input"))
    game.settimeout(2.0)
    results: list[ControlResult] = []
    switched: list[bool] = []
    router = InputRouter(
        game_input=tmp_path / "game.input",
        worker_control=None,
        request_keyframe=lambda: None,
        on_frame_generation=switched.append,
        on_control_result=results.append,
    )
    try:
        router.handle("g/input/a", b'{"type":"control","frame_generation":true,"seq":5}')
        router.handle("g/input/a", b'{"type":"control","frame_generation":false,"seq":6}')
        sent = [json.loads(game.recv(1024)) for _ in range(2)]
    finally:
        game.close()
    assert [m["frame_generation"] for m in sent] == [True, False]
    assert [m["seq"] for m in sent] == [5, 6]
    assert switched == [True, False]
    assert [(r.seq, r.accepted) for r in results] == [(5, True), (6, True)]


def test_an_upscaler_switch_is_accepted_only_when_the_worker_says_so(tmp_path: Path) -> None:
    control = ControlServer(tmp_path / "worker.ctl")
    results: list[ControlResult] = []

    async def scenario() -> None:
        router = _router(results, worker=control.path)
        router.handle("g/input/a", b'{"type":"control","upscaler":"bicubic","seq":1}')
        router.handle("g/input/a", b'{"type":"control","upscaler":"lanczos2","seq":2}')
        deadline = time.monotonic() + 5
        while len(results) < 2 and time.monotonic() < deadline:
            for data, addr in control.poll():
                msg = parse_message(data)
                assert isinstance(msg, SetUpscaler)
                ok = msg.name == "bicubic"  # the worker refuses the other one
                control.reply(addr, {"ok": ok, "error": None if ok else "out of memory"})
            await asyncio.sleep(0.01)

    try:
        asyncio.run(scenario())
    finally:
        control.close()
    by_seq = {r.seq: r for r in results}
    assert by_seq[1].accepted and by_seq[1].reason is None
    assert not by_seq[2].accepted and "out of memory" in (by_seq[2].reason or "")


def _status(seq: int) -> bytes:
    return (
        StatusRecord(broadcast="game", upscaler="bilinear", scale=2.0, fps=seq, frames=seq)
        .model_dump_json()
        .encode()
    )


def test_status_track_gives_a_late_subscriber_the_current_state() -> None:
    h = Harness()
    h.broadcast.set_status(_status(1))
    h.broadcast.set_status(_status(2))
    sub = h.pipe.server.subscribe("game", "status")
    h.sync()
    assert h.frames(sub) == [(1, _status(2))]  # only the current state, as group 1
    h.broadcast.set_status(_status(3))
    h.sync()
    assert h.frames(sub)[-1] == (2, _status(3))  # a change is a new group
    assert isinstance(h.pipe, Pipe)
    refused = [e for e in h.relay_events if isinstance(e, ev.SubscribeClosed)]
    assert not refused


def _control(relay: str, *args: str) -> subprocess.CompletedProcess[str]:
    cli = [sys.executable, "-m", "server.cli", "control"]
    return subprocess.run(
        [*cli, "--relay", relay, "--broadcast", "ctl-1", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
    )


@pytest.mark.slow
def test_upcast_control_switches_a_served_session_and_reports_refusals() -> None:
    with serve(5210, "--sessions", "1", "--broadcast-prefix", "ctl", *SMALL) as served:
        token = ["--token", served.player_token("ctl-1")]
        # Without a token the relay refuses the request's input broadcast: nothing changes.
        anonymous = _control(served.relay_url, "--upscaler", "bicubic", "--timeout", "5")
        assert anonymous.returncode == 1
        assert served.sessions()[0]["upscaler"] == "bilinear"

        done = _control(served.relay_url, "--upscaler", "bicubic", *token)
        assert done.returncode == 0, done.stderr
        record = StatusRecord.model_validate_json(done.stdout)
        assert record.upscaler == "bicubic"
        assert record.last_control is not None and record.last_control.accepted
        served.wait(lambda rows: rows[0]["upscaler"] == "bicubic", 10, "/sessions to follow")

        refused = _control(served.relay_url, "--upscaler", "no_such_method", *token)
        assert refused.returncode == 1
        record = StatusRecord.model_validate_json(refused.stdout)
        assert record.upscaler == "bicubic"  # unchanged
        assert record.last_control is not None and not record.last_control.accepted
        assert "unknown 'no_such_method'" in (record.last_control.reason or "")
        assert "refused" in refused.stderr

        scaled = _control(served.relay_url, "--scale", "2", *token)
        assert scaled.returncode == 0, scaled.stderr  # scale alone: applied by the game

        # A request the CLI would not send (out of range) is refused by the session itself.
        record = asyncio.run(request_control(served.player_url("ctl-1"), "ctl-1", {"scale": 99}))
        assert record.last_control is not None and not record.last_control.accepted
        assert "scale" in (record.last_control.reason or "")


def test_a_cache_policy_follows_the_switch_and_reaches_the_stream_state(tmp_path: Path) -> None:
    control = ControlServer(tmp_path / "worker.ctl")
    results: list[ControlResult] = []
    seen: list[tuple[str, object]] = []
    policies: list[str | None] = []

    async def scenario() -> None:
        router = _router(results, worker=control.path)
        router.on_cache_policy = policies.append
        router.handle(
            "g/input/a",
            b'{"type":"control","upscaler":"unet_cached","cache_policy":"budget@43","seq":1}',
        )
        router.handle("g/input/a", b'{"type":"control","cache_policy":"every_2","seq":2}')
        deadline = time.monotonic() + 5
        while len(results) < 2 and time.monotonic() < deadline:
            for data, addr in control.poll():
                msg = parse_message(data)
                if isinstance(msg, SetUpscaler):
                    seen.append(("upscaler", msg.name))
                    control.reply(addr, {"ok": True, "cache_policy": "delta_l"})
                elif isinstance(msg, SetCachePolicy):
                    seen.append(("policy", msg.policy))
                    ok = msg.policy == "budget@43"  # the worker refuses the other one
                    control.reply(
                        addr,
                        {"ok": True, "cache_policy": msg.policy}
                        if ok
                        else {"ok": False, "error": "upscaler 'bicubic' has no layer cache"},
                    )
            await asyncio.sleep(0.01)

    try:
        asyncio.run(scenario())
    finally:
        control.close()
    # The switch goes first, then the policy: the new method runs it from its first frame.
    assert seen[:2] == [("upscaler", "unet_cached"), ("policy", "budget@43")]
    by_seq = {r.seq: r for r in results}
    assert by_seq[1].accepted and by_seq[1].requested["cache_policy"] == "budget@43"
    assert not by_seq[2].accepted and "no layer cache" in (by_seq[2].reason or "")
    assert policies == ["delta_l", "budget@43"]  # what the worker reported, in order
