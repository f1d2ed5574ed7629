"""What a viewer reports about the video it receives, a few times a second.

The player page and the load-test viewers send a ``feedback`` message on their
``input`` track (server/session/viewer_input.py) every ``FEEDBACK_INTERVAL_MS``:

- ``frames``: the video frames that arrived since the last report, each as
  ``[pts_us, arrival_ms]``: the frame's presentation time from its CMAF fragment
  (``tfdt``, the encoder's pts in microseconds) and when its last byte arrived on
  the viewer's own monotonic clock (``performance.now()``). The session knows when
  and how big it sent each pts, so from these pairs it measures the throughput and
  the one-way delay trend of the path itself (a delay-based estimate), without
  trusting a number the viewer computed.
- cumulative counters since the viewer subscribed (a lost report loses nothing,
  the session takes differences): video ``bytes`` received, frames ``lost``
  (gaps in the fragments' sequence numbers), groups ``skipped`` (gaps in the group
  sequence), ``freezes`` (more than ``FREEZE_MS`` between two shown frames) and
  their total ``freeze_ms``, frames ``late`` (dropped by the player or shown after
  their deadline).
- ``player``: this viewer plays (it sends input); its link sets the session's
  bitrate. Spectators report too, for metrics, and keep the relay's skip-ahead.

Feedback may lie: the session clamps what it derives to what it can check
(server/session/rate_control.py).
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

FEEDBACK_INTERVAL_MS = 250
FREEZE_MS = 200  # a gap between shown frames longer than this is a freeze
MAX_FEEDBACK_FRAMES = 64  # 240 fps at a 250 ms interval; more are dropped by the sender

_Count = Annotated[int, Field(strict=True, ge=0, lt=1 << 53)]
_Pts = Annotated[int, Field(strict=True, ge=0, lt=1 << 53)]
_Ms = Annotated[float, Field(ge=0, lt=1e13, allow_inf_nan=False)]


class FeedbackFields(BaseModel):
    """The body of a ``feedback`` message (without ``type``/``seq``/``sent_ms``)."""

    model_config = ConfigDict(extra="ignore")

    player: bool = False
    frames: list[tuple[_Pts, _Ms]] = Field(default_factory=list, max_length=MAX_FEEDBACK_FRAMES)
    bytes: _Count = 0
    lost: _Count = 0
    skipped: _Count = 0
    freezes: _Count = 0
    freeze_ms: _Ms = 0.0
    late: _Count = 0
