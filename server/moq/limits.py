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
