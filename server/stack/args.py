"""The game-session flags shared by ``upcast up`` and ``upcast preview``, and the
SessionConfig they fill (kept light: ``--help`` must not import torch)."""

from __future__ import annotations

import argparse
import logging
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from server.stack.local import SessionConfig
    from server.stack.machine_fit import FittedDefaults

log = logging.getLogger(__name__)


def add_session_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default="default", help="scene preset (default: default)")
    parser.add_argument(
        "--render-size",
        default=None,
        help="game render size WIDTHxHEIGHT (default: fitted to this machine's cores: half the "
        "display size with 4 or more per session, 3/8 below; the log says which)",
    )
    parser.add_argument("--display-size", default="1280x720", help="upscaled size WIDTHxHEIGHT")
    parser.add_argument(
        "--fps",
        type=float,
        default=None,
        help="game (and stream) frame rate (default: fitted to this machine's cores: 60 with 8 "
        "or more per session, else 30; the log says which)",
    )
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
    x11 = parser.add_argument_group("stream a real application (--source x11)")
    add_x11_source_arguments(x11, size_flag="--render-size")
    x11.add_argument(
        "--gamepad-map",
        default=None,
        help='gamepad -> keys for the application, e.g. "button:0=z,button:1=x,axis:0-=arrowleft" '
        "(default: d-pad and left stick = arrows, A space, B control, X shift, Y alt, "
        "start enter, back escape)",
    )


def add_x11_source_arguments(group: argparse._ArgumentGroup, *, size_flag: str) -> None:
    """--source, --app, --app-exit, --x11-display: for upcast up/preview/serve and for
    the game process itself (whose screen size is ``size_flag``)."""
    group.add_argument(
        "--source",
        choices=("game", "x11"),
        default="game",
        help="game: the built-in renderer (default); x11: an application on a virtual X "
        f"display (Xvfb) of {size_flag}, captured and streamed; spatial upscalers only",
    )
    group.add_argument(
        "--app",
        default=None,
        help='x11: the application, one quoted command line, e.g. "/usr/games/pingus '
        f'--geometry 640x360" (make it draw at {size_flag})',
    )
    group.add_argument(
        "--app-exit",
        choices=("stop", "restart"),
        default="stop",
        help="x11: when the application exits, stop the session (default) or restart it",
    )
    group.add_argument(
        "--x11-display",
        default=None,
        help="x11: capture this running X server (e.g. :0) instead of starting Xvfb",
    )


def session_config_from(args: argparse.Namespace, sessions: int = 1) -> SessionConfig | None:
    """The SessionConfig of those flags (None: refused, the reason printed); an unset
    ``--fps`` or ``--render-size`` is fitted to this machine for ``sessions`` streams."""
    from server.config_errors import validated
    from server.stack.local import SessionConfig

    fps, render_size = args.fps, args.render_size
    if fps is None or render_size is None:
        fitted = _fitted(args.display_size, sessions)
        if fitted is not None:
            fps = fitted.fps if fps is None else fps
            render_size = str(fitted.render_size) if render_size is None else render_size
            log.info(
                "defaults for this machine: %g fps, render size %s (%s; --fps and "
                "--render-size override)",
                fps, render_size, fitted.reason,
            )  # fmt: skip
    return validated(
        SessionConfig,
        "session",
        scene=args.scene,
        render_size=render_size,
        display_size=args.display_size,
        fps=fps,
        upscaler=args.upscaler,
        frame_generation=args.frame_generation,
        predictor=args.predictor,
        cache_policy=args.cache_policy,
        source=args.source,
        app=args.app,
        app_exit=args.app_exit,
        x11_display=args.x11_display,
        gamepad=_gamepad_spec(args.gamepad_map),
    )


def _gamepad_spec(text: str | None) -> dict[str, str] | None:
    """``button:0=z,axis:0-=arrowleft`` -> the config's dict (checked by the model)."""
    if text is None:
        return None
    spec: dict[str, str] = {}
    for item in text.split(","):
        entry, sep, key = item.strip().partition("=")
        # A malformed item goes through as is: the model's check names it.
        spec[entry.strip()] = key.strip() if sep else ""
    return spec


def _fitted(display_size: str, sessions: int) -> FittedDefaults | None:
    """None where the display size does not parse: the config check then names it."""
    from server.frames.frame import Size
    from server.stack.machine_fit import fitted_defaults

    try:
        display = Size.parse(display_size)
    except ValueError:
        return None
    return fitted_defaults(display, sessions=sessions)
