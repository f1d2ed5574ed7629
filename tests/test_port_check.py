"""deploy/port_check.py: smoke's precondition names what holds a port it needs."""

from __future__ import annotations

import importlib.util
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "deploy" / "port_check.py"
# A script beside smoke.sh, not a package module: loaded from its path.
_spec = importlib.util.spec_from_file_location("port_check", SCRIPT)
assert _spec is not None and _spec.loader is not None
port_check = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(port_check)


def _released_port() -> int:
    """A port the kernel just handed out and this test let go of again."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        udp.bind(("127.0.0.1", 0))
        return int(udp.getsockname()[1])


@pytest.mark.parametrize("kind", [socket.SOCK_DGRAM, socket.SOCK_STREAM], ids=["udp", "tcp"])
def test_a_taken_port_is_reported_with_the_process_that_holds_it(kind: int) -> None:
    with socket.socket(socket.AF_INET, kind) as held:
        held.bind(("127.0.0.1", 0))
        port = int(held.getsockname()[1])
        if kind == socket.SOCK_STREAM:
            held.listen()
        problems = port_check.report([port])
        done = subprocess.run(
            [sys.executable, str(SCRIPT), str(port)],
            capture_output=True, text=True, timeout=30, check=False,
        )  # fmt: skip
    assert len(problems) == 1, problems
    assert f"port {port}" in problems[0] and f"pid {os.getpid()}:" in problems[0]
    assert ("udp" if kind == socket.SOCK_DGRAM else "tcp") in problems[0]
    assert "python" in problems[0]  # the holder's command line
    assert done.returncode == 1 and f"pid {os.getpid()}:" in done.stderr, done.stderr


def test_free_ports_and_a_connection_to_a_port_do_not_count() -> None:
    assert port_check.report([_released_port()]) == []
    # A client connected *to* a listening port holds an ephemeral port of its own: the
    # listener counts, the client's socket does not.
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        target = int(listener.getsockname()[1])
        with socket.create_connection(("127.0.0.1", target)) as client:
            local = int(client.getsockname()[1])
            accepted, _ = listener.accept()
            with accepted:
                # The listener; not the accepted connection on the same port.
                assert len(port_check.socket_inodes(target)) == 1
                assert port_check.socket_inodes(local) == {}
    assert port_check.main([str(_released_port())]) == 0
    assert port_check.main(["not-a-port"]) == 2
