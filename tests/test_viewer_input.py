"""Browser input frames: validation, mapping to game inputs, held keys."""

from __future__ import annotations

import pytest

from server.session.viewer_input import (
    MAX_MESSAGE_BYTES,
    BadViewerMessage,
    ControlMessage,
    HeldKeys,
    KeyframeMessage,
    KeysMessage,
    LookMessage,
    look_input,
    parse_viewer_message,
)


def test_each_message_type_parses() -> None:
    assert isinstance(parse_viewer_message(b'{"type":"look","dx":5,"dy":-2,"seq":3}'), LookMessage)
    keys = parse_viewer_message(b'{"type":"keys","down":["w","ArrowLeft"],"seq":4,"sent_ms":1.5}')
    assert isinstance(keys, KeysMessage) and keys.down == ["w", "ArrowLeft"]
    ctl = parse_viewer_message(b'{"type":"control","upscaler":"easu"}')
    assert isinstance(ctl, ControlMessage) and ctl.upscaler == "easu" and ctl.scale is None
    assert isinstance(parse_viewer_message(b'{"type":"keyframe"}'), KeyframeMessage)


@pytest.mark.parametrize(
    "payload",
    [
        b"not json",
        b"[]",
        b'{"type":"teleport"}',
        b'{"type":"look","dx":NaN,"dy":0}',
        b'{"type":"look","dx":1e9,"dy":0}',
        b'{"type":"keys","down":["' + b"w" * 40 + b'"]}',
        b'{"type":"keys","down":' + str(["w"] * 40).replace("'", '"').encode() + b"}",
        b'{"type":"control","scale":9}',
        b'{"type":"look","dx":1,"dy":1,"seq":-1}',
        b"{" + b" " * MAX_MESSAGE_BYTES + b"}",
        b"\xff\xfe",
    ],
)
def test_bad_frames_raise_one_clear_error(payload: bytes) -> None:
    with pytest.raises(BadViewerMessage, match="input frame"):
        parse_viewer_message(payload)


def test_look_turns_the_way_the_mouse_drags_and_is_bounded() -> None:
    right = look_input(LookMessage(type="look", dx=50, dy=0, seq=9))
    assert right.dyaw_deg < 0 and right.dpitch_deg == 0 and right.seq == 9
    huge = look_input(LookMessage(type="look", dx=9000, dy=-9000))
    assert huge.dyaw_deg == -90 and huge.dpitch_deg == 90


def test_held_keys_move_at_a_steady_speed_and_stop() -> None:
    held = HeldKeys(speed_m_s=3.0)
    assert held.step(1 / 60) is None
    held.update(KeysMessage(type="keys", down=["w", "d"], seq=5))
    move = held.step(1 / 60)
    assert move is not None and move.seq == 5
    assert move.forward == pytest.approx(0.05) and move.right == pytest.approx(0.05)
    stalled = held.step(5.0)  # a stalled tick is capped: never a teleport
    assert stalled is not None and stalled.forward == pytest.approx(0.3)
    held.update(KeysMessage(type="keys", down=["w", "s", "x"], seq=6))  # opposite keys cancel
    assert held.step(1 / 60) is None
    held.update(KeysMessage(type="keys", down=[], seq=7))
    assert not held.moving
