"""moq-lite control messages (lite-03, with the cheap lite-04 differences).

Each message knows its body encoding (`body(version)`) and decodes from a complete Reader
over its body (`decode(reader, version)`); the size prefix is handled by `encode` and by
`Reader.message`. Optional group numbers travel as `n + 1`, with 0 meaning "none".
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import Protocol, Self

from .errors import ErrorCode, ProtocolError
from .wire import Reader, encode_bool, encode_message, encode_string, encode_u8, encode_varint

MAX_HOPS = 256  # same bound as @moq/lite, stops a peer from making us build huge lists


class Version(IntEnum):
    LITE_03 = 0xFF0DAD03
    LITE_04 = 0xFF0DAD04


class StreamType(IntEnum):
    """First varint of a bidirectional stream."""

    SESSION = 0  # lite-01/02 setup stream; never valid with ALPN-negotiated lite-03
    ANNOUNCE = 1
    SUBSCRIBE = 2
    FETCH = 3
    PROBE = 4
    GOAWAY = 5


GROUP_STREAM_TYPE = 0  # first byte (u8) of a unidirectional stream


class SubscribeResponseType(IntEnum):
    OK = 0
    DROP = 1


class Message(Protocol):
    def body(self, version: Version) -> bytes: ...


def encode(message: Message, version: Version = Version.LITE_03) -> bytes:
    """The size-prefixed wire form of a message."""
    return encode_message(message.body(version))


def _optional_group(value: int | None) -> bytes:
    return encode_varint(0 if value is None else value + 1)


def _read_optional_group(r: Reader) -> int | None:
    value = r.varint()
    return None if value == 0 else value - 1


@dataclass(frozen=True, slots=True)
class AnnounceInterest:
    prefix: str
    exclude_hop: int = 0  # lite-04 only

    def body(self, version: Version) -> bytes:
        out = encode_string(self.prefix)
        if version >= Version.LITE_04:
            out += encode_varint(self.exclude_hop)
        return out

    @classmethod
    def decode(cls, r: Reader, version: Version) -> Self:
        prefix = r.string()
        exclude_hop = r.varint() if version >= Version.LITE_04 else 0
        return cls(prefix, exclude_hop)


@dataclass(frozen=True, slots=True)
class Announce:
    active: bool
    suffix: str
    hop_count: int = 0  # lite-03 sends only the count; lite-04 sends the ids in `hops`
    hops: tuple[int, ...] = ()

    def body(self, version: Version) -> bytes:
        out = encode_bool(self.active) + encode_string(self.suffix)
        if version >= Version.LITE_04:
            out += encode_varint(len(self.hops))
            out += b"".join(encode_varint(h) for h in self.hops)
        else:
            out += encode_varint(self.hop_count)
        return out

    @classmethod
    def decode(cls, r: Reader, version: Version) -> Self:
        active = r.bool()
        suffix = r.string()
        count = r.varint()
        if count > MAX_HOPS:
            raise ProtocolError(ErrorCode.PROTOCOL_VIOLATION, f"hop count {count} > {MAX_HOPS}")
        hops = tuple(r.varint() for _ in range(count)) if version >= Version.LITE_04 else ()
        return cls(active, suffix, count, hops)


@dataclass(frozen=True, slots=True)
class Subscribe:
    id: int
    broadcast: str
    track: str
    priority: int = 0
    ordered: bool = False
    max_latency_ms: int = 0  # 0 = no bound
    start_group: int | None = None  # None = latest
    end_group: int | None = None  # None = open ended

    def body(self, version: Version) -> bytes:
        return b"".join(
            (
                encode_varint(self.id),
                encode_string(self.broadcast),
                encode_string(self.track),
                encode_u8(self.priority),
                encode_bool(self.ordered),
                encode_varint(self.max_latency_ms),
                _optional_group(self.start_group),
                _optional_group(self.end_group),
            )
        )

    @classmethod
    def decode(cls, r: Reader, version: Version) -> Self:
        return cls(
            id=r.varint(),
            broadcast=r.string(),
            track=r.string(),
            priority=r.u8(),
            ordered=r.bool(),
            max_latency_ms=r.varint(),
            start_group=_read_optional_group(r),
            end_group=_read_optional_group(r),
        )


@dataclass(frozen=True, slots=True)
class SubscribeOk:
    """Also the layout of SUBSCRIBE_UPDATE (sent by the subscriber on its stream)."""

    priority: int = 0
    ordered: bool = True
    max_latency_ms: int = 0
    start_group: int | None = None
    end_group: int | None = None

    def body(self, version: Version) -> bytes:
        return b"".join(
            (
                encode_u8(self.priority),
                encode_bool(self.ordered),
                encode_varint(self.max_latency_ms),
                _optional_group(self.start_group),
                _optional_group(self.end_group),
            )
        )

    @classmethod
    def decode(cls, r: Reader, version: Version) -> Self:
        return cls(
            priority=r.u8(),
            ordered=r.bool(),
            max_latency_ms=r.varint(),
            start_group=_read_optional_group(r),
            end_group=_read_optional_group(r),
        )


@dataclass(frozen=True, slots=True)
class SubscribeUpdate(SubscribeOk):
    pass


@dataclass(frozen=True, slots=True)
class SubscribeDrop:
    """Groups `start..end` of a subscription will not be delivered (error says why)."""

    start: int
    end: int
    error: int

    def body(self, version: Version) -> bytes:
        return encode_varint(self.start) + encode_varint(self.end) + encode_varint(self.error)

    @classmethod
    def decode(cls, r: Reader, version: Version) -> Self:
        return cls(r.varint(), r.varint(), r.varint())


def encode_subscribe_response(
    response: SubscribeOk | SubscribeDrop, version: Version = Version.LITE_03
) -> bytes:
    kind = SubscribeResponseType.DROP if isinstance(response, SubscribeDrop) else 0
    return encode_varint(kind) + encode(response, version)


@dataclass(frozen=True, slots=True)
class Probe:
    bitrate: int
    rtt_ms: int | None = None  # lite-04 only

    def body(self, version: Version) -> bytes:
        out = encode_varint(self.bitrate)
        if version >= Version.LITE_04:
            out += encode_varint(0 if self.rtt_ms is None else max(self.rtt_ms, 1))
        return out

    @classmethod
    def decode(cls, r: Reader, version: Version) -> Self:
        bitrate = r.varint()
        rtt = r.varint() if version >= Version.LITE_04 else 0
        return cls(bitrate, rtt or None)


@dataclass(frozen=True, slots=True)
class Fetch:
    broadcast: str
    track: str
    priority: int
    group: int

    def body(self, version: Version) -> bytes:
        return (
            encode_string(self.broadcast)
            + encode_string(self.track)
            + encode_u8(self.priority)
            + encode_varint(self.group)
        )

    @classmethod
    def decode(cls, r: Reader, version: Version) -> Self:
        return cls(r.string(), r.string(), r.u8(), r.varint())


@dataclass(frozen=True, slots=True)
class Goaway:
    uri: str

    def body(self, version: Version) -> bytes:
        return encode_string(self.uri)

    @classmethod
    def decode(cls, r: Reader, version: Version) -> Self:
        return cls(r.string())


@dataclass(frozen=True, slots=True)
class GroupHeader:
    subscribe_id: int
    sequence: int

    def body(self, version: Version) -> bytes:
        return encode_varint(self.subscribe_id) + encode_varint(self.sequence)

    @classmethod
    def decode(cls, r: Reader, version: Version) -> Self:
        return cls(r.varint(), r.varint())


def encode_group_stream_header(header: GroupHeader, version: Version = Version.LITE_03) -> bytes:
    """Opening bytes of a group's unidirectional stream."""
    return encode_u8(GROUP_STREAM_TYPE) + encode(header, version)


def encode_frame(payload: bytes) -> bytes:
    return encode_varint(len(payload)) + payload
