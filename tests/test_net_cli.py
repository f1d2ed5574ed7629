"""``upcast netem``: addresses, errors, and a short run that shapes and prints figures."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time

import pytest

from server.cli import main
from server.commands.netem import parse_address


@pytest.mark.parametrize(
    ("text", "address"),
    [
        ("4444", ("localhost", 4444)),
        ("127.0.0.1:0", ("127.0.0.1", 0)),
        ("[::1]:4444", ("::1", 4444)),
        ("::1:4444", ("::1", 4444)),
    ],
)
def test_listen_addresses(text: str, address: tuple[str, int]) -> None:
    assert parse_address(text, "localhost") == address


@pytest.mark.parametrize("text", ["4443", "host:", "127.0.0.1:70000", "[::1]4443"])
def test_bad_upstream_addresses(text: str) -> None:
    with pytest.raises(ValueError, match="is not HOST:PORT"):
        parse_address(text, None)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--profile", "dsl"], "unknown profile 'dsl'"),
        (["--profile", "lan", "--to", "10.1.2.3:4443"], "not loopback"),
        (["--profile", "lan", "--listen", "0.0.0.0:4444"], "not loopback"),
    ],
)
def test_errors_exit_2_with_a_message(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["netem", *argv]) == 2
    assert message in capsys.readouterr().err


def test_a_run_shapes_and_reports() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as echo:
        echo.bind(("127.0.0.1", 0))
        echo.settimeout(3.0)
        command = [sys.executable, "-m", "server.cli", "netem", "--listen", "localhost:0"]
        command += ["--to", f"127.0.0.1:{echo.getsockname()[1]}", "--profile", "cable"]
        command += ["--stats-every", "0.2"]
        proc = subprocess.Popen(command, stdout=subprocess.PIPE, text=True, env=os.environ)
        try:
            assert proc.stdout is not None
            lines = [proc.stdout.readline() for _ in range(4)]
            assert lines[0] == "upcast netem: profile cable\n"
            assert "20 Mbit/s, 15 ms RTT" in lines[1]
            port = int(lines[3].split(" port ")[1].split()[0])
            with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as client:
                client.settimeout(3.0)
                start = time.monotonic()
                client.sendto(b"ping", ("::1", port))
                data, source = echo.recvfrom(100)
                echo.sendto(data, source)
                assert client.recv(100) == b"ping"
                assert time.monotonic() - start >= 0.0145
            # A line printed before the ping still says clients 0; a later one says 1.
            progress = []
            while len(progress) < 20 and " clients 1 | down " not in "".join(progress[-1:]):
                progress.append(proc.stdout.readline())
            assert " s step 0 clients 1 | down " in progress[-1], progress
        finally:
            proc.send_signal(signal.SIGINT)
            out, _ = proc.communicate(timeout=10)
        assert proc.returncode == 0
        assert "upcast netem: stopped;" in out
        assert "1 pkt" in out.splitlines()[-1]
