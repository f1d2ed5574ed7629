"""``upcast preview`` end to end (real processes) and the preview server on a test-fed ring."""

from __future__ import annotations

import http.client
import io
import json
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from PIL import Image

from server.frames.frame import Size
from server.frames.ring import SHM_DIR
from server.frames.ring_frames import create_display_ring
from server.frames.timing import Stage
from server.ops.process import stop_child
from upscalers import registry

RENDER = "320x180"
DISPLAY = (640, 360)
BANNER_TIMEOUT_S = 45.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _request(
    port: int,
    method: str,
    path: str,
    body: bytes | None = None,
    timeout_s: float = 10.0,
) -> tuple[int, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout_s)
    try:
        headers = {"Content-Type": "application/json"} if body is not None else {}
        conn.request(method, path, body=body, headers=headers)
        resp = conn.getresponse()
        return resp.status, resp.read()
    finally:
        conn.close()


def _json(port: int, method: str, path: str, payload: Any = None) -> tuple[int, Any]:
    body = None if payload is None else json.dumps(payload).encode()
    status, data = _request(port, method, path, body)
    return status, json.loads(data)


def _snapshot(port: int) -> np.ndarray[Any, Any]:
    status, data = _request(port, "GET", "/snapshot.jpg")
    assert status == 200, data[:200]
    with Image.open(io.BytesIO(data)) as im:
        return np.asarray(im.convert("RGB"), dtype=np.float32)


def _wait_for(predicate: Any, timeout_s: float, interval_s: float = 0.25) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            return value
        time.sleep(interval_s)


@dataclass
class Session:
    proc: subprocess.Popen[str]
    port: int
    stderr_path: Path

    def stats(self) -> dict[str, Any]:
        status, payload = _json(self.port, "GET", "/stats")
        assert status == 200
        assert isinstance(payload, dict)
        return payload

    def log(self) -> str:
        return self.stderr_path.read_text(errors="replace")[-4000:]


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Session]:
    port = _free_port()
    stderr_path = tmp_path_factory.mktemp("up") / "stderr.txt"
    # fmt: off
    cmd = [
        sys.executable, "-m", "server.cli", "preview", "--scene", "static",
        "--render-size", RENDER, "--display-size", f"{DISPLAY[0]}x{DISPLAY[1]}",
        "--fps", "20", "--port", str(port), "--duration", "80",
    ]
    # fmt: on
    with stderr_path.open("w") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True)
    lines: queue.Queue[str] = queue.Queue()

    def pump() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line)

    threading.Thread(target=pump, daemon=True).start()
    sess = Session(proc, port, stderr_path)
    try:
        deadline = time.monotonic() + BANNER_TIMEOUT_S
        banner = ""
        while "upcast preview is up" not in banner:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or proc.poll() is not None:
                pytest.fail(f"no banner from `upcast preview`; stderr:\n{sess.log()}")
            try:
                banner = lines.get(timeout=min(remaining, 0.5))
            except queue.Empty:
                continue
        assert f"http://127.0.0.1:{port}/" in banner
        assert "Ctrl-C" in banner
        yield sess
    finally:
        stop_child(proc, 20, signal.SIGINT)


def test_page_has_stream_and_controls(session: Session) -> None:
    status, body = _request(session.port, "GET", "/")
    assert status == 200
    page = body.decode()
    assert '<img id="view" src="/stream.mjpg"' in page
    assert "/control" in page and "/input" in page and "/stats" in page
    assert "local preview" in page
    status, _ = _request(session.port, "GET", "/nope")
    assert status == 404


def test_snapshot_is_a_display_size_picture(session: Session) -> None:
    img = _snapshot(session.port)
    assert img.shape == (DISPLAY[1], DISPLAY[0], 3)
    assert float(img.std()) > 5.0, "snapshot is uniform"


def test_stats_report_frames_flowing(session: Session) -> None:
    stats = _wait_for(lambda: (s := session.stats())["fps"] > 0 and s, 15.0)
    assert stats, f"fps stayed 0; stderr:\n{session.log()}"
    assert stats["upscalers"] == sorted(stats["upscalers"]) and "bicubic" in stats["upscalers"]
    assert stats["upscaler"] == "bilinear"
    assert stats["worker"]["ok"] is True
    assert stats["session"]["worker_pid"] > 0
    first = stats["frame_id"]
    assert _wait_for(lambda: (session.stats()["frame_id"] or -1) > first, 10.0)
    # A snapshot forces an encode, so the stage latencies are filled in.
    _snapshot(session.port)
    stages = session.stats()["stages_ms"]
    for name in ("render", "upscale", "ring_u_handoff", "encode"):
        assert stages[name] is not None and stages[name] >= 0, stages


