"""Adaptive quality's options, shared by upcast up, serve and session (one help text)."""

from __future__ import annotations

import argparse


def add_quality_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--quality",
        choices=("auto", "fixed"),
        default="auto",
        help="auto (default): the session chooses upscaler, render scale and frame"
        " generation to hold its frame rate with the best picture the host's load and the"
        " scene allow, one log line per change; fixed: it keeps the settings it started with",
    )
    parser.add_argument(
        "--quality-preference",
        choices=("framerate", "resolution", "balanced"),
        default="framerate",
        help="what auto gives up first: framerate (default) trades picture and lowers the"
        " frame rate (30, 20, 15, 10 fps of 30) only when the cheapest picture misses;"
        " resolution lowers the frame rate before the picture goes below the start;"
        " balanced lets the rate sag to 3/4 of the target and lowers it before the"
        " encoded size",
    )
    parser.add_argument(
        "--min-scale",
        type=float,
        default=1.0,
        help="auto's lowest render scale, display / render (default 1: native)",
    )
    parser.add_argument(
        "--max-scale",
        type=float,
        default=4.0,
        help="auto's highest render scale (default 4)",
    )
    parser.add_argument(
        "--quality-methods",
        default="",
        help="comma-separated upscalers auto may choose (default: every method with"
        " speed-against-error figures: bilinear, bicubic, lanczos2, easu, easu_rcas, temporal)",
    )


def quality_fields(args: argparse.Namespace) -> dict[str, object]:
    """The StreamConfig fields of these options."""
    methods = [m.strip() for m in str(args.quality_methods).split(",") if m.strip()]
    return {
        "quality": args.quality,
        "quality_preference": args.quality_preference,
        "min_scale": args.min_scale,
        "max_scale": args.max_scale,
        "quality_methods": methods,
    }
