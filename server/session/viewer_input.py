"""What a browser sends on its ``input`` track, validated, and how it reaches the game.

The browser publishes its own broadcast (``<broadcast>/input/<id>``) with one
track, ``input``, whose frames are JSON objects with a ``type`` (see
``ViewerMessage``). Inputs ride MoQ rather than a side channel so they go
through any moq-lite relay a provider puts in front (issue 7's scale-out),
with the same authentication and limits as everything else.

Held keys are state, not events: the page sends the set of keys held when it
changes; ``HeldKeys`` turns that into one movement step per game frame, so the
camera moves at the same speed whatever the network does with the messages.
The pointer (absolute, with buttons) and gamepads are state too, for real
applications under X11: each message is the whole state, so a lost or late one
is corrected by the next.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from server.game.input import MAX_LOOK_DEG, InputMessage
from server.session.feedback import FeedbackFields
from server.session.session_control import SessionControl

MAX_MESSAGE_BYTES = 2048
LOOK_DEG_PER_PX = 0.2  # drag right by 5 px: turn right by 1 degree
MOVE_SPEED_M_S = 3.0
MAX_KEYS = 16
# PointerEvent.buttons, a bit mask: 1 primary, 2 secondary, 4 middle, 8 back, 16 forward.
MAX_POINTER_BUTTONS = 31
MAX_GAMEPADS = 4  # navigator.getGamepads() has 4 slots in Chromium and Firefox
MAX_GAMEPAD_BUTTONS = 32  # the standard layout has 17; room for odd pads, still bounded
MAX_GAMEPAD_AXES = 8  # standard: 4 (two sticks)

# Every key name the page sends (client_web/src/keys.ts, KeyboardEvent.key lower-cased,
# " " as "space"); a gamepad key map may only name these, so its keys take the same
# path to the application as the keyboard's.
PAGE_KEYS: frozenset[str] = frozenset(
    [*"abcdefghijklmnopqrstuvwxyz0123456789", *"-=[]\\;',./`"]
    + ["arrowup", "arrowdown", "arrowleft", "arrowright", "space", "enter", "escape"]
    + ["tab", "backspace", "shift", "control", "alt"]
    + [f"f{n}" for n in range(1, 13)]
)

# Browser key names (KeyboardEvent.key, lower-cased) -> (forward, right, up) direction.
KEY_DIRECTIONS: dict[str, tuple[float, float, float]] = {
    "w": (1, 0, 0), "arrowup": (1, 0, 0),
    "s": (-1, 0, 0), "arrowdown": (-1, 0, 0),
    "a": (0, -1, 0), "arrowleft": (0, -1, 0),
    "d": (0, 1, 0), "arrowright": (0, 1, 0),
    " ": (0, 0, 1), "space": (0, 0, 1),
    "c": (0, 0, -1),
}  # fmt: skip


class _Base(BaseModel):
    model_config = ConfigDict(extra="ignore")  # pages may add debug fields

    seq: int = Field(default=0, ge=0, lt=1 << 53)
    sent_ms: float | None = Field(default=None, allow_inf_nan=False)


class LookMessage(_Base):
    type: Literal["look"]
    dx: float = Field(ge=-10_000, le=10_000, allow_inf_nan=False)
    dy: float = Field(ge=-10_000, le=10_000, allow_inf_nan=False)
    # Sent under pointer lock; without it the drag also arrives as absolute `pointer`
    # messages, which a captured application takes instead.
    locked: bool = False


class KeysMessage(_Base):
    type: Literal["keys"]
    down: list[Annotated[str, Field(max_length=16)]] = Field(max_length=MAX_KEYS)


class ControlMessage(_Base, SessionControl):
    """A control request (server/session/session_control.py): its fields plus ``type``/``seq``."""

    type: Literal["control"]


class KeyframeMessage(_Base):
    type: Literal["keyframe"]


class FeedbackMessage(_Base, FeedbackFields):
    """What the viewer received lately (server/session/feedback.py)."""

    type: Literal["feedback"]


_Unit = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]
_Axis = Annotated[float, Field(ge=-1, le=1, allow_inf_nan=False)]
_ButtonIndex = Annotated[int, Field(strict=True, ge=0, lt=MAX_GAMEPAD_BUTTONS)]


class PointerMessage(_Base):
    """The pointer over the picture: x, y in 0..1 of the video picture (not the element:
    letterbox bars excluded), and the PointerEvent.buttons bit mask held."""

    type: Literal["pointer"]
    x: _Unit
    y: _Unit
    buttons: int = Field(strict=True, ge=0, le=MAX_POINTER_BUTTONS)


class GamepadMessage(_Base):
    """One gamepad's whole state (W3C Gamepad API): the indices of its pressed buttons
    and its axes (a dead zone already applied by the page)."""

    type: Literal["gamepad"]
    index: int = Field(strict=True, ge=0, lt=MAX_GAMEPADS)
    buttons: list[_ButtonIndex] = Field(max_length=MAX_GAMEPAD_BUTTONS)
    axes: list[_Axis] = Field(max_length=MAX_GAMEPAD_AXES)


ViewerMessage = Annotated[
    LookMessage
    | KeysMessage
    | ControlMessage
    | KeyframeMessage
    | PointerMessage
    | GamepadMessage
    | FeedbackMessage,
    Field(discriminator="type"),
]
_VIEWER_MESSAGE: TypeAdapter[ViewerMessage] = TypeAdapter(ViewerMessage)


class BadViewerMessage(ValueError):
    """A frame on an input track that is not a valid viewer message."""


def parse_viewer_message(payload: bytes) -> ViewerMessage:
    if len(payload) > MAX_MESSAGE_BYTES:
        raise BadViewerMessage(f"input frame of {len(payload)} bytes > {MAX_MESSAGE_BYTES}")
    try:
        return _VIEWER_MESSAGE.validate_json(payload)
    except ValidationError as exc:
        first = exc.errors(include_url=False)[0]
        where = ".".join(str(p) for p in first["loc"]) or "message"
        raise BadViewerMessage(f"bad input frame: {where}: {first['msg']}") from None


def look_input(message: LookMessage) -> InputMessage:
    """Mouse drag in pixels -> camera turn in degrees (drag right turns right)."""

    def clamp(v: float) -> float:
        return max(-MAX_LOOK_DEG, min(MAX_LOOK_DEG, v))

    return InputMessage(
        dyaw_deg=clamp(-message.dx * LOOK_DEG_PER_PX),
        dpitch_deg=clamp(-message.dy * LOOK_DEG_PER_PX),
        seq=message.seq,
    )


def _unit(v: float) -> float:
    return max(-1.0, min(1.0, v))


class HeldKeys:
    """The keys a viewer holds, turned into one movement step per game frame."""

    def __init__(self, speed_m_s: float = MOVE_SPEED_M_S) -> None:
        self.speed_m_s = speed_m_s
        self.direction = (0.0, 0.0, 0.0)
        self.seq = 0

    def update(self, message: KeysMessage) -> None:
        f = r = u = 0.0
        for key in message.down:
            df, dr, du = KEY_DIRECTIONS.get(key.lower(), (0, 0, 0))
            f, r, u = f + df, r + dr, u + du
        # Opposite keys cancel; two keys for one direction do not double the speed.
        self.direction = (_unit(f), _unit(r), _unit(u))
        self.seq = max(self.seq, message.seq)

    @property
    def moving(self) -> bool:
        return self.direction != (0.0, 0.0, 0.0)

    def step(self, dt_s: float) -> InputMessage | None:
        """The move for ``dt_s`` seconds of holding, or None when nothing is held."""
        if not self.moving:
            return None
        distance = self.speed_m_s * min(dt_s, 0.1)  # a stalled tick never teleports
        f, r, u = self.direction
        return InputMessage(forward=f * distance, right=r * distance, up=u * distance, seq=self.seq)
