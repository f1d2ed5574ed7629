"""CPU shares per session (server/ops/cpu_shares.py): weights from the target's cost,
enforced by cgroup v1 where it can be written, and a clear "not enforced" where not."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from server.ops.cpu_shares import BASE_SHARES, CGROUP_ROOT, CpuShares, shares_for

BUSY = [sys.executable, "-c", "while True: pass"]


def test_a_session_weighs_what_its_target_costs() -> None:
    assert shares_for(30.0, 1280 * 720) == BASE_SHARES
    assert shares_for(60.0, 1920 * 1080) == round(BASE_SHARES * 60 * 1920 * 1080 / (30 * 921600))
    assert shares_for(15.0, 320 * 180) >= 2  # never under the kernel's minimum
    assert shares_for(1e9, 10**8) == 262_144  # nor over its maximum


def test_without_a_writable_hierarchy_it_says_why_and_does_nothing(tmp_path: Path) -> None:
    shares = CpuShares("upcast-serve-test", root=tmp_path / "no-cgroups")
    assert not shares.available
    assert "no writable cgroup v1 cpu hierarchy" in (shares.reason or "")
    assert shares.place("session-1", os.getpid(), 1024) is False
    assert shares.shares("session-1") is None and shares.cpu_seconds("session-1") is None
    shares.close()  # nothing to remove, no error


def _usage(shares: CpuShares, group: str) -> float:
    value = shares.cpu_seconds(group)
    assert value is not None
    return value


def test_under_contention_the_heavier_session_gets_more_cpu() -> None:
    """Two groups of busy loops, more loops than cores, weights 4:1: the kernel gives the
    heavier group about four times the CPU (asserted: more than twice)."""
    shares = CpuShares(f"upcast-test-{os.getpid()}")
    if not shares.available:
        # Where cgroups cannot be written (no root, cgroup v2 only) shares are off and
        # say so: the test above covers that; nothing here can be enforced.
        assert shares.reason
        return
    loops = (os.cpu_count() or 2) * 2
    procs: list[subprocess.Popen[bytes]] = []
    try:
        for i in range(loops):
            proc = subprocess.Popen(BUSY)
            procs.append(proc)
            group, weight = ("heavy", 4 * BASE_SHARES) if i % 2 else ("light", BASE_SHARES)
            assert shares.place(group, proc.pid, weight)
        assert shares.shares("heavy") == 4 * BASE_SHARES
        time.sleep(0.5)  # every loop started and placed
        before = {g: _usage(shares, g) for g in ("heavy", "light")}
        time.sleep(3.0)
        used = {g: _usage(shares, g) - before[g] for g in ("heavy", "light")}
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()
        time.sleep(0.2)
        shares.close()
    print("cpu seconds over 3 s:", used)
    assert used["heavy"] > 2.0 * used["light"], used
    # Every group made here is gone once its processes are.
    assert not (CGROUP_ROOT / "cpu" / f"upcast-test-{os.getpid()}").exists()


def test_a_placed_sessions_weight_can_be_moved(tmp_path: Path) -> None:
    """The share planner's writes: a new weight reads back; a session never placed, or a
    host without cgroups, answers False."""
    assert CpuShares("x", root=tmp_path / "none").set_shares("session-1", 2048) is False
    shares = CpuShares(f"upcast-test-move-{os.getpid()}")
    if not shares.available:
        assert shares.reason
        return
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        assert shares.place("session-1", proc.pid, BASE_SHARES)
        assert shares.set_shares("session-1", 3 * BASE_SHARES)
        assert shares.shares("session-1") == 3 * BASE_SHARES
        assert shares.set_shares("never-placed", BASE_SHARES) is False
    finally:
        proc.kill()
        proc.wait()
        time.sleep(0.2)
        shares.close()
