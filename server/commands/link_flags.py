"""The stream's link options, shared by upcast up, serve and session (one help text)."""

from __future__ import annotations

import argparse

from server.stream_config import DEFAULT_DIVISORS, parse_divisors


def _ladder(text: str) -> tuple[int, ...]:
    try:
        return parse_divisors(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_link_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--rate-control",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="the bitrate follows the player's link, reported by its page (default: on;"
        " the configured bitrate is the ceiling; --no-rate-control: fixed bitrate)",
    )
    parser.add_argument(
        "--intra-refresh",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="refresh the picture in sweeps of intra blocks every --gop-seconds instead of"
        " periodic keyframes (default: on; keyframes still come on demand)",
    )
    parser.add_argument(
        "--ladder",
        type=_ladder,
        default=DEFAULT_DIVISORS,
        metavar="DIVISORS",
        help="spectator renditions beside the player's stream: the display size divided by"
        " each divisor, each its own track with a keyframe every second (default:"
        f" {','.join(map(str, DEFAULT_DIVISORS))}, half and a quarter; 'off': the player's"
        " stream only, which saves their encode time on a busy host)",
    )
