"""Player input into the game process: JSON datagrams on a Unix socket.

Same transport as the worker's control socket (server/worker/control.py) for the same
reasons; the streaming layer forwards browser inputs here. A receiver thread
validates each datagram and queues it for the game loop, which applies queued
inputs at the start of the next frame.
"""

from __future__ import annotations

import logging
import socket
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from server.game.render.camera import CameraInput

log = logging.getLogger(__name__)

MAX_INPUT_BYTES = 1024
# Bounds on one event: a browser sending absurd deltas must not teleport the camera.
MAX_LOOK_DEG = 90.0
MAX_MOVE_M = 5.0
MAX_KEYS = 16
MAX_POINTER_PX = 10_000.0


class InputMessage(BaseModel):
    """One input event: look deltas in degrees, moves in metres (player's frame)."""

    model_config = ConfigDict(extra="forbid")

    dyaw_deg: float = Field(default=0.0, ge=-MAX_LOOK_DEG, le=MAX_LOOK_DEG, allow_inf_nan=False)
    dpitch_deg: float = Field(default=0.0, ge=-MAX_LOOK_DEG, le=MAX_LOOK_DEG, allow_inf_nan=False)
    forward: float = Field(default=0.0, ge=-MAX_MOVE_M, le=MAX_MOVE_M, allow_inf_nan=False)
    right: float = Field(default=0.0, ge=-MAX_MOVE_M, le=MAX_MOVE_M, allow_inf_nan=False)
    up: float = Field(default=0.0, ge=-MAX_MOVE_M, le=MAX_MOVE_M, allow_inf_nan=False)
    # The sender's sequence number; the game writes the last one it applied into
    # every frame header (input_seq) so clients can measure input-to-photon latency.
    seq: int = Field(default=0, ge=0, lt=1 << 62)
    # Render scale (display / render size) wanted from the next frame on; None: unchanged.
    render_scale: float | None = Field(default=None, ge=1.0, le=4.0, allow_inf_nan=False)
    # Camera jitter on/off from the next frame on (on only for temporal upscalers).
    jitter: bool | None = None
    # Frame generation on/off from the next frame on: the game renders every other
    # frame fully and draws only its moving objects on the others.
    frame_generation: bool | None = None
    # Frames per second the game renders (and the stream carries) from the next frame on;
    # game time keeps its pace (a tick advances it by 1 / this rate). None: unchanged.
    frame_rate: float | None = Field(default=None, ge=1.0, le=240.0, allow_inf_nan=False)
    # For sources that take raw input (a captured X11 application, server/game/x11):
    # the browser keys held now (KeyboardEvent.key lower-cased; None: unchanged), the
    # pointer's position as a fraction of the picture, relative pointer motion in
    # display pixels, and PointerEvent.buttons (1 primary, 2 secondary, 4 middle).
    # The built-in renderer reads the camera fields above instead.
    keys_down: list[Annotated[str, Field(max_length=16)]] | None = Field(
        default=None, max_length=MAX_KEYS
    )
    pointer_x: float | None = Field(default=None, ge=0.0, le=1.0, allow_inf_nan=False)
    pointer_y: float | None = Field(default=None, ge=0.0, le=1.0, allow_inf_nan=False)
    pointer_dx: float = Field(
        default=0.0, ge=-MAX_POINTER_PX, le=MAX_POINTER_PX, allow_inf_nan=False
    )
    pointer_dy: float = Field(
        default=0.0, ge=-MAX_POINTER_PX, le=MAX_POINTER_PX, allow_inf_nan=False
    )
    buttons: int | None = Field(default=None, ge=0, le=31)

    def to_event(self) -> CameraInput:
        return CameraInput(self.dyaw_deg, self.dpitch_deg, self.forward, self.right, self.up)


class InputReceiver:
    """Binds ``path`` and hands every valid event and its seq to ``sink`` from a daemon
    thread. The event is ``convert(message)``: the camera input by default; a source
    that takes raw keys and pointer (X11) asks for the message itself."""

    def __init__(
        self,
        path: Path,
        sink: Callable[[Any, int], None],
        on_scale: Callable[[float], None] | None = None,
        on_jitter: Callable[[bool], None] | None = None,
        on_frame_generation: Callable[[bool], None] | None = None,
        on_frame_rate: Callable[[float], None] | None = None,
        convert: Callable[[InputMessage], Any] = InputMessage.to_event,
    ) -> None:
        self.path = path
        self._convert = convert
        self.accepted = 0
        self.refused = 0
        path.unlink(missing_ok=True)
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.bind(str(path))
        self._sock.settimeout(0.2)
        self._sink = sink
        self._on_scale = on_scale
        self._on_jitter = on_jitter
        self._on_frame_generation = on_frame_generation
        self._on_frame_rate = on_frame_rate
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="game-input", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                data = self._sock.recv(MAX_INPUT_BYTES + 1)
            except TimeoutError:
                continue
            except OSError:
                return
            try:
                if len(data) > MAX_INPUT_BYTES:
                    raise ValueError(f"input datagram of {len(data)} bytes")
                message = InputMessage.model_validate_json(data)
            except (ValidationError, ValueError) as exc:
                self.refused += 1
                log.warning("input refused: %s", str(exc).splitlines()[0])
                continue
            self.accepted += 1
            if message.render_scale is not None and self._on_scale is not None:
                self._on_scale(message.render_scale)
            if message.jitter is not None and self._on_jitter is not None:
                self._on_jitter(message.jitter)
            if message.frame_generation is not None and self._on_frame_generation is not None:
                self._on_frame_generation(message.frame_generation)
            if message.frame_rate is not None and self._on_frame_rate is not None:
                self._on_frame_rate(message.frame_rate)
            self._sink(self._convert(message), message.seq)

    def close(self) -> None:
        self._stop.set()
        self._sock.close()
        self._thread.join(1.0)
        self.path.unlink(missing_ok=True)


def send_input(path: Path, message: InputMessage) -> None:
    """Fire-and-forget one input event to a game's input socket."""
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        sock.sendto(message.model_dump_json().encode(), str(path))
    finally:
        sock.close()
