"""The reaper: ends a process's children and removes its files once that process is gone.

``python -m server.ops.reaper FD`` is started by server/ops/orphan_guard.py and reads
one line per change from the pipe ``FD``, whose write end only its parent holds. A
parent that dies by any means (SIGKILL, the OOM killer) closes that end in the
kernel, so the read returns EOF with nobody's cooperation; the reaper then sends
SIGTERM to every process still registered (a process group where asked), removes
every registered path, gives them ``GRACE_S`` to exit, SIGKILLs the rest and
exits. A parent that cleaned up after itself has forgotten everything by then: the
reaper finds nothing and exits at once. It runs in a session of its own, so a
Ctrl-C or a signal to its parent's process group never reaches it.

The lines (``Watchlist`` parses them; no sockets, testable on its own):

    pid PID STARTTIME GROUP   watch PID (GROUP 1: its whole process group); STARTTIME
                              is field 22 of /proc/PID/stat, so a pid the kernel gave
                              to another process meanwhile is never signalled
    -pid PID                  forget it (it was stopped and waited for)
    path PATH                 remove PATH (a file, socket or folder) at the end
    -path PATH                forget it
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from server.ops.process import pid_alive

log = logging.getLogger("upcast.reaper")

LEFTOVER_S = 2.0  # how long paths that cannot go yet are retried after the processes end
GRACE_S = 1.0  # SIGTERM, then SIGKILL: within the 2 s that anything may outlive its owner
POLL_S = 0.02


def start_time(pid: int) -> int | None:
    """Field 22 of /proc/PID/stat (clock ticks after boot); None when there is no such
    process. With the pid it names one process for as long as the machine runs."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat = f.read()
    except OSError:
        return None
    fields = stat[stat.rfind(b")") + 2 :].split()
    try:
        return int(fields[19])
    except (IndexError, ValueError):
        return None


@dataclass(frozen=True)
class Watched:
    pid: int
    start: int
    group: bool


@dataclass
class Watchlist:
    """What the reaper will end and remove; fed the parent's lines."""

    processes: dict[int, Watched] = field(default_factory=dict)
    paths: dict[str, None] = field(default_factory=dict)  # ordered set

    def feed(self, line: str) -> None:
        verb, _, rest = line.rstrip("\n").partition(" ")
        if verb == "pid":
            pid, start, group = rest.split()
            self.processes[int(pid)] = Watched(int(pid), int(start), group == "1")
        elif verb == "-pid":
            self.processes.pop(int(rest), None)
        elif verb == "path" and rest:
            self.paths[rest] = None
        elif verb == "-path":
            self.paths.pop(rest, None)
        else:
            raise ValueError(f"reaper: not a watch line: {line!r}")

    def empty(self) -> bool:
        return not self.processes and not self.paths


def _same_process(w: Watched) -> bool:
    return start_time(w.pid) == w.start and pid_alive(w.pid)


def _alive(w: Watched) -> bool:
    if _same_process(w):
        return True
    if not w.group or start_time(w.pid) is not None:
        return False  # no group left, or its number now names another process
    try:
        os.killpg(w.pid, 0)  # any member left (a group's id outlives its leader)
    except (ProcessLookupError, PermissionError):
        return False
    return True


def _signal(w: Watched, sig: signal.Signals) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        if w.group:
            os.killpg(w.pid, sig)
        else:
            os.kill(w.pid, sig)


def _remove(path: str) -> None:
    p = Path(path)
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        with contextlib.suppress(OSError):
            p.unlink(missing_ok=True)


def reap(watch: Watchlist, grace_s: float = GRACE_S) -> tuple[int, int]:
    """SIGTERM what is watched, remove the paths, SIGKILL what outlived ``grace_s``.
    Returns (processes ended, paths removed)."""
    living = [w for w in watch.processes.values() if _alive(w)]
    ended = len(living)
    for w in living:
        _signal(w, signal.SIGTERM)
    removed = sum(1 for p in watch.paths if os.path.lexists(p))
    for p in watch.paths:
        _remove(p)
    deadline = time.monotonic() + grace_s
    while living and time.monotonic() < deadline:
        time.sleep(POLL_S)
        living = [w for w in living if _alive(w)]
    for w in living:
        log.warning("reaper: pid %d outlived SIGTERM by %.1f s: SIGKILL", w.pid, grace_s)
        _signal(w, signal.SIGKILL)
    # Again: a process that ended just now may have left one, and a cgroup can only go
    # once the last process in it (a group member that outlived its leader) has exited.
    deadline = time.monotonic() + LEFTOVER_S
    while True:
        for p in watch.paths:
            _remove(p)
        if not any(os.path.lexists(p) for p in watch.paths) or time.monotonic() >= deadline:
            break
        time.sleep(POLL_S)
    return ended, removed


def run(fd: int) -> int:
    watch = Watchlist()
    with os.fdopen(fd, "r", encoding="utf-8", errors="surrogateescape") as pipe:
        for line in pipe:  # until EOF: the parent is gone
            try:
                watch.feed(line)
            except ValueError as exc:
                log.error("%s", exc)
    if watch.empty():
        return 0
    ended, removed = reap(watch)
    if ended or removed:  # else another reaper (or the process's own stop) was first
        log.warning(
            "reaper: its process exited without cleaning up: ended %d processes, removed %d paths",
            ended,
            removed,
        )
    return 0


def main(argv: list[str]) -> int:
    if len(argv) != 1 or not argv[0].isdigit():
        print("usage: python -m server.ops.reaper FD (started by orphan_guard)", file=sys.stderr)
        return 2
    # The parent's terminal may send these to its group; the reaper is in its own
    # session, but a parent started without one must not take it along either.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    return run(int(argv[0]))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
