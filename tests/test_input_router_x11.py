"""InputRouter for a captured application (source x11, ``color_only=True``).

The application gets raw input: the union of every viewer's held keys, relative
pointer motion from drags; and the controls it cannot honour (a method that needs
depth and motion, a scale change, frame generation) are refused with the reason.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

from server.game.input import InputMessage, InputReceiver
from server.session.input_router import InputRouter
from server.session.session_control import ControlResult

A, B = "game/input/a", "game/input/b"


def _wait(pred: object, timeout: float = 3.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():  # type: ignore[operator]
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def _router(tmp_path: Path) -> tuple[InputRouter, InputReceiver, list[InputMessage]]:
    got: list[InputMessage] = []
    receiver = InputReceiver(
        tmp_path / "game.sock", lambda message, seq: got.append(message), convert=lambda m: m
    )
    router = InputRouter(
        game_input=receiver.path,
        worker_control=None,
        request_keyframe=lambda: None,
        color_only=True,
    )
    return router, receiver, got


def test_the_application_gets_the_union_of_the_viewers_keys(tmp_path: Path) -> None:
    router, receiver, got = _router(tmp_path)
    try:
        router.handle(A, b'{"type":"keys","down":["arrowleft","Space"],"seq":1}')
        _wait(lambda: len(got) == 1)
        assert got[-1].keys_down == ["arrowleft", "space"] and got[-1].seq == 1
        router.handle(B, b'{"type":"keys","down":["x"],"seq":1}')
        _wait(lambda: len(got) == 2)
        assert got[-1].keys_down == ["arrowleft", "space", "x"]
        router.handle(A, b'{"type":"keys","down":[],"seq":2}')
        _wait(lambda: len(got) == 3)
        assert got[-1].keys_down == ["x"]
        router.forget(B)  # the viewer left: its keys are released
        _wait(lambda: len(got) == 4)
        assert got[-1].keys_down == []
        router.tick()  # no camera stepping for a captured application
        time.sleep(0.1)
        assert len(got) == 4
    finally:
        receiver.close()


def test_pointer_lock_motion_is_relative_and_drags_come_absolute(tmp_path: Path) -> None:
    router, receiver, got = _router(tmp_path)
    try:
        # A plain drag's look deltas also arrive as absolute pointer messages: not twice.
        router.handle(A, b'{"type":"look","dx":40,"dy":0,"seq":4}')
        router.handle(A, b'{"type":"look","dx":12.5,"dy":-3,"locked":true,"seq":5}')
        router.handle(A, b'{"type":"pointer","x":0.25,"y":1,"buttons":3,"seq":6}')
        _wait(lambda: len(got) == 2)
        time.sleep(0.05)
        assert len(got) == 2
        assert (got[0].pointer_dx, got[0].pointer_dy, got[0].seq) == (12.5, -3.0, 5)
        assert (got[1].pointer_x, got[1].pointer_y, got[1].buttons) == (0.25, 1.0, 3)
    finally:
        receiver.close()


def test_a_gamepad_holds_keys_with_the_keyboard(tmp_path: Path) -> None:
    router, receiver, got = _router(tmp_path)
    try:
        router.handle(A, b'{"type":"keys","down":["x"],"seq":1}')
        # standard map: button 0 -> space, left stick right -> arrowright
        router.handle(A, b'{"type":"gamepad","index":0,"buttons":[0],"axes":[0.9,0],"seq":2}')
        _wait(lambda: len(got) == 2)
        assert got[-1].keys_down == ["arrowright", "space", "x"]
        router.handle(A, b'{"type":"gamepad","index":0,"buttons":[],"axes":[0,0],"seq":3}')
        _wait(lambda: len(got) == 3)
        assert got[-1].keys_down == ["x"]
    finally:
        receiver.close()


def test_controls_the_source_cannot_honour_are_refused(tmp_path: Path) -> None:
    router, receiver, got = _router(tmp_path)
    results: list[ControlResult] = []
    router.on_control_result = results.append

    async def main() -> None:
        router.handle(A, b'{"type":"control","upscaler":"temporal","seq":1}')
        router.handle(A, b'{"type":"control","scale":3,"seq":2}')
        router.handle(A, b'{"type":"control","frame_generation":true,"seq":3}')
        router.handle(A, b'{"type":"control","frame_generation":false,"seq":4}')
        await asyncio.sleep(0)

    try:
        asyncio.run(main())
        by_seq = {r.seq: r for r in results}
        assert not by_seq[1].accepted and "needs depth, motion and jitter" in str(by_seq[1].reason)
        assert "easu_rcas" in str(by_seq[1].reason)
        assert not by_seq[2].accepted and "size the application draws at" in str(by_seq[2].reason)
        assert not by_seq[3].accepted and "frame_generation" in str(by_seq[3].reason)
        assert by_seq[4].accepted  # turning it off is what it is already
        time.sleep(0.1)
        assert all(m.render_scale is None for m in got)  # nothing refused reached the game
    finally:
        receiver.close()


def test_the_built_in_game_keeps_its_camera_keys(tmp_path: Path) -> None:
    """Without color_only, keys (and a gamepad's d-pad) move the camera, no raw key list
    is sent and pointer messages are not the camera's."""
    got: list[InputMessage] = []
    receiver = InputReceiver(
        tmp_path / "game.sock", lambda message, seq: got.append(message), convert=lambda m: m
    )
    router = InputRouter(
        game_input=receiver.path, worker_control=None, request_keyframe=lambda: None
    )
    try:
        router.handle(A, b'{"type":"keys","down":["w"],"seq":1}')
        _wait(lambda: len(got) == 1)
        assert got[0].forward > 0 and got[0].keys_down is None
        router.handle(A, b'{"type":"pointer","x":0.5,"y":0.5,"buttons":1,"seq":2}')
        router.handle(A, b'{"type":"keys","down":[],"seq":3}')
        router.handle(A, b'{"type":"gamepad","index":1,"buttons":[15],"axes":[],"seq":4}')
        _wait(lambda: len(got) == 2)
        assert got[1].right > 0 and got[1].forward == 0  # d-pad right: arrowright
    finally:
        receiver.close()
