"""``--log-format json|text`` and ``UPCAST_LOG_FORMAT``: one JSON object per line."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

from server.cli import _selected_command, build_parser
from server.ops.logging_setup import ENV_VAR, JsonLineFormatter, default_log_format

ROOT = Path(__file__).resolve().parents[1]


def record(msg: str, *args: object, **extra: object) -> logging.LogRecord:
    return logging.makeLogRecord(
        {"name": "upcast.test", "levelno": logging.WARNING, "levelname": "WARNING",
         "msg": msg, "args": args, **extra}
    )  # fmt: skip


def test_json_line_has_the_fields_and_the_extras() -> None:
    line = JsonLineFormatter().format(record("viewer %d joined", 3, broadcast="game-1", n=2))
    assert "\n" not in line
    entry = json.loads(line)
    assert entry["msg"] == "viewer 3 joined"
    assert entry["level"] == "WARNING" and entry["logger"] == "upcast.test"
    assert entry["pid"] == os.getpid() and entry["process"] == "MainProcess"
    assert entry["ts"].endswith("+00:00") and "T" in entry["ts"]
    assert entry["extra"] == {"broadcast": "game-1", "n": 2}


def test_exceptions_and_odd_extras_stay_on_one_line() -> None:
    try:
        raise ValueError("bad\nthing")
    except ValueError:
        rec = record("failed", thing=object())
        rec.exc_info = sys.exc_info()
    line = JsonLineFormatter().format(rec)
    assert "\n" not in line
    entry = json.loads(line)
    assert "ValueError: bad" in entry["exc"]
    assert entry["extra"]["thing"].startswith("<object object")


def test_environment_default_and_bad_value() -> None:
    assert default_log_format({}) == "text"
    assert default_log_format({ENV_VAR: "JSON"}) == "json"
    with pytest.raises(ValueError, match=ENV_VAR):
        default_log_format({ENV_VAR: "xml"})


def test_option_value_is_not_taken_for_the_command() -> None:
    assert _selected_command(["--log-format", "json", "relay", "--port", "1"]) == "relay"
    assert _selected_command(["--log-format=json", "relay"]) == "relay"
    args = build_parser("relay").parse_args(["--log-format", "json", "relay"])
    assert args.log_format == "json" and args.command == "relay"
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--log-format", "xml", "relay"])


def run_cli(argv: list[str], env_format: str | None) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != ENV_VAR}
    env["PYTHONPATH"] = str(ROOT)
    if env_format is not None:
        env[ENV_VAR] = env_format
    return subprocess.run(
        [sys.executable, "-m", "server.cli", *argv],
        capture_output=True, text=True, env=env, timeout=60, cwd=ROOT,
    )  # fmt: skip


def relay_argv() -> list[str]:
    """A relay on a free port that logs its start and stop, then exits by itself."""
    return ["relay", "--no-auth", "--host", "127.0.0.1", "--port", "0", "--duration", "0.2"]


def test_a_process_logs_json_lines_from_the_flag_or_the_environment() -> None:
    for argv, env_format in (
        (["--log-format", "json", *relay_argv()], None),
        (relay_argv(), "json"),
        (["--log-format", "json", *relay_argv()], "text"),  # the flag wins
    ):
        done = run_cli(argv, env_format)
        assert done.returncode == 0, done.stderr
        # The relay's own "listening on" summary is a print for people, not a log line.
        lines = [ln for ln in done.stderr.splitlines() if not ln.startswith("upcast relay:")]
        entries = [json.loads(ln) for ln in lines if ln.strip()]
        assert {e["logger"] for e in entries} >= {"server.relay.relay", "server.commands.relay"}
        assert all({"ts", "level", "logger", "msg", "process", "pid"} <= set(e) for e in entries)
        assert any("relay listening" in e["msg"] for e in entries)


def test_text_stays_the_default() -> None:
    done = run_cli(relay_argv(), None)
    assert done.returncode == 0, done.stderr
    assert " INFO server.relay.relay: relay listening" in done.stderr
    assert not any(ln.startswith("{") for ln in done.stderr.splitlines())


def test_bad_environment_value_is_refused_naming_the_variable() -> None:
    done = run_cli(relay_argv(), "xml")
    assert done.returncode == 2
    assert ENV_VAR in done.stderr
