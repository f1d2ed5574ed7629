"""InputInjector on a real Xvfb: what it fakes arrives at a window of ours."""

from __future__ import annotations

import logging
import os
import signal
import time
from collections.abc import Iterator
from typing import Any

import pytest
from Xlib import X

from server.game.x11.capture import DisplayGone
from server.game.x11.display import VirtualDisplay
from server.game.x11.inject import InputInjector
from server.game.x11.keys import NAMED_KEYS, keysym_of
from server.session.viewer_input import PAGE_KEYS
from tests.x11util import EventWindow

W, H = 200, 100


@pytest.fixture
def rig() -> Iterator[tuple[InputInjector, EventWindow]]:
    with VirtualDisplay.start(W, H) as display:
        window = EventWindow(display.name, W, H)
        injector = InputInjector(display.name, W, H)
        try:
            yield injector, window
        finally:
            injector.close()
            window.close()


def _keys(events: list[Any]) -> list[tuple[str, int]]:
    names = {X.KeyPress: "press", X.KeyRelease: "release"}
    return [(names[e.type], e.detail) for e in events if e.type in names]


def _buttons(events: list[Any]) -> list[tuple[str, int]]:
    names = {X.ButtonPress: "press", X.ButtonRelease: "release"}
    return [(names[e.type], e.detail) for e in events if e.type in names]


def test_keys_are_pressed_and_released_by_difference(
    rig: tuple[InputInjector, EventWindow],
) -> None:
    injector, window = rig
    a, shift, up = window.keycode("a"), window.keycode("Shift_L"), window.keycode("Up")
    injector.set_keys_down(["a", "shift"])
    assert sorted(_keys(window.events())) == sorted([("press", a), ("press", shift)])
    injector.set_keys_down(["a", "shift"])  # the same state again: nothing new
    assert _keys(window.events()) == []
    injector.set_keys_down(["a", "arrowup"])
    assert sorted(_keys(window.events())) == sorted([("release", shift), ("press", up)])
    injector.release_all()
    assert sorted(_keys(window.events())) == sorted([("release", a), ("release", up)])


def test_unknown_keys_are_ignored_and_logged_once(
    rig: tuple[InputInjector, EventWindow], caplog: pytest.LogCaptureFixture
) -> None:
    injector, window = rig
    caplog.set_level(logging.INFO, logger="server.game.x11.inject")
    injector.set_keys_down(["hyper-warp", "\x07", "space"])
    injector.set_keys_down(["hyper-warp", "space", "enter"])
    space, enter = window.keycode("space"), window.keycode("Return")
    assert _keys(window.events()) == [("press", space), ("press", enter)]
    assert sum("hyper-warp" in m for m in caplog.messages) == 1


def test_every_named_key_and_printable_character_has_a_keycode(
    rig: tuple[InputInjector, EventWindow],
) -> None:
    injector, _ = rig
    # Every name the page sends (server/session/viewer_input.py) presses a key.
    names = [*NAMED_KEYS, *PAGE_KEYS, *"abcdefghijklmnopqrstuvwxyz0123456789-=,./;'[]\\`"]
    missing = [n for n in names if injector.keycode(n) is None]
    assert missing == []
    assert keysym_of("arrowleft") != keysym_of("arrowright")


def test_pointer_moves_to_fractions_of_the_screen_clamped(
    rig: tuple[InputInjector, EventWindow],
) -> None:
    injector, window = rig
    root = window.display.screen().root
    for (x, y), expected in (
        ((0.5, 0.25), (100, 25)),
        ((0.0, 0.0), (0, 0)),
        ((1.0, 1.0), (W - 1, H - 1)),
        ((7.0, -3.0), (W - 1, 0)),
    ):
        injector.move_pointer_to(x, y)
        pointer = root.query_pointer()
        assert (pointer.root_x, pointer.root_y) == expected
    motions = [e for e in window.events() if e.type == X.MotionNotify]
    assert motions and (motions[-1].root_x, motions[-1].root_y) == (W - 1, 0)


def test_pointer_moves_by_pixels_keeping_fractions(
    rig: tuple[InputInjector, EventWindow],
) -> None:
    injector, window = rig
    root = window.display.screen().root
    injector.move_pointer_to(0.5, 0.5)
    injector.move_pointer_by(10, -5)
    pointer = root.query_pointer()
    assert (pointer.root_x, pointer.root_y) == (110, 45)
    for _ in range(4):  # four quarter pixels make one
        injector.move_pointer_by(0.25, 0)
    assert root.query_pointer().root_x == 111
    injector.move_pointer_by(-1000, 1000)  # the server keeps it on the screen
    pointer = root.query_pointer()
    assert (pointer.root_x, pointer.root_y) == (0, H - 1)


def test_buttons_follow_the_pointer_event_mask(rig: tuple[InputInjector, EventWindow]) -> None:
    injector, window = rig
    injector.move_pointer_to(0.5, 0.5)
    injector.set_buttons(1 | 2)  # primary and secondary: X buttons 1 and 3
    assert sorted(_buttons(window.events())) == [("press", 1), ("press", 3)]
    injector.set_buttons(4)  # middle only
    assert sorted(_buttons(window.events())) == [("press", 2), ("release", 1), ("release", 3)]
    injector.release_all()
    assert _buttons(window.events()) == [("release", 2)]
    injector.release_all()
    assert _buttons(window.events()) == []


def test_a_dead_server_raises_display_gone() -> None:
    display = VirtualDisplay.start(W, H)
    try:
        injector = InputInjector(display.name, W, H)
        injector.set_keys_down(["a"])
        os.kill(display.pid, signal.SIGKILL)
        while display.alive():
            time.sleep(0.01)
        with pytest.raises(DisplayGone):
            injector.set_keys_down(["b"])
            injector.move_pointer_to(0.1, 0.1)
        injector.close()  # must not raise either
    finally:
        display.close()
