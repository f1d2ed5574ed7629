"""X11Source on a real Xvfb: taps, clicks after a jump, keys a program ignores, a
window or screen that changes size mid-stream, each frame flagged COLOR_ONLY."""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest
from Xlib import X

from server.frames.frame import FrameFlags, Size
from server.game.input import InputMessage
from server.game.x11.source import MIN_TAP_S, X11Source
from tests.x11util import EventWindow, resize_screen

SIZE = Size(160, 90)


@pytest.fixture
def source() -> Iterator[tuple[X11Source, EventWindow]]:
    src = X11Source(SIZE, None)  # a screen and nothing on it but our window
    window = EventWindow(src.display, SIZE.width, SIZE.height)
    try:
        yield src, window
    finally:
        window.close()
        src.close()


INPUT = {X.KeyPress, X.KeyRelease, X.ButtonPress, X.ButtonRelease}


def kinds(events: list[object], of: set[int] = INPUT) -> list[int]:
    """The event types among ``of`` (not the MappingNotify and motion around them)."""
    return [e.type for e in events if e.type in of]  # type: ignore[attr-defined]


def test_frames_are_colour_only_and_the_first_resets(
    source: tuple[X11Source, EventWindow],
) -> None:
    src, _ = source
    first, second = src.render(0, 0.0), src.render(1, 0.1)
    assert first.meta.flags == FrameFlags.COLOR_ONLY | FrameFlags.RESET
    assert second.meta.flags == FrameFlags.COLOR_ONLY
    assert first.color.shape == (SIZE.height, SIZE.width, 3)


def test_a_tap_within_one_tick_is_held_until_a_tick_after_the_minimum(
    source: tuple[X11Source, EventWindow],
) -> None:
    src, window = source
    src.apply_input(InputMessage(keys_down=["a"]))
    src.apply_input(InputMessage(keys_down=[]))  # released at once, as a quick tap
    src.render(0, 0.0)  # the next tick, too early: still held
    assert kinds(window.events(settle_s=0.02)) == [X.KeyPress]
    time.sleep(MIN_TAP_S)
    src.render(1, 0.1)
    assert kinds(window.events()) == [X.KeyRelease]


def test_keys_a_program_ignores_or_nobody_knows_change_nothing_else(
    source: tuple[X11Source, EventWindow],
) -> None:
    src, window = source
    src.apply_input(InputMessage(keys_down=["nosuchkey", "f7"]))
    events = [e for e in window.events() if e.type in INPUT]  # type: ignore[attr-defined]
    assert kinds(events) == [X.KeyPress]
    assert events[0].detail == window.keycode("F7")  # type: ignore[attr-defined]
    src.render(0, 0.0)  # and the stream goes on


def test_a_click_with_a_jump_lands_a_tick_after_the_move(
    source: tuple[X11Source, EventWindow],
) -> None:
    src, window = source
    src.apply_input(InputMessage(pointer_x=0.25, pointer_y=0.5, buttons=1))
    moved = window.events()
    assert kinds(moved, INPUT | {X.MotionNotify}) == [X.MotionNotify]  # the move only
    src.render(0, 0.0)
    press = [e for e in window.events() if e.type == X.ButtonPress]  # type: ignore[attr-defined]
    assert len(press) == 1
    assert (press[0].event_x, press[0].event_y) == (40, 45)  # type: ignore[attr-defined]
    # Without a jump the release goes out at once (it was held long enough).
    time.sleep(MIN_TAP_S)
    src.apply_input(InputMessage(pointer_x=0.25, pointer_y=0.5, buttons=0))
    assert kinds(window.events()) == [X.ButtonRelease]


def test_a_window_or_screen_that_changes_size_keeps_the_stream(
    source: tuple[X11Source, EventWindow],
) -> None:
    src, window = source
    window.window.configure(width=50, height=30)
    window.display.sync()
    assert src.render(0, 0.0).color.shape == (SIZE.height, SIZE.width, 3)
    resize_screen(src.display, 120, 60)  # the program switched its mode: smaller screen
    frame = src.render(1, 0.1)
    assert frame.color.shape == (SIZE.height, SIZE.width, 3)
    assert not np.any(frame.color[60:, :, :]) and not np.any(frame.color[:, 120:, :])
