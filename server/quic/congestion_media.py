"""A congestion controller for real-time media on lossy links: ``upcast-media``.

Why not NewReno or CUBIC (aioquic's own): they read every loss as congestion and
halve the window each time. At 1 % random loss on an 8 Mbit/s, 30 ms path that
leaves a 5 Mbit/s video stream with 1.4 Mbit/s. Media wants a sender that holds its
rate while the path delivers, and backs off when the path says it is full.

The model, in the spirit of BBR (a rate estimate, not a loss-driven window):

- **Delivery rate** is sampled on every ACK as in draft-cheng-iccrg-delivery-rate-
  estimation: bytes delivered between a packet's send and its ACK, over the longer
  of the send and the ACK interval. A windowed **max filter** (``BW_WINDOW_S``)
  keeps the bottleneck estimate ``bw``; a 10 s **min filter** keeps ``min_rtt``.
- **Window** ``cwnd = CWND_GAIN * bw * (min_rtt + ACK_ALLOWANCE_S)``, at least
  ``MIN_WINDOW_PACKETS``. aioquic paces at ``cwnd / srtt`` (a controller cannot
  set the pacing rate itself), so pacing follows the estimate: a few times ``bw``
  on an empty queue, which spreads a video frame's burst, and ``bw`` once our own
  queue stands. The same gain makes the sender probe: while a link has room, each
  round's samples are higher and the window at least doubles per round trip (no
  separate slow start). ``ACK_ALLOWANCE_S`` (40 ms) covers the peer's ACK delay
  (QUIC's default max_ack_delay is 25 ms) and event-loop stalls of a busy host,
  which on loopback dwarf the path's RTT and would otherwise starve the window;
  the price is a standing queue of up to ~2 x (min_rtt + 40 ms) for a bulk sender,
  which video, app-limited below the link, does not build.

How it reacts:

- **Random loss of 1-2 %**: not at all. Lost packets only shave the delivered
  bytes; the window does not move.
- **Sustained loss above ``LOSS_THRESHOLD`` (10 %)**, measured over at least a
  round trip and ``LOSS_MIN_PACKETS`` packets so a few unlucky drops never count:
  a cap ``window_cap`` on the window is set to ``LOSS_BACKOFF`` (0.7) x the window,
  once per loss episode (losses of packets sent before the cut are the same
  event, as in Reno's recovery period); every clean round lets it grow by
  ``CAP_GROWTH_PACKETS`` (Reno's pace) until it no longer binds. A cap on bytes
  in flight, not on the rate, as BBRv2's inflight_hi: the delivery samples of a
  lossy link stay high, and what overflows a shallow buffer (a receiver's socket
  on a busy host among them) is the burst the window allows.
- **Queueing delay growth**: when every RTT sample for a while (our window's RTT
  term, at least ``QUEUE_MIN_PERIOD_S``) exceeds what our own window can queue
  (``QUEUE_RTT_FACTOR`` x ``CWND_GAIN`` x (min_rtt + allowance)), the estimate is
  stale (the link slowed down) or others fill the queue. The estimate drops to the
  rate delivered meanwhile (through the full queue: the link's rate), at most
  halving per period: averaged over the period rather than per ACK, and bounded,
  because a busy host that holds ACKs for 100 ms looks like a queue too.
- **Rate drop from 20 to 2 Mbit/s**: the queue builds, the delay rule halves the
  estimate every ~0.2 s down to the delivered rate; the max filter would forget
  the old rate within ``BW_WINDOW_S`` anyway. About 1.5 s in all (simulated: the
  estimate reaches 2.0 Mbit/s 1.75 s after the drop through a deep buffer).
- **Persistent congestion** (e.g. 3 s of 100 % loss): the window collapses to the
  minimum, the estimate and the cap are forgotten; growth restarts from the first
  ACKs and doubles per round trip.
- **App-limited periods** (video is app-limited most of the time): a packet sent
  after the sender sat idle with room in its window marks the connection
  app-limited until what is in flight is delivered. Such samples may raise the
  estimate (they are real measurements) but never lower it, and the filter keeps
  its best value while only app-limited samples arrive: idle scenes neither inflate
  nor collapse the estimate. The window grows only from measured rates, never from
  mere ACKs.

Per-packet state is a snapshot taken at send time, in a dict keyed by (epoch,
packet number): numbers are unique within a packet number space and aioquic hands
every in-flight packet back exactly once (acked, lost or expired), where it is
dropped.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from aioquic.quic.congestion.base import QuicCongestionControl, register_congestion_control
from aioquic.quic.packet_builder import QuicSentPacket
from aioquic.tls import Epoch

NAME = "upcast-media"

CWND_GAIN = 2.0
ACK_ALLOWANCE_S = 0.040
MIN_WINDOW_PACKETS = 4
BW_WINDOW_S = 1.0
MIN_RTT_WINDOW_S = 10.0
LOSS_THRESHOLD = 0.10
LOSS_MIN_PACKETS = 32
LOSS_BACKOFF = 0.7
CAP_GROWTH_PACKETS = 1
QUEUE_RTT_FACTOR = 1.25
QUEUE_MIN_PERIOD_S = 0.2
QUEUE_MAX_CUT = 0.5
IDLE_GAP_S = 0.002


@dataclass(frozen=True, slots=True)
class _SendState:
    """The connection's delivery counters when a packet left."""

    delivered: int
    delivered_time: float
    first_sent_time: float
    app_limited: bool


