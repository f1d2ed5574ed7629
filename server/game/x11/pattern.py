"""A known picture drawn straight onto a screen's root window, to check captures.

Colour bars in the manner of a test card, plus a one-pixel frame whose corners
differ, so that a swapped channel, a flipped or shifted image and a lost edge
row or column all show as a pixel mismatch.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from Xlib import display as xdisplay

Rgb = tuple[int, int, int]
Rect = tuple[int, int, int, int, Rgb]  # x, y, width, height, colour

BARS: tuple[Rgb, ...] = (
    (255, 255, 255),
    (255, 255, 0),
    (0, 255, 255),
    (0, 255, 0),
    (255, 0, 255),
    (255, 0, 0),
    (0, 0, 255),
    (16, 32, 64),
)


def card_rects(width: int, height: int) -> list[Rect]:
    """The rectangles of the picture for a ``width`` x ``height`` screen, painted in order."""
    rects: list[Rect] = []
    for i, colour in enumerate(BARS):
        x0, x1 = i * width // len(BARS), (i + 1) * width // len(BARS)
        rects.append((x0, 0, x1 - x0, height, colour))
    rects += [
        (0, 0, width, 1, (1, 2, 3)),
        (0, height - 1, width, 1, (4, 5, 6)),
        (0, 0, 1, height, (7, 8, 9)),
        (width - 1, 0, 1, height, (10, 11, 12)),
        (width - 1, height - 1, 1, 1, (200, 100, 50)),
    ]
    return rects


def render(rects: list[Rect], width: int, height: int) -> npt.NDArray[np.uint8]:
    """What ``rects`` look like on a black ``width`` x ``height`` RGB screen."""
    image = np.zeros((height, width, 3), np.uint8)
    for x, y, w, h, colour in rects:
        image[y : y + h, x : x + w] = colour
    return image


def paint(display_name: str, rects: list[Rect]) -> None:
    """Fill ``rects`` on the root window of ``display_name`` (24-bit TrueColor) and wait."""
    display = xdisplay.Display(display_name)
    try:
        root = display.screen().root
        for x, y, w, h, (r, g, b) in rects:
            gc = root.create_gc(foreground=(r << 16) | (g << 8) | b)
            root.fill_rectangle(gc, x, y, w, h)
            gc.free()
        display.sync()  # drawn before the caller captures
    finally:
        display.close()
