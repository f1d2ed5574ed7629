"""Run ``upcast serve`` as a subprocess for a test, and read its ``/sessions``."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from server.auth import AuthKey, generate_key, load_key
from server.auth.minting import session_tokens
from server.ops.process import stop_child
from server.quic.moq_link import with_token

ROOT = Path(__file__).resolve().parents[1]
# 160x90 -> 320x180 at 15 fps: small enough for 4 sessions on a 2-core CI machine.
SMALL = ["--render-size", "160x90", "--display-size", "320x180", "--fps", "15"]


@dataclass
class Served:
    proc: subprocess.Popen[str]
    port: int
    http_port: int
    key: AuthKey  # serve's relay checks tokens signed with it

    @property
    def relay_url(self) -> str:
        """The relay without a token: what an anonymous viewer (or an attacker) uses."""
        return f"http://127.0.0.1:{self.port}/"

    def player_token(self, broadcast: str) -> str:
        """What serve puts in a session's watch URL: watch it and send it inputs."""
        return session_tokens(self.key, broadcast).player

    def player_url(self, broadcast: str) -> str:
        return with_token(self.relay_url, self.player_token(broadcast))

    def get(self, path: str) -> tuple[int, bytes]:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{self.http_port}{path}", timeout=5) as r:
                return int(r.status), bytes(r.read())
        except urllib.error.HTTPError as exc:
            return int(exc.code), bytes(exc.read())

    def sessions(self) -> list[dict[str, Any]]:
        rows: list[dict[str, Any]] = self.answer()["sessions"]
        return rows

    def answer(self) -> dict[str, Any]:
        """The whole ``/sessions`` answer (``relay`` and ``sessions``)."""
        status, body = self.get("/sessions")
        assert status == 200
        answer: dict[str, Any] = json.loads(body)
        return answer

    def wait(self, pred: Any, timeout_s: float, what: str) -> list[dict[str, Any]]:
        deadline = time.monotonic() + timeout_s
        while True:
            assert self.proc.poll() is None, f"upcast serve exited with {self.proc.returncode}"
            with contextlib.suppress(OSError, AssertionError, ValueError):
                rows = self.sessions()
                if pred(rows):
                    return rows
            assert time.monotonic() < deadline, f"timed out waiting for {what}"
            time.sleep(0.5)


@contextlib.contextmanager
def serve(port: int, *args: str, up_timeout_s: float = 120.0) -> Iterator[Served]:
    """``upcast serve --port PORT --auth-key KEY ARGS...`` until every session is up;
    stopped after. The key is made here so the test can mint players' tokens."""
    tmp = tempfile.TemporaryDirectory(prefix="upcast-serve-test-")
    key_path = Path(tmp.name) / "relay.jwk"
    generate_key(key_path)
    cmd = [sys.executable, "-m", "server.cli", "serve", "--port", str(port)]
    cmd += ["--auth-key", str(key_path), *args]
    if "--quality" not in args:
        # These tests assert the settings they start with or ask for; adaptive quality
        # has tests of its own (tests/test_quality_*.py).
        cmd += ["--quality", "fixed"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, text=True)
    served = Served(proc, port, port + 1, load_key(key_path))
    try:
        served.wait(
            lambda rows: rows and all(r["state"] == "up" and r["frames"] > 0 for r in rows),
            up_timeout_s,
            "every session up",
        )
        yield served
    finally:
        stop_child(proc, 40)
        tmp.cleanup()
