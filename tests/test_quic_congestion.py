"""The ``upcast-media`` controller driven through aioquic's own loss recovery
(``QuicPacketRecovery``: RTT, loss detection, persistent congestion, the pacer) by
synthetic packets over a simulated bottleneck. No sockets, no wall clock."""

from __future__ import annotations

import heapq
import random
from collections.abc import Callable
from dataclasses import dataclass, field

import pytest
from aioquic.quic.packet import QuicPacketType
from aioquic.quic.packet_builder import QuicDeliveryState, QuicSentPacket
from aioquic.quic.rangeset import RangeSet
from aioquic.quic.recovery import QuicPacketRecovery, QuicPacketSpace
from aioquic.tls import Epoch

from server.quic.congestion_media import ACK_ALLOWANCE_S, NAME, MediaCongestionControl
from server.quic.congestion_register import algorithm_names

MSS = 1280
MBIT = 1e6 / 8  # bytes per second
STEP_S = 0.0005


@dataclass
class Link:
    """A FIFO bottleneck: rate (may change over time), queue limit, random loss,
    propagation delay split evenly both ways; ACKs travel back unqueued."""

    rate: Callable[[float], float]
    rtt_s: float = 0.030
    loss: Callable[[float], float] = lambda t: 0.0
    queue_bytes: int = 200_000
    seed: int = 1
    _free_at: float = 0.0

    def __post_init__(self) -> None:
        self._rng = random.Random(self.seed)

    def admit(self, now: float, size: int) -> float | None:
        """Arrival time at the receiver, or None when dropped."""
        start = max(now, self._free_at)
        if (start - now) * self.rate(now) + size > self.queue_bytes:
            return None  # tail drop
        self._free_at = start + size / self.rate(now)
        if self._rng.random() < self.loss(now):
            return None  # random loss after the queue: it still took link time
        return self._free_at + self.rtt_s / 2


@dataclass
class Sim:
    algorithm: str
    link: Link
    app_rate: Callable[[float], float] | None = None  # bytes/s of video; None = bulk
    frame_interval_s: float = 1 / 30
    now: float = 0.0
    received: list[tuple[float, int, float]] = field(default_factory=list)  # (arrival, bytes, sent)
    trace: list[tuple[float, int, float]] = field(default_factory=list)  # (t, cwnd, bandwidth)
    _probe: bool = False

    def __post_init__(self) -> None:
        self.recovery = QuicPacketRecovery(
            congestion_control_algorithm=self.algorithm,
            initial_rtt=0.1,
            max_datagram_size=MSS,
            peer_completed_address_validation=True,
            send_probe=self._want_probe,
        )
        self.recovery.handshake_confirmed = True
        self.space = QuicPacketSpace(is_application_data=True)
        self.recovery.spaces = [self.space]
        self.cc = self.recovery._cc
        self._acks: list[tuple[float, int]] = []
        self._pn = 0
        self._backlog = 0  # app bytes waiting (video) incl. retransmissions
        self._next_frame = 0.0

    @property
    def media(self) -> MediaCongestionControl:
        assert isinstance(self.cc, MediaCongestionControl)
        return self.cc

    def _want_probe(self) -> None:
        self._probe = True

    def _lost(self, state: QuicDeliveryState, size: int) -> None:
        if state == QuicDeliveryState.LOST:
            self._backlog += size

    def _send(self) -> None:
        packet = QuicSentPacket(
            epoch=Epoch.ONE_RTT,
            in_flight=True,
            is_ack_eliciting=True,
            is_crypto_packet=False,
            packet_number=self._pn,
            packet_type=QuicPacketType.ONE_RTT,
            sent_time=self.now,
            sent_bytes=MSS,
        )
        packet.delivery_handlers.append((self._lost, (MSS,)))
        self._pn += 1
        self.recovery.on_packet_sent(packet=packet, space=self.space)
        self.recovery._pacer.update_after_send(now=self.now)
        arrival = self.link.admit(self.now, MSS)
        if arrival is not None:
            self.received.append((arrival, MSS, self.now))
            heapq.heappush(self._acks, (arrival + self.link.rtt_s / 2, packet.packet_number))

    def run(self, until: float) -> None:
        while self.now < until:
            self.now += STEP_S
            acked = RangeSet()
            while self._acks and self._acks[0][0] <= self.now:
                _, pn = heapq.heappop(self._acks)
                acked.add(pn)
            if len(acked):
                self.recovery.on_ack_received(
                    ack_rangeset=acked, ack_delay=0.0, now=self.now, space=self.space
                )
            timer = self.recovery.get_loss_detection_time(amplification_limited=False)
            if timer is not None and timer <= self.now:
                self.recovery.on_loss_detection_timeout(now=self.now)
            if self.app_rate is not None:
                while self._next_frame <= self.now:
                    self._backlog += int(self.app_rate(self.now) * self.frame_interval_s)
                    self._next_frame += self.frame_interval_s
            if self._probe:
                self._probe = False
                self._send()
            while self.app_rate is None or self._backlog >= MSS:
                if self.recovery.bytes_in_flight + MSS > self.recovery.congestion_window:
                    break
                if self.recovery._pacer.next_send_time(self.now) is not None:
                    break
                self._send()
                self._backlog = max(0, self._backlog - MSS)
            bw = self.cc.bandwidth if isinstance(self.cc, MediaCongestionControl) else 0.0
            self.trace.append((self.now, self.recovery.congestion_window, bw))

    def goodput(self, start: float, end: float) -> float:
        """Bytes/s that arrived in [start, end)."""
        got = sum(size for arrival, size, _ in self.received if start <= arrival < end)
        return got / (end - start)

    def delays(self, start: float, end: float) -> list[float]:
        return sorted(a - s for a, _, s in self.received if start <= s < end)


