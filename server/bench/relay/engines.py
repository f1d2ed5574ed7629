"""The two relays under test, each started as its own process on a free loopback port.

- ``upcast``: ``upcast relay --no-auth`` (server/relay/process.py); the broadcast is
  seen on its ``/stats``.
- ``moq-rs``: ``python -m server.bench.relay.rust_relay`` (moq-dev's Rust relay core);
  the broadcast is seen on its stdout, where it prints what gets announced.

Both get the same kind of certificate (ECDSA P-256 from server/quic/certs.py), and
the publisher and viewers reach both as ``https://127.0.0.1:PORT/`` pinning its hash.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.util
import json
import os
import queue
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Protocol

from server.loadtest.plan import RelayAddress
from server.loadtest.relay_probe import relay_broadcasts
from server.ops import orphan_guard
from server.ops.process import stop_child
from server.quic.certs import generate_cert
from server.relay.process import RelayProcess

HOST = "127.0.0.1"
ENGINES = ("upcast", "moq-rs")
START_TIMEOUT_S = 30.0
POLL_S = 0.2
MOQ_RS_PIP = "pip install 'moq-rs==0.5.1'  (or: pip install -e '.[dev]')"


class RunningRelay(Protocol):
    engine: str
    url: str
    cert_sha256: str
    pid: int

    def wait_broadcast(self, name: str, timeout_s: float) -> None: ...

    def stop(self) -> None: ...


def moq_rs_available() -> bool:
    return importlib.util.find_spec("moq") is not None


@contextlib.contextmanager
def children_print_to_stderr() -> Iterator[None]:
    """Children started inside inherit stderr as their stdout: ``upcast relay`` prints
    its listening line on stdout, which is the benchmark's table."""
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    try:
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


class UpcastRelay:
    engine = "upcast"

    def __init__(self) -> None:
        self._process = RelayProcess(HOST, 0)  # no auth key: --no-auth
        with children_print_to_stderr():
            endpoint = self._process.start(START_TIMEOUT_S)
        assert self._process.proc is not None
        self.pid = self._process.proc.pid
        self.port = endpoint.port
        self.url = f"https://{HOST}:{endpoint.port}/"
        self.cert_sha256 = endpoint.cert_sha256

    def wait_broadcast(self, name: str, timeout_s: float) -> None:
        address = RelayAddress("http", HOST, self.port)
        deadline = time.monotonic() + timeout_s
        while True:
            found = asyncio.run(relay_broadcasts(address)) or []
            if name.strip("/") in (b.strip("/") for b in found):
                return
            if time.monotonic() > deadline:
                raise TimeoutError(f"upcast relay: no broadcast {name!r} after {timeout_s:g} s")
            time.sleep(POLL_S)

    def stop(self) -> None:
        self._process.stop()


class RustRelay:
    engine = "moq-rs"

    def __init__(self, workdir: Path) -> None:
        cert = generate_cert(directory=workdir)
        argv = [sys.executable, "-m", "server.bench.relay.rust_relay", "--host", HOST]
        argv += ["--cert", str(cert.cert_path), "--key", str(cert.key_path)]
        self._proc = subprocess.Popen(argv, stdout=subprocess.PIPE, text=True)
        self.pid = self._proc.pid
        orphan_guard.watch_process(self.pid)  # ended should the bench die first
        self._lines: queue.Queue[dict[str, object]] = queue.Queue()
        self._announced: set[str] = set()
        assert self._proc.stdout is not None
        threading.Thread(target=self._read, args=(self._proc.stdout,), daemon=True).start()
        try:
            ready = self._next_line(START_TIMEOUT_S)
        except BaseException:
            self.stop()
            raise
        self.url = str(ready["url"])
        self.cert_sha256 = str(ready["cert_sha256"])

    def _read(self, stdout: IO[str]) -> None:
        for line in stdout:
            try:
                record = json.loads(line)
            except ValueError:
                continue
            if isinstance(record, dict):
                self._lines.put(record)

    def _next_line(self, timeout_s: float) -> dict[str, object]:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                return self._lines.get(timeout=POLL_S)
            except queue.Empty:
                code = self._proc.poll()
                if code is not None:
                    raise RuntimeError(f"moq-rs relay exited with code {code}") from None
                if time.monotonic() > deadline:
                    raise TimeoutError(f"moq-rs relay: nothing after {timeout_s:g} s") from None

    def wait_broadcast(self, name: str, timeout_s: float) -> None:
        want = name.strip("/")
        deadline = time.monotonic() + timeout_s
        while want not in self._announced:
            record = self._next_line(max(0.0, deadline - time.monotonic()))
            path = str(record.get("announced", "")).strip("/")
            if record.get("active"):
                self._announced.add(path)
            else:
                self._announced.discard(path)

    def stop(self) -> None:
        stop_child(self._proc, 5.0)
        orphan_guard.forget_process(self.pid)


def start_relay(engine: str, workdir: Path) -> RunningRelay:
    if engine == "upcast":
        return UpcastRelay()
    if engine == "moq-rs":
        return RustRelay(workdir)
    raise ValueError(f"unknown engine {engine!r}; choose from {', '.join(ENGINES)}")
