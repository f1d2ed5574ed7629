"""Helpers of the X11 tests: screens, resizing, events seen by a window of our own."""

from __future__ import annotations

import time
from typing import Any

from Xlib import X
from Xlib import display as xdisplay
from Xlib.ext import randr


def resize_screen(display_name: str, width: int, height: int) -> None:
    """What an application's RandR call does: a new root size (CRTCs off first, a
    screen smaller than a CRTC is refused)."""
    display = xdisplay.Display(display_name)
    try:
        root = display.screen().root
        resources = randr.get_screen_resources(root)
        for crtc in resources.crtcs:
            randr.set_crtc_config(
                display, crtc, resources.config_timestamp, 0, 0, 0, randr.Rotate_0, []
            )
        randr.set_screen_size(root, width, height, width // 4, height // 4)
        display.sync()
        geometry = root.get_geometry()
        assert (geometry.width, geometry.height) == (width, height)
    finally:
        display.close()


EVENT_MASK = (
    X.KeyPressMask
    | X.KeyReleaseMask
    | X.ButtonPressMask
    | X.ButtonReleaseMask
    | X.PointerMotionMask
    | X.StructureNotifyMask
)


class EventWindow:
    """A full-screen window with the input focus that records what reaches it."""

    def __init__(self, display_name: str, width: int, height: int) -> None:
        self.display = xdisplay.Display(display_name)
        root = self.display.screen().root
        self.window = root.create_window(
            0,
            0,
            width,
            height,
            0,
            X.CopyFromParent,
            override_redirect=True,
            event_mask=EVENT_MASK,
        )
        self.window.map()
        self.wait(lambda e: e.type == X.MapNotify)
        self.window.set_input_focus(X.RevertToParent, X.CurrentTime)
        self.display.sync()

    def events(self, timeout_s: float = 1.0, settle_s: float = 0.1) -> list[Any]:
        """Every event until none came for ``settle_s`` (or ``timeout_s`` passed)."""
        out: list[Any] = []
        deadline = time.monotonic() + timeout_s
        quiet_since = time.monotonic()
        while time.monotonic() < deadline:
            self.display.sync()
            if self.display.pending_events():
                out.append(self.display.next_event())
                quiet_since = time.monotonic()
            elif time.monotonic() - quiet_since > settle_s:
                break
            else:
                time.sleep(0.005)
        return out

    def wait(self, match: Any, timeout_s: float = 2.0) -> Any:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.display.pending_events():
                event = self.display.next_event()
                if match(event):
                    return event
            else:
                time.sleep(0.005)
        raise AssertionError("the awaited X event did not come")

    def keycode(self, keysym_name: str) -> int:
        from Xlib import XK

        return int(self.display.keysym_to_keycode(XK.string_to_keysym(keysym_name)))

    def close(self) -> None:
        self.display.close()
