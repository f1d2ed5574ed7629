"""InputRouter: viewer messages reach the game socket, the worker control and the encoder."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

from server.game.input import InputReceiver
from server.game.render.camera import CameraInput
from server.session.input_router import InputRouter
from server.worker.control import ControlServer, SetUpscaler, parse_message


def _wait(pred: object, timeout: float = 3.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():  # type: ignore[operator]
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_inputs_reach_the_game_with_their_seq(tmp_path: Path) -> None:
    got: list[tuple[CameraInput, int]] = []
    scales: list[float] = []
    receiver = InputReceiver(
        tmp_path / "game.sock", lambda e, seq: got.append((e, seq)), on_scale=scales.append
    )
    keyframes: list[int] = []
    router = InputRouter(
        game_input=receiver.path,
        worker_control=None,
        request_keyframe=lambda: keyframes.append(1),
    )
    try:
        router.handle("game/input/a", b'{"type":"look","dx":10,"dy":0,"seq":1}')
        router.handle("game/input/a", b'{"type":"keys","down":["w"],"seq":2}')
        router.handle("game/input/a", b'{"type":"keyframe","seq":3}')
        router.handle("game/input/a", b'{"type":"control","scale":3,"seq":4}')
        router.handle("game/input/a", b"garbage")
        _wait(lambda: len(got) >= 3)
        look, move = got[0], got[1]
        assert look[1] == 1 and look[0].dyaw_deg < 0
        assert move[1] == 2 and move[0].forward > 0  # the press moves at once
        assert keyframes == [1]
        _wait(lambda: scales == [3.0])
        assert router.accepted == 4 and router.refused == 1
        router.tick()  # still held: keeps moving
        _wait(lambda: len(got) >= 4)
        router.forget("game/input/a")
        n = len(got)
        router.tick()
        time.sleep(0.1)
        assert len(got) == n  # released when the viewer left
    finally:
        receiver.close()


def test_upscaler_switch_goes_to_the_worker_and_unknown_names_do_not(tmp_path: Path) -> None:
    control = ControlServer(tmp_path / "worker.ctl")
    switched: list[str] = []

    async def scenario() -> list[SetUpscaler]:
        router = InputRouter(
            game_input=None,
            worker_control=control.path,
            request_keyframe=lambda: None,
            on_upscaler_set=switched.append,
        )
        router.handle("v", b'{"type":"control","upscaler":"no_such_method"}')
        router.handle("v", b'{"type":"control","upscaler":"bicubic"}')
        seen: list[SetUpscaler] = []
        deadline = time.monotonic() + 3
        while not seen and time.monotonic() < deadline:
            for data, addr in control.poll():
                msg = parse_message(data)
                assert isinstance(msg, SetUpscaler)
                seen.append(msg)
                control.reply(addr, {"ok": True, "upscaler": msg.name})
            await asyncio.sleep(0.01)
        for _ in range(100):
            if switched:
                break
            await asyncio.sleep(0.01)
        return seen

    try:
        seen = asyncio.run(scenario())
    finally:
        control.close()
    assert [m.name for m in seen] == ["bicubic"]
    assert switched == ["bicubic"]