def constant(value: float) -> Callable[[float], float]:
    return lambda t: value


def test_registered_with_aiquic_names() -> None:
    names = algorithm_names()
    assert names[0] == NAME
    assert {"reno", "cubic"} <= set(names)


@pytest.mark.parametrize("loss", [0.01, 0.02])
def test_random_loss_keeps_the_rate(loss: float) -> None:
    figures = {}
    for algorithm in (NAME, "reno"):
        sim = Sim(algorithm, Link(constant(8 * MBIT), loss=constant(loss), queue_bytes=60_000))
        sim.run(10.0)
        figures[algorithm] = sim.goodput(2.0, 10.0) / MBIT
    shown = ", ".join(f"{k} {v:.2f} Mbit/s" for k, v in figures.items())
    assert figures[NAME] >= 0.85 * 8 * (1 - loss), shown
    assert figures[NAME] >= 1.4 * figures["reno"], shown


def test_sustained_heavy_loss_backs_off() -> None:
    sim = Sim(NAME, Link(constant(8 * MBIT), loss=lambda t: 0.25 if t >= 3 else 0.0))
    sim.run(3.0)
    sim.run(6.0)
    assert sim.goodput(5.0, 6.0) < 0.3 * sim.goodput(2.0, 3.0), sim.goodput(5.0, 6.0) / MBIT
    assert min(cwnd for _, cwnd, _ in sim.trace) >= sim.media.min_window


def test_loss_backoff_is_released_when_loss_ends() -> None:
    sim = Sim(NAME, Link(constant(8 * MBIT), loss=lambda t: 0.25 if 2 <= t < 4 else 0.0))
    sim.run(10.0)
    assert sim.goodput(7.0, 10.0) >= 0.85 * 8 * MBIT, sim.goodput(7.0, 10.0) / MBIT


