"""The decoupled worker process: same bits as in-process, run-time switching, bad input."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from server.frames.frame import RenderFrame, Size
from server.frames.ring import RingMode
from server.frames.ring_frames import (
    create_display_ring,
    create_render_ring,
    display_frame_of,
    put_render_frame,
)
from server.game.render.renderer import Renderer, RenderTargets
from server.worker.control import GetStatus, SetCachePolicy, SetUpscaler, send_control
from upscalers.host import UpscalerHost
from upscalers.output import to_uint8

RENDER = Size(160, 90)
DISPLAY = Size(240, 135)  # scale 1.5: a non-integer scale on purpose


class WorkerUnderTest:
    """Rings plus a real `upcast worker` process, as a game session runs it."""

    def __init__(self, name: str, tmp: Path, upscaler: str = "bilinear") -> None:
        self.ring_r = create_render_ring(f"{name}-r", RENDER, mode=RingMode.LOSSLESS)
        self.ring_u = create_display_ring(f"{name}-u", DISPLAY, mode=RingMode.LOSSLESS)
        self.ring_r.attach_as_producer()
        self.ring_u.attach_as_consumer()
        self.control = tmp / "worker.ctl"
        self.name = name
        self.upscaler = upscaler
        self.proc = self.spawn()

    def spawn(self) -> subprocess.Popen[bytes]:
        self.control.unlink(missing_ok=True)
        proc = subprocess.Popen(
            [sys.executable, "-m", "server.cli", "worker", "--ring-in", f"{self.name}-r",
             "--ring-out", f"{self.name}-u", "--upscaler", self.upscaler,
             "--display-size", str(DISPLAY), "--control", str(self.control)],
        )  # fmt: skip
        deadline = time.monotonic() + 60
        while not self.control.exists():
            assert proc.poll() is None, "worker exited at start"
            assert time.monotonic() < deadline, "worker never came up"
            time.sleep(0.05)
        return proc

    def send(self, frame: RenderFrame) -> None:
        assert put_render_frame(self.ring_r, frame, 5.0)

    def receive(self, count: int) -> list[tuple[int, np.ndarray]]:
        out = []
        for _ in range(count):
            lease = self.ring_u.acquire_read(20.0)
            assert lease is not None, "worker produced nothing"
            with lease:
                frame = display_frame_of(lease)
                out.append((frame.meta.frame_id, frame.color.copy()))
        return out

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            self.proc.wait(10)
        for ring in (self.ring_r, self.ring_u):
            ring.unlink()
            ring.close()


@pytest.fixture
def worker(ring_name: str, tmp_path: Path) -> Iterator[WorkerUnderTest]:
    w = WorkerUnderTest(ring_name, tmp_path)
    yield w
    w.close()


def rendered_frames(count: int, scene: str = "moving_objects") -> list[RenderFrame]:
    renderer = Renderer(scene, RENDER, scale=DISPLAY.width / RENDER.width)
    return [renderer.render(i, i / 30, RenderTargets.allocate(RENDER)) for i in range(count)]


def test_decoupled_output_is_bit_identical_and_switchable(worker: WorkerUnderTest) -> None:
    frames = rendered_frames(8)
    for frame in frames[:4]:
        worker.send(frame)
    first = worker.receive(4)
    reply = send_control(worker.control, SetUpscaler(name="bicubic"))
    assert reply == {"ok": True, "upscaler": "bicubic", "cache_policy": None}
    for frame in frames[4:]:
        worker.send(frame)
    second = worker.receive(4)

    host = UpscalerHost("bilinear", DISPLAY)
    expected = []
    for i, frame in enumerate(frames):
        if i == 4:
            host.switch("bicubic")
        expected.append(to_uint8(host.upscale(frame)))
    got = first + second
    assert [fid for fid, _ in got] == list(range(8))
    for (_, image), want in zip(got, expected, strict=True):
        assert image.shape == (DISPLAY.height, DISPLAY.width, 3)
        assert np.array_equal(image, want)
    # and the switch really changed the method
    bilinear_4 = to_uint8(UpscalerHost("bilinear", DISPLAY).upscale(frames[4]))
    assert not np.array_equal(expected[4], bilinear_4)
    status = send_control(worker.control, GetStatus())
    assert status["frames"] == 8 and status["switches"] == 1


def test_worker_survives_nan_inf_and_bad_control(worker: WorkerUnderTest) -> None:
    frame = rendered_frames(1)[0]
    frame.depth[:10] = np.nan
    frame.depth[10:12] = np.inf
    frame.motion[:, :5] = -np.inf
    frame.meta.jitter = (float("nan"), 0.25)
    worker.send(frame)
    ((fid, image),) = worker.receive(1)
    assert fid == 0 and image.shape == (DISPLAY.height, DISPLAY.width, 3)
    refused = send_control(worker.control, SetUpscaler(name="does-not-exist"))
    assert refused["ok"] is False and "allowed" in refused["error"]
    # bilinear has no layer cache: a policy for it is refused, the worker goes on.
    refused = send_control(worker.control, SetCachePolicy(policy="budget"))
    assert refused["ok"] is False and "no layer cache" in refused["error"]
    import socket

    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.sendto(b"\xff not json", str(worker.control))
    sock.close()
    status = send_control(worker.control, GetStatus())
    assert status["sanitized_frames"] == 1
    assert status["sanitized_values"] == 12 * RENDER.width + 5 * RENDER.height * 2 + 1
    assert worker.proc.poll() is None
    worker.send(rendered_frames(2)[1])
    assert worker.receive(1)[0][0] == 1


def test_truncated_frame_is_rejected_and_worker_goes_on(worker: WorkerUnderTest) -> None:
    lease = worker.ring_r.acquire_write(1.0)
    assert lease is not None
    lease.header["width"] = RENDER.width * 50  # beyond what the planes hold
    lease.header["height"] = RENDER.height
    lease.commit()
    good = rendered_frames(1)[0]
    worker.send(good)
    ((fid, _),) = worker.receive(1)
    assert fid == 0
    assert worker.ring_r.counters().rejected == 1
    assert worker.proc.poll() is None


def test_killed_worker_restarts_and_reattaches_by_name(worker: WorkerUnderTest) -> None:
    frames = rendered_frames(3)
    worker.send(frames[0])
    assert worker.receive(1)[0][0] == 0
    os.kill(worker.proc.pid, signal.SIGKILL)
    worker.proc.wait(10)
    # The game keeps producing while no worker runs (lossless ring: up to its slots).
    worker.send(frames[1])
    worker.proc = worker.spawn()
    worker.send(frames[2])
    got = worker.receive(2)
    assert [fid for fid, _ in got] == [1, 2]
