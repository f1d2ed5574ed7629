"""Run ``upcast relay`` as a child process and learn its port and certificate hash.

The relay is its own process (as in a deployment: it serves every session of
a host and survives a session restart); ``upcast up`` starts one next to the
game session. The child writes its port and certificate hash to a ready file
once both listeners are bound, so the parent never races the bind.
"""

from __future__ import annotations

import contextlib
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from server.ops import orphan_guard

READY_TIMEOUT_S = 30.0


@dataclass(frozen=True)
class RelayEndpoint:
    port: int
    cert_sha256: str


class RelayProcess:
    def __init__(
        self,
        host: str,
        port: int,
        web_root: Path | None = None,
        *,
        auth_key: Path | None = None,
        public_viewers: bool = True,
        extra_args: tuple[str, ...] = (),
    ) -> None:
        """Without ``auth_key`` the relay runs with ``--no-auth`` (benchmarks on
        loopback); ``upcast up`` always passes one."""
        self.host = host
        self.port = port
        self.web_root = web_root
        self.auth_key = auth_key
        self.public_viewers = public_viewers
        self.extra_args = extra_args  # more `upcast relay` options (a benchmark's settings)
        self.proc: subprocess.Popen[bytes] | None = None
        self.endpoint: RelayEndpoint | None = None
        self.restarts = 0
        self._dir = Path(tempfile.mkdtemp(prefix="upcast-relay-"))

    def start(self, timeout_s: float = READY_TIMEOUT_S) -> RelayEndpoint:
        ready = self._dir / "ready"
        ready.unlink(missing_ok=True)
        port = self.endpoint.port if self.endpoint is not None else self.port
        args = [sys.executable, "-m", "server.cli", "relay", "--host", self.host]
        args += ["--port", str(port), "--ready-file", str(ready)]
        if self.web_root is not None:
            args += ["--web-root", str(self.web_root)]
        if self.auth_key is None:
            args.append("--no-auth")
        else:
            args += ["--auth-key", str(self.auth_key)]
            args.append("--public-viewers" if self.public_viewers else "--no-public-viewers")
        args += self.extra_args
        if self.proc is not None:  # a restart: the dead one is not to be ended
            orphan_guard.forget_process(self.proc.pid)
        self.proc = subprocess.Popen(args)
        orphan_guard.watch_process(self.proc.pid)  # ended should this process die first
        deadline = time.monotonic() + timeout_s
        while True:
            if ready.exists():
                text = ready.read_text().split()
                if len(text) == 2:
                    self.endpoint = RelayEndpoint(int(text[0]), text[1])
                    return self.endpoint
            code = self.proc.poll()
            if code is not None:
                raise RuntimeError(f"relay exited with code {code} while starting")
            if time.monotonic() > deadline:
                self.stop()
                raise TimeoutError(f"relay did not come up in {timeout_s:.0f}s")
            time.sleep(0.05)

    def check(self) -> bool:
        """Restart the relay if it died (same port; viewers and the session reconnect).
        Returns True when a restart happened."""
        if self.proc is None or self.proc.poll() is None:
            return False
        self.restarts += 1
        self.start()
        return True

    def stop(self) -> None:
        proc = self.proc
        if proc is not None and proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)
        if proc is not None:
            orphan_guard.forget_process(proc.pid)
        with contextlib.suppress(OSError):
            (self._dir / "ready").unlink(missing_ok=True)
            self._dir.rmdir()