@pytest.mark.parametrize("queue_bytes", [1_000_000, 40_000])
def test_rate_drop_converges_within_two_seconds(queue_bytes: int) -> None:
    """20 -> 2 Mbit/s at t=4: a deep buffer (delay says it) or a shallow one (loss)."""
    link = Link(lambda t: (20 if t < 4 else 2) * MBIT, queue_bytes=queue_bytes)
    sim = Sim(NAME, link)
    sim.run(4.0)
    assert sim.goodput(3.0, 4.0) >= 0.9 * 20 * MBIT
    sim.run(7.0)
    assert sim.media.bandwidth < 3 * MBIT, sim.media.bandwidth / MBIT
    delays = sim.delays(5.5, 6.5)
    # queue drained: what is sent 1.5 s after the drop waits less than 150 ms
    assert delays[len(delays) // 2] < 0.015 + 0.150, delays[len(delays) // 2]
    assert sim.goodput(5.5, 7.0) >= 0.8 * 2 * MBIT


def test_queueing_delay_from_other_traffic_backs_off() -> None:
    """An unresponsive 6 Mbit/s flood joins the 8 Mbit/s queue at t=3: the
    sender yields instead of holding its share and the queue's delay."""
    link = Link(constant(8 * MBIT), queue_bytes=2_000_000)
    flood = {"next": 3.0}
    admit = link.admit

    def admit_with_flood(now: float, size: int) -> float | None:
        while flood["next"] <= now:
            admit(flood["next"], MSS)
            flood["next"] += MSS / (6 * MBIT)
        return admit(now, size)

    link.admit = admit_with_flood  # type: ignore[method-assign]
    sim = Sim(NAME, link)
    sim.run(3.0)
    before = sim.media.bandwidth
    sim.run(8.0)
    assert sim.media.bandwidth < 0.5 * before, (before / MBIT, sim.media.bandwidth / MBIT)
    delays = sim.delays(6.0, 7.5)
    assert delays[len(delays) // 2] < 0.015 + 0.300, delays[len(delays) // 2]


def test_persistent_congestion_collapses_then_recovers() -> None:
    link = Link(constant(8 * MBIT), loss=lambda t: 1.0 if 3 <= t < 6 else 0.0)
    sim = Sim(NAME, link)
    sim.run(3.0)
    assert sim.goodput(2.0, 3.0) >= 0.85 * 8 * MBIT
    # aioquic's probe timeout backs off exponentially: the first probe after the
    # outage leaves near t=7.8 and its ACK establishes persistent congestion
    sim.run(8.5)
    collapsed = [t for t, cwnd, _ in sim.trace if t > 6 and cwnd == sim.media.min_window]
    assert collapsed, "the window never collapsed to its minimum"
    assert min(cwnd for _, cwnd, _ in sim.trace) >= sim.media.min_window
    sim.run(10.0)
    assert sim.goodput(9.0, 10.0) >= 0.85 * 8 * MBIT, sim.goodput(9.0, 10.0) / MBIT


def test_app_limited_neither_inflates_nor_collapses() -> None:
    """Video at 3 Mbit/s on a 20 Mbit/s link, then 2 s of silence, then video again."""
    sim = Sim(NAME, Link(constant(20 * MBIT)), app_rate=lambda t: 0 if 4 <= t < 6 else 3 * MBIT)
    sim.run(4.0)
    estimate = sim.media.bandwidth
    window = sim.recovery.congestion_window
    # measured from bursts, so never above the link; the window follows the estimate
    assert estimate <= 20 * MBIT * 1.05
    assert window <= 2.5 * estimate * (sim.media.min_rtt + ACK_ALLOWANCE_S)
    sim.run(5.9)
    assert sim.media.bandwidth >= 0.9 * estimate, "the idle period collapsed the estimate"
    assert sim.recovery.congestion_window >= 0.9 * window
    sim.run(8.0)
    assert sim.goodput(6.5, 8.0) >= 0.95 * 3 * MBIT
    delays = sim.delays(6.5, 8.0)
    assert delays[int(len(delays) * 0.95)] < 0.015 + 0.040, delays[int(len(delays) * 0.95)]


def test_app_limited_samples_do_not_lower_the_estimate() -> None:
    cc = MediaCongestionControl(max_datagram_size=MSS)
    pn = 0

    def packet(t: float) -> QuicSentPacket:
        nonlocal pn
        pn += 1
        return QuicSentPacket(
            epoch=Epoch.ONE_RTT,
            in_flight=True,
            is_ack_eliciting=True,
            is_crypto_packet=False,
            packet_number=pn,
            packet_type=QuicPacketType.ONE_RTT,
            sent_time=t,
            sent_bytes=MSS,
        )

    # a busy sender, one packet per millisecond (10.24 Mbit/s), each acked 30 ms
    # later: a real measurement
    in_flight: list[QuicSentPacket] = []
    for i in range(300):
        t = i * 0.001
        while (
            in_flight and in_flight[0].sent_time is not None and in_flight[0].sent_time <= t - 0.030
        ):
            acked = in_flight.pop(0)
            cc.on_packet_acked(now=t, packet=acked)
            cc.on_rtt_measurement(now=t, rtt=0.030)
        p = packet(t)
        cc.on_packet_sent(packet=p)
        in_flight.append(p)
    for p in in_flight:
        cc.on_packet_acked(now=0.330, packet=p)
    measured = cc.bandwidth
    assert 8 * MBIT < measured < 12 * MBIT
    # then a trickle, one packet every 100 ms after idling: app-limited
    t = 1.0
    for _ in range(20):
        p = packet(t)
        cc.on_packet_sent(packet=p)
        cc.on_packet_acked(now=t + 0.030, packet=p)
        cc.on_rtt_measurement(now=t + 0.030, rtt=0.030)
        t += 0.1
    assert cc.bandwidth == measured


def test_relay_setting_defaults_to_media_and_accepts_reno_cubic() -> None:
    from pydantic import ValidationError

    from server.quic.certs import generate_cert
    from server.quic.server import server_configuration
    from server.relay.settings import RelaySettings

    assert RelaySettings(no_auth=True).congestion_control == NAME
    for name in ("reno", "cubic"):
        assert RelaySettings(no_auth=True, congestion_control=name).congestion_control == name
    with pytest.raises(ValidationError, match=r"(?s)congestion_control.*allowed: upcast-media"):
        RelaySettings(no_auth=True, congestion_control="bbr9")
    cert = generate_cert()
    assert server_configuration(cert).congestion_control_algorithm == NAME
    assert server_configuration(cert, congestion_control="reno").congestion_control_algorithm == (
        "reno"
    )
