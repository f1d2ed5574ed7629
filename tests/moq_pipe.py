"""In-memory transport for MoqSession tests: QUIC stream numbering, ordered delivery.

A `Pipe` joins a client and a server session. `flush()` moves transmits across until both
sides are quiet. Holding a direction (`hold_to_client`) keeps its bytes queued, which is how
a viewer that never reads looks to the relay: `buffered_bytes(stream_id)` grows.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Hashable
from dataclasses import dataclass, field
from typing import Any

from server.moq.limits import MoqLimits
from server.moq.relay_core import RelayCore
from server.moq.session import MoqSession
from server.moq.transmit import CloseSession, ResetStream, SendData, StopSending, Transmit


class StreamIds:
    """QUIC ids: client bidi 0,4,8..; server bidi 1,5..; client uni 2,6..; server uni 3,7.."""

    def __init__(self, is_client: bool) -> None:
        self._next = {False: 0 if is_client else 1, True: 2 if is_client else 3}

    def open(self, is_unidirectional: bool) -> int:
        stream_id = self._next[is_unidirectional]
        self._next[is_unidirectional] += 4
        return stream_id


@dataclass
class Pipe:
    client_limits: MoqLimits | None = None
    server_limits: MoqLimits | None = None
    hold_to_client: bool = False
    client: MoqSession = field(init=False)
    server: MoqSession = field(init=False)
    closes: dict[str, CloseSession] = field(default_factory=dict)  # side that sent it
    _held: list[Transmit] = field(default_factory=list)
    _held_bytes: dict[int, int] = field(default_factory=lambda: defaultdict(int))

    def __post_init__(self) -> None:
        self.client = MoqSession(
            is_client=True, open_stream=StreamIds(True).open, limits=self.client_limits
        )
        self.server = MoqSession(
            is_client=False, open_stream=StreamIds(False).open, limits=self.server_limits
        )

    def flush(self) -> bool:
        """Deliver until quiet; True if anything moved."""
        moved = False
        while True:
            to_server = self.client.take_transmit()
            to_client = self.server.take_transmit()
            if not to_server and not to_client:
                return moved
            moved = True
            self._deliver(to_server, self.server, "client")
            if self.hold_to_client:
                for transmit in to_client:
                    if isinstance(transmit, SendData):
                        self._held_bytes[transmit.stream_id] += len(transmit.data)
                self._held.extend(to_client)
            else:
                self._deliver(to_client, self.client, "server")

    def release(self) -> None:
        """Stop holding and deliver what was held to the client."""
        self.hold_to_client = False
        held, self._held = self._held, []
        self._held_bytes.clear()
        self._deliver(held, self.client, "server")

    def buffered_bytes(self, stream_id: int) -> int:
        return self._held_bytes.get(stream_id, 0)

    def _deliver(self, transmits: list[Transmit], target: MoqSession, sender: str) -> None:
        for transmit in transmits:
            if isinstance(transmit, SendData):
                target.receive(transmit.stream_id, transmit.data, transmit.end_stream)
            elif isinstance(transmit, ResetStream | StopSending):
                target.stream_reset(transmit.stream_id, transmit.error_code)
            else:
                self.closes[sender] = transmit


class RelayNet:
    """A RelayCore with one Pipe per named connection; `pump()` runs until all is quiet."""

    def __init__(self, **relay_options: Any) -> None:
        self.now = 0.0
        self.pipes: dict[str, Pipe] = {}
        self.relay = RelayCore(self._buffered, clock=lambda: self.now, **relay_options)

    def connect(self, name: str, limits: MoqLimits | None = None) -> MoqSession:
        """A new peer; returns its (client) session. The relay side gets `limits`."""
        pipe = Pipe(server_limits=limits)
        self.pipes[name] = pipe
        self.relay.add_connection(name, pipe.server)
        self.pump()
        return pipe.client

    def disconnect(self, name: str) -> None:
        del self.pipes[name]
        self.relay.remove_connection(name)
        self.pump()

    def pump(self) -> None:
        for _ in range(1000):
            moved = False
            for name, pipe in list(self.pipes.items()):
                moved |= pipe.flush()
                self.relay.handle(name)  # its writes show up in the next round of flushes
            if not moved:
                return
        raise AssertionError("relay network does not settle")

    def _buffered(self, conn_id: Hashable, stream_id: int) -> int:
        pipe = self.pipes.get(str(conn_id))
        return 0 if pipe is None else pipe.buffered_bytes(stream_id)
