"""A whole stack with tokens, every process at DEBUG: no token and no key in any log.

``upcast -v --log-format json up --auth-key KEY`` runs the relay, the game, the
worker and the session publisher (four processes, one stderr); beside it a viewer
process connects with a valid token (and watches a frame), then with two bad ones,
and logs the URLs it used, as a careless caller would; a synthetic publisher retries
with a wrong token. Every line of every process's stdout and stderr is searched for
the tokens, the key (as the JWK's base64url, standard base64, hex) and anything
JWT-shaped. The one allowed place is ``upcast up``'s own banner on stdout: it hands
the player's watch URL to the person who started it (by design, not a log line).
"""

from __future__ import annotations

import base64
import json
import os
import re
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from server.auth import Claims, generate_key, load_key, sign
from server.auth.keys import AuthKey
from server.ops.process import stop_child

ROOT = Path(__file__).resolve().parents[1]
UP_SECONDS = 30.0
BANNER = "upcast is up: watch at"
JWT_SHAPE = re.compile(r"eyJ[A-Za-z0-9_-]*\.eyJ[A-Za-z0-9_-]*\.[A-Za-z0-9_-]+")
NOT_A_JWT = "upcast-secret-not-a-jwt-7f3a9c"

# The viewer: a real client process with upcast's own logging at DEBUG, JSON lines.
VIEWER = r"""
import asyncio, logging, sys
from server.ops.logging_setup import configure_logging
from server.moq.events import FrameReceived
from server.quic.moq_link import connect_moq, with_token
from server.quic.client import WtConnectError

configure_logging(logging.DEBUG, "json")
log = logging.getLogger("upcast.test.viewer")
url, good, bad_jwt, bad_text = sys.argv[1:5]

async def main() -> None:
    got = asyncio.Event()
    def on_events(link, events):
        if any(isinstance(e, FrameReceived) for e in events):
            got.set()
    link = await connect_moq(url, token=good, on_events=on_events, timeout=10)
    # Careless on purpose: the URL with its token, straight into a log call.
    log.info("viewer connected to %s", with_token(url, good))
    log.debug(f"request path {link.request.path if link.request else '?'}")
    link.moq.subscribe("game", "catalog.json")
    link.flush()
    await asyncio.wait_for(got.wait(), 20)
    log.info("viewer got a catalog frame")
    link.close(0, "done")
    for bad in (bad_jwt, bad_text):
        try:
            await connect_moq(url, token=bad, timeout=5)
        except WtConnectError as exc:
            log.warning("viewer refused: %s", exc)
            log.debug("refusal traceback", exc_info=True)
        else:
            raise SystemExit("a bad token was accepted")
    print("viewer done", flush=True)

asyncio.run(main())
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def key_forms(key_path: Path, key: AuthKey) -> list[str]:
    """Every text form the key's secret could leak as."""
    k = json.loads(key_path.read_text())["k"]
    std = base64.b64encode(key.secret).decode()
    return [k, std, std.rstrip("="), key.secret.hex(), key.secret.hex().upper()]


def token_forms(token: str) -> list[str]:
    """The token, and its signature alone (a truncated token still leaks it)."""
    return [token, token.rsplit(".", 1)[-1]] if "." in token else [token]


@dataclass
class Captured:
    name: str
    lines: list[str]


