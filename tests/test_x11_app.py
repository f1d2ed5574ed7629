"""Application: its own process group, output drained, stop kills the whole group."""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import pytest

from server.game.x11.app import Application, ApplicationError


def _group_members(pgid: int) -> list[int]:
    members = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
        except OSError:
            continue
        fields = stat.rpartition(")")[2].split()
        # fields[0] is the state; fields[2] the process group. Zombies hold no resources.
        if int(fields[2]) == pgid and fields[0] != "Z":
            members.append(int(entry))
    return members


def _wait_for(condition: object, timeout_s: float = 2.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:  # type: ignore[operator]
        time.sleep(0.01)


def test_stop_kills_the_program_and_its_children() -> None:
    app = Application.start(["sh", "-c", "sleep 100 & sleep 100"], dict(os.environ))
    _wait_for(lambda: len(_group_members(app.pid)) == 3)
    assert len(_group_members(app.pid)) == 3  # sh and both sleeps
    assert app.exit_code() is None
    assert app.stop() == -15
    _wait_for(lambda: not _group_members(app.pid))
    assert _group_members(app.pid) == []


def test_stop_kills_what_ignores_sigterm_after_the_timeout() -> None:
    app = Application.start(["sh", "-c", "trap '' TERM; sleep 100"], dict(os.environ))
    _wait_for(lambda: len(_group_members(app.pid)) == 2)
    started = time.monotonic()
    assert app.stop(timeout_s=0.3) == -9
    assert time.monotonic() - started < 2.0
    _wait_for(lambda: not _group_members(app.pid))
    assert _group_members(app.pid) == []


def test_exit_code_of_a_program_that_ends_by_itself() -> None:
    app = Application.start(["sh", "-c", "exit 3"], dict(os.environ))
    _wait_for(lambda: app.exit_code() is not None)
    assert app.exit_code() == 3
    assert app.stop() == 3


def test_output_goes_to_the_log_file_with_the_environment_given(tmp_path: Path) -> None:
    log = tmp_path / "app.log"
    env = {"PATH": os.environ["PATH"], "DISPLAY": ":42"}
    app = Application.start(
        ["sh", "-c", 'echo "display $DISPLAY"; echo oops >&2; cat; pwd'],
        env,
        cwd=str(tmp_path),
        log_path=log,
    )
    _wait_for(lambda: app.exit_code() is not None)
    assert app.stop() == 0  # stdin is /dev/null: cat ends at once
    assert log.read_text().splitlines() == ["display :42", "oops", str(tmp_path)]


def test_output_goes_to_logging_without_a_file(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG, logger="server.game.x11.app")
    app = Application.start(["sh", "-c", "echo hello from the game"], dict(os.environ))
    _wait_for(lambda: app.exit_code() is not None)
    app.stop()
    assert "sh: hello from the game" in caplog.messages


def test_a_chatty_program_never_blocks() -> None:
    # 4 MB of output is far more than a pipe holds: it ends only if someone drains it.
    app = Application.start(
        ["sh", "-c", "head -c 4000000 /dev/zero | tr '\\0' x"], dict(os.environ)
    )
    _wait_for(lambda: app.exit_code() is not None, timeout_s=5)
    assert app.stop() == 0


def test_a_missing_command_is_a_clear_error() -> None:
    with pytest.raises(ApplicationError, match="cannot start 'no-such-game-xyz': not found"):
        Application.start(["no-such-game-xyz", "--fullscreen"], dict(os.environ))


def test_a_file_that_is_not_executable_is_a_clear_error(tmp_path: Path) -> None:
    game = tmp_path / "game.sh"
    game.write_text("#!/bin/sh\n")
    with pytest.raises(ApplicationError, match="not executable"):
        Application.start([str(game)], dict(os.environ))


def test_a_relative_path_is_found_from_the_working_directory_given(tmp_path: Path) -> None:
    game = tmp_path / "bin" / "game.sh"
    game.parent.mkdir()
    game.write_text("#!/bin/sh\nexit 7\n")
    game.chmod(0o755)
    app = Application.start(["./bin/game.sh"], dict(os.environ), cwd=str(tmp_path))
    _wait_for(lambda: app.exit_code() is not None)
    assert app.stop() == 7
