"""The link's decisions, without sockets: drop a packet, or when it leaves.

Sans-IO like server/moq/session.py: ``offer(size, now)`` takes a packet's length
and arrival time (seconds on any monotonic clock; the caller injects it) and
answers a ``Decision``. The emulator holds the packet until ``depart_at``.

A packet meets, in this order (netem's order, so figures compare with netem's):

1. loss: random (``loss``) and bursty (Gilbert-Elliott), decided on arrival;
   a lost packet takes no room in the queue;
2. the drop-tail queue: dropped if the bytes waiting ahead of it plus its own
   exceed the limit (a packet that finds the link idle is always taken, so a
   limit below one packet does not silence the link);
3. serialization: the link sends one packet at a time at ``rate_bps``, so a
   packet is on the far end ``len * 8 / rate`` after the previous one finished;
4. propagation: ``delay_ms`` +- ``jitter_ms``, never before the packet in front
   of it (a queue keeps order) unless ``reorder`` picks it, then it skips the
   delay line altogether and overtakes whatever is in it.

Every direction draws from its own seeded ``random.Random``, so the uplink's
traffic never changes the downlink's losses: a run is repeatable from its seed.
"""

from __future__ import annotations

import enum
import hashlib
import random
from dataclasses import asdict, dataclass

from server.net.link_profile import Direction, Schedule


class Fate(enum.Enum):
    DELIVER = "deliver"
    LOST = "lost"
    QUEUE_FULL = "queue_full"


@dataclass(frozen=True, slots=True)
class Decision:
    fate: Fate
    depart_at: float = 0.0
    """When the packet leaves the far end (same clock as ``now``); only for DELIVER."""


@dataclass(slots=True)
class DirectionCounters:
    packets_in: int = 0
    bytes_in: int = 0
    lost: int = 0
    """Dropped by random or bursty loss."""
    queue_dropped: int = 0
    """Dropped because the queue was full (the sender outran the rate)."""
    delivered: int = 0
    """Taken by the link: sent, or still in the queue or the delay line."""
    bytes_delivered: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


def _seed_for(seed: int, name: str) -> int:
    # Python's hash() of a str changes per process; a digest does not.
    digest = hashlib.sha256(f"{seed}/{name}".encode()).digest()
    return int.from_bytes(digest[:8], "big")


class DirectionShaper:
    """One direction of the link following one side (``down`` or ``up``) of a schedule."""

    def __init__(self, schedule: Schedule, side: str, seed: int, origin: float = 0.0) -> None:
        if side not in ("down", "up"):
            raise ValueError(f"side must be 'down' or 'up', not {side!r}")
        self._directions: tuple[Direction, ...] = tuple(
            getattr(step.profile, side) for step in schedule.steps
        )
        self._schedule = schedule
        self._rng = random.Random(_seed_for(seed, side))
        self.origin = origin
        self.counters = DirectionCounters()
        self._link_free_at = -float("inf")  # when the link finishes the last accepted packet
        self._last_departure = -float("inf")  # the order floor for the next packet
        self._in_bad_state = False  # Gilbert-Elliott chain

    def direction_at(self, now: float) -> Direction:
        return self._directions[self._schedule.index_at(now - self.origin)]

    def offer(self, size: int, now: float) -> Decision:
        direction = self.direction_at(now)
        counters = self.counters
        counters.packets_in += 1
        counters.bytes_in += size
        if self._is_lost(direction):
            counters.lost += 1
            return Decision(Fate.LOST)
        if direction.rate_bps is None:
            sent = now
        else:
            start = max(now, self._link_free_at)
            waited = start - now
            tx_s = size * 8.0 / direction.rate_bps
            if waited > 0.0 and waited + tx_s > direction.queue_limit_s:
                counters.queue_dropped += 1
                return Decision(Fate.QUEUE_FULL)
            self._link_free_at = sent = start + tx_s
        depart_at = self._propagate(direction, sent)
        counters.delivered += 1
        counters.bytes_delivered += size
        return Decision(Fate.DELIVER, depart_at)

    def _is_lost(self, direction: Direction) -> bool:
        lost = direction.loss > 0.0 and self._rng.random() < direction.loss
        chain = direction.burst_loss
        if chain is None:
            self._in_bad_state = False
            return lost
        flip = chain.p_bad_to_good if self._in_bad_state else chain.p_good_to_bad
        if self._rng.random() < flip:
            self._in_bad_state = not self._in_bad_state
        p_loss = chain.loss_in_bad if self._in_bad_state else chain.loss_in_good
        # Draw even when already lost, so the chain's sequence does not depend on `loss`.
        in_state = p_loss > 0.0 and self._rng.random() < p_loss
        return lost or in_state

    def _propagate(self, direction: Direction, sent: float) -> float:
        if direction.reorder > 0.0 and self._rng.random() < direction.reorder:
            # Skips the delay line; the floor stays, so the packets behind keep their order.
            return sent
        delay_s = direction.delay_ms / 1000.0
        if direction.jitter_ms > 0.0:
            jitter_s = direction.jitter_ms / 1000.0
            delay_s = max(0.0, delay_s + self._rng.uniform(-jitter_s, jitter_s))
        depart_at = max(sent + delay_s, self._last_departure)
        self._last_departure = depart_at
        return depart_at


class LinkShaper:
    """Both directions of one emulated link, on one schedule and one seed."""

    def __init__(self, schedule: Schedule, seed: int = 0, origin: float = 0.0) -> None:
        self.schedule = schedule
        self.down = DirectionShaper(schedule, "down", seed, origin)
        self.up = DirectionShaper(schedule, "up", seed, origin)

    @property
    def origin(self) -> float:
        return self.down.origin

    def restart_schedule(self, origin: float) -> None:
        """Make schedule time 0 be ``origin`` (e.g. when a benchmark's stream starts)."""
        self.down.origin = self.up.origin = origin

    def step_index(self, now: float) -> int:
        return self.schedule.index_at(now - self.origin)
