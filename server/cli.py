"""The ``upcast`` command line: one subcommand module per job under server/commands/."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Callable, Sequence

from server.commands.extras import missing_extra
from server.commands.help_format import DefaultsHelpFormatter
from server.ops.logging_setup import (
    ENV_VAR,
    LOG_FORMATS,
    configure_logging,
    default_log_format,
    default_verbose,
)

# name -> module under server.commands; each module has add_arguments(parser) and run(args).
# Imported lazily so `upcast --help` does not pay for torch.
COMMANDS: dict[str, tuple[str, str]] = {
    "render": ("render", "render a scene to PNG and .npz files for a person to look at"),
    "bench": ("bench", "benchmarks that write the JSON report of DESIGN.md"),
    "eval": ("eval", "quality evaluations: speed against error, tables and plots"),
    "worker": ("worker", "run the upscaler worker on existing rings (normally started for you)"),
    "game": ("game", "run the reference game into ring R (normally started for you)"),
    "up": ("up", "start game, worker, session, relay and web page; print where to watch"),
    "preview": ("preview", "game + worker + a local MJPEG preview page (no streaming server)"),
    "relay": ("relay", "run the moq-lite relay: publishers in, browsers and viewers out"),
    "session": ("session", "stream an existing game session's ring U to a relay"),
    "serve": ("serve", "N game sessions, each its own process, on one relay; restarts the dead"),
    "control": ("control", "change a session's upscaler or scale over MoQ; print the result"),
    "loadtest": ("loadtest", "many moq-lite viewers against a relay: fps, loss, latency, CPU"),
    "token": ("token", "make the relay's key file (generate) and tokens signed with it (sign)"),
    "calibrate": (
        "calibrate",
        "time every upscaler on this machine for adaptive quality; cache it",
    ),
    "train": ("train", "train a neural upscaler (unet, unetpp) on the game's own frames"),
    "netem": ("netem", "shape UDP between viewers and the relay: rate, delay, loss (loopback)"),
}


def _load(module: str) -> tuple[Callable[[argparse.ArgumentParser], None], Callable[..., int]]:
    mod = importlib.import_module(f"server.commands.{module}")
    return mod.add_arguments, mod.run


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    """The parser; only the ``selected`` command's module is imported (the rest
    are listed by name), so one command's heavy imports never slow another."""
    parser = argparse.ArgumentParser(
        prog="upcast",
        description="upcast: cloud-gaming streaming server with a decoupled upscaler worker",
        formatter_class=DefaultsHelpFormatter,
    )
    parser.add_argument(
        "-v", "--verbose", action="store_true", help="debug logging (also UPCAST_VERBOSE=1)"
    )
    parser.add_argument(
        "--log-format",
        choices=LOG_FORMATS,
        default=None,
        help=f"text or json (one object per line); default: ${ENV_VAR} or text",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(
            name, help=help_text, description=help_text, formatter_class=DefaultsHelpFormatter
        )
        if name == selected:
            add_arguments, run = _load(module)
            add_arguments(p)
            p.set_defaults(handler=run)
    return parser


# Global options that take a value: their value is not the command name.
_GLOBAL_WITH_VALUE = frozenset({"--log-format"})


def _selected_command(argv: Sequence[str]) -> str | None:
    skip_next = False
    for arg in argv:
        if skip_next:
            skip_next = False
        elif arg in _GLOBAL_WITH_VALUE:
            skip_next = True
        elif not arg.startswith("-"):
            return arg if arg in COMMANDS else None
    return None


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = _selected_command(argv)
    try:
        return _main(argv, command)
    except ModuleNotFoundError as exc:
        # A game command on the base install: name the extra, not a traceback.
        message = missing_extra(exc, f"upcast {command}" if command else "upcast")
        if message is None:
            raise
        print(message, file=sys.stderr)
        return 2


def _main(argv: list[str], command: str | None) -> int:
    parser = build_parser(command)
    args = parser.parse_args(argv)
    try:
        log_format = args.log_format or default_log_format()
    except ValueError as exc:
        parser.error(str(exc))
    verbose = args.verbose or default_verbose()
    configure_logging(logging.DEBUG if verbose else logging.INFO, log_format)
    if not verbose:
        # aioquic logs every handshake at INFO; our own loggers say what matters.
        logging.getLogger("quic").setLevel(logging.WARNING)
    try:
        return int(args.handler(args))
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
