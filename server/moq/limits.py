"""Bounds on what one peer can make a session hold; crossing one closes that session."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class MoqLimits:
    max_message_size: int = 64 * 1024  # one control message body (announce, subscribe, ...)
    max_frame_size: int = 16 * 1024 * 1024  # one frame payload on a group stream
    max_buffered_bytes: int = 64 * 1024 * 1024  # partial messages/frames over all streams
    max_incoming_streams: int = 1024  # concurrently open peer-initiated streams
    max_subscriptions: int = 256  # concurrent subscriptions the peer holds on us
    max_announce_interests: int = 64  # concurrent announce interests the peer holds on us


@dataclass(frozen=True, slots=True)
class IngressLimits:
    """Bytes per second a connection may send to the relay, by what its token allows.

    A viewer sends requests and small input messages; a publisher sends video. Without
    a bound, a viewer's connection could make the relay parse (and buffer) at line rate.
    The burst absorbs a keyframe or a reconnect's catch-up.
    """

    viewer_bytes_per_s: int = 256 * 1024
    viewer_burst_bytes: int = 1024 * 1024
    publisher_bytes_per_s: int = 64 * 1024 * 1024  # 512 Mbit/s: far above any one stream
    publisher_burst_bytes: int = 64 * 1024 * 1024


class TokenBucket:
    """Sans-IO token bucket: ``take(n, now)`` is False once more than ``rate * elapsed +
    burst`` bytes were taken."""

    __slots__ = ("_last", "_tokens", "burst", "rate")

    def __init__(self, rate: float, burst: float, now: float) -> None:
        if rate <= 0 or burst <= 0:
            raise ValueError(f"rate and burst must be positive, got {rate} and {burst}")
        self.rate = rate
        self.burst = burst
        self._tokens = burst
        self._last = now

    def take(self, amount: int, now: float) -> bool:
        elapsed = max(0.0, now - self._last)
        self._last = now
        self._tokens = min(self.burst, self._tokens + elapsed * self.rate)
        self._tokens -= amount
        return self._tokens >= 0
