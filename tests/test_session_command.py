"""``upcast session``: refuses bad settings by name and a missing ring clearly."""

from __future__ import annotations

import subprocess
import sys


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "server.cli", "session", *args],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_bad_broadcast_name_is_refused_naming_the_field() -> None:
    done = _run("--ring", "x", "--relay", "http://localhost:1/", "--broadcast", "a//b")
    assert done.returncode == 2
    assert "broadcast" in done.stderr


def test_relay_must_be_a_url() -> None:
    done = _run("--ring", "x", "--relay", "localhost:4443")
    assert done.returncode == 2 and "--relay" in done.stderr


def test_missing_ring_is_named() -> None:
    done = _run(
        "--ring",
        "upcast-no-such-ring-u",
        "--relay",
        "http://localhost:1/",
        "--attach-timeout",
        "0.2",
    )
    assert done.returncode == 1
    assert "upcast-no-such-ring-u" in done.stderr
