"""``upcast bench NAME ...``: dispatches to server/bench/<NAME>.py (add_arguments, run).

Only the chosen benchmark's module is imported, so each keeps its own
dependencies to itself.
"""

from __future__ import annotations

import argparse
import importlib

BENCHMARKS: dict[str, str] = {
    "transfer": "ring handoff (READY -> usable views) against a memcpy of the same bytes",
    "pipeline": "game -> worker -> ring U for a while: fps, drops, per-stage latency",
    "render": "reference renderer speed per scene",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = "benchmarks:\n" + "\n".join(f"  {k:10} {v}" for k, v in BENCHMARKS.items())
    parser.add_argument("benchmark", choices=sorted(BENCHMARKS), help="which benchmark")
    parser.add_argument("options", nargs=argparse.REMAINDER, help="its options (see NAME --help)")


def run(args: argparse.Namespace) -> int:
    name: str = args.benchmark
    mod = importlib.import_module(f"server.bench.{name}")
    sub = argparse.ArgumentParser(prog=f"upcast bench {name}", description=BENCHMARKS[name])
    mod.add_arguments(sub)
    return int(mod.run(sub.parse_args(args.options)))
