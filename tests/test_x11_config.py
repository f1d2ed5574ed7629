"""Session config and CLI checks of source x11: refused at start with the reason."""

from __future__ import annotations

import subprocess
import sys

import pytest
from pydantic import ValidationError

from server.stack.local import LocalStack, SessionConfig


def x11(**fields: object) -> SessionConfig:
    return SessionConfig(source="x11", render_size="640x360", **fields)  # type: ignore[arg-type]


def test_an_application_session_builds_the_x11_game_command() -> None:
    config = x11(app="/usr/games/pingus --geometry 640x360", app_exit="restart")
    args = LocalStack(config)._x11_args()
    assert args[:3] == ["game", "--source", "x11"]
    assert args[args.index("--app") + 1] == "/usr/games/pingus --geometry 640x360"
    assert args[args.index("--app-exit") + 1] == "restart"
    assert "--jitter" not in args and "--frame-generation" not in args


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({}, "needs app"),
        ({"app": "pingus", "upscaler": "temporal"}, "needs depth, motion and jitter"),
        ({"app": "pingus", "frame_generation": True}, "frame_generation needs depth"),
        ({"app": "'unclosed"}, "not a command line"),
        ({"app": "   "}, "not a command line"),
    ],
)
def test_bad_x11_sessions_are_refused_with_the_reason(
    fields: dict[str, object], message: str
) -> None:
    with pytest.raises(ValidationError, match=message):
        x11(**fields)


def test_app_needs_source_x11() -> None:
    with pytest.raises(ValidationError, match="source 'x11' only"):
        SessionConfig(app="pingus")


def test_game_command_refuses_x11_without_an_application() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "server.cli", "game", "--ring", "none", "--source", "x11"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2
    assert "needs --app" in done.stderr


def test_a_per_application_gamepad_map_from_the_command_line() -> None:
    import argparse

    from server.stack.args import add_session_arguments, session_config_from

    parser = argparse.ArgumentParser()
    add_session_arguments(parser)
    good = parser.parse_args(
        ["--source", "x11", "--app", "pingus", "--render-size", "640x360", "--fps", "30",
         "--gamepad-map", "button:0=z, axis:0-=arrowleft"]
    )  # fmt: skip
    config = session_config_from(good)
    assert config is not None and config.gamepad is not None
    assert config.gamepad.spec() == {"button:0": "z", "axis:0-": "arrowleft"}
    bad = parser.parse_args(
        ["--source", "x11", "--app", "pingus", "--render-size", "640x360", "--fps", "30",
         "--gamepad-map", "button:0=nosuchkey"]
    )  # fmt: skip
    assert session_config_from(bad) is None  # refused, the reason printed