def run_stack(tmp: Path) -> tuple[list[Captured], AuthKey, list[str]]:
    key_path = tmp / "relay.jwk"
    generate_key(key_path)
    key = load_key(key_path)
    port = _free_port()
    relay = f"http://127.0.0.1:{port}/"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "UPCAST_LOG_FORMAT": "json"}
    outs = {n: (tmp / f"{n}.out", tmp / f"{n}.err") for n in ("up", "viewer", "publisher")}

    def popen(name: str, argv: list[str]) -> subprocess.Popen[bytes]:
        out, err = outs[name]
        with out.open("wb") as o, err.open("wb") as e:
            return subprocess.Popen(argv, cwd=ROOT, env=env, stdout=o, stderr=e)

    # fmt: off
    up = popen("up", [
        sys.executable, "-m", "server.cli", "-v", "--log-format", "json", "up",
        "--auth-key", str(key_path), "--host", "127.0.0.1", "--port", str(port),
        "--render-size", "160x90", "--display-size", "320x180", "--fps", "15",
        "--duration", str(UP_SECONDS),
    ])
    # fmt: on
    other_key = AuthKey(b"\x01" * 32)
    viewer_token = sign(key, Claims.for_("game", get=("",), expires_in_s=600))
    wrong_key_token = sign(other_key, Claims.for_("game", get=("",), expires_in_s=600))
    wrong_publisher = sign(other_key, Claims.for_("game", put=("",)))
    tokens = [viewer_token, wrong_key_token, wrong_publisher, NOT_A_JWT]
    try:
        deadline = time.monotonic() + 60
        while BANNER not in outs["up"][0].read_text(errors="replace"):
            assert up.poll() is None, outs["up"][1].read_text()[-3000:]
            assert time.monotonic() < deadline, "upcast up never said it was up"
            time.sleep(0.2)
        viewer = popen("viewer", [sys.executable, "-c", VIEWER, relay, *tokens[:2], NOT_A_JWT])
        # fmt: off
        publisher = popen("publisher", [
            sys.executable, "-m", "server.loadtest.synthetic", "--relay", relay,
            "--token", wrong_publisher, "--size", "160x90", "--fps", "10", "--duration", "4",
        ])
        # fmt: on
        assert viewer.wait(60) == 0, outs["viewer"][1].read_text()[-3000:]
        assert publisher.wait(30) == 0, outs["publisher"][1].read_text()[-3000:]
    finally:
        stop_child(up, 30)
    assert up.returncode == 0, outs["up"][1].read_text()[-3000:]
    captured = [
        Captured(f"{name} {path.suffix[1:]}", path.read_text(errors="replace").splitlines())
        for name, paths in outs.items()
        for path in paths
    ]
    secrets = [f for t in tokens for f in token_forms(t)] + key_forms(key_path, key)
    return captured, key, secrets


@pytest.mark.slow
def test_no_token_or_key_in_any_log_line_of_any_process(tmp_path: Path) -> None:
    captured, _, secrets = run_stack(tmp_path)
    by_name = {c.name: c.lines for c in captured}

    banners = [x for x in by_name["up out"] if x.startswith(BANNER)]
    assert len(banners) == 1
    leaks: list[str] = []
    scanned = 0
    for capture in captured:
        for number, line in enumerate(capture.lines, 1):
            if capture.name == "up out" and line.startswith(BANNER):
                line = JWT_SHAPE.sub("", line, count=1)  # the player's link, by design
            scanned += 1
            found = [s for s in secrets if s in line] + JWT_SHAPE.findall(line)
            if found or "eyJ" in line:
                leaks.append(f"{capture.name}:{number}: {line[:300]}")
    assert not leaks, "\n".join(leaks[:20])

    # The stack really ran, at DEBUG, with each process's lines in the capture.
    up_pids = {json.loads(x)["pid"] for x in by_name["up err"] if x.startswith("{")}
    assert len(up_pids) >= 4, "relay, game, worker and up itself"
    assert any('"level": "DEBUG"' in x for x in by_name["up err"])
    viewer = "\n".join(by_name["viewer err"])
    assert "viewer got a catalog frame" in viewer and viewer.count("viewer refused") == 2
    assert "status 401" in viewer and "REDACTED" in viewer
    assert any("unreachable" in x for x in by_name["publisher err"])
    relay_refusals = [x for x in by_name["up err"] if "refused WebTransport session" in x]
    assert len(relay_refusals) >= 3, "two bad viewers and the publisher's retries"
    counts = ", ".join(f"{c.name} {len(c.lines)}" for c in captured)
    print(f"scanned {scanned} lines ({counts}) of {len(up_pids) + 2} processes")
