"""The game-session flags shared by ``upcast up`` and ``upcast preview``, and the
SessionConfig they fill (kept light: ``--help`` must not import torch)."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from server.stack import SessionConfig


def add_session_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default="default", help="scene preset (default: default)")
    parser.add_argument("--render-size", default="640x360", help="game render size WIDTHxHEIGHT")
    parser.add_argument("--display-size", default="1280x720", help="upscaled size WIDTHxHEIGHT")
    parser.add_argument("--fps", type=float, default=60.0, help="game (and stream) frame rate")
    parser.add_argument("--upscaler", default="bilinear", help="initial upscaler")
    parser.add_argument(
        "--frame-generation",
        action=argparse.BooleanOptionalAction,
        default=False,
        help="render every other frame and predict the rest (the stream keeps --fps; "
        "switchable at run time; default: off)",
    )
    parser.add_argument(
        "--predictor", default="mpe", help="frame predictor for frame generation (default: mpe)"
    )
    parser.add_argument(
        "--cache-policy",
        default=None,
        help="layer-cache policy of the unet_cached upscaler: delta_l (default), delta_h, "
        "budget, budget@DB, every_N, deepcache, motion (switchable at run time)",
    )


def session_config_from(args: argparse.Namespace) -> SessionConfig | None:
    """The SessionConfig of those flags (None: refused, the reason printed)."""
    from server.config_errors import validated
    from server.stack import SessionConfig

    return validated(
        SessionConfig,
        "session",
        scene=args.scene,
        render_size=args.render_size,
        display_size=args.display_size,
        fps=args.fps,
        upscaler=args.upscaler,
        frame_generation=args.frame_generation,
        predictor=args.predictor,
        cache_policy=args.cache_policy,
    )
