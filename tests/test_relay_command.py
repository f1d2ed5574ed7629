"""``upcast relay`` refuses a bad configuration at start, naming the field."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from server.auth import generate_key
from server.commands import relay


def start(*argv: str) -> int:
    parser = argparse.ArgumentParser()
    relay.add_arguments(parser)
    return relay.run(parser.parse_args(list(argv)))


def test_no_key_and_no_explicit_open_relay_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert start("--port", "0") == 2
    err = capsys.readouterr().err
    assert "invalid relay configuration" in err and "upcast token generate" in err


@pytest.mark.parametrize(
    ("argv", "field"),
    [
        (["--max-backlog-kib", "4"], "max_backlog_kib"),
        (["--max-latency-ms", "-1"], "max_latency_ms"),
        (["--max-sessions", "0"], "max_sessions"),
        (["--port", "70000"], "port"),
        (["--viewer-upload-kib-s", "0"], "viewer_upload_kib_s"),
        (["--publisher-upload-mib-s", "0"], "publisher_upload_mib_s"),
    ],
)
def test_a_bad_value_names_its_field(
    argv: list[str], field: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert start("--no-auth", *argv) == 2
    assert f"  {field}: " in capsys.readouterr().err


def test_key_and_open_relay_exclude_each_other(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    key = tmp_path / "relay.jwk"
    generate_key(key)
    assert start("--auth-key", str(key), "--no-auth") == 2
    assert "exclude each other" in capsys.readouterr().err


def test_a_malformed_key_file_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    key = tmp_path / "broken.jwk"
    key.write_text('{"kty": "oct"}')
    assert start("--auth-key", str(key)) == 2
    err = capsys.readouterr().err
    assert str(key) in err and "'k'" in err


def test_cert_without_its_key_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert start("--no-auth", "--cert", "/nonexistent.pem") == 2
    assert "cert and key go together" in capsys.readouterr().err
