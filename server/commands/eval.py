"""``upcast eval NAME ...``: evaluations in server/eval/ that compare methods."""

from __future__ import annotations

import argparse

from server.commands.dispatch import add_choice_arguments, run_choice

EVALUATIONS: dict[str, str] = {
    "upscalers": "speed against error of every upscaler, per scene and scale",
    "content": "fetch (--fetch) or list the real photographs of the evaluation",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_choice_arguments(parser, "evaluation", EVALUATIONS)


def run(args: argparse.Namespace) -> int:
    return run_choice("eval", "server.eval", EVALUATIONS, args)
