"""Bitrate against capacity over time, for ``upcast bench network``.

Every ``SAMPLE_EVERY_S`` the benchmark notes, at ``t_s`` seconds after its
measurement window opened (when the emulator's schedule restarted):

- ``bitrate_target_bps``: the bitrate the session's encoder aims at now (x264's
  target, moved by rate control when the session has it); None if unknown;
- ``capacity_bps``: the emulated downlink's rate in force (None: unlimited, 0
  during 100 % loss), from the emulator's own step index;
- ``link_delivered_bps``: bytes the emulator delivered downstream since the last
  sample (every viewer on the link, audio, timing and QUIC overhead included);
- ``page_received_bps``: the page's own count of video bytes received, where the
  page exposes one (``bytesReceived``), else None;
- ``frame_divisor``: 1, or 2 when rate control sends every other frame (a bitrate
  too low for the full frame rate); None when the session has no rate control.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from server.net.link_profile import Schedule

SAMPLE_EVERY_S = 0.5


def capacity_bps(schedule: Schedule, step: int) -> float | None:
    """The downlink of step ``step``: its rate (None: unlimited), 0 when it loses all."""
    down = schedule.steps[step].profile.down
    if down.loss >= 1.0:
        return 0.0
    return None if down.rate_bps is None else float(down.rate_bps)


@dataclass
class RateSeries:
    schedule: Schedule
    t0: float  # time.monotonic() of t_s = 0
    t_s: list[float] = field(default_factory=list)
    bitrate_target_bps: list[int | None] = field(default_factory=list)
    capacity_bps: list[float | None] = field(default_factory=list)
    link_delivered_bps: list[float | None] = field(default_factory=list)
    page_received_bps: list[float | None] = field(default_factory=list)
    frame_divisor: list[int | None] = field(default_factory=list)
    _last: tuple[float, int, int | None] | None = None  # now, link bytes, page bytes

    def sample(
        self,
        now: float,
        *,
        target_bps: int | None,
        step: int,
        link_bytes: int,
        page_bytes: int | None,
        frame_divisor: int | None = None,
    ) -> None:
        """One sample; the rates are over the time since the previous one (the first
        sample only sets the counters' base)."""
        last, self._last = self._last, (now, link_bytes, page_bytes)
        if last is None:
            return
        span = now - last[0]
        if span <= 0:
            return
        self.t_s.append(round(now - self.t0, 3))
        self.bitrate_target_bps.append(target_bps)
        self.capacity_bps.append(capacity_bps(self.schedule, step))
        self.link_delivered_bps.append(round((link_bytes - last[1]) * 8 / span, 1))
        page = None
        if page_bytes is not None and last[2] is not None:
            page = round((page_bytes - last[2]) * 8 / span, 1)
        self.page_received_bps.append(page)
        self.frame_divisor.append(frame_divisor)

    def as_dict(self) -> dict[str, Any]:
        return {
            "every_s": SAMPLE_EVERY_S,
            "t_s": self.t_s,
            "bitrate_target_bps": self.bitrate_target_bps,
            "capacity_bps": self.capacity_bps,
            "link_delivered_bps": self.link_delivered_bps,
            "page_received_bps": self.page_received_bps,
            "frame_divisor": self.frame_divisor,
        }

    def means(self) -> dict[str, float | None]:
        """Mean of each series over the samples where it is known (Mbit/s in the table)."""

        def mean(values: list[Any]) -> float | None:
            known = [float(v) for v in values if v is not None]
            return round(sum(known) / len(known), 1) if known else None

        return {
            "bitrate_target_bps": mean(self.bitrate_target_bps),
            "capacity_bps": mean(self.capacity_bps),
            "link_delivered_bps": mean(self.link_delivered_bps),
            "page_received_bps": mean(self.page_received_bps),
        }
