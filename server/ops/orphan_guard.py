"""Nothing outlives its owner: register children and files with this process's reaper.

A process that starts children (``upcast up`` its relay, game and worker; ``upcast
serve`` its session processes; a session its game and worker; an X11 source its
Xvfb, PulseAudio and application) registers each here, and each file it must not
leave behind (rings in /dev/shm, sockets). The first registration starts the
process's reaper (server/ops/reaper.py), which ends and removes whatever is still
registered once this process is gone by any signal, SIGKILL included: it learns
that from the kernel (EOF on a pipe only this process writes), not from us. A
normal stop forgets what it stopped, so the reaper then has nothing to do.

Why not the kernel's parent-death signal: it fires when the *thread* that started
the child exits (children started from an executor thread would die with it), and
setting it on a program we do not write (Xvfb, an application) needs ``preexec_fn``,
unsafe in a process with threads.

Registration never fails the caller: without a reaper (it could not start) the
process runs as before, with a warning.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import threading
from pathlib import Path

from server.ops.reaper import start_time

log = logging.getLogger(__name__)


class OrphanGuard:
    """This process's end of the pipe to its reaper (one per process, made lazily)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._fd: int | None = None
        self._reaper: subprocess.Popen[bytes] | None = None
        self._broken = False

    @property
    def reaper_pid(self) -> int | None:
        return None if self._reaper is None else self._reaper.pid

    def watch_process(self, pid: int, *, group: bool = False) -> None:
        """End ``pid`` (``group``: its whole process group, which it leads) if this
        process dies first."""
        start = start_time(pid)
        if start is not None:  # None: it is gone already
            self._send(f"pid {pid} {start} {int(group)}")

    def forget_process(self, pid: int) -> None:
        self._send(f"-pid {pid}")

    def watch_path(self, path: Path | str) -> None:
        """Remove ``path`` (file, socket or folder) if this process dies first."""
        self._send(f"path {os.fspath(path)}")

    def forget_path(self, path: Path | str) -> None:
        self._send(f"-path {os.fspath(path)}")

    def _send(self, line: str) -> None:
        if "\n" in line:
            raise ValueError(f"a watched path cannot hold a newline: {line!r}")
        data = (line + "\n").encode("utf-8", "surrogateescape")
        with self._lock:
            if self._fd is None and line.startswith("-"):
                return  # nothing was registered: no reaper to start for a forget
            fd = self._fd if self._fd is not None else self._start()
            if fd is None:
                return
            try:
                os.write(fd, data)  # one line < PIPE_BUF: written whole or not at all
            except OSError as exc:  # the reaper died: carry on without one
                log.warning("orphan guard: reaper gone (%s); children may outlive a crash", exc)
                self._close()
                self._broken = True

    def _start(self) -> int | None:
        if self._broken:
            return None
        read_fd, write_fd = os.pipe()  # both close-on-exec: no other child inherits them
        try:
            self._reaper = subprocess.Popen(
                [sys.executable, "-m", "server.ops.reaper", str(read_fd)],
                pass_fds=(read_fd,),
                stdin=subprocess.DEVNULL,
                start_new_session=True,  # signals to our group are not its
            )
        except OSError as exc:
            os.close(write_fd)
            log.warning("orphan guard: cannot start the reaper (%s)", exc)
            self._broken = True
            return None
        finally:
            os.close(read_fd)
        self._fd = write_fd
        return write_fd

    def _close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def after_fork(self) -> None:
        """In a forked child: the parent's registrations are not ours; start afresh."""
        self._lock = threading.Lock()
        self._close()
        self._reaper = None
        self._broken = False


GUARD = OrphanGuard()
os.register_at_fork(after_in_child=GUARD.after_fork)

watch_process = GUARD.watch_process
forget_process = GUARD.forget_process
watch_path = GUARD.watch_path
forget_path = GUARD.forget_path