class WindowedMax:
    """Max of the samples of the last `window` seconds (a monotonic deque).

    Without new samples the best value stays: the estimate ages only when fresher
    measurements replace it.
    """

    def __init__(self, window: float) -> None:
        self.window = window
        self._samples: deque[tuple[float, float]] = deque()

    def update(self, now: float, value: float) -> None:
        while self._samples and self._samples[-1][1] <= value:
            self._samples.pop()
        self._samples.append((now, value))
        while self._samples[0][0] < now - self.window:
            self._samples.popleft()

    def reset(self, now: float, value: float) -> None:
        self._samples.clear()
        if value > 0:
            self._samples.append((now, value))

    @property
    def value(self) -> float:
        return self._samples[0][1] if self._samples else 0.0


class MediaCongestionControl(QuicCongestionControl):
    """Rate-based, loss-tolerant controller (see the module docstring)."""

    def __init__(self, *, max_datagram_size: int) -> None:
        super().__init__(max_datagram_size=max_datagram_size)
        self._mss = max_datagram_size
        self.min_window = MIN_WINDOW_PACKETS * max_datagram_size
        self.bw_filter = WindowedMax(BW_WINDOW_S)
        self.window_cap = math.inf  # bytes in flight, set by heavy loss
        self.min_rtt = math.inf
        self._min_rtt_stamp = 0.0
        self._sent: dict[tuple[Epoch, int], _SendState] = {}
        # delivery-rate state
        self.delivered = 0
        self._delivered_time = 0.0
        self._first_sent_time = 0.0
        self._last_sent_time: float | None = None
        self._app_limited_until = 0
        self._now = 0.0  # of the latest ACK
        # round trips: a round ends when a packet sent after it began is acked
        self.rounds = 0
        self._next_round_delivered = 0
        # queueing: since when every RTT sample is above what our window can queue
        self._queued_since: float | None = None
        self._queued_delivered = 0
        # loss accounting over at least one round and LOSS_MIN_PACKETS packets
        self._loss_acked = 0
        self._loss_lost = 0
        self._backoff_time = -math.inf  # losses of packets sent before it were answered

    # -- the estimate --------------------------------------------------------

    @property
    def bandwidth(self) -> float:
        """The bottleneck rate estimate, bytes per second."""
        return self.bw_filter.value

    def _model_window(self) -> float:
        if self.bandwidth <= 0 or math.isinf(self.min_rtt):
            return math.inf  # nothing measured yet
        return CWND_GAIN * self.bandwidth * (self.min_rtt + ACK_ALLOWANCE_S)

    def _update_window(self) -> None:
        target = min(self._model_window(), self.window_cap)
        if math.isinf(target):
            return  # nothing measured yet: keep the initial (or collapsed) window
        self.congestion_window = max(self.min_window, int(target))

    # -- aioquic's interface ---------------------------------------------------

    def on_packet_sent(self, *, packet: QuicSentPacket) -> None:
        now = packet.sent_time or 0.0
        if self.bytes_in_flight == 0:
            self._first_sent_time = self._delivered_time = now
        idle = self._last_sent_time is not None and now - self._last_sent_time > IDLE_GAP_S
        if idle and self.bytes_in_flight + packet.sent_bytes < self.congestion_window:
            # The sender had room and sent nothing: it was short of data. Samples
            # until what is in flight now is delivered measure the app, not the path.
            self._app_limited_until = max(self.delivered + self.bytes_in_flight, 1)
        self._last_sent_time = now
        self._sent[packet.epoch, packet.packet_number] = _SendState(
            self.delivered, self._delivered_time, self._first_sent_time, self._app_limited_until > 0
        )
        self.bytes_in_flight += packet.sent_bytes

    def on_packet_acked(self, *, now: float, packet: QuicSentPacket) -> None:
        self.bytes_in_flight -= packet.sent_bytes
        self.delivered += packet.sent_bytes
        self._delivered_time = now
        self._loss_acked += 1
        state = self._sent.pop((packet.epoch, packet.packet_number), None)
        self._now = now
        if self._app_limited_until and self.delivered > self._app_limited_until:
            self._app_limited_until = 0
        if state is None or packet.sent_time is None:
            return
        self._first_sent_time = packet.sent_time
        if state.delivered >= self._next_round_delivered:
            self._end_round()

        interval = max(packet.sent_time - state.first_sent_time, now - state.delivered_time)
        if interval <= 0 or interval < min(self.min_rtt, 1.0):
            return  # shorter than a round trip: ACK compression, not a rate
        rate = (self.delivered - state.delivered) / interval
        if not state.app_limited or rate >= self.bw_filter.value:
            self.bw_filter.update(now, rate)
        self._update_window()

    def on_packets_expired(self, *, packets: Iterable[QuicSentPacket]) -> None:
        for packet in packets:
            self.bytes_in_flight -= packet.sent_bytes
            self._sent.pop((packet.epoch, packet.packet_number), None)

    def on_packets_lost(self, *, now: float, packets: Iterable[QuicSentPacket]) -> None:
        for packet in packets:
            self.bytes_in_flight -= packet.sent_bytes
            self._sent.pop((packet.epoch, packet.packet_number), None)
            if packet.sent_time is not None and packet.sent_time > self._backoff_time:
                self._loss_lost += 1

    def on_persistent_congestion(self) -> None:
        self.bw_filter.reset(0.0, 0.0)
        self.window_cap = math.inf
        self._loss_acked = self._loss_lost = 0
        self.congestion_window = self.min_window

    def on_rtt_measurement(self, *, now: float, rtt: float) -> None:
        if rtt <= self.min_rtt or now - self._min_rtt_stamp > MIN_RTT_WINDOW_S:
            self.min_rtt = rtt
            self._min_rtt_stamp = now
        own_rtt = CWND_GAIN * (self.min_rtt + ACK_ALLOWANCE_S)  # the most we queue
        if rtt <= QUEUE_RTT_FACTOR * own_rtt:
            self._queued_since = None
        elif self._queued_since is None:
            self._queued_since, self._queued_delivered = now, self.delivered
        elif now - self._queued_since >= max(own_rtt, QUEUE_MIN_PERIOD_S):
            self._on_queue(now, self._queued_since)
            self._queued_since, self._queued_delivered = now, self.delivered

    def get_log_data(self) -> dict[str, Any]:
        data = super().get_log_data()
        data["bandwidth"] = self.bandwidth
        return data

    # -- congestion signals ----------------------------------------------------

    def _on_queue(self, now: float, since: float) -> None:
        """Every RTT sample since `since` was above what our own window can queue:
        the link slowed down, or others fill the queue."""
        best = self.bw_filter.value
        # What was delivered meanwhile went through the standing queue: the link's
        # rate. Averaged over the period, as single samples shrink to nothing when
        # a busy host holds ACKs; at most halved each time, so that a slow moment
        # of the host cannot wipe the estimate.
        through_queue = (self.delivered - self._queued_delivered) / (now - since)
        if through_queue < best:
            self.bw_filter.reset(now, max(through_queue, QUEUE_MAX_CUT * best))
            self._update_window()

    def _end_round(self) -> None:
        self.rounds += 1
        self._next_round_delivered = self.delivered
        counted = self._loss_acked + self._loss_lost
        lossy = self._loss_lost > LOSS_THRESHOLD * max(counted, LOSS_MIN_PACKETS)
        if lossy:
            # once per loss episode, as Reno's recovery period: the rest of a burst
            # of drops (packets sent before now) is the same event
            self.window_cap = max(self.min_window, LOSS_BACKOFF * self.congestion_window)
            self._backoff_time = self._now
        elif self.window_cap < math.inf:
            self.window_cap += CAP_GROWTH_PACKETS * self._mss
            if self.window_cap > self._model_window():
                self.window_cap = math.inf
        if lossy or counted >= LOSS_MIN_PACKETS:
            self._loss_acked = self._loss_lost = 0
        self._update_window()


def register() -> None:
    """Make ``upcast-media`` a name ``QuicConfiguration.congestion_control_algorithm``
    accepts (idempotent)."""
    register_congestion_control(NAME, MediaCongestionControl)


register()
