"""``upcast eval NAME ...``: evaluations that compare methods (server/eval/<NAME>.py)."""

from __future__ import annotations

import argparse
import importlib

EVALUATIONS: dict[str, str] = {
    "upscalers": "speed against error of every upscaler, per scene and scale",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("evaluation", choices=sorted(EVALUATIONS), help="which evaluation")
    parser.add_argument("options", nargs=argparse.REMAINDER, help="its options (NAME --help)")


def run(args: argparse.Namespace) -> int:
    name: str = args.evaluation
    mod = importlib.import_module(f"server.eval.{name}")
    sub = argparse.ArgumentParser(prog=f"upcast eval {name}", description=EVALUATIONS[name])
    mod.add_arguments(sub)
    return int(mod.run(sub.parse_args(args.options)))
