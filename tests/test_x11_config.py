"""Session config and CLI checks of source x11: refused at start with the reason."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

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


def test_serve_sessions_can_stream_applications(tmp_path: Path) -> None:
    """upcast serve --config: one session the built-in game, one an application with
    its own gamepad map, one refused (a temporal upscaler on a captured application)."""
    from server.serve.config import ConfigFileError, load_overrides, session_configs
    from server.stream_config import StreamConfig

    path = tmp_path / "sessions.toml"
    path.write_text(
        "[[sessions]]\n\n"
        '[[sessions]]\nsource = "x11"\napp = "/usr/games/supertux2 --geometry 640x360"\n'
        'app_exit = "restart"\ngamepad = { "button:0" = "space" }\n'
    )
    configs = session_configs(
        SessionConfig(render_size="640x360"), StreamConfig(), load_overrides(path), 2, "game"
    )
    game, app = configs[0][0], configs[1][0]
    assert game.source == "game" and app.source == "x11" and app.app_exit == "restart"
    assert app.gamepad is not None and app.gamepad.spec() == {"button:0": "space"}
    path.write_text('[[sessions]]\nsource = "x11"\napp = "pingus"\nupscaler = "temporal"\n')
    with pytest.raises(ConfigFileError, match=r"(?s)session 1:.*needs depth, motion and jitter"):
        session_configs(SessionConfig(), StreamConfig(), load_overrides(path), 1, "game")
