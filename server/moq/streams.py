"""Per-stream and per-subscription bookkeeping records of a MoqSession (no logic)."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum, auto


class Kind(Enum):
    """What a stream carries, from our point of view, as far as we have parsed it."""

    BIDI_NEW = auto()  # peer bidi, type varint not read yet
    UNI_NEW = auto()  # peer uni, group header not read yet
    ANNOUNCE_IN_WAIT = auto()  # peer announce interest: waiting for the prefix
    ANNOUNCE_IN = auto()  # peer announce interest: we answer with announces
    SUBSCRIBE_IN_WAIT = auto()  # peer subscribe: waiting for SUBSCRIBE
    SUBSCRIBE_IN = auto()  # peer subscribe: SUBSCRIBE_UPDATEs may follow
    FETCH_IN = auto()  # refused once the request is read
    GOAWAY_IN = auto()
    PROBE_IN = auto()  # held open; we may send PROBE, we ignore what the peer sends
    DISCARD = auto()  # read and drop until FIN (refused fetch, goaway)
    ANNOUNCE_OUT = auto()  # our announce interest
    SUBSCRIBE_OUT = auto()  # our subscription
    GROUP_IN = auto()  # a group of one of our subscriptions


@dataclass(slots=True)
class StreamState:
    stream_id: int
    kind: Kind
    buffer: bytearray = field(default_factory=bytearray)
    fin_received: bool = False
    # Set once the kind is known: the prefix, request/subscription id, group sequence.
    prefix: str = ""
    ref_id: int = -1
    sequence: int = -1


@dataclass(slots=True)
class InboundRequest:
    """A subscription the peer made on us."""

    stream_id: int
    broadcast: str
    track: str
    priority: int
    ordered: bool
    max_latency_ms: int
    accepted: bool = False
    groups: set[int] = field(default_factory=set)  # our open group streams for it


@dataclass(slots=True)
class OutboundSubscription:
    """A subscription we made on the peer."""

    stream_id: int
    broadcast: str
    track: str
    accepted: bool = False
