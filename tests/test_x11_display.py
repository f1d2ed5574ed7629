"""VirtualDisplay on a real Xvfb: start, environment, two at once, cleanup, errors."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
from Xlib import display as xdisplay

from server.game.x11.capture import ScreenCapture
from server.game.x11.display import SOCKET_DIR, DisplayError, VirtualDisplay
from server.game.x11.pattern import paint


def _socket(display: VirtualDisplay) -> Path:
    return SOCKET_DIR / f"X{display.number}"


def test_start_gives_a_connectable_screen_of_the_size_asked() -> None:
    with VirtualDisplay.start(320, 200) as display:
        assert display.alive()
        assert display.name == f":{display.number}"
        assert display.env({"HOME": "/x"}) == {"HOME": "/x", "DISPLAY": display.name}
        assert display.env()["DISPLAY"] == display.name
        conn = xdisplay.Display(display.name)
        try:
            screen = conn.screen()
            assert (screen.width_in_pixels, screen.height_in_pixels) == (320, 200)
            assert screen.root_depth == 24
            # OpenGL games need GLX; capture relies on MIT-SHM.
            assert conn.query_extension("GLX") is not None
            assert conn.query_extension("MIT-SHM") is not None
        finally:
            conn.close()
    assert not display.alive()


def test_two_displays_side_by_side_keep_their_own_pictures() -> None:
    with VirtualDisplay.start(64, 32) as a, VirtualDisplay.start(64, 32) as b:
        assert a.name != b.name
        paint(a.name, [(0, 0, 64, 32, (255, 0, 0))])
        paint(b.name, [(0, 0, 64, 32, (0, 0, 255))])
        for display, colour in ((a, (255, 0, 0)), (b, (0, 0, 255))):
            capture = ScreenCapture(display.name, 64, 32)
            out = np.zeros((32, 64, 3), np.uint8)
            capture.grab_into(out)
            capture.close()
            assert (out == colour).all()


def test_close_leaves_no_socket() -> None:
    display = VirtualDisplay.start(32, 32)
    socket = _socket(display)
    assert socket.exists()
    display.close()
    assert not socket.exists()
    assert not Path(f"/tmp/.X{display.number}-lock").exists()
    display.close()  # twice is harmless


def test_close_after_the_server_was_killed_removes_what_it_left() -> None:
    display = VirtualDisplay.start(32, 32)
    socket = _socket(display)
    os.kill(display.pid, signal.SIGKILL)
    deadline = time.monotonic() + 2
    while display.alive() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert not display.alive()
    assert socket.exists()  # SIGKILL gives Xvfb no chance to clean up
    display.close()
    assert not socket.exists()


def test_missing_xvfb_says_which_package(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PATH", "/nonexistent")
    with pytest.raises(DisplayError, match="Xvfb not found: install Debian's package xvfb"):
        VirtualDisplay.start(32, 32)


def test_a_refused_screen_reports_xvfb_s_words() -> None:
    with pytest.raises(DisplayError, match="Xvfb exited"):
        VirtualDisplay.start(32, 32, depth=7)
