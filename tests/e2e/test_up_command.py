"""``upcast up`` as a user runs it: banner, a page that plays, Ctrl-C, nothing left behind.

The command runs in its own process group and gets SIGINT on the whole group,
as a terminal's Ctrl-C does (the relay, game and worker children see it too).
"""

from __future__ import annotations

import os
import queue
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from server.frames.ring import SHM_DIR
from tests.e2e.conftest import DISPLAY, RENDER, needs, open_player, stats

pytestmark = [*needs("index.html"), pytest.mark.timeout(120)]

BANNER_TIMEOUT_S = 60.0
BANNER = re.compile(r"upcast is up: watch at (http://localhost:(\d+)/\?broadcast=game)\b")


def _free_port() -> int:
    # The relay needs the number free on both UDP and TCP.
    while True:
        with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as udp:
            udp.bind(("::", 0))
            port = int(udp.getsockname()[1])
            with socket.socket(socket.AF_INET6, socket.SOCK_STREAM) as tcp:
                try:
                    tcp.bind(("::", port))
                except OSError:
                    continue
        return port


def _children(pid: int) -> set[int]:
    """Direct children of ``pid`` (from /proc)."""
    found = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[1]) == pid:
            found.add(int(stat.parent.name))
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def _leftovers(pid: int, tmpdir: Path) -> list[Path]:
    prefix = f"upcast-{pid}-"  # SessionConfig.name of the `up` process: its rings
    return [*SHM_DIR.glob(f"{prefix}*"), *sorted(tmpdir.rglob("*"))]


def test_up_plays_in_chromium_and_stops_cleanly_on_ctrl_c(browser: Any, tmp_path: Path) -> None:
    port = _free_port()
    # fmt: off
    cmd = [
        sys.executable, "-m", "server.cli", "up", "--scene", "default",
        "--render-size", RENDER, "--display-size", DISPLAY, "--fps", "30",
        "--port", str(port), "--metrics-port", "0", "--duration", "90",
    ]
    # fmt: on
    log_path = tmp_path / "up.log"
    # Its own TMPDIR: whatever the session and its children leave in a temp dir shows.
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    env = {**os.environ, "TMPDIR": str(tmpdir)}
    with log_path.open("w") as log:
        proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=log, text=True, start_new_session=True, env=env
        )
    lines: queue.Queue[str] = queue.Queue()

    def pump() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line)

    threading.Thread(target=pump, daemon=True).start()
    try:
        deadline = time.monotonic() + BANNER_TIMEOUT_S
        match = None
        while match is None and time.monotonic() < deadline and proc.poll() is None:
            try:
                match = BANNER.search(lines.get(timeout=0.5))
            except queue.Empty:
                continue
        assert match is not None, f"no banner; log:\n{log_path.read_text()[-3000:]}"
        url, shown_port = match.group(1), int(match.group(2))
        assert shown_port == port

        page = open_player(browser, url, frames=5)
        try:
            first = stats(page)["framesPresented"]
            page.wait_for_timeout(2000)
            last = stats(page)
        finally:
            page.close()
        assert last["version"] == "moq-lite-03"
        assert last["framesPresented"] - first >= 20, (first, last["framesPresented"])

        children = _children(proc.pid)
        assert len(children) >= 3, children  # relay, game, worker
        os.killpg(proc.pid, signal.SIGINT)
        code = proc.wait(30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
    log_text = log_path.read_text()
    assert code == 0, log_text[-3000:]
    assert "Traceback" not in log_text, log_text[-3000:]
    assert "restart" not in log_text, log_text[-3000:]  # no child died on the way
    deadline = time.monotonic() + 10
    while any(_alive(c) for c in children) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [c for c in children if _alive(c)], "children outlived upcast up"
    # (A generated relay certificate, key included, must not outlive the relay either.)
    assert _leftovers(proc.pid, tmpdir) == [], "files left behind by upcast up"
