"""PyAV's x11grab input device (FFmpeg's XCB + MIT-SHM grabber): a benchmark baseline.

The device grabs a fixed region chosen at open, so a change of region reopens it;
its frame rate is set far above any use so that it never sleeps to pace frames.
"""

from __future__ import annotations

from collections.abc import Iterator

import av
import av.container
import av.video.frame
from Xlib import display as xdisplay

from server.game.x11.grab_base import Frame


class X11GrabGrabber:
    def __init__(self, display_name: str) -> None:
        self._name = display_name
        # FFmpeg's device goes on returning its last picture when the server dies:
        # this idle connection notices (its socket reads EOF) at no round trip's cost.
        self._watch = xdisplay.Display(display_name)
        screen = self._watch.screen()
        self._size = (int(screen.width_in_pixels), int(screen.height_in_pixels))
        self._region: tuple[int, int] | None = None
        self._container: av.container.InputContainer | None = None
        self._frames: Iterator[av.video.frame.VideoFrame] | None = None

    def screen_size(self) -> tuple[int, int]:
        return self._size

    def _open(self, w: int, h: int) -> Iterator[av.video.frame.VideoFrame]:
        self._close_device()
        self._container = av.open(
            f"{self._name}+0,0",
            format="x11grab",
            options={"video_size": f"{w}x{h}", "framerate": "10000", "draw_mouse": "0"},
        )
        self._region = (w, h)
        self._frames = self._container.decode(video=0)
        return self._frames

    def grab_into(self, out: Frame) -> None:
        self._watch.pending_events()  # raises ConnectionClosedError once the server is gone
        h, w = out.shape[:2]
        frames = self._frames if self._region == (w, h) else None
        if frames is None:
            frames = self._open(w, h)
        out[...] = next(frames).to_ndarray(format="rgb24")

    def close(self) -> None:
        self._close_device()
        self._watch.close()

    def _close_device(self) -> None:
        if self._container is not None:
            self._container.close()
        self._container = None
        self._frames = None
        self._region = None
