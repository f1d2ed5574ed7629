"""Error codes and the one exception the moq-lite decoders raise.

moq-lite does not fix numeric codes on the wire (the browser only logs them), so these are
ours. They travel in RESET_STREAM / STOP_SENDING and in the WebTransport CLOSE_SESSION.
"""

from __future__ import annotations

from enum import IntEnum


class ErrorCode(IntEnum):
    """Application error codes used for stream resets and session closes."""

    CANCEL = 0  # we no longer want this stream (unsubscribe, group finished elsewhere)
    INTERNAL = 1
    PROTOCOL_VIOLATION = 2  # malformed bytes, unknown stream type, wrong message order
    LIMIT_EXCEEDED = 3  # a MoqLimits bound was crossed
    NOT_FOUND = 4  # subscribe to a broadcast/track nobody publishes
    UNSUPPORTED = 5  # fetch, and other requests we do not serve
    DUPLICATE = 6  # a subscription id reused while still active
    SKIPPED = 7  # relay dropped this group because the viewer fell behind
    GONE = 8  # the publisher of this track went away
    UNAUTHORIZED = 9  # the session's token does not allow this publish or subscribe


class ProtocolError(Exception):
    """The peer sent something that is not valid moq-lite; fatal for that session only."""

    def __init__(self, code: ErrorCode, reason: str) -> None:
        super().__init__(f"{code.name}: {reason}")
        self.code = code
        self.reason = reason
