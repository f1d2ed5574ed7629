"""moq-lite-03 (the protocol of @moq/lite) as sans-IO state machines, plus a relay core.

- `wire`, `messages`: encodings; `session.MoqSession`: one session, both roles;
- `relay_core.RelayCore`: fan-out over many sessions; no sockets anywhere in this package.

May import: nothing of ``server`` outside this package (sans-IO: no sockets, no asyncio).
"""

from .errors import ErrorCode, ProtocolError
from .limits import MoqLimits
from .messages import Version
from .relay_core import ConnStats, RelayCore
from .session import MoqSession, SessionClosedError
from .transmit import (
    CloseSession,
    ResetStream,
    SendData,
    StopSending,
    Transmit,
    is_client_initiated,
    is_unidirectional,
)

ALPN_LITE_03 = "moq-lite-03"  # the WebTransport protocol name to answer with

__all__ = [
    "ALPN_LITE_03",
    "CloseSession",
    "ConnStats",
    "ErrorCode",
    "MoqLimits",
    "MoqSession",
    "ProtocolError",
    "RelayCore",
    "ResetStream",
    "SendData",
    "SessionClosedError",
    "StopSending",
    "Transmit",
    "Version",
    "is_client_initiated",
    "is_unidirectional",
]
