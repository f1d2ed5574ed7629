"""``upcast bench congestion``: QUIC congestion controllers carrying video through
lossy links.

For each link (rate, RTT, random loss) and each controller (reno, cubic,
upcast-media), an aioquic server sends video-like chunks (one every 33 ms, sized
for ``--rate-mbit``, on one stream) through a user-space link on loopback to an
aioquic client. Reported per case: goodput (chunk bytes that arrived, over the
send period), the share of chunk bytes that arrived within ``--deadline-ms`` of
being sent, and the per-chunk delivery delay (send -> last byte arrived) as
median and p95. A chunk that never arrived counts as late. Cases run interleaved
(link by link, controllers in turn) and are compared as ratios to reno.

The link: server/net's emulator (in the same loop), a FIFO bottleneck at the
given rate with a queue of ``--queue-ms``, random loss before the queue, half the
RTT of propagation each way, both directions shaped alike. The link ``0/0/0`` is
plain loopback (no emulator), to
check that the controller costs nothing where the network is not the limit.
Sender and receiver share one clock (one process).
"""

from __future__ import annotations

import argparse
import asyncio
import struct
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from aioquic.asyncio.client import connect
from aioquic.asyncio.protocol import QuicConnectionProtocol
from aioquic.asyncio.server import serve
from aioquic.quic.configuration import QuicConfiguration
from aioquic.quic.events import HandshakeCompleted, QuicEvent, StreamDataReceived

from server.net import LinkProfile, NetworkEmulator, Schedule
from server.ops.report import BenchReport, summarize_ms
from server.quic.certs import generate_cert
from server.quic.congestion_register import algorithm_names

ALPN = "upcast-cc-bench"
CHUNK_HEADER = struct.Struct("!dII")  # send time, chunk index, payload size
FRAME_INTERVAL_S = 1 / 30


@dataclass(frozen=True)
class LinkSpec:
    rate_mbit: float
    rtt_ms: float
    loss: float
    queue_ms: float = 100.0

    def profile(self) -> LinkProfile:
        """Both directions alike: the rate, loss and queue each way, half the RTT."""
        return LinkProfile.both_ways(
            rate_bps=self.rate_mbit * 1e6,
            up_rate_bps=self.rate_mbit * 1e6,
            rtt_ms=self.rtt_ms,
            loss=self.loss,
            queue_ms=self.queue_ms,
        )

    @property
    def label(self) -> str:
        if self.rate_mbit <= 0:
            return "loopback"
        return f"{self.rate_mbit:g}mbit_{self.rtt_ms:g}ms_{100 * self.loss:g}pct"


DEFAULT_LINKS = (
    LinkSpec(8.0, 30.0, 0.01),
    LinkSpec(4.0, 60.0, 0.02),
    LinkSpec(20.0, 15.0, 0.0),
    LinkSpec(0.0, 0.0, 0.0),  # plain loopback: no forwarder
)


@dataclass
class Transfer:
    """What one run sent and when each chunk arrived (loop time, seconds)."""

    algorithm: str
    link: LinkSpec
    seconds: float
    sent: dict[int, tuple[float, int]] = field(default_factory=dict)  # index -> (time, bytes)
    arrived: dict[int, float] = field(default_factory=dict)

    def delays_s(self) -> list[float]:
        """Per chunk, send -> complete arrival; a lost chunk counts as infinitely late."""
        return [self.arrived.get(i, float("inf")) - t for i, (t, _) in self.sent.items()]

    def on_time_fraction(self, deadline_s: float) -> float:
        total = sum(size for _, size in self.sent.values())
        on_time = sum(
            size
            for i, (t, size) in self.sent.items()
            if i in self.arrived and self.arrived[i] - t <= deadline_s
        )
        return on_time / total if total else 0.0

    def goodput_mbit(self) -> float:
        got = sum(self.sent[i][1] for i in self.arrived)
        return got * 8 / 1e6 / self.seconds


class _Sender(QuicConnectionProtocol):
    """Server side: once the handshake is done, send a chunk every frame interval."""

    transfer: Transfer
    chunk_bytes: int
    done: asyncio.Event

    def quic_event_received(self, event: QuicEvent) -> None:
        if isinstance(event, HandshakeCompleted):
            asyncio.get_running_loop().create_task(self._send_chunks())

    async def _send_chunks(self) -> None:
        loop = asyncio.get_running_loop()
        stream_id = self._quic.get_next_available_stream_id(is_unidirectional=True)
        start = loop.time()
        index = 0
        while (t := start + index * FRAME_INTERVAL_S) < start + self.transfer.seconds:
            await asyncio.sleep(max(0.0, t - loop.time()))
            now = loop.time()
            payload = CHUNK_HEADER.pack(now, index, self.chunk_bytes) + bytes(self.chunk_bytes)
            self.transfer.sent[index] = (now, self.chunk_bytes)
            self._quic.send_stream_data(stream_id, payload)
            self.transmit()
            index += 1
        self.done.set()


