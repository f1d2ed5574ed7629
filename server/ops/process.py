"""Process liveness (the rings take slots back from dead peers), stopping a child, and a
process's CPU time and memory as /proc shows them (every thread; no cooperation needed)."""

from __future__ import annotations

import os
import signal
import subprocess
from typing import Any

CLK_TCK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def cpu_seconds(pid: int) -> float:
    """utime + stime of ``pid`` (Linux), all its threads."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK  # utime, stime


def rss_mb(pid: int) -> float:
    """Resident memory of ``pid`` in MB (NaN where /proc does not say)."""
    with open(f"/proc/{pid}/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


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
