"""Pointer and gamepad messages from the page: every value in range parses, none out of it."""

from __future__ import annotations

import json

import pytest
from hypothesis import given
from hypothesis import strategies as st

from server.session.viewer_input import (
    MAX_GAMEPAD_AXES,
    MAX_GAMEPAD_BUTTONS,
    MAX_GAMEPADS,
    MAX_POINTER_BUTTONS,
    BadViewerMessage,
    GamepadMessage,
    KeysMessage,
    PointerMessage,
    parse_viewer_message,
)


def _parse(message: dict[str, object]) -> object:
    return parse_viewer_message(json.dumps(message).encode())


def test_the_pages_pointer_and_gamepad_messages_parse() -> None:
    # Exactly what client_web/src/input.ts sends (seq and sent_ms added by the publisher).
    pointer = parse_viewer_message(
        b'{"type":"pointer","x":0.25,"y":1,"buttons":3,"seq":7,"sent_ms":1700000000000.5}'
    )
    assert pointer == PointerMessage(
        type="pointer", x=0.25, y=1.0, buttons=3, seq=7, sent_ms=1700000000000.5
    )
    pad = parse_viewer_message(
        b'{"type":"gamepad","index":1,"buttons":[0,12],"axes":[-0.5,0,0,1],"seq":8}'
    )
    assert pad == GamepadMessage(
        type="gamepad", index=1, buttons=[0, 12], axes=[-0.5, 0, 0, 1], seq=8
    )
    released = _parse({"type": "gamepad", "index": 0, "buttons": [], "axes": []})
    assert isinstance(released, GamepadMessage) and released.buttons == [] == released.axes


unit = st.floats(0, 1, allow_nan=False)
axis = st.floats(-1, 1, allow_nan=False)


@given(x=unit, y=unit, buttons=st.integers(0, MAX_POINTER_BUTTONS))
def test_no_pointer_in_range_is_refused(x: float, y: float, buttons: int) -> None:
    message = _parse({"type": "pointer", "x": x, "y": y, "buttons": buttons})
    assert message == PointerMessage(type="pointer", x=x, y=y, buttons=buttons)


outside_unit = st.one_of(
    st.floats(max_value=0, exclude_max=True), st.floats(min_value=1, exclude_min=True)
)


@given(bad=outside_unit, coordinate=st.sampled_from(["x", "y"]))
def test_no_pointer_off_the_picture_is_accepted(bad: float, coordinate: str) -> None:
    message: dict[str, object] = {"type": "pointer", "x": 0.5, "y": 0.5, "buttons": 0}
    message[coordinate] = bad
    # json.dumps writes NaN/Infinity, which the JSON parser refuses too.
    with pytest.raises(BadViewerMessage, match=rf"input frame: pointer\.{coordinate}"):
        _parse(message)


@given(buttons=st.one_of(st.integers(max_value=-1), st.integers(min_value=MAX_POINTER_BUTTONS + 1)))
def test_no_pointer_button_mask_out_of_range_is_accepted(buttons: int) -> None:
    with pytest.raises(BadViewerMessage, match="buttons"):
        _parse({"type": "pointer", "x": 0, "y": 0, "buttons": buttons})


@pytest.mark.parametrize("buttons", [1.5, "1", True, None])
def test_pointer_buttons_are_a_json_integer(buttons: object) -> None:
    with pytest.raises(BadViewerMessage, match="buttons"):
        _parse({"type": "pointer", "x": 0, "y": 0, "buttons": buttons})


@given(
    index=st.integers(0, MAX_GAMEPADS - 1),
    buttons=st.lists(st.integers(0, MAX_GAMEPAD_BUTTONS - 1), max_size=MAX_GAMEPAD_BUTTONS),
    axes=st.lists(axis, max_size=MAX_GAMEPAD_AXES),
)
def test_no_gamepad_in_range_is_refused(index: int, buttons: list[int], axes: list[float]) -> None:
    message = _parse({"type": "gamepad", "index": index, "buttons": buttons, "axes": axes})
    assert message == GamepadMessage(type="gamepad", index=index, buttons=buttons, axes=axes)


bad_gamepads = st.one_of(
    st.builds(lambda i: {"index": i}, st.one_of(st.integers(max_value=-1), st.integers(4))),
    st.builds(
        lambda b: {"buttons": [0, b]},
        st.one_of(st.integers(max_value=-1), st.integers(MAX_GAMEPAD_BUTTONS)),
    ),
    st.builds(lambda n: {"buttons": [0] * n}, st.integers(MAX_GAMEPAD_BUTTONS + 1, 100)),
    st.builds(
        lambda a: {"axes": [0.0, a]},
        st.one_of(
            st.floats(max_value=-1, exclude_max=True), st.floats(min_value=1, exclude_min=True)
        ),
    ),
    st.builds(lambda n: {"axes": [0.0] * n}, st.integers(MAX_GAMEPAD_AXES + 1, 60)),
)


@given(change=bad_gamepads)
def test_no_gamepad_out_of_range_is_accepted(change: dict[str, object]) -> None:
    message: dict[str, object] = {"type": "gamepad", "index": 0, "buttons": [], "axes": []}
    message.update(change)
    (field,) = change
    with pytest.raises(BadViewerMessage, match=rf"input frame: gamepad\.{field}"):
        _parse(message)


@pytest.mark.parametrize(
    "message",
    [
        {"type": "pointer", "x": 0.5, "y": 0.5},
        {"type": "pointer", "x": 0.5, "buttons": 0},
        {"type": "gamepad", "index": 0, "buttons": []},
        {"type": "gamepad", "index": 0, "buttons": ["a"], "axes": []},
        {"type": "gamepad", "index": 0, "buttons": [], "axes": "0.5"},
    ],
)
def test_incomplete_or_mistyped_messages_are_refused(message: dict[str, object]) -> None:
    with pytest.raises(BadViewerMessage, match="input frame"):
        _parse(message)


def test_keys_messages_are_unchanged_by_the_wider_key_set() -> None:
    # The page now sends any game key; the server takes any short name, as before.
    keys = _parse({"type": "keys", "down": ["f11", "escape", "shift", "/", "space"]})
    assert isinstance(keys, KeysMessage) and keys.down[-1] == "space"


def test_nan_and_infinity_are_refused() -> None:
    for payload in (
        b'{"type":"pointer","x":NaN,"y":0,"buttons":0}',
        b'{"type":"pointer","x":0,"y":Infinity,"buttons":0}',
        b'{"type":"gamepad","index":0,"buttons":[],"axes":[NaN]}',
        b'{"type":"gamepad","index":0,"buttons":[],"axes":[-Infinity]}',
    ):
        with pytest.raises(BadViewerMessage, match="input frame"):
            parse_viewer_message(payload)
