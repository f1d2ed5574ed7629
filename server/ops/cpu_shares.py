"""CPU shares per session with the kernel's cgroups (version 1 ``cpu`` controller).

``upcast serve`` puts each session process in a cgroup of its own under
``/sys/fs/cgroup/cpu/upcast-serve-<pid>/session-<i>``; the game, worker and anything
else the session starts inherit it. Under contention the kernel divides CPU time
between the groups by their ``cpu.shares`` (a weight; idle cores are never held
back), the way Docker's ``--cpu-shares`` and Kubernetes' CPU requests do: one
session's runaway application cannot take more than its part from the others.

The weight of a session is proportional to what its target costs: frames per second
times display pixels (a 60 fps 1080p session gets about 4.5 times a 30 fps 720p
one), ``BASE_SHARES`` for a 30 fps 720p one. The group's ``cpuacct`` twin, where
mounted, gives each session's CPU time for ``/sessions``.

Without a writable cgroup hierarchy (no root, cgroup v2 only, a container without
the mount) everything here answers "not available" with the reason, once in the
log, and the sessions run as before, sharing the host through the kernel's fair
scheduler per thread.
"""

from __future__ import annotations

import contextlib
import logging
import os
from pathlib import Path

log = logging.getLogger(__name__)

CGROUP_ROOT = Path("/sys/fs/cgroup")
BASE_SHARES = 1024  # the kernel's default weight: a 30 fps 720p session
BASE_COST = 30.0 * 1280 * 720
MIN_SHARES = 2  # the kernel's bounds
MAX_SHARES = 262_144


def shares_for(fps: float, display_pixels: int) -> int:
    """The weight of a session whose target is ``fps`` frames of ``display_pixels``."""
    cost = max(1.0, fps * display_pixels)
    return max(MIN_SHARES, min(MAX_SHARES, round(BASE_SHARES * cost / BASE_COST)))


class CpuShares:
    def __init__(self, name: str, root: Path = CGROUP_ROOT) -> None:
        """``name``: this supervisor's group (``upcast-serve-<pid>``)."""
        self._cpu = root / "cpu" / name
        self._acct = root / "cpuacct" / name
        self.reason: str | None = None  # why shares are not enforced, None when they are
        try:
            self._cpu.mkdir(exist_ok=True)
        except OSError as exc:
            self.reason = f"no writable cgroup v1 cpu hierarchy at {root / 'cpu'} ({exc.strerror})"
            log.info("CPU shares not enforced: %s", self.reason)
        self._has_acct = False
        if self.reason is None:
            with contextlib.suppress(OSError):
                self._acct.mkdir(exist_ok=True)
                self._has_acct = True

    @property
    def available(self) -> bool:
        return self.reason is None

    @property
    def paths(self) -> list[Path]:
        """The groups made here (for the reaper: removed should the supervisor die)."""
        return [p for p in (self._cpu, self._acct if self._has_acct else None) if p is not None]

    def place(self, session: str, pid: int, shares: int) -> bool:
        """Put process ``pid`` (its children to come with it) in ``session``'s group
        with weight ``shares``. False (and a log line) when that failed."""
        if not self.available:
            return False
        try:
            group = self._cpu / session
            group.mkdir(exist_ok=True)
            (group / "cpu.shares").write_text(str(shares))
            (group / "cgroup.procs").write_text(str(pid))
            if self._has_acct:
                acct = self._acct / session
                acct.mkdir(exist_ok=True)
                (acct / "cgroup.procs").write_text(str(pid))
        except OSError as exc:
            log.warning("CPU shares: could not place pid %d in %s: %s", pid, session, exc)
            return False
        return True

    def set_shares(self, session: str, shares: int) -> bool:
        """A placed session's new weight; False (and a log line) when it could not be set."""
        if not self.available:
            return False
        try:
            (self._cpu / session / "cpu.shares").write_text(str(shares))
        except OSError as exc:
            log.warning("CPU shares: could not set %s to %d: %s", session, shares, exc)
            return False
        return True

    def shares(self, session: str) -> int | None:
        with contextlib.suppress(OSError, ValueError):
            return int((self._cpu / session / "cpu.shares").read_text())
        return None

    def cpu_seconds(self, session: str) -> float | None:
        """CPU time the session's processes used since placed (cpuacct), if known."""
        if not self._has_acct:
            return None
        with contextlib.suppress(OSError, ValueError):
            return int((self._acct / session / "cpuacct.usage").read_text()) / 1e9
        return None

    def remove(self, session: str) -> None:
        """Drop an empty session group (its processes ended)."""
        for base in (self._cpu, self._acct):
            with contextlib.suppress(OSError):
                (base / session).rmdir()

    def close(self) -> None:
        """Drop every group made here; a group still holding a process stays (EBUSY)."""
        for base in (self._cpu, self._acct):
            if not base.is_dir():
                continue
            for child in base.iterdir():
                if child.is_dir():
                    with contextlib.suppress(OSError):
                        child.rmdir()
            with contextlib.suppress(OSError):
                base.rmdir()


def supervisor_group_name() -> str:
    return f"upcast-serve-{os.getpid()}"
