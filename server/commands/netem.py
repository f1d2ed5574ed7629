"""``upcast netem``: a shaped UDP proxy on loopback between viewers and the relay.

The kernel's netem is missing here (NOTES.md); this runs server/net's user-space
emulator until Ctrl-C and prints one line of figures per ``--stats-every``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import signal
import sys
from typing import TYPE_CHECKING, Any

from server.net.profiles import PROFILES

if TYPE_CHECKING:
    from server.net.emulator import NetworkEmulator

EPILOG = (
    "profiles:\n"
    + "\n".join(f"  {name:9} {schedule.description}" for name, schedule in PROFILES.items())
    + """

A schedule file (.json or .toml) holds one profile's fields, or steps:
  [[steps]]                     # the first at 0 s; each lasts until the next
  at_s = 0
  rate_bps = "10mbit"           # downlink; absent = unlimited
  delay_ms = 10                 # one way, both directions (RTT = 2x)
  [[steps]]
  at_s = 5
  rate_bps = "1mbit"
  delay_ms = 10
  loss = 0.02                   # both directions

Fields: rate_bps, up_rate_bps, delay_ms, jitter_ms, loss, reorder, queue_ms
(default 100) or queue_bytes, burst_loss = {p_good_to_bad, p_bad_to_good,
loss_in_bad, loss_in_good}; or "down" and "up" tables with their own fields.

Viewers connect to --listen; a browser uses https://localhost:PORT (both
127.0.0.1 and ::1 are served). Loopback addresses only."""
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EPILOG
    parser.add_argument(
        "--listen",
        default="localhost:4450",
        metavar="[HOST:]PORT",
        # Not 4444-4446: upcast up serves the session's, game's and worker's metrics
        # there, and the TCP pass-through would collide with the first.
        help="where viewers connect (localhost = 127.0.0.1 and ::1; [::1]:PORT for one;"
        " default port 4450, clear of upcast up's 4443-4446)",
    )
    parser.add_argument(
        "--to",
        default="127.0.0.1:4443",
        metavar="HOST:PORT",
        help="the relay (or any UDP server) on loopback",
    )
    parser.add_argument(
        "--profile",
        required=True,
        metavar="NAME|FILE",
        help=f"a named link ({', '.join(PROFILES)}) or a .json/.toml schedule file",
    )
    parser.add_argument("--seed", type=int, default=0, help="random seed for loss and jitter")
    parser.add_argument(
        "--stats-every",
        type=float,
        default=1.0,
        metavar="SECONDS",
        help="seconds between progress lines (0 = none)",
    )
    parser.add_argument(
        "--idle-timeout",
        type=float,
        default=30.0,
        metavar="SECONDS",
        help="close a client's upstream socket after this long without packets",
    )
    parser.add_argument(
        "--no-tcp",
        action="store_true",
        help="do not forward TCP on the same port (the relay's HTTP, unshaped)",
    )


def parse_address(text: str, default_host: str | None) -> tuple[str, int]:
    """``PORT``, ``HOST:PORT`` or ``[V6]:PORT``; ValueError says what was expected."""
    host: str | None
    if text.startswith("["):
        host, _, port = text[1:].partition("]:")
    elif ":" not in text:
        host, port = default_host, text
    else:
        host, _, port = text.rpartition(":")
    if not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        expected = "[HOST:]PORT" if default_host else "HOST:PORT"
        raise ValueError(f"{text!r} is not {expected} (IPv6 as [::1]:PORT)")
    return host, int(port)


def _mbit(stats_now: dict[str, int], stats_before: dict[str, int], seconds: float) -> float:
    delivered = stats_now["bytes_delivered"] - stats_before["bytes_delivered"]
    return delivered * 8 / seconds / 1e6 if seconds > 0 else 0.0


def progress_line(now: dict[str, Any], before: dict[str, Any]) -> str:
    """One line of figures since ``before`` (both ``NetworkEmulator.stats()``)."""
    seconds = now["elapsed_s"] - before["elapsed_s"]
    parts = [f"{now['elapsed_s']:7.1f} s step {now['step']} clients {now['clients']}"]
    for side in ("down", "up"):
        c, b = now[side], before[side]
        parts.append(
            f"{side} {_mbit(c, b, seconds):6.2f} Mbit/s {c['delivered'] - b['delivered']:5d} pkt"
            f" lost {c['lost'] - b['lost']} queue-dropped {c['queue_dropped'] - b['queue_dropped']}"
        )
    late = now["release_late_ms"]
    if late:
        parts.append(f"late p50 {late['p50']:.1f} p99 {late['p99']:.1f} ms")
    return " | ".join(parts)


async def _serve(args: argparse.Namespace, emulator: NetworkEmulator) -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)
    async with emulator:
        hosts = "127.0.0.1 and ::1" if args.listen_host == "localhost" else args.listen_host
        print(f"upcast netem: {hosts} port {emulator.port} -> {args.to}", flush=True)
        before = emulator.stats()
        while not stop.is_set():
            every = args.stats_every if args.stats_every > 0 else 3600.0
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), every)
            if args.stats_every > 0 and not stop.is_set():
                now = emulator.stats()
                print(progress_line(now, before), flush=True)
                before = now
        total = emulator.stats()
        print("upcast netem: stopped; " + progress_line(total, _zero(total)), flush=True)


def _zero(stats: dict[str, Any]) -> dict[str, Any]:
    zero = {k: 0 for k in stats["down"]}
    return {"elapsed_s": 0.0, "down": zero, "up": zero}


def run(args: argparse.Namespace) -> int:
    from server.net.emulator import NetworkEmulator, NonLoopbackError, emulator_loop
    from server.net.profiles import ProfileError, resolve

    try:
        listen = parse_address(args.listen, "localhost")
        upstream = parse_address(args.to, None)
        schedule = resolve(args.profile)
        emulator = NetworkEmulator(
            listen,
            upstream,
            schedule,
            args.seed,
            idle_timeout_s=args.idle_timeout,
            tcp_passthrough=not args.no_tcp,
        )
    except (ValueError, ProfileError, NonLoopbackError) as exc:
        print(f"upcast netem: {exc}", file=sys.stderr)
        return 2
    args.listen_host = listen[0]
    print(f"upcast netem: profile {args.profile}", flush=True)
    print(schedule.describe(), flush=True)
    try:
        with asyncio.Runner(loop_factory=emulator_loop) as runner:
            runner.run(_serve(args, emulator))
    except OSError as exc:
        print(f"upcast netem: cannot listen on {args.listen}: {exc.strerror}", file=sys.stderr)
        return 2
    return 0
