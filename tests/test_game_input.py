"""The game's input socket: valid events reach the game, bad ones are refused."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import pytest
from pydantic import ValidationError

from server.game.input import InputMessage, InputReceiver, send_input
from server.game.render.camera import CameraInput


def _wait(pred: object, timeout: float = 3.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():  # type: ignore[operator]
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_events_arrive_in_order_and_garbage_is_refused(tmp_path: Path) -> None:
    got: list[CameraInput] = []
    receiver = InputReceiver(tmp_path / "in.sock", lambda event, _seq: got.append(event))
    try:
        send_input(receiver.path, InputMessage(dyaw_deg=5.0))
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        for junk in (b"not json", b'{"dyaw_deg": 1e9}', b'{"teleport": 1}', b"x" * 5000,
                     b'{"forward": NaN}'):  # fmt: skip
            sock.sendto(junk, str(receiver.path))
        sock.close()
        send_input(receiver.path, InputMessage(forward=1.5, right=-0.5))
        _wait(lambda: len(got) == 2 and receiver.refused == 5)
        assert got == [CameraInput(dyaw_deg=5.0), CameraInput(forward=1.5, right=-0.5)]
    finally:
        receiver.close()
    assert not (tmp_path / "in.sock").exists()


def test_input_bounds_are_enforced() -> None:
    with pytest.raises(ValidationError):
        InputMessage(dpitch_deg=500.0)
    with pytest.raises(ValidationError):
        InputMessage(up=float("inf"))
