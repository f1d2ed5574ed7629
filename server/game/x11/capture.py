"""Read an X screen's pixels into a caller's RGB buffer, once per frame.

``ScreenCapture`` wraps a ``Grabber`` (grabbers.py) with what a game loop needs
around it: the wanted size may exceed the screen (an application changed the
screen size through RandR; the part outside is black, not an error), and a dead
X server must end the session with ``DisplayGone`` rather than an odd library
error. Any grabber error is answered by one reconnect: if that fails the server
is gone; if it works the grab is retried at the new screen size.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from server.game.x11.errors import DisplayError, DisplayGone
from server.game.x11.grab_base import Frame, Grabber
from server.game.x11.grabbers import DEFAULT_GRABBER, GRABBERS

__all__ = ["DisplayError", "DisplayGone", "ScreenCapture"]

log = logging.getLogger(__name__)

# While the screen is smaller than the wanted size, reconnect this often to see it
# grow back: a connection's idea of the screen size is fixed at connect time.
RECHECK_S = 1.0


class ScreenCapture:
    """The top-left ``width`` x ``height`` of ``display_name``'s root window as RGB."""

    def __init__(
        self, display_name: str, width: int, height: int, *, grabber: str = DEFAULT_GRABBER
    ) -> None:
        if grabber not in GRABBERS:
            raise ValueError(f"unknown grabber {grabber!r}: one of {', '.join(GRABBERS)}")
        if width <= 0 or height <= 0:
            raise ValueError(f"capture size must be positive, got {width}x{height}")
        self.display_name = display_name
        self.width = width
        self.height = height
        self.grabber_name = grabber
        try:
            self._grabber: Grabber | None = GRABBERS[grabber](display_name)
        except DisplayError:
            raise
        except Exception as exc:
            raise DisplayError(
                f"cannot open display {display_name} for capture ({grabber}): {exc}"
            ) from exc
        self._connected_at = time.monotonic()

    def _region(self) -> tuple[int, int]:
        assert self._grabber is not None
        screen_w, screen_h = self._grabber.screen_size()
        return min(self.width, screen_w), min(self.height, screen_h)

    def _reconnect(self, cause: BaseException) -> Grabber:
        self._drop()
        try:
            self._grabber = GRABBERS[self.grabber_name](self.display_name)
        except Exception as exc:
            raise DisplayGone(f"display {self.display_name} is gone ({cause!r})") from exc
        self._connected_at = time.monotonic()
        return self._grabber

    def grab_into(self, out: Frame) -> None:
        """Write the screen's top-left pixels into ``out`` ((height, width, 3) uint8) in place."""
        if out.shape != (self.height, self.width, 3) or out.dtype != np.uint8:
            raise ValueError(
                f"out must be uint8 of shape {(self.height, self.width, 3)}, "
                f"got {out.dtype} {out.shape}"
            )
        if self._grabber is None:
            self._reconnect(DisplayGone("an earlier capture failed"))
        w, h = self._region()
        if (w, h) != (self.width, self.height) and (
            time.monotonic() - self._connected_at > RECHECK_S
        ):
            self._reconnect(RuntimeError("screen smaller than the capture"))
            w, h = self._region()
        try:
            self._grab(out, w, h)
        except Exception as exc:
            log.info("capture of %s failed (%r): reconnecting", self.display_name, exc)
            self._reconnect(exc)
            w, h = self._region()
            try:
                self._grab(out, w, h)
            except Exception as again:
                self._drop()
                raise DisplayGone(
                    f"display {self.display_name} fails captures ({again!r})"
                ) from again
        if w < self.width or h < self.height:
            out[h:] = 0
            out[:h, w:] = 0

    def _grab(self, out: Frame, w: int, h: int) -> None:
        assert self._grabber is not None
        if w > 0 and h > 0:
            self._grabber.grab_into(out if (w, h) == (self.width, self.height) else out[:h, :w])

    def _drop(self) -> None:
        grabber, self._grabber = self._grabber, None
        if grabber is not None:
            try:
                grabber.close()
            except Exception as exc:  # a dead connection may complain as it closes
                log.debug("closing the grabber of %s: %r", self.display_name, exc)

    def close(self) -> None:
        self._drop()
