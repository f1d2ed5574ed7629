"""moq-lite primitive encodings: QUIC varints, strings, bools, size-prefixed messages.

`Reader` serves two cases with one API: a *complete* buffer (a message body whose size is
known) where running out of bytes is malformed input, and an *incomplete* stream buffer
where running out means "wait for more bytes" (`NeedMore`). Every failure on peer bytes is a
`ProtocolError`; no IndexError/UnicodeDecodeError escapes.
"""

from __future__ import annotations

from .errors import ErrorCode, ProtocolError

MAX_VARINT = (1 << 62) - 1


class NeedMore(Exception):
    """Internal signal: the stream buffer ends before the item; retry with more bytes."""


def encode_varint(value: int) -> bytes:
    """RFC 9000 section 16, shortest form."""
    if value < 0 or value > MAX_VARINT:
        raise ValueError(f"varint out of range: {value}")
    if value < 1 << 6:
        return bytes((value,))
    if value < 1 << 14:
        return (value | 0x4000).to_bytes(2, "big")
    if value < 1 << 30:
        return (value | 0x8000_0000).to_bytes(4, "big")
    return (value | 0xC000_0000_0000_0000).to_bytes(8, "big")


def encode_u8(value: int) -> bytes:
    if not 0 <= value <= 0xFF:
        raise ValueError(f"u8 out of range: {value}")
    return bytes((value,))


def encode_bool(value: bool) -> bytes:
    return b"\x01" if value else b"\x00"


def encode_string(value: str) -> bytes:
    data = value.encode("utf-8")
    return encode_varint(len(data)) + data


def encode_message(body: bytes) -> bytes:
    """Every moq-lite control message is `varint size + body`."""
    return encode_varint(len(body)) + body


class Reader:
    """Cursor over bytes; see the module docstring for complete vs incomplete buffers."""

    __slots__ = ("_complete", "_data", "pos")

    def __init__(self, data: bytes | bytearray | memoryview, *, complete: bool) -> None:
        self._data = memoryview(data)
        self._complete = complete
        self.pos = 0

    def release(self) -> None:
        """Drop the view so the caller may resize the bytearray it reads from."""
        self._data.release()

    @property
    def remaining(self) -> int:
        return len(self._data) - self.pos

    def _need(self, size: int) -> None:
        if self.pos + size > len(self._data):
            if self._complete:
                raise ProtocolError(ErrorCode.PROTOCOL_VIOLATION, "message truncated")
            raise NeedMore

    def varint(self) -> int:
        self._need(1)
        first = self._data[self.pos]
        length = 1 << (first >> 6)
        self._need(length)
        value = int.from_bytes(self._data[self.pos : self.pos + length], "big")
        self.pos += length
        return value & ((1 << (8 * length - 2)) - 1)

    def u8(self) -> int:
        self._need(1)
        value = self._data[self.pos]
        self.pos += 1
        return value

    def bool(self) -> bool:
        value = self.u8()
        if value > 1:
            raise ProtocolError(ErrorCode.PROTOCOL_VIOLATION, f"invalid bool {value}")
        return value == 1

    def raw(self, size: int) -> bytes:
        self._need(size)
        value = bytes(self._data[self.pos : self.pos + size])
        self.pos += size
        return value

    def string(self) -> str:
        size = self.varint()
        # Check before reading so a huge declared length cannot make us wait forever on a
        # complete buffer; on an incomplete one the caller's size limits bound it.
        data = self.raw(size)
        try:
            return data.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ProtocolError(ErrorCode.PROTOCOL_VIOLATION, "invalid UTF-8 string") from exc

    def message(self, max_size: int) -> Reader:
        """Read a size-prefixed message; returns a complete Reader over its body."""
        size = self.varint()
        if size > max_size:
            raise ProtocolError(
                ErrorCode.LIMIT_EXCEEDED, f"message of {size} bytes exceeds {max_size}"
            )
        return Reader(self.raw(size), complete=True)

    def expect_end(self) -> None:
        """A message body must be consumed exactly (same rule as @moq/lite)."""
        if self.remaining:
            raise ProtocolError(
                ErrorCode.PROTOCOL_VIOLATION, f"{self.remaining} trailing bytes in message"
            )
