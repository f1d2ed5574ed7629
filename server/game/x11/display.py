"""A private virtual X screen (Xvfb) for one application.

Xvfb picks a free display number itself (``-displayfd``): guessing one and
retrying races with every other Xvfb on the host, the server's own lock file
does not. The number it writes means it listens; one real connection confirms
it before ``start`` returns.
"""

from __future__ import annotations

import os
import select
import shutil
import signal
import subprocess
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from typing import IO, Self

from Xlib import display as xdisplay
from Xlib import error as xerror

from server.game.x11.errors import DisplayError
from server.ops import orphan_guard

XVFB = "Xvfb"
# GLX so Mesa's OpenGL (llvmpipe) games draw; MIT-SHM is Xvfb's default but say it,
# capture relies on it. -noreset: the last client leaving must not reset the screen.
EXTENSIONS = ("+extension", "GLX", "+extension", "MIT-SHM")
SOCKET_DIR = Path("/tmp/.X11-unix")


class VirtualDisplay:
    """One running Xvfb; ``start`` makes one, ``close`` (or ``with``) ends it."""

    def __init__(self, process: subprocess.Popen[bytes], number: int, log: IO[bytes]) -> None:
        self._process = process
        self.number = number
        self.name = f":{number}"
        self._log = log
        # The socket file as it was at start: a killed server leaves it behind, and
        # only this very file (not a later server's on the same number) is ours to remove.
        self._socket = SOCKET_DIR / f"X{number}"
        self._socket_id = _file_id(self._socket)

    @classmethod
    def start(
        cls, width: int, height: int, *, depth: int = 24, timeout_s: float = 10.0
    ) -> VirtualDisplay:
        if width <= 0 or height <= 0:
            raise ValueError(f"screen size must be positive, got {width}x{height}")
        exe = shutil.which(XVFB)
        if exe is None:
            raise DisplayError("Xvfb not found: install Debian's package xvfb")
        read_fd, write_fd = os.pipe()
        # A file, not a pipe: a chatty server must never block on a full pipe.
        log = tempfile.TemporaryFile(prefix="upcast-xvfb-")  # noqa: SIM115 - lives as long as the server
        try:
            process = subprocess.Popen(
                [
                    exe,
                    "-displayfd",
                    str(write_fd),
                    "-nolisten",
                    "tcp",
                    "-noreset",
                    "-screen",
                    "0",
                    f"{width}x{height}x{depth}",
                    *EXTENSIONS,
                ],
                pass_fds=(write_fd,),
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=log,
                start_new_session=True,  # a Ctrl-C meant for us is not the server's
            )
        except OSError as exc:
            os.close(read_fd)
            log.close()
            raise DisplayError(f"cannot run {exe}: {exc}") from exc
        finally:
            os.close(write_fd)
        # Its own session (above), so our group's signals miss it: the reaper ends it
        # (SIGTERM: it removes its socket and lock) should this process die first.
        orphan_guard.watch_process(process.pid, group=True)
        try:
            number = _read_display_number(read_fd, process, log, timeout_s)
        except BaseException:
            _end(process, 1.0)
            log.close()
            raise
        finally:
            os.close(read_fd)
        self = cls(process, number, log)
        try:
            self._wait_connectable(time.monotonic() + timeout_s)
        except BaseException:
            self.close()
            raise
        return self

    def _wait_connectable(self, deadline: float) -> None:
        while True:
            try:
                xdisplay.Display(self.name).close()
                return
            except (xerror.DisplayError, OSError) as exc:
                if not self.alive() or time.monotonic() > deadline:
                    raise DisplayError(
                        f"cannot open display {self.name}: {exc}; Xvfb said: {self.log_tail()}"
                    ) from exc
                time.sleep(0.02)

    def env(self, base: Mapping[str, str] | None = None) -> dict[str, str]:
        """``base`` (default: this process's environment) with DISPLAY set to this screen."""
        out = dict(os.environ if base is None else base)
        out["DISPLAY"] = self.name
        return out

    def alive(self) -> bool:
        return self._process.poll() is None

    @property
    def pid(self) -> int:
        return self._process.pid

    def log_tail(self, limit: int = 2000) -> str:
        """The end of what Xvfb wrote (for error messages)."""
        if self._log.closed:
            return ""
        self._log.seek(0)
        return self._log.read()[-limit:].decode(errors="replace").strip()

    def close(self, timeout_s: float = 3.0) -> None:
        """Terminate the server (kill it after ``timeout_s``) and remove what it left."""
        _end(self._process, timeout_s)
        # A killed server leaves its socket (and lock, if it made one); remove what is ours.
        if self._socket_id is not None and _file_id(self._socket) == self._socket_id:
            self._socket.unlink(missing_ok=True)
        lock = Path(f"/tmp/.X{self.number}-lock")
        if _lock_owner(lock) == self._process.pid:
            lock.unlink(missing_ok=True)
        self._log.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"VirtualDisplay({self.name}, pid={self._process.pid}, alive={self.alive()})"


def _read_display_number(
    fd: int, process: subprocess.Popen[bytes], log: IO[bytes], timeout_s: float
) -> int:
    deadline = time.monotonic() + timeout_s
    data = b""
    while not data.endswith(b"\n"):
        left = deadline - time.monotonic()
        if left <= 0:
            raise DisplayError(f"Xvfb did not start within {timeout_s:g} s")
        ready, _, _ = select.select([fd], [], [], min(left, 0.1))
        chunk = os.read(fd, 64) if ready else b""
        if ready and not chunk:  # EOF: Xvfb exited (bad option, cannot lock...)
            process.wait(1.0)
            log.seek(0)
            said = log.read()[-2000:].decode(errors="replace").strip()
            raise DisplayError(f"Xvfb exited with code {process.returncode}: {said}")
        data += chunk
    return int(data.strip())


def _end(process: subprocess.Popen[bytes], timeout_s: float) -> None:
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    orphan_guard.forget_process(process.pid)


def _lock_owner(lock: Path) -> int | None:
    try:
        return int(lock.read_text().strip())
    except (OSError, ValueError):
        return None


def _file_id(path: Path) -> tuple[int, int] | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_dev, st.st_ino
