"""The streamed program: one process group, output to a log, stopped as a whole.

Games start helpers (launcher scripts, shader compilers, audio daemons); a group
of their own lets ``stop`` reach all of them with one signal. Their output goes
to a file or, by default, to this process's logging through a reader thread: a
pipe nobody drains would block a chatty game mid-frame.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import signal
import subprocess
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import IO

from server.ops import orphan_guard

log = logging.getLogger(__name__)

MAX_LOG_LINE = 500


class ApplicationError(RuntimeError):
    """The program could not be started (not found, not executable)."""


class Application:
    """A running program; ``start`` makes one, ``stop`` ends it and its children."""

    def __init__(self, process: subprocess.Popen[bytes], name: str) -> None:
        self._process = process
        self.name = name
        self.pid = process.pid
        self._reader: threading.Thread | None = None

    @classmethod
    def start(
        cls,
        command: Sequence[str],
        env: Mapping[str, str],
        *,
        cwd: str | None = None,
        log_path: Path | None = None,
    ) -> Application:
        """Run ``command`` with exactly ``env``; its output goes to ``log_path`` (appended) or,
        without one, to this module's logger at DEBUG."""
        if not command:
            raise ApplicationError("no command given")
        exe = command[0]
        search_path = env.get("PATH", os.defpath)
        # A path with a slash is not searched, and is relative to the program's cwd.
        where = os.path.join(cwd or ".", exe) if os.sep in exe else exe
        if shutil.which(where, path=search_path) is None:
            why = "not executable" if os.path.exists(where) else "not found"
            raise ApplicationError(f"cannot start {exe!r}: {why} (PATH={search_path})")
        name = os.path.basename(exe)
        out: IO[bytes] | int = subprocess.PIPE
        if log_path is not None:
            out = open(log_path, "ab")  # noqa: SIM115 - the child holds it; closed below
        try:
            process = subprocess.Popen(
                list(command),
                env=dict(env),
                cwd=cwd,
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,  # its own process group, leader = pid
            )
        except OSError as exc:
            raise ApplicationError(f"cannot start {exe!r}: {exc}") from exc
        finally:
            if not isinstance(out, int):
                out.close()
        # A group of its own (above) that our signals miss: the reaper ends the group
        # should this process die without stop().
        orphan_guard.watch_process(process.pid, group=True)
        self = cls(process, name)
        if process.stdout is not None:
            self._reader = threading.Thread(
                target=_forward, args=(process.stdout, name), name=f"app-log-{name}", daemon=True
            )
            self._reader.start()
        log.info("started %s (pid %d)", " ".join(command), process.pid)
        return self

    def exit_code(self) -> int | None:
        """None while running; else its exit code (negative: killed by that signal)."""
        return self._process.poll()

    def stop(self, timeout_s: float = 3.0) -> int | None:
        """SIGTERM to the whole group, SIGKILL after ``timeout_s``; the program's exit code."""
        self._signal_group(signal.SIGTERM)
        try:
            self._process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self._signal_group(signal.SIGKILL)
            self._process.wait()
        # The leader may have obeyed while a child of it ignores SIGTERM: kill the rest.
        self._signal_group(signal.SIGKILL)
        orphan_guard.forget_process(self.pid)
        if self._reader is not None:
            self._reader.join(1.0)
        return self._process.returncode

    def _signal_group(self, sig: signal.Signals) -> None:
        with contextlib.suppress(ProcessLookupError, PermissionError):  # the group is empty
            os.killpg(self.pid, sig)

    def __repr__(self) -> str:
        return f"Application({self.name}, pid={self.pid}, exit_code={self.exit_code()})"


def _forward(stream: IO[bytes], name: str) -> None:
    with stream:
        for line in stream:
            text = line[:MAX_LOG_LINE].decode(errors="replace").rstrip()
            log.debug("%s: %s", name, text)
