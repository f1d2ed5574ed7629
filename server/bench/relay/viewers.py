"""The load-test viewers of ``bench relay``, in their own process (their CPU is not the
relay's): ``upcast loadtest``'s run (server/loadtest/run.py) with the window it measured.

``python -m server.bench.relay.viewers --relay URL --cert-hash HEX --viewers N
--duration S --warmup S --processes K --json OUT``

OUT gets the load test's cases, notes and verdict (as ``upcast loadtest --json`` writes
them) plus ``window_monotonic``: the measured window's edges in ``time.monotonic()``
seconds, one clock for every process on Linux, so the parent reads the relay's CPU
over exactly that window. ``upcast loadtest`` itself does not report the edges.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from pathlib import Path

from server.loadtest.plan import LoadConfig
from server.loadtest.results import build_report
from server.loadtest.run import LoadTestError, run_load
from server.ops.event_loop import install_uvloop


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m server.bench.relay.viewers")
    parser.add_argument("--relay", required=True, help="relay URL (https://HOST:PORT/)")
    parser.add_argument("--cert-hash", required=True, help="the relay's certificate SHA-256")
    parser.add_argument("--viewers", type=int, required=True, help="viewers")
    parser.add_argument("--duration", type=float, required=True, help="measured seconds")
    parser.add_argument("--warmup", type=float, default=3.0, help="seconds before measuring")
    parser.add_argument("--processes", type=int, default=1, help="viewer worker processes")
    parser.add_argument("--broadcast", default="game", help="broadcast to watch")
    parser.add_argument("--json", type=Path, required=True, help="where the result goes")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    config = LoadConfig(
        relay_url=args.relay,
        viewers=args.viewers,
        duration_s=args.duration,
        broadcast=args.broadcast,
        warmup_s=args.warmup,
        processes=args.processes,
        cert_hash_hex=args.cert_hash,
    )
    problem = config.problem()
    if problem is not None:
        sys.stderr.write(f"viewers: {problem}\n")
        return 2
    install_uvloop()
    try:
        result = asyncio.run(run_load(config, progress=False))
    except LoadTestError as exc:
        sys.stderr.write(f"viewers: {exc}\n")
        return 1
    report = build_report(result)
    out = {
        "window_monotonic": [result.plan.window_start, result.plan.window_end],
        "cases": report.cases,
        "verdict": report.verdict,
        "notes": report.notes,
    }
    args.json.write_text(json.dumps(out) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
