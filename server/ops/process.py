"""Process liveness (the rings take slots back from dead peers) and stopping a child."""

from __future__ import annotations

import os
import signal
import subprocess
from typing import Any


def pid_alive(pid: int) -> bool:
    """True if ``pid`` names a running (not zombie) process visible from here.

    A killed child that its parent has not reaped yet is a zombie: ``kill(pid, 0)``
    still succeeds on it, so /proc is consulted first where it exists.
    """
    if pid <= 0:
        return False
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read()
        state = stat[stat.rfind(b")") + 2 : stat.rfind(b")") + 3]
        return state not in (b"Z", b"X")
    except FileNotFoundError:
        return False
    except OSError:
        pass
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def stop_child(
    proc: subprocess.Popen[Any], grace_s: float, sig: signal.Signals = signal.SIGTERM
) -> None:
    """Ask a child to stop with ``sig`` (it cleans up its own children, rings and
    sockets), wait ``grace_s``, then kill it; returns once it is reaped."""
    if proc.poll() is not None:
        return
    proc.send_signal(sig)
    try:
        proc.wait(grace_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(5)
