"""The stream's link options, shared by upcast up, serve and session (one help text)."""

from __future__ import annotations

import argparse


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