class _Receiver(QuicConnectionProtocol):
    """Client side: parse chunks off the stream and stamp their arrival."""

    transfer: Transfer

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._buffer = bytearray()

    def quic_event_received(self, event: QuicEvent) -> None:
        if not isinstance(event, StreamDataReceived):
            return
        self._buffer += event.data
        now = asyncio.get_running_loop().time()
        while len(self._buffer) >= CHUNK_HEADER.size:
            _, index, size = CHUNK_HEADER.unpack_from(self._buffer)
            if len(self._buffer) < CHUNK_HEADER.size + size:
                break
            del self._buffer[: CHUNK_HEADER.size + size]
            self.transfer.arrived[index] = now


async def measure(
    algorithm: str,
    link: LinkSpec,
    *,
    seconds: float = 4.0,
    rate_mbit: float = 6.0,
    seed: int = 1,
    grace_s: float = 1.0,
) -> Transfer:
    """Send `rate_mbit` of chunks for `seconds` over `link` with `algorithm`
    controlling the sender; wait up to `grace_s` afterwards for stragglers. A link
    of rate 0 is plain loopback, no forwarder."""
    transfer = Transfer(algorithm, link, seconds)
    chunk_bytes = int(rate_mbit * 1e6 / 8 * FRAME_INTERVAL_S)
    done = asyncio.Event()
    cert = generate_cert()
    server_config = QuicConfiguration(
        alpn_protocols=[ALPN], is_client=False, congestion_control_algorithm=algorithm
    )
    server_config.load_cert_chain(cert.cert_path, cert.key_path)

    def create_sender(*args: Any, **kwargs: Any) -> _Sender:
        sender = _Sender(*args, **kwargs)
        sender.transfer, sender.chunk_bytes, sender.done = transfer, chunk_bytes, done
        return sender

    server = await serve("127.0.0.1", 0, configuration=server_config, create_protocol=create_sender)
    assert server._transport is not None
    server_port = server._transport.get_extra_info("sockname")[1]
    loop = asyncio.get_running_loop()
    emulator: NetworkEmulator | None = None
    port = server_port
    if link.rate_mbit > 0:
        emulator = NetworkEmulator(
            listen=("127.0.0.1", 0),
            upstream=("127.0.0.1", server_port),
            schedule=Schedule.constant(link.profile()),
            seed=seed,
        )
        await emulator.start()
        port = emulator.port
    client_config = QuicConfiguration(
        alpn_protocols=[ALPN],
        is_client=True,
        congestion_control_algorithm=algorithm,
        verify_mode=0,  # ssl.CERT_NONE: a throwaway self-signed certificate
    )

    def create_receiver(*args: Any, **kwargs: Any) -> _Receiver:
        receiver = _Receiver(*args, **kwargs)
        receiver.transfer = transfer
        return receiver

    try:
        async with connect(
            "127.0.0.1", port, configuration=client_config, create_protocol=create_receiver
        ):
            async with asyncio.timeout(seconds + 10):
                await done.wait()
            deadline = loop.time() + grace_s
            while len(transfer.arrived) < len(transfer.sent) and loop.time() < deadline:
                await asyncio.sleep(0.02)
    finally:
        if emulator is not None:
            await emulator.stop()
        server.close()
    return transfer


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, required=True, help="report path")
    parser.add_argument(
        "--algorithms",
        default="reno,cubic,upcast-media",
        help="controllers to compare, comma-separated (first one is the ratio baseline)",
    )
    parser.add_argument(
        "--links",
        default=",".join(f"{x.rate_mbit:g}/{x.rtt_ms:g}/{x.loss:g}" for x in DEFAULT_LINKS),
        help="links as MBIT/RTT_MS/LOSS, comma-separated; 0/0/0 is plain loopback",
    )
    parser.add_argument("--rate-mbit", type=float, default=6.0, help="video rate offered")
    parser.add_argument(
        "--load", type=float, default=0.75, help="offer at most this share of the link's rate"
    )
    parser.add_argument("--seconds", type=float, default=6.0, help="send period per case")
    parser.add_argument("--repeats", type=int, default=1, help="runs per case (interleaved)")
    parser.add_argument("--queue-ms", type=float, default=100.0, help="bottleneck queue")
    parser.add_argument("--deadline-ms", type=float, default=500.0, help="'on time' bound")


