"""``upcast up`` without --fps/--render-size picks what the machine's cores hold, says so in
one log line, and explicit flags override."""

from __future__ import annotations

import argparse
import logging

import pytest

from server.frames.frame import Size
from server.stack import machine_fit
from server.stack.args import add_session_arguments, session_config_from
from server.stack.machine_fit import fitted_defaults

HD = Size(1280, 720)


@pytest.mark.parametrize(
    ("cores", "sessions", "fps", "render"),
    [
        (2, 1, 30.0, Size(480, 270)),  # this machine: 60 fps at 640x360 held 25-28
        (4, 1, 30.0, Size(640, 360)),
        (16, 1, 60.0, Size(640, 360)),
        (16, 4, 30.0, Size(640, 360)),  # 4 cores each
        (8, 4, 30.0, Size(480, 270)),
    ],
)
def test_fitted_defaults_follow_the_cores(
    cores: int, sessions: int, fps: float, render: Size
) -> None:
    fitted = fitted_defaults(HD, cores=cores, sessions=sessions)
    assert (fitted.fps, fitted.render_size) == (fps, render)
    assert f"{cores} cores" in fitted.reason


def test_render_size_follows_the_display_and_stays_even() -> None:
    assert fitted_defaults(Size(1920, 1080), cores=2).render_size == Size(720, 404)
    assert fitted_defaults(Size(320, 180), cores=2).render_size == Size(120, 68)


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_session_arguments(parser)
    return parser.parse_args(list(argv))


def test_unset_flags_are_fitted_and_logged_once(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(machine_fit, "usable_cores", lambda: 2)
    with caplog.at_level(logging.INFO, logger="server.stack.args"):
        config = session_config_from(_args())
    assert config is not None
    assert (config.fps, config.render_size) == (30.0, "480x270")
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "30 fps, render size 480x270" in lines[0] and "2 cores" in lines[0]


def test_explicit_flags_override(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(machine_fit, "usable_cores", lambda: 2)
    with caplog.at_level(logging.INFO, logger="server.stack.args"):
        config = session_config_from(_args("--fps", "60", "--render-size", "640x360"))
    assert config is not None and (config.fps, config.render_size) == (60.0, "640x360")
    assert not caplog.records
    # Only one of the two given: the other is still fitted.
    partial = session_config_from(_args("--fps", "45"))
    assert partial is not None and (partial.fps, partial.render_size) == (45.0, "480x270")