def test_control_switches_upscaler(session: Session) -> None:
    status, reply = _json(session.port, "POST", "/control", {"upscaler": "bicubic"})
    assert status == 200, reply
    assert reply["upscaler"] == "bicubic"
    assert session.stats()["upscaler"] == "bicubic"

    status, reply = _json(session.port, "POST", "/control", {"upscaler": "magic"})
    assert status == 400
    assert "magic" in reply["error"]
    assert reply["allowed"] == registry.available()
    assert "bilinear" in reply["error"]
    assert session.stats()["upscaler"] == "bicubic"


def _blocks(img: np.ndarray[Any, Any], k: int = 8) -> np.ndarray[Any, Any]:
    """Mean of k x k blocks: keeps the picture, drops sub-pixel jitter and JPEG noise."""
    h, w, c = img.shape
    blocks = img[: h // k * k, : w // k * k].reshape(h // k, k, w // k, k, c)
    return np.asarray(blocks.mean(axis=(1, 3)))


def test_input_turns_the_camera(session: Session) -> None:
    a = _blocks(_snapshot(session.port))
    time.sleep(0.5)
    b = _blocks(_snapshot(session.port))
    still = float(np.abs(a - b).mean())
    status, reply = _json(session.port, "POST", "/input", {"dyaw_deg": 60.0})
    assert status == 200, reply
    # Input is applied at the next frame; leave time for render + upscale + encode.
    time.sleep(1.5)
    c = _blocks(_snapshot(session.port))
    turned = float(np.abs(b - c).mean())
    assert turned > 3.0 * still + 5.0, (still, turned)
    print(f"mean abs difference: still {still:.2f}, after a 60 deg yaw {turned:.2f}")


@pytest.mark.parametrize(
    ("path", "body", "status"),
    [
        ("/input", b"not json", 400),
        ("/input", b'{"dyaw_deg": 1e9}', 400),
        ("/input", b'{"dyaw_deg": "left"}', 400),
        ("/input", b'{"bogus": 1}', 400),
        ("/input", b"[1, 2]", 400),
        ("/control", b"{{{", 400),
        ("/control", b'{"upscaler": 3}', 400),
        ("/control", b"{}", 400),
        ("/control", b"\xff\xfe", 400),
        ("/input", b"x" * 5000, 413),
        ("/elsewhere", b"{}", 404),
    ],
)
def test_bad_requests_are_refused(session: Session, path: str, body: bytes, status: int) -> None:
    got, data = _request(session.port, "POST", path, body)
    assert got == status, data
    assert "error" in json.loads(data)
    assert session.stats()["worker"]["ok"] is True  # still serving


def test_killed_worker_is_restarted(session: Session) -> None:
    before = session.stats()
    pid = before["session"]["worker_pid"]
    os.kill(pid, signal.SIGKILL)

    def restarted() -> dict[str, Any] | None:
        s = session.stats()
        ok = s["session"]["worker_restarts"] >= 1 and s["session"]["worker_pid"] != pid
        return s if ok and s["worker"]["ok"] else None

    after = _wait_for(restarted, 40.0, 0.5)
    assert after, f"worker not restarted; stderr:\n{session.log()}"
    frame = after["frame_id"] or -1
    assert _wait_for(lambda: (session.stats()["frame_id"] or -1) > frame, 15.0), session.log()
    assert _snapshot(session.port).shape == (DISPLAY[1], DISPLAY[0], 3)
    assert "restarting" in session.log()
    # a method switched at run time survives the restart
    assert after["upscaler"] == before["upscaler"]


def test_stop_cleans_up(session: Session) -> None:
    info = session.stats()["session"]
    name = info["name"]
    session.proc.send_signal(signal.SIGINT)
    assert session.proc.wait(30) == 0, session.log()
    leftovers = sorted(p.name for p in SHM_DIR.glob(f"{name}*"))
    assert leftovers == [], leftovers
    for pid in (info["game_pid"], info["worker_pid"]):
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)
    with pytest.raises(ConnectionRefusedError):
        _request(session.port, "GET", "/stats", timeout_s=2.0)


def _run_up(*args: str, timeout_s: float = 30.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "server.cli", "preview", *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )


def test_port_in_use_is_named() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        done = _run_up("--port", str(port), "--duration", "5")
    assert done.returncode == 1
    assert f"port {port}" in done.stderr and "--port" in done.stderr
    assert "upcast preview is up" not in done.stdout


