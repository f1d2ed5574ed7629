"""The ways to read the root window's pixels, behind one interface (``Grabber``).

Each grabber holds one connection and writes the top-left ``out.shape`` pixels
of the screen into ``out`` as RGB; ``ScreenCapture`` (capture.py) does the
clamping, reconnecting and error mapping around them, so a grabber stays a thin
adapter over its library. Measured by ``upcast bench capture``
(docs/reports/capture.json, 2 shared cores): mss's XShmGetImage is the default,
median 0.44 ms at 640x360 and 1.6 ms at 1280x720, against 0.88 / 3.8 ms for
mss's XGetImage, 0.99 / 2.8 ms for PyAV's x11grab and 1.7 / 10.5 ms for
python-xlib's XGetImage (pure Python socket reads).
"""

from __future__ import annotations

from collections.abc import Callable

import mss
import numpy as np

from server.game.x11.errors import DisplayError
from server.game.x11.grab_base import Frame, Grabber, bgrx_to_rgb

# The shared libraries mss opens at run time (no wheel ships them).
XCB_PACKAGES = "libxcb1 libxcb-randr0 libxcb-render0 libxcb-shm0 libxcb-xfixes0"


class MssGrabber:
    """mss: XShmGetImage into a shared segment (``backend="xshmgetimage"``) or XGetImage."""

    def __init__(self, display_name: str, backend: str = "xshmgetimage") -> None:
        try:
            self._mss = mss.MSS(display=display_name, backend=backend)
        except mss.ScreenShotError as exc:
            if "not found" in str(exc):  # mss loads the XCB libraries with ctypes
                raise DisplayError(f"{exc}: install Debian's packages {XCB_PACKAGES}") from exc
            raise
        root = self._mss.monitors[0]
        self._size = (int(root["width"]), int(root["height"]))

    def screen_size(self) -> tuple[int, int]:
        return self._size

    def grab_into(self, out: Frame) -> None:
        h, w = out.shape[:2]
        shot = self._mss.grab({"left": 0, "top": 0, "width": w, "height": h})
        bgrx_to_rgb(np.frombuffer(shot.raw, np.uint8).reshape(h, w, 4), out)

    def close(self) -> None:
        self._mss.close()


def _mss_xgetimage(display_name: str) -> Grabber:
    return MssGrabber(display_name, backend="xgetimage")


def _xlib(display_name: str) -> Grabber:
    from server.game.x11.grab_xlib import XlibGrabber

    return XlibGrabber(display_name)


def _x11grab(display_name: str) -> Grabber:
    # Imported on use: loading FFmpeg's device libraries is not free.
    from server.game.x11.grab_x11grab import X11GrabGrabber

    return X11GrabGrabber(display_name)


# Name -> factory(display name); the first is the default.
GRABBERS: dict[str, Callable[[str], Grabber]] = {
    "mss": MssGrabber,
    "mss-xgetimage": _mss_xgetimage,
    "xlib": _xlib,
    "x11grab": _x11grab,
}
DEFAULT_GRABBER = "mss"
