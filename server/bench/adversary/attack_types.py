"""What an attack scenario is given, what it reports, and what the relay should count."""

from __future__ import annotations

import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field

from server.auth.keys import AuthKey
from server.bench.adversary.client import AttackConnection, Target, count_still_served

GUARD = "upcast_relay_guard_refusals_total"
UNAUTHORIZED = "upcast_relay_sessions_unauthorized_total"
SKIPPED = "upcast_relay_groups_skipped_total"

# Bounds every scenario keeps whatever its duration: the adversary must never be the
# thing that exhausts the machine.
MAX_CONNECTIONS = 2000
MAX_FLOOD_BYTES = 256 * 1024 * 1024


@dataclass(frozen=True)
class AttackContext:
    target: Target
    auth_key: AuthKey | None = None  # an auth relay's key (bad-token scenarios mint with it)
    broadcast: str = "game"  # what the good viewers watch (stalled viewers join it)
    publisher_token: str | None = None


@dataclass(frozen=True)
class Expectation:
    """A counter sample that must grow during the attack: ``metric`` with its ``reason``
    label among ``reasons`` (any of them; none: the unlabelled sample)."""

    metric: str
    reasons: tuple[str, ...] = ()

    def describe(self) -> str:
        return f"{self.metric}{{reason in {list(self.reasons)}}}" if self.reasons else self.metric


@dataclass
class AttackResult:
    """What the attacker saw. Times are time.monotonic()."""

    name: str
    started: float = field(default_factory=time.monotonic)
    ended: float = 0.0
    connections: int = 0
    bytes_sent: int = 0
    crossed_at: float | None = None  # first crossing of the limit under test
    closed_at: float | None = None  # the relay closing the first connection that crossed it
    close_codes: list[int] = field(default_factory=list)  # QUIC/HTTP/3 CONNECTION_CLOSE codes
    statuses: list[str] = field(default_factory=list)  # :status of each request sent
    session_closes: list[int] = field(default_factory=list)  # WebTransport CLOSE codes
    open_at_end: int = 0  # attacking connections the relay had not closed at the end
    sent_log: list[tuple[float, int]] = field(default_factory=list)  # first connection
    notes: list[str] = field(default_factory=list)

    @property
    def close_delay_s(self) -> float | None:
        if self.crossed_at is None or self.closed_at is None:
            return None
        return self.closed_at - self.crossed_at

    def time_at_bytes(self, count: int) -> float | None:
        """When the first connection had sent ``count`` bytes (None: it never did)."""
        return next((t for t, n in self.sent_log if n >= count), None)

    async def finish(self, conns: Sequence[AttackConnection]) -> None:
        """The attack is over: note which connections the relay still serves, then drop
        them all without a word (a vanished client costs the relay its idle timeout at
        most)."""
        self.open_at_end = await count_still_served(conns)
        for conn in conns:
            conn.vanish()
        self.ended = time.monotonic()

    def record_close(self, conn: AttackConnection, *, first: bool) -> None:
        if conn.closed is not None and conn.closed.by_peer:
            self.close_codes.append(conn.closed.error_code)
            if first and self.closed_at is None:
                self.closed_at = conn.closed.at

    def as_dict(self) -> dict[str, object]:
        return {
            "connections": self.connections,
            "bytes_sent": self.bytes_sent,
            "close_delay_s": self.close_delay_s,
            "close_codes": sorted(set(self.close_codes)),
            "statuses": sorted(set(self.statuses)),
            "session_close_codes": sorted(set(self.session_closes)),
            "open_at_end": self.open_at_end,
            "notes": self.notes,
        }


AttackFn = Callable[[AttackContext, float], Awaitable[AttackResult]]


@dataclass(frozen=True)
class Scenario:
    name: str
    run: AttackFn
    description: str
    expects: tuple[Expectation, ...] = ()
    closes_attacker: bool = True  # the relay must close every attacking connection
    auth: bool = False  # needs a relay that checks tokens (AttackContext.auth_key)