def _parse_links(text: str, queue_ms: float) -> list[LinkSpec]:
    links = []
    for item in text.split(","):
        rate, rtt, loss = (float(x) for x in item.split("/"))
        links.append(LinkSpec(rate, rtt, loss, queue_ms))
    return links


def _summary(runs: list[Transfer], deadline_s: float) -> dict[str, Any]:
    delays_ms = [1000 * d for r in runs for d in r.delays_s()]
    finite = [d for d in delays_ms if d != float("inf")]
    stats = summarize_ms(finite)
    lost = len(delays_ms) - len(finite)
    p95 = float("inf") if lost > 0.05 * len(delays_ms) else stats.get("p95_ms", float("inf"))
    return {
        "goodput_mbit": sum(r.goodput_mbit() for r in runs) / len(runs),
        "on_time_fraction": sum(r.on_time_fraction(deadline_s) for r in runs) / len(runs),
        "median_ms": stats.get("median_ms"),
        "p95_ms": p95 if p95 != float("inf") else None,
        "chunks_never_arrived": lost,
        "delay_stats": stats,
    }


def run(args: argparse.Namespace) -> int:
    algorithms = [a.strip() for a in args.algorithms.split(",") if a.strip()]
    unknown = [a for a in algorithms if a not in algorithm_names()]
    if unknown:
        print(f"unknown algorithm(s) {unknown}; known: {algorithm_names()}", file=sys.stderr)
        return 2
    links = _parse_links(args.links, args.queue_ms)
    deadline_s = args.deadline_ms / 1000
    report = BenchReport(
        "congestion",
        {
            "algorithms": algorithms,
            "links": [vars(x) for x in links],
            "video_rate_mbit": args.rate_mbit,
            "offered_share_of_link_at_most": args.load,
            "chunk_interval_ms": 1000 * FRAME_INTERVAL_S,
            "seconds_per_run": args.seconds,
            "repeats": args.repeats,
            "deadline_ms": args.deadline_ms,
            "delay_definition": "chunk handed to the sender's QUIC stream -> its last byte"
            " parsed by the receiver (one clock); chunks that never arrived are excluded"
            " from median/p95 and counted, p95 is null when they exceed 5 %",
        },
    )
    print(f"{'link':22} {'algorithm':13} {'goodput':>8} {'on time':>8} {'p50 ms':>8} {'p95 ms':>8}")
    for link in links:
        rate_mbit = args.rate_mbit
        if link.rate_mbit > 0:
            rate_mbit = min(rate_mbit, args.load * link.rate_mbit)
        runs: dict[str, list[Transfer]] = {a: [] for a in algorithms}
        for repeat in range(args.repeats):
            for algorithm in algorithms:
                runs[algorithm].append(
                    asyncio.run(
                        measure(
                            algorithm,
                            link,
                            seconds=args.seconds,
                            rate_mbit=rate_mbit,
                            seed=repeat + 1,
                        )
                    )
                )
        summaries = {a: _summary(runs[a], deadline_s) for a in algorithms}
        for algorithm, s in summaries.items():
            report.add_case(
                f"{link.label}_{algorithm}",
                link=link.label,
                algorithm=algorithm,
                offered_mbit=rate_mbit,
                **s,
            )
            p50 = f"{s['median_ms']:.0f}" if s["median_ms"] is not None else "-"
            p95 = f"{s['p95_ms']:.0f}" if s["p95_ms"] is not None else "-"
            print(
                f"{link.label:22} {algorithm:13} {s['goodput_mbit']:8.2f} "
                f"{100 * s['on_time_fraction']:7.1f}% {p50:>8} {p95:>8}"
            )
        base = algorithms[0]
        for algorithm in algorithms[1:]:
            if summaries[base]["goodput_mbit"] > 0:
                report.add_ratio(
                    f"{link.label}_goodput_{algorithm}_over_{base}",
                    f"{link.label}_{algorithm}",
                    f"{link.label}_{base}",
                    summaries[algorithm]["goodput_mbit"] / summaries[base]["goodput_mbit"],
                )
        media = summaries.get("upcast-media")
        if media is not None:
            verdict = "PASS" if media["on_time_fraction"] >= 0.9 else "FAIL"
            report.notes.append(
                f"{verdict}: {link.label}: upcast-media delivered"
                f" {100 * media['on_time_fraction']:.1f} % of {rate_mbit:g} Mbit/s on time"
                f" (within {args.deadline_ms:g} ms); "
                + ", ".join(
                    f"{a} {100 * s['on_time_fraction']:.1f} %"
                    for a, s in summaries.items()
                    if a != "upcast-media"
                )
            )
    report.write(args.json)
    print(f"report written to {args.json}")
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    add_arguments(parser)
    sys.exit(run(parser.parse_args()))