def test_bad_config_names_the_field() -> None:
    done = _run_up("--render-size", "2000x2000", "--upscaler", "magic", "--duration", "5")
    assert done.returncode == 2
    assert "invalid session configuration" in done.stderr
    assert "upscaler" in done.stderr and "magic" in done.stderr


# ---- the preview server alone, on a ring this test feeds


def test_preview_serves_a_test_fed_ring(ring_name: str, tmp_path: Path) -> None:
    from server.stack.preview import PreviewServer

    size = Size(64, 48)
    ring = create_display_ring(ring_name, size)
    try:
        lease = ring.acquire_write(1.0)
        assert lease is not None
        color = lease.views(size.width, size.height)["color"]
        color[...] = np.linspace(0, 255, size.width, dtype=np.uint8)[None, :, None]
        lease.header["frame_id"] = 7
        now = time.monotonic_ns()
        for stage, ms in ((Stage.RENDER_START, 0), (Stage.RENDER_END, 3), (Stage.UPSCALE_START, 4)):
            lease.header["stamps"][stage] = (now + ms * 1_000_000, 1)
        lease.header["stamps"][Stage.UPSCALE_END] = (now + 6_000_000, 1)
        lease.commit(stamp_stage=Stage.RING_U_READY)

        preview = PreviewServer(
            ring, tmp_path / "no-worker.ctl", tmp_path / "no-game.input", port=0, max_fps=10
        )
        with preview:
            port = preview.bound_port
            assert preview.url == f"http://127.0.0.1:{port}/"
            img = _snapshot(port)
            assert img.shape == (48, 64, 3)
            assert img[:, -1].mean() > img[:, 0].mean() + 100  # the gradient survived
            status, stats = _json(port, "GET", "/stats")
            assert status == 200
            assert stats["frame_id"] == 7 and stats["jpeg_frame_id"] == 7
            assert stats["stages_ms"]["render"] == pytest.approx(3.0)
            assert stats["stages_ms"]["upscale"] == pytest.approx(2.0)
            assert stats["worker"]["ok"] is False  # no worker: reported, not fatal
            status, reply = _json(port, "POST", "/input", {"dyaw_deg": 1.0})
            assert status == 503 and "game unreachable" in reply["error"]
            status, reply = _json(port, "POST", "/control", {"upscaler": "nope"})
            assert status == 400 and reply["allowed"]
            status, reply = _json(port, "POST", "/control", {"upscaler": "nearest"})
            assert status == 504
    finally:
        ring.unlink()
        ring.close()


def test_preview_snapshot_before_any_frame_is_503(ring_name: str, tmp_path: Path) -> None:
    from server.stack.preview import PreviewServer

    ring = create_display_ring(ring_name, Size(32, 32))
    try:
        with PreviewServer(ring, tmp_path / "c", tmp_path / "i", port=0) as preview:
            t0 = time.monotonic()
            status, body = _request(preview.bound_port, "GET", "/snapshot.jpg")
            assert status == 503 and b"no frame yet" in body
            assert time.monotonic() - t0 < 5.0
    finally:
        ring.unlink()
        ring.close()


def test_duration_ends_the_session_cleanly() -> None:
    port = _free_port()
    # fmt: off
    done = _run_up(
        "--scene", "static", "--render-size", RENDER, "--display-size", "640x360",
        "--fps", "10", "--port", str(port), "--duration", "2",
        timeout_s=60.0,
    )
    # fmt: on
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"upcast preview is up: watch at http://127.0.0.1:{port}/" in done.stdout
    name = done.stderr.split("session ", 1)[1].split(":", 1)[0]
    assert name.startswith("upcast-")
    assert sorted(p.name for p in SHM_DIR.glob(f"{name}*")) == []
    assert "cleaned up" in done.stderr


def test_a_restarted_worker_starts_with_the_method_switched_to(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from server.stack import local as stack_module
    from server.stack.local import LocalStack, SessionConfig

    launched: list[list[str]] = []

    def popen(argv: list[str], **_: object) -> SimpleNamespace:
        launched.append(argv)
        return SimpleNamespace(pid=0)  # no such process: the reaper is told nothing

    monkeypatch.setattr(stack_module.subprocess, "Popen", popen)
    stack = LocalStack(SessionConfig(upscaler="bilinear", cache_policy="budget@41"))
    stack._spawn_worker()
    stack.remember_upscaler("unet_cached")  # a run-time switch the worker accepted
    stack._spawn_worker()  # what check_children does when the worker died

    def option(argv: list[str], flag: str) -> str:
        return argv[argv.index(flag) + 1]

    assert [option(a, "--upscaler") for a in launched] == ["bilinear", "unet_cached"]
    assert all(option(a, "--cache-policy") == "budget@41" for a in launched)
