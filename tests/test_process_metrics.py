"""Prometheus metrics of the game and worker processes (server/game/metrics.py,
server/worker/metrics.py)."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
from prometheus_client import CollectorRegistry, generate_latest

from server.frames.frame import Size
from server.frames.ring import RingMode
from server.frames.ring_frames import create_display_ring, create_render_ring, put_render_frame
from server.game.loop import GameLoop
from server.game.metrics import GAME_METRICS, game_registry
from server.game.render.camera import CameraInput
from server.game.render.renderer import Renderer, RenderTargets
from server.worker.control import ControlServer, GetStatus, SetUpscaler, send_control
from server.worker.metrics import WORKER_METRICS, worker_registry
from server.worker.upscale import UpscaleWorker
from upscalers.host import UpscalerHost

RENDER = Size(96, 54)
DISPLAY = Size(192, 108)
ROOT = Path(__file__).resolve().parents[1]


def exported_names(registry: CollectorRegistry) -> set[str]:
    return {m.name for m in registry.collect()}


def test_game_counts_frames_inputs_render_time_and_ring_overwrites(ring_name: str) -> None:
    ring = create_render_ring(ring_name, RENDER)  # real-time, nobody reads: overwrites
    loop = GameLoop(Renderer("default", RENDER), ring, fps=200.0)
    registry = game_registry(loop)
    loop.push_input(CameraInput(dyaw_deg=5.0), seq=1)
    loop.push_input(CameraInput(dpitch_deg=1.0), seq=2)
    loop.run(threading.Event(), max_frames=6)
    value = registry.get_sample_value
    assert value("upcast_game_frames_rendered_total") == 6
    assert value("upcast_game_inputs_applied_total") == 2
    assert value("upcast_game_render_seconds_count") == 6
    assert 0 < (value("upcast_game_render_seconds_sum") or 0) < 6
    labels = {"ring": ring_name, "outcome": "dropped_overwritten"}
    assert value("upcast_ring_frames_total", labels) == 6 - ring.slot_count
    assert exported_names(registry) >= set(GAME_METRICS)
    ring.close()


def send_frame(ring_r: object, renderer: Renderer, index: int, poison: bool = False) -> None:
    frame = renderer.render(index, index / 30, RenderTargets.allocate(RENDER))
    if poison:
        frame.depth[:2] = np.nan
    assert put_render_frame(ring_r, frame, 5.0)  # type: ignore[arg-type]


def test_worker_counts_upscales_sanitized_frames_control_and_upscaler(
    ring_name: str, tmp_path: Path
) -> None:
    ring_r = create_render_ring(f"{ring_name}-r", RENDER, mode=RingMode.LOSSLESS)
    ring_u = create_display_ring(f"{ring_name}-u", DISPLAY, mode=RingMode.REALTIME)
    ring_r.attach_as_producer()
    worker = UpscaleWorker(ring_r, ring_u, UpscalerHost("bilinear", DISPLAY))
    registry = worker_registry(worker)
    control = ControlServer(tmp_path / "worker.ctl")
    stop = threading.Event()
    thread = threading.Thread(target=worker.run, args=(stop, control))
    thread.start()
    try:
        renderer = Renderer("moving_objects", RENDER, scale=2.0)
        for i in range(4):
            send_frame(ring_r, renderer, i, poison=(i == 1))
        assert send_control(tmp_path / "worker.ctl", SetUpscaler(name="nope"))["ok"] is False
        assert send_control(tmp_path / "worker.ctl", SetUpscaler(name="bicubic"))["ok"] is True
        deadline = time.monotonic() + 20
        while send_control(tmp_path / "worker.ctl", GetStatus())["frames"] < 4:
            assert time.monotonic() < deadline, "worker did not upscale the frames"
            time.sleep(0.02)
    finally:
        stop.set()
        thread.join(10)
        control.close()
    value = registry.get_sample_value
    assert value("upcast_worker_frames_upscaled_total") == 4
    assert value("upcast_worker_upscale_seconds_count") == 4
    assert value("upcast_worker_frames_sanitized_total") == 1
    assert value("upcast_worker_values_sanitized_total") == 2 * RENDER.width
    assert value("upcast_worker_control_messages_total", {"result": "refused"}) == 1
    assert (value("upcast_worker_control_messages_total", {"result": "ok"}) or 0) >= 2
    assert value("upcast_worker_upscaler", {"upscaler": "bicubic"}) == 1
    assert value("upcast_worker_upscaler", {"upscaler": "bilinear"}) is None
    assert value("upcast_worker_frames_dropped_total", {"reason": "truncated"}) == 0
    assert exported_names(registry) >= set(WORKER_METRICS)
    for ring in (ring_r, ring_u):
        ring.unlink()
        ring.close()


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def test_worker_process_serves_metrics_on_its_port(ring_name: str) -> None:
    ring_r = create_render_ring(f"{ring_name}-r", RENDER)
    ring_u = create_display_ring(f"{ring_name}-u", DISPLAY)
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "server.cli", "worker", "--ring-in", f"{ring_name}-r",
         "--ring-out", f"{ring_name}-u", "--display-size", str(DISPLAY),
         "--metrics-port", str(port)],
        cwd=ROOT,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while True:
            assert proc.poll() is None, "worker exited"
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=2) as r:
                    text = r.read().decode()
                break
            except OSError:
                assert time.monotonic() < deadline, "no /metrics from the worker"
                time.sleep(0.1)
        assert 'upcast_worker_upscaler{upscaler="bilinear"} 1.0' in text
        assert "upcast_worker_frames_upscaled_total 0.0" in text
        assert "process_cpu_seconds_total" in text
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(10)
        for ring in (ring_r, ring_u):
            ring.unlink()
            ring.close()


def test_metric_text_is_what_prometheus_scrapes(ring_name: str) -> None:
    ring = create_render_ring(ring_name, RENDER)
    loop = GameLoop(Renderer("static", RENDER), ring, fps=60.0)
    text = generate_latest(game_registry(loop)).decode()
    assert "# TYPE upcast_game_frames_rendered_total counter" in text
    assert "upcast_game_frames_rendered_total 0.0" in text
    assert "# TYPE upcast_game_render_seconds histogram" in text
    assert 'upcast_game_render_seconds_bucket{le="+Inf"} 0.0' in text
    ring.close()
