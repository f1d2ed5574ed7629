"""Keeps a session's ``status`` track current: state, fps, and control results.

A control result goes out at once (``upcast control`` waits for it); the
rolling fps at most once a second, so the track costs nothing next to video.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING

from server.session.session_control import ControlResult, StatusRecord

if TYPE_CHECKING:
    from server.session.runner import StreamingSession

MIN_INTERVAL_S = 1.0


class StatusReporter:
    def __init__(self, session: StreamingSession) -> None:
        self.session = session
        self.last_control: ControlResult | None = None
        self._sent_at = -math.inf
        session.router.on_control_result = self.control_result

    def record(self) -> StatusRecord:
        state = self.session.broadcast.stream_state
        upscaler, scale = state.get("upscaler"), state.get("scale")
        return StatusRecord(
            broadcast=self.session.settings.broadcast,
            upscaler=upscaler if isinstance(upscaler, str) else None,
            scale=float(scale) if isinstance(scale, int | float) else None,
            frame_generation=fg if isinstance(fg := state.get("frame_generation"), bool) else None,
            cache_policy=cp if isinstance(cp := state.get("cache_policy"), str) else None,
            encoded=e if isinstance(e := state.get("encoded"), str) else None,
            quality=q if isinstance(q := state.get("quality"), str) else None,
            quality_reason=r if isinstance(r := state.get("quality_reason"), str) else None,
            quality_at_floor=f if isinstance(f := state.get("quality_at_floor"), bool) else None,
            quality_cores_short=(
                float(w) if isinstance(w := state.get("quality_cores_short"), int | float) else None
            ),
            expected_psnr_db=(
                float(e) if isinstance(e := state.get("expected_psnr_db"), int | float) else None
            ),
            frame_rate=(
                float(r) if isinstance(r := state.get("frame_rate"), int | float) else None
            ),
            fps=round(self.session.monitor.snapshot().fps, 2),
            frames=self.session.monitor.frames,
            last_control=self.last_control,
        )

    def control_result(self, result: ControlResult) -> None:
        self.last_control = result
        self.publish()

    def tick(self) -> None:
        if time.monotonic() - self._sent_at >= MIN_INTERVAL_S:
            self.publish()

    def publish(self) -> None:
        self._sent_at = time.monotonic()
        self.session.broadcast.set_status(self.record().model_dump_json().encode())
        link = self.session.link
        if link is not None and not link.closed:
            link.flush()
