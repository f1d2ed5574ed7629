"""Per-frame timing stamps: the one place where every stage boundary is defined.

Each stamp is a pair (monotonic ns, wall-clock ns). Monotonic stamps are only
comparable inside one machine; wall-clock stamps let figures from the relay and
the browser line up with the server's. A stamp of 0 means "not reached".

Stage boundaries (what exactly is measured, so that runs mean the same thing):

- ``render_start``   the game begins rendering the frame (before scene update).
- ``render_end``     every G-buffer plane is written into the ring R slot.
- ``ring_r_ready``   the ring R slot is marked READY (the fence is signalled).
- ``upscale_start``  the worker holds read-only views of the ring R slot.
- ``upscale_end``    the display-size frame is written into its ring U slot.
- ``ring_u_ready``   the ring U slot is marked READY.
- ``encode_start``   the encoder receives the display frame.
- ``encode_end``     the CMAF fragment of the frame is complete.
- ``publish``        the fragment is handed to the QUIC stream.
- ``relay_in``       the relay has read the whole frame from the publisher.
- ``relay_out``      the relay has written the frame to a viewer's stream.
- ``client_receive`` the browser has the whole frame.
- ``client_decode``  WebCodecs returned the decoded picture.
- ``client_present`` the picture was drawn (requestAnimationFrame after draw).
"""

from __future__ import annotations

import time
from enum import IntEnum

import numpy as np
import numpy.typing as npt


class Stage(IntEnum):
    RENDER_START = 0
    RENDER_END = 1
    RING_R_READY = 2
    UPSCALE_START = 3
    UPSCALE_END = 4
    RING_U_READY = 5
    ENCODE_START = 6
    ENCODE_END = 7
    PUBLISH = 8
    RELAY_IN = 9
    RELAY_OUT = 10
    CLIENT_RECEIVE = 11
    CLIENT_DECODE = 12
    CLIENT_PRESENT = 13

    @property
    def label(self) -> str:
        return self.name.lower()


STAGE_COUNT = len(Stage)

# (stage_from, stage_to) pairs reported as "latency of a stage".
STAGE_SPANS: tuple[tuple[str, Stage, Stage], ...] = (
    ("render", Stage.RENDER_START, Stage.RENDER_END),
    ("ring_r_handoff", Stage.RING_R_READY, Stage.UPSCALE_START),
    ("upscale", Stage.UPSCALE_START, Stage.UPSCALE_END),
    ("ring_u_handoff", Stage.RING_U_READY, Stage.ENCODE_START),
    ("encode", Stage.ENCODE_START, Stage.ENCODE_END),
    ("publish", Stage.ENCODE_END, Stage.PUBLISH),
    ("relay", Stage.RELAY_IN, Stage.RELAY_OUT),
    ("decode", Stage.CLIENT_RECEIVE, Stage.CLIENT_DECODE),
    ("present", Stage.CLIENT_DECODE, Stage.CLIENT_PRESENT),
)


def new_stamps() -> npt.NDArray[np.int64]:
    """An empty timing record: shape (STAGE_COUNT, 2), columns (monotonic_ns, wall_ns)."""
    return np.zeros((STAGE_COUNT, 2), dtype=np.int64)


def stamp(record: npt.NDArray[np.int64], stage: Stage) -> int:
    """Write now into ``record[stage]`` (works on a ring slot's header view too)."""
    mono = time.monotonic_ns()
    record[stage, 0] = mono
    record[stage, 1] = time.time_ns()
    return mono


def span_ms(record: npt.NDArray[np.int64], start: Stage, end: Stage) -> float | None:
    """Monotonic milliseconds between two stamps, or None if either is missing."""
    a = int(record[start, 0])
    b = int(record[end, 0])
    if a == 0 or b == 0:
        return None
    return (b - a) / 1e6
