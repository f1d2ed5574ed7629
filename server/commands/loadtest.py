"""``upcast loadtest``: N moq-lite viewers against a relay: fps, loss, latency, CPU.

Exit status: 0 when the run completed (the verdict is in the table and the
JSON), 1 when it could not run (relay unreachable, no broadcast), 2 for bad
arguments.
"""

from __future__ import annotations

import argparse
import asyncio
import subprocess
import sys
from pathlib import Path
from typing import Any

from server.loadtest.plan import MAX_DURATION_S, MAX_VIEWERS, LoadConfig
from server.ops.event_loop import install_uvloop

SYNTHETIC_SLACK_S = 120.0  # the synthetic publisher outlives the run by at most this


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--relay", required=True, help="relay URL, e.g. http://localhost:4443/")
    parser.add_argument(
        "--viewers",
        type=int,
        default=10,
        help=f"viewers (1..{MAX_VIEWERS}; with --find-max: the most tried)",
    )
    parser.add_argument(
        "--duration",
        type=float,
        required=True,
        help=f"measured seconds (max {MAX_DURATION_S:g}; with --find-max: per step)",
    )
    parser.add_argument("--broadcast", default="game", help="broadcast to watch (default: game)")
    parser.add_argument("--json", type=Path, default=None, help="write the JSON report here")
    parser.add_argument("--ramp", type=float, default=20.0, help="new viewers per second")
    parser.add_argument(
        "--warmup", type=float, default=2.0, help="seconds after the ramp before measuring"
    )
    parser.add_argument(
        "--processes", type=int, default=1, help="worker processes for the viewers (default 1)"
    )
    parser.add_argument(
        "--connect-timeout", type=float, default=10.0, help="seconds for one viewer's handshake"
    )
    parser.add_argument(
        "--wait-broadcast", type=float, default=15.0, help="seconds to wait for the broadcast"
    )
    parser.add_argument("--min-fps", type=float, default=29.0, help="a viewer holds at >= this")
    parser.add_argument(
        "--max-p95-ms", type=float, default=50.0, help="... and p95 publish->receive <= this"
    )
    parser.add_argument("--cert-hash", default=None, help="pin this certificate SHA-256 (hex)")
    parser.add_argument(
        "--find-max",
        action="store_true",
        help="step the viewer count up to --viewers; report the largest count that holds",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress line")
    parser.add_argument(
        "--token",
        default=None,
        help="the viewers' relay token (default: none, for a relay with public viewers)",
    )
    parser.add_argument(
        "--feedback",
        action="store_true",
        help="each viewer publishes <broadcast>/input/<id> and sends a feedback message every"
        " 250 ms, as the browser does (--token must allow publishing input: a player token)",
    )
    parser.add_argument(
        "--player", action="store_true", help="with --feedback: viewer 0 reports as the player"
    )
    parser.add_argument(
        "--rendition",
        default="first",
        help="video rendition to watch: first (the player's track, default), smallest (the"
        " lowest rung of the rendition ladder, as a spectator on a narrow link), or a track"
        " name from the catalog such as video.640x360",
    )
    group = parser.add_argument_group("synthetic publisher (instead of a game session)")
    group.add_argument(
        "--synthetic-publisher",
        action="store_true",
        help="start python -m server.loadtest.synthetic on the relay for the run",
    )
    group.add_argument(
        "--publisher-token", default=None, help="the synthetic publisher's relay token"
    )
    group.add_argument("--size", default="1280x720", help="synthetic frame size")
    group.add_argument("--fps", type=float, default=30.0, help="synthetic frames per second")
    group.add_argument("--bitrate-kbps", type=int, default=None, help="synthetic video bitrate")
    group.add_argument(
        "--encode", choices=("loop", "live"), default="loop", help="see synthetic.py"
    )


def config_from(args: argparse.Namespace) -> LoadConfig:
    return LoadConfig(
        relay_url=args.relay,
        viewers=args.viewers,
        duration_s=args.duration,
        broadcast=args.broadcast,
        ramp_per_s=args.ramp,
        warmup_s=args.warmup,
        processes=min(args.processes, args.viewers) if args.find_max else args.processes,
        connect_timeout_s=args.connect_timeout,
        wait_broadcast_s=args.wait_broadcast,
        min_fps=args.min_fps,
        max_p95_ms=args.max_p95_ms,
        cert_hash_hex=args.cert_hash,
        token=args.token,
        feedback=args.feedback or args.player,
        player=args.player,
        rendition=args.rendition,
    )


def _synthetic_argv(args: argparse.Namespace, duration_s: float) -> list[str]:
    argv = [sys.executable, "-m", "server.loadtest.synthetic", "--relay", args.relay]
    argv += ["--broadcast", args.broadcast, "--size", args.size, "--fps", str(args.fps)]
    argv += ["--encode", args.encode, "--duration", f"{duration_s:.0f}"]
    if args.bitrate_kbps is not None:
        argv += ["--bitrate-kbps", str(args.bitrate_kbps)]
    if args.cert_hash is not None:
        argv += ["--cert-hash", args.cert_hash]
    if args.publisher_token is not None:
        argv += ["--token", args.publisher_token]
    return argv


def _synthetic_problem(args: argparse.Namespace) -> str | None:
    from server.frames.frame import Size
    from server.loadtest.synthetic import SyntheticSettings

    try:
        size = Size.parse(args.size)
    except ValueError as exc:
        return f"--size: {exc}"
    if args.bitrate_kbps is not None and args.bitrate_kbps < 10:
        return f"--bitrate-kbps must be at least 10, got {args.bitrate_kbps}"
    return SyntheticSettings(args.relay, size, args.fps, encode=args.encode).problem()


def _run_bound_s(config: LoadConfig, find_max: bool) -> float:
    """Longest the whole command can take (the synthetic publisher's own limit)."""
    from server.loadtest.findmax import MAX_REFINE_STEPS, ladder

    counts = ladder(config.viewers) + [config.viewers] * MAX_REFINE_STEPS
    if not find_max:
        counts = [config.viewers]
    per_step = config.warmup_s + config.duration_s + config.connect_timeout_s + 5
    return sum(n / config.ramp_per_s + per_step for n in counts) + SYNTHETIC_SLACK_S


def run(args: argparse.Namespace) -> int:
    config = config_from(args)
    problem = config.problem()
    if problem is None and args.synthetic_publisher:
        problem = _synthetic_problem(args)
    if problem is not None:
        print(f"upcast loadtest: {problem}", file=sys.stderr)
        return 2
    install_uvloop()
    publisher: subprocess.Popen[bytes] | None = None
    if args.synthetic_publisher:
        bound = min(_run_bound_s(config, args.find_max), 4 * 3600.0)
        publisher = subprocess.Popen(_synthetic_argv(args, bound))
    try:
        return asyncio.run(_main(args, config))
    finally:
        if publisher is not None:
            publisher.terminate()
            try:
                publisher.wait(10)
            except subprocess.TimeoutExpired:
                publisher.kill()
                publisher.wait(5)


def _publisher_config(args: argparse.Namespace) -> dict[str, Any]:
    if not args.synthetic_publisher:
        return {"publisher": "external (not started by the load test)"}
    from server.frames.frame import Size
    from server.media.encode import default_bitrate

    size = Size.parse(args.size)
    bitrate_kbps = args.bitrate_kbps or default_bitrate(size.width, size.height, args.fps) // 1000
    return {
        "publisher": "synthetic (python -m server.loadtest.synthetic, own process)",
        "synthetic": {
            "size": args.size,
            "fps": args.fps,
            "bitrate_kbps": bitrate_kbps,
            "encode": args.encode,
        },
    }


async def _main(args: argparse.Namespace, config: LoadConfig) -> int:
    from server.loadtest.findmax import build_findmax_report, find_max, findmax_table
    from server.loadtest.results import build_report, summary_lines, table
    from server.loadtest.run import LoadResult, LoadTestError, run_load

    try:
        if args.find_max:

            async def step(cfg: LoadConfig, label: str) -> LoadResult:
                return await run_load(cfg, progress=not args.quiet, label=label)

            def on_step(viewers: int, ok: bool, result: LoadResult) -> None:
                # The full table of every step would bury the answer; the JSON has them.
                print("\n".join(summary_lines(result)), flush=True)
                print(f"--- {viewers} viewers: {'held' if ok else 'NOT held'}", flush=True)

            found = await find_max(config, config.duration_s, step, on_step)
            print(findmax_table(found), flush=True)
            report = build_findmax_report(config, config.duration_s, found)
            report.config.update(_publisher_config(args))
        else:
            result = await run_load(config, progress=not args.quiet)
            print(table(result), flush=True)
            report = build_report(result, _publisher_config(args))
    except LoadTestError as exc:
        print(f"upcast loadtest: {exc}", file=sys.stderr)
        return 1
    if args.json is not None:
        report.write(args.json)
        print(f"report written to {args.json}", flush=True)
    return 0
