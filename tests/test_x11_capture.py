"""ScreenCapture on a real Xvfb: exact pixels, every grabber, a smaller screen, a dead server."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator

import numpy as np
import pytest

from server.game.x11 import capture as capture_module
from server.game.x11.capture import DisplayError, DisplayGone, ScreenCapture
from server.game.x11.display import VirtualDisplay
from server.game.x11.grabbers import DEFAULT_GRABBER, GRABBERS
from server.game.x11.pattern import card_rects, paint, render
from tests.x11util import resize_screen

W, H = 160, 90


@pytest.fixture(scope="module")
def screen() -> Iterator[VirtualDisplay]:
    with VirtualDisplay.start(W, H) as display:
        paint(display.name, card_rects(W, H))
        yield display


@pytest.mark.parametrize("grabber", list(GRABBERS))
def test_every_grabber_returns_the_exact_picture(screen: VirtualDisplay, grabber: str) -> None:
    capture = ScreenCapture(screen.name, W, H, grabber=grabber)
    try:
        out = np.zeros((H, W, 3), np.uint8)
        for _ in range(2):  # the second grab reuses the connection and buffers
            out[...] = 0
            capture.grab_into(out)
            np.testing.assert_array_equal(out, render(card_rects(W, H), W, H))
    finally:
        capture.close()


def test_the_default_is_mss_with_shared_memory() -> None:
    assert DEFAULT_GRABBER == "mss"


def test_writes_in_place_into_a_strided_view(screen: VirtualDisplay) -> None:
    big = np.full((H + 10, W + 20, 3), 77, np.uint8)
    view = big[5 : 5 + H, 10 : 10 + W]
    capture = ScreenCapture(screen.name, W, H)
    capture.grab_into(view)
    capture.close()
    np.testing.assert_array_equal(view, render(card_rects(W, H), W, H))
    assert (big[:5] == 77).all() and (big[:, :10] == 77).all()


def test_a_part_of_the_screen(screen: VirtualDisplay) -> None:
    capture = ScreenCapture(screen.name, W // 2, H // 3)
    out = np.zeros((H // 3, W // 2, 3), np.uint8)
    capture.grab_into(out)
    capture.close()
    np.testing.assert_array_equal(out, render(card_rects(W, H), W, H)[: H // 3, : W // 2])


def test_a_screen_smaller_than_the_capture_is_padded_with_black() -> None:
    with VirtualDisplay.start(W // 2, H // 2) as display:
        paint(display.name, [(0, 0, W // 2, H // 2, (9, 99, 199))])
        capture = ScreenCapture(display.name, W, H)
        out = np.full((H, W, 3), 255, np.uint8)
        capture.grab_into(out)
        capture.close()
    assert (out[: H // 2, : W // 2] == (9, 99, 199)).all()
    assert (out[H // 2 :] == 0).all() and (out[:, W // 2 :] == 0).all()


@pytest.mark.parametrize("grabber", ["mss", "xlib"])
def test_the_screen_shrinking_and_growing_back_under_the_capture(
    grabber: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(capture_module, "RECHECK_S", 0.0)
    with VirtualDisplay.start(W, H) as display:
        paint(display.name, [(0, 0, W, H, (200, 10, 20))])
        capture = ScreenCapture(display.name, W, H, grabber=grabber)
        out = np.zeros((H, W, 3), np.uint8)
        capture.grab_into(out)
        assert (out == (200, 10, 20)).all()

        resize_screen(display.name, W // 2, H // 2)
        out[...] = 255
        capture.grab_into(out)
        assert (out[H // 2 :] == 0).all() and (out[:, W // 2 :] == 0).all()

        resize_screen(display.name, W, H)
        paint(display.name, [(0, 0, W, H, (1, 2, 250))])
        capture.grab_into(out)
        assert (out == (1, 2, 250)).all()
        capture.close()


@pytest.mark.parametrize("grabber", list(GRABBERS))
def test_killing_the_server_raises_display_gone_within_a_second(grabber: str) -> None:
    display = VirtualDisplay.start(W, H)
    try:
        capture = ScreenCapture(display.name, W, H, grabber=grabber)
        out = np.zeros((H, W, 3), np.uint8)
        capture.grab_into(out)
        os.kill(display.pid, signal.SIGKILL)
        while display.alive():
            time.sleep(0.01)
        started = time.monotonic()
        with pytest.raises(DisplayGone):
            capture.grab_into(out)
        assert time.monotonic() - started < 1.0
        with pytest.raises(DisplayGone):  # and every call after
            capture.grab_into(out)
        capture.close()
    finally:
        display.close()


def test_a_display_that_does_not_exist() -> None:
    with pytest.raises(DisplayError, match="cannot open display :987"):
        ScreenCapture(":987", W, H)


def test_a_wrong_buffer_is_refused(screen: VirtualDisplay) -> None:
    capture = ScreenCapture(screen.name, W, H)
    with pytest.raises(ValueError, match="uint8 of shape"):
        capture.grab_into(np.zeros((H, W, 4), np.uint8))
    with pytest.raises(ValueError, match="uint8 of shape"):
        capture.grab_into(np.zeros((H, W, 3), np.float32))
    capture.close()
    with pytest.raises(ValueError, match="unknown grabber"):
        ScreenCapture(screen.name, W, H, grabber="nope")
