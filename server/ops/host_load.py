"""How many of the host's cores are busy, from /proc/stat (every process, not ours).

The quality controller steps up only into cores nobody else uses: on a host shared
by sessions (or with a compile, a browser, a second game), that is what is left for
it. Read as the change of the kernel's busy and idle jiffies between two calls, so a
reading covers exactly the time since the one before.
"""

from __future__ import annotations

from pathlib import Path

from server.ops.machine import usable_cores

PROC_STAT = Path("/proc/stat")


def _jiffies(text: str) -> tuple[int, int] | None:
    """(busy, total) jiffies of the ``cpu`` line; None when there is none."""
    for line in text.splitlines():
        fields = line.split()
        if fields and fields[0] == "cpu":
            values = [int(v) for v in fields[1:] if v.isdigit()]
            if len(values) < 4:
                return None
            # user nice system idle iowait irq softirq steal guest guest_nice: guest time
            # is already counted in user and nice.
            counted = values[:8]
            idle = counted[3] + (counted[4] if len(counted) > 4 else 0)
            total = sum(counted)
            return total - idle, total
    return None


class HostLoad:
    """``busy_cores()``: busy cores since the last call (None at the first, or where
    /proc/stat cannot be read: not Linux, or a sandbox without it)."""

    def __init__(self, path: Path = PROC_STAT, cores: int | None = None) -> None:
        self.path = path
        self.cores = float(cores if cores is not None else usable_cores())
        self._last = self._read()
        self._host_cpus = self._count_cpus()

    def _read(self) -> tuple[int, int] | None:
        try:
            return _jiffies(self.path.read_text())
        except (OSError, ValueError):
            return None

    def _count_cpus(self) -> int:
        try:
            text = self.path.read_text()
        except OSError:
            return 0
        return sum(1 for line in text.splitlines() if line[:3] == "cpu" and line[3:4].isdigit())

    def busy_cores(self) -> float | None:
        now = self._read()
        last, self._last = self._last, now
        if now is None or last is None or now[1] <= last[1] or self._host_cpus <= 0:
            return None
        share = (now[0] - last[0]) / (now[1] - last[1])
        # /proc/stat counts every CPU of the host; a container may use fewer of them.
        busy = max(0.0, min(1.0, share)) * self._host_cpus
        return min(busy, self.cores) if self._host_cpus > self.cores else busy
