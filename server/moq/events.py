"""What a MoqSession reports to the application.

Two id spaces exist, one per direction, because each subscriber picks its own ids:
- `request_id`: a subscription the *peer* made on us (we publish; we answer it);
- `subscription_id`: a subscription *we* made on the peer (we receive its groups).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class AnnounceInterestReceived:
    """The peer wants to learn our broadcasts under `prefix` (answered automatically)."""

    stream_id: int
    prefix: str


@dataclass(frozen=True, slots=True)
class AnnounceReceived:
    """The peer (un)announced `path` in reply to our interest `handle`."""

    handle: int
    path: str
    active: bool
    hop_count: int


@dataclass(frozen=True, slots=True)
class AnnouncesEnded:
    """The peer closed (error_code None) or reset one of our announce interests."""

    handle: int
    error_code: int | None


@dataclass(frozen=True, slots=True)
class SubscribeRequested:
    request_id: int
    broadcast: str
    track: str
    priority: int
    ordered: bool
    max_latency_ms: int
    start_group: int | None
    end_group: int | None


@dataclass(frozen=True, slots=True)
class SubscribeUpdated:
    request_id: int
    priority: int
    ordered: bool
    max_latency_ms: int
    start_group: int | None
    end_group: int | None


@dataclass(frozen=True, slots=True)
class SubscribeCancelled:
    """The peer ended its subscription `request_id`; its open groups were reset."""

    request_id: int
    error_code: int | None


@dataclass(frozen=True, slots=True)
class SubscribeAccepted:
    subscription_id: int
    priority: int
    ordered: bool
    max_latency_ms: int
    start_group: int | None
    end_group: int | None


@dataclass(frozen=True, slots=True)
class SubscribeDropped:
    """SUBSCRIBE_DROP: groups start..end of our subscription will not come."""

    subscription_id: int
    start: int
    end: int
    error_code: int


@dataclass(frozen=True, slots=True)
class SubscribeClosed:
    """Our subscription ended: publisher finished (error_code None), rejected or reset it."""

    subscription_id: int
    error_code: int | None
    accepted: bool  # False: it was refused before any SUBSCRIBE_OK


@dataclass(frozen=True, slots=True)
class GroupOpened:
    subscription_id: int
    sequence: int
    stream_id: int


@dataclass(frozen=True, slots=True)
class FrameReceived:
    subscription_id: int
    sequence: int
    stream_id: int
    payload: bytes


@dataclass(frozen=True, slots=True)
class GroupClosed:
    """complete: FIN after whole frames; otherwise reset (error_code) by the publisher."""

    subscription_id: int
    sequence: int
    stream_id: int
    complete: bool
    error_code: int | None


@dataclass(frozen=True, slots=True)
class GroupCancelled:
    """The peer stopped one of our outgoing group streams (STOP_SENDING)."""

    request_id: int
    stream_id: int
    error_code: int


@dataclass(frozen=True, slots=True)
class GoawayReceived:
    uri: str


@dataclass(frozen=True, slots=True)
class SessionError:
    """We closed the session because of the peer (a CloseSession transmit is queued)."""

    error_code: int
    reason: str


Event = (
    AnnounceInterestReceived
    | AnnounceReceived
    | AnnouncesEnded
    | SubscribeRequested
    | SubscribeUpdated
    | SubscribeCancelled
    | SubscribeAccepted
    | SubscribeDropped
    | SubscribeClosed
    | GroupOpened
    | FrameReceived
    | GroupClosed
    | GroupCancelled
    | GoawayReceived
    | SessionError
)
