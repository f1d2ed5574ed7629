"""WebTransport error codes carried inside HTTP/3's error code space.

A WebTransport application error code n travels on the wire (RESET_STREAM,
STOP_SENDING) as 0x52e4a40fa8db + n + n // 0x1e, skipping the reserved
"greasing" codepoints. Browsers do this mapping themselves, so the server must
too, or the JavaScript side sees different numbers from the ones we sent.
"""

from __future__ import annotations

FIRST = 0x52E4A40FA8DB
LAST = 0x52E5AC983162
MAX_APP_CODE = 0xFFFFFFFF

# HTTP/3 codes used to close the CONNECT stream or the whole connection.
H3_NO_ERROR = 0x100
H3_REQUEST_REJECTED = 0x10B
CLOSE_WEBTRANSPORT_SESSION = 0x2843
SETTINGS_WT_MAX_SESSIONS = 0x14E9CD29


def to_http_code(code: int) -> int:
    if not 0 <= code <= MAX_APP_CODE:
        raise ValueError(f"WebTransport error code out of range: {code}")
    return FIRST + code + code // 0x1E


def from_http_code(code: int) -> int | None:
    """The WebTransport code for an HTTP/3 code, or None when it is not one."""
    if not FIRST <= code <= LAST:
        return None
    shifted = code - FIRST
    if shifted % 0x1F == 0x1E:
        return None  # a reserved greasing codepoint
    return shifted - shifted // 0x1F
