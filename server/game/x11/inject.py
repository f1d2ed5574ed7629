"""Viewer input into an X application through the XTest extension.

The viewer side sends state (keys held, buttons held, pointer position), not
events; the injector diffs each new state against the last one it sent and
fakes only the changes, so a lost or repeated state message cannot leave a key
stuck down or pressed twice. One python-xlib connection, one round trip per
call (sync, not just flush: the server has applied the input when the call
returns, whatever its other clients asked meanwhile, about 0.1 ms): an
xdotool process per event would cost milliseconds each.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterable
from typing import TypeVar

from Xlib import X
from Xlib import display as xdisplay
from Xlib import error as xerror
from Xlib.ext import xtest

from server.game.x11.errors import DisplayError, DisplayGone
from server.game.x11.keys import keysym_of

log = logging.getLogger(__name__)

# PointerEvent.buttons bit -> X button: primary, secondary, middle, back, forward.
BUTTONS = {1: 1, 2: 3, 4: 2, 8: 8, 16: 9}

T = TypeVar("T")


class InputInjector:
    """Fakes keys, pointer motion and buttons on a ``width`` x ``height`` screen."""

    def __init__(self, display_name: str, width: int, height: int) -> None:
        self.display_name = display_name
        self.width = width
        self.height = height
        try:
            self._display = xdisplay.Display(display_name)
        except (xerror.DisplayError, OSError) as exc:
            raise DisplayError(f"cannot open display {display_name}: {exc}") from exc
        if not self._display.has_extension("XTEST"):
            self._display.close()
            raise DisplayError(f"display {display_name} has no XTEST extension")
        self._keycodes: dict[str, int | None] = {}
        self._keys_down: set[int] = set()
        self._buttons_down: set[int] = set()
        # Sub-pixel remainders of relative motion, so slow mice still move.
        self._carry_x = 0.0
        self._carry_y = 0.0

    def keycode(self, name: str) -> int | None:
        """The X keycode that browser key ``name`` presses here, or None (ignored)."""
        if name not in self._keycodes:
            keysym = keysym_of(name)
            code = int(self._display.keysym_to_keycode(keysym)) if keysym else 0
            self._keycodes[name] = code or None
            if not code:
                log.info("key %r has no X keycode here: ignored", name)
        return self._keycodes[name]

    def _send(self, fake: Callable[[], T]) -> T:
        try:
            result = fake()
            self._display.sync()
        except (xerror.ConnectionClosedError, OSError) as exc:
            raise DisplayGone(f"display {self.display_name} is gone ({exc})") from exc
        return result

    def _fake(self, event_type: int, detail: int, x: int = 0, y: int = 0) -> None:
        xtest.fake_input(self._display, event_type, detail, x=x, y=y)

    def set_keys_down(self, keys: Iterable[str]) -> None:
        """Make ``keys`` (browser names) exactly the keys held down."""
        wanted = {code for code in map(self.keycode, keys) if code is not None}
        up, down = self._keys_down - wanted, wanted - self._keys_down

        def fake() -> None:
            for code in sorted(up):
                self._fake(X.KeyRelease, code)
            for code in sorted(down):
                self._fake(X.KeyPress, code)

        self._send(fake)
        self._keys_down = wanted

    def move_pointer_to(self, x: float, y: float) -> None:
        """Put the pointer at (x, y), fractions of the screen's width and height (clamped)."""
        px = min(max(int(x * self.width), 0), self.width - 1)
        py = min(max(int(y * self.height), 0), self.height - 1)
        self._send(lambda: self._fake(X.MotionNotify, False, px, py))

    def move_pointer_by(self, dx: float, dy: float) -> None:
        """Move the pointer by (dx, dy) screen pixels (the server keeps it on the screen)."""
        self._carry_x += dx
        self._carry_y += dy
        ix, iy = int(self._carry_x), int(self._carry_y)
        if ix == 0 and iy == 0:
            return
        self._carry_x -= ix
        self._carry_y -= iy
        # XTest's motion fields are 16-bit; no screen needs more in one step.
        ix, iy = (min(max(v, -32768), 32767) for v in (ix, iy))
        self._send(lambda: self._fake(X.MotionNotify, True, ix, iy))

    def set_buttons(self, mask: int) -> None:
        """Make the buttons of PointerEvent.buttons ``mask`` exactly the buttons held."""
        wanted = {button for bit, button in BUTTONS.items() if mask & bit}
        up, down = self._buttons_down - wanted, wanted - self._buttons_down

        def fake() -> None:
            for button in sorted(up):
                self._fake(X.ButtonRelease, button)
            for button in sorted(down):
                self._fake(X.ButtonPress, button)

        self._send(fake)
        self._buttons_down = wanted

    def release_all(self) -> None:
        """Every key and button up (the viewer left: nothing may stay held)."""
        self.set_keys_down(())
        self.set_buttons(0)

    def close(self) -> None:
        with contextlib.suppress(DisplayGone):
            self.release_all()
        with contextlib.suppress(xerror.ConnectionClosedError, OSError):
            self._display.close()
