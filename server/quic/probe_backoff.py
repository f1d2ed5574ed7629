"""A cap on the backoff of QUIC's probe timeout, for a sender of live media.

RFC 9002 doubles the probe timeout (PTO) every time one fires unanswered. Through an
outage of a few seconds the doublings add up, and the next probe after the path comes
back can be seconds away; until it goes out and is acknowledged nothing else does,
because the congestion window is spent on the packets lost in the outage. In
``upcast bench network``'s blackout (3 s of 100 % loss on a 15 ms path) the stream
came back 0.3 to 1.2 s after the link did in most runs and 7 s after it in one: it
depends on where the doubling had got to. A player waiting for live frames is better
served by a probe at most every ``MAX_PROBE_INTERVAL_S``: after the handshake the
backed-off PTO is capped there (never below the PTO without backoff). What it costs
is one probe packet per interval while a path is dead; the idle timeout still ends a
connection whose peer is gone.

aioquic (pinned in pyproject.toml) keeps its recovery state in ``QuicConnection._loss``
and has no setting for this; the cap is a subclass swapped onto that object.
"""

from __future__ import annotations

import logging
import math

from aioquic.quic.connection import QuicConnection
from aioquic.quic.recovery import QuicPacketRecovery

log = logging.getLogger(__name__)

MAX_PROBE_INTERVAL_S = 0.5


class CappedProbeRecovery(QuicPacketRecovery):
    """aioquic's loss recovery with the PTO's backoff capped (module docstring)."""

    def get_loss_detection_time(self, *, amplification_limited: bool) -> float | None:
        count = self._pto_count
        if not self.handshake_confirmed or count == 0:
            return super().get_loss_detection_time(amplification_limited=amplification_limited)
        base = self.get_probe_timeout(include_max_ack_delay=True)
        doublings = max(0, math.floor(math.log2(MAX_PROBE_INTERVAL_S / base))) if base > 0 else 0
        self._pto_count = min(count, doublings)
        try:
            return super().get_loss_detection_time(amplification_limited=amplification_limited)
        finally:
            self._pto_count = count


def cap_probe_backoff(quic: QuicConnection) -> None:
    """Give ``quic`` the capped probe backoff (a no-op, logged, if aioquic's recovery
    object is not where this version keeps it)."""
    loss = getattr(quic, "_loss", None)
    if type(loss) is QuicPacketRecovery:
        loss.__class__ = CappedProbeRecovery
    elif not isinstance(loss, CappedProbeRecovery):
        log.warning("aioquic keeps no QuicPacketRecovery in _loss: probe backoff not capped")
