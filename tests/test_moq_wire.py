"""moq-lite wire encodings: varints, strings, messages, and every message's round trip."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.moq import messages as m
from server.moq.errors import ErrorCode, ProtocolError
from server.moq.wire import (
    MAX_VARINT,
    NeedMore,
    Reader,
    encode_bool,
    encode_message,
    encode_string,
    encode_varint,
)

VARINTS = st.integers(min_value=0, max_value=MAX_VARINT)
U8 = st.integers(min_value=0, max_value=255)
TEXT = st.text(max_size=40)
OPT_GROUP = st.none() | st.integers(min_value=0, max_value=MAX_VARINT - 1)
VERSIONS = st.sampled_from(list(m.Version))


@pytest.mark.parametrize(
    ("value", "wire"),
    [
        (37, bytes.fromhex("25")),
        (63, bytes.fromhex("3f")),
        (64, bytes.fromhex("4040")),
        (15293, bytes.fromhex("7bbd")),
        (16383, bytes.fromhex("7fff")),
        (16384, bytes.fromhex("80004000")),
        (494878333, bytes.fromhex("9d7f3e7d")),
        ((1 << 30) - 1, bytes.fromhex("bfffffff")),
        (1 << 30, bytes.fromhex("c000000040000000")),
        (151288809941952652, bytes.fromhex("c2197c5eff14e88c")),
        (MAX_VARINT, bytes.fromhex("ffffffffffffffff")),
    ],
)
def test_varint_vectors(value: int, wire: bytes) -> None:
    """RFC 9000 appendix A.1 examples and the boundaries of all four lengths."""
    assert encode_varint(value) == wire
    reader = Reader(wire, complete=True)
    assert reader.varint() == value
    reader.expect_end()


def test_varint_non_minimal_is_accepted() -> None:
    assert Reader(bytes.fromhex("4025"), complete=True).varint() == 37


@pytest.mark.parametrize("value", [-1, MAX_VARINT + 1, 1 << 64])
def test_varint_out_of_range_is_refused(value: int) -> None:
    with pytest.raises(ValueError):
        encode_varint(value)


@given(VARINTS)
def test_varint_round_trip(value: int) -> None:
    assert Reader(encode_varint(value), complete=True).varint() == value


def test_truncated_input_needs_more_or_is_malformed() -> None:
    wire = encode_varint(1 << 40)
    with pytest.raises(NeedMore):
        Reader(wire[:3], complete=False).varint()
    with pytest.raises(ProtocolError) as info:
        Reader(wire[:3], complete=True).varint()
    assert info.value.code is ErrorCode.PROTOCOL_VIOLATION


def test_string_utf8() -> None:
    assert Reader(encode_string("jeu/vidéo"), complete=True).string() == "jeu/vidéo"
    with pytest.raises(ProtocolError):
        Reader(b"\x02\xc3\x28", complete=True).string()


def test_bool_strict() -> None:
    assert Reader(encode_bool(True) + encode_bool(False), complete=True).bool() is True
    with pytest.raises(ProtocolError):
        Reader(b"\x02", complete=True).bool()


def test_message_size_limit_and_exact_consumption() -> None:
    wire = encode_message(b"\x01\x02")
    body = Reader(wire, complete=True).message(max_size=2)
    assert body.raw(2) == b"\x01\x02"
    body.expect_end()
    with pytest.raises(ProtocolError) as info:
        Reader(wire, complete=True).message(max_size=1)
    assert info.value.code is ErrorCode.LIMIT_EXCEEDED
    body = Reader(wire, complete=True).message(max_size=10)
    body.u8()
    with pytest.raises(ProtocolError):
        body.expect_end()


MESSAGES = st.one_of(
    st.builds(m.AnnounceInterest, TEXT, VARINTS),
    st.builds(
        m.Announce,
        st.booleans(),
        TEXT,
        st.integers(0, m.MAX_HOPS),
        st.lists(VARINTS, max_size=4).map(tuple),
    ),
    st.builds(m.Subscribe, VARINTS, TEXT, TEXT, U8, st.booleans(), VARINTS, OPT_GROUP, OPT_GROUP),
    st.builds(m.SubscribeOk, U8, st.booleans(), VARINTS, OPT_GROUP, OPT_GROUP),
    st.builds(m.SubscribeUpdate, U8, st.booleans(), VARINTS, OPT_GROUP, OPT_GROUP),
    st.builds(m.SubscribeDrop, VARINTS, VARINTS, VARINTS),
    st.builds(m.Probe, VARINTS, st.none() | st.integers(1, MAX_VARINT)),
    st.builds(m.Fetch, TEXT, TEXT, U8, VARINTS),
    st.builds(m.Goaway, TEXT),
    st.builds(m.GroupHeader, VARINTS, VARINTS),
)


def _as_sent(message: m.Message, version: m.Version) -> m.Message:
    """Fields a version does not carry come back as their defaults."""
    if version is m.Version.LITE_03:
        if isinstance(message, m.AnnounceInterest):
            return m.AnnounceInterest(message.prefix)
        if isinstance(message, m.Announce):
            return m.Announce(message.active, message.suffix, message.hop_count)
        if isinstance(message, m.Probe):
            return m.Probe(message.bitrate)
    elif isinstance(message, m.Announce):
        return m.Announce(message.active, message.suffix, len(message.hops), message.hops)
    return message


@settings(max_examples=300)
@given(MESSAGES, VERSIONS)
def test_every_message_round_trips(message: m.Message, version: m.Version) -> None:
    wire = m.encode(message, version)
    body = Reader(wire, complete=True).message(max_size=1 << 20)
    decoded = type(message).decode(body, version)  # type: ignore[attr-defined]
    body.expect_end()
    assert decoded == _as_sent(message, version)


def test_subscribe_wire_layout_matches_moq_lite() -> None:
    """Hand-assembled from @moq/lite lite/subscribe.js: start/end travel as n+1."""
    wire = m.encode(m.Subscribe(5, "game", "video", 2, True, 100, None, 7))
    assert wire == bytes([18, 5, 4, *b"game", 5, *b"video", 2, 1, 0x40, 100, 0, 8])
    ok = m.encode_subscribe_response(m.SubscribeOk(2, True, 0))
    assert ok == bytes([0, 5, 2, 1, 0, 0, 0])
    drop = m.encode_subscribe_response(m.SubscribeDrop(1, 2, 3))
    assert drop == bytes([1, 3, 1, 2, 3])
    group = m.encode_group_stream_header(m.GroupHeader(3, 9))
    assert group == bytes([0, 2, 3, 9])
    assert m.encode_frame(b"ab") == b"\x02ab"


DECODERS = [
    m.AnnounceInterest,
    m.Announce,
    m.Subscribe,
    m.SubscribeOk,
    m.SubscribeUpdate,
    m.SubscribeDrop,
    m.Probe,
    m.Fetch,
    m.Goaway,
    m.GroupHeader,
]


@settings(max_examples=400)
@given(st.sampled_from(DECODERS), VERSIONS, st.binary(max_size=64))
def test_decoders_on_random_bytes_raise_only_protocol_error(
    decoder: type[m.AnnounceInterest], version: m.Version, data: bytes
) -> None:
    reader = Reader(data, complete=True)
    try:
        decoder.decode(reader, version)
        reader.expect_end()
    except ProtocolError:
        pass
