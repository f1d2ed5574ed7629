"""python-xlib's XGetImage grabber (pure Python, no shared memory): a benchmark baseline."""

from __future__ import annotations

import numpy as np
from Xlib import X
from Xlib import display as xdisplay

from server.game.x11.grab_base import Frame, bgrx_to_rgb


class XlibGrabber:
    def __init__(self, display_name: str) -> None:
        self._display = xdisplay.Display(display_name)
        self._root = self._display.screen().root
        geometry = self._root.get_geometry()
        self._size = (int(geometry.width), int(geometry.height))

    def screen_size(self) -> tuple[int, int]:
        return self._size

    def grab_into(self, out: Frame) -> None:
        h, w = out.shape[:2]
        image = self._root.get_image(0, 0, w, h, X.ZPixmap, 0xFFFFFFFF)
        bgrx_to_rgb(np.frombuffer(image.data, np.uint8).reshape(h, w, 4), out)

    def close(self) -> None:
        self._display.close()
