"""``upcast control``: change one session's upscaler, scale or quality goal at run time,
over MoQ.

Publishes one control request on ``<broadcast>/input/control-<id>`` (where the
page's controls send theirs), waits for the session's ``status`` track to
show the result, prints that status record as JSON and exits 0 when the
request was accepted, 1 when refused or unanswered.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from server.session.session_control import SessionControl


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--relay", required=True, help="relay URL, e.g. http://localhost:4443/")
    parser.add_argument("--broadcast", required=True, help="the session's broadcast name")
    parser.add_argument("--token", default=None, help="token to publish the request with")
    parser.add_argument("--cert-sha256", default=None, help="pin this certificate hash")
    parser.add_argument("--upscaler", default=None, help="switch the worker to this method")
    parser.add_argument("--scale", type=float, default=None, help="display / render size")
    parser.add_argument(
        "--cache-policy",
        default=None,
        help="layer-cache policy of unet_cached: delta_l, delta_h, budget, budget@DB, every_N, "
        "deepcache, motion, delta@SMAPE",
    )
    parser.add_argument(
        "--frame-generation",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="frame generation on/off (the game renders every other frame, the worker predicts)",
    )
    parser.add_argument(
        "--encode-scale",
        type=float,
        default=None,
        help="display / encoded size (1-4): the encoder sends a smaller picture, the viewers"
        " follow without a reload; 1: the display size",
    )
    parser.add_argument(
        "--frame-rate",
        type=float,
        default=None,
        help="frames per second the game renders and the stream carries (at most the"
        " session's configured rate; game time keeps its pace)",
    )
    parser.add_argument(
        "--quality",
        choices=("auto", "fixed"),
        default=None,
        help="auto: the session adapts upscaler, scale, frame generation, encoded size and,"
        " last, the frame rate (and lets go of every pin); fixed: it keeps what it runs."
        " --upscaler/--scale/--frame-generation/--encode-scale/--frame-rate under auto pin"
        " that field",
    )
    parser.add_argument(
        "--target-fps",
        type=float,
        default=None,
        help="the frame rate auto holds (at most the session's configured rate)",
    )
    parser.add_argument(
        "--preference",
        choices=("framerate", "resolution", "balanced"),
        default=None,
        help="what auto gives up first (see upcast up --quality-preference)",
    )
    parser.add_argument("--min-scale", type=float, default=None, help="auto's lowest scale")
    parser.add_argument("--max-scale", type=float, default=None, help="auto's highest scale")
    parser.add_argument(
        "--methods", default=None, help="comma-separated upscalers auto may choose from"
    )
    parser.add_argument("--timeout", type=float, default=15.0, help="seconds to wait for it")


def run(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from server.config_errors import format_validation_error
    from server.serve.tokens import with_token
    from server.session.session_control import SessionControl

    try:
        control = SessionControl(
            upscaler=args.upscaler,
            scale=args.scale,
            cache_policy=args.cache_policy,
            frame_generation=args.frame_generation,
            encode_scale=args.encode_scale,
            frame_rate=args.frame_rate,
            quality=args.quality,
            target_fps=args.target_fps,
            preference=args.preference,
            min_scale=args.min_scale,
            max_scale=args.max_scale,
            methods=None
            if args.methods is None
            else [m.strip() for m in args.methods.split(",") if m.strip()],
        )
    except ValidationError as exc:
        print(format_validation_error("control request", exc), file=sys.stderr)
        return 2
    if not control.requested():
        print(
            "upcast control: nothing to change: give --upscaler, --scale, --cache-policy, "
            "--frame-generation, --encode-scale, --frame-rate and/or the quality goal (--quality, "
            "--target-fps, --preference, --min-scale, --max-scale, --methods)",
            file=sys.stderr,
        )
        return 2
    if not args.relay.startswith(("http://", "https://")):
        print(f"upcast control: --relay must be http(s)://, got {args.relay}", file=sys.stderr)
        return 2
    return asyncio.run(_main(args, with_token(args.relay, args.token), control))


async def _main(args: argparse.Namespace, relay_url: str, control: SessionControl) -> int:
    from server.serve.control_client import ControlError, request_control

    try:
        record = await request_control(
            relay_url,
            args.broadcast,
            control,
            cert_hash_hex=args.cert_sha256,
            timeout_s=args.timeout,
        )
    except ControlError as exc:
        print(f"upcast control: {exc}", file=sys.stderr)
        return 1
    print(record.model_dump_json(indent=2))
    result = record.last_control
    assert result is not None
    if not result.accepted:
        print(f"upcast control: refused: {result.reason}", file=sys.stderr)
        return 1
    return 0
