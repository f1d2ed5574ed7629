"""Producer/consumer stress: no torn frame, no frame twice, every frame accounted for."""

from __future__ import annotations

import multiprocessing as mp
import threading
import time

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from server.frames.frame import Size
from server.frames.ring import FrameRing, RingMode
from server.frames.ring_frames import attach_render_ring, create_render_ring
from tests.ringutil import child_produce, fill_frame, frame_checksum

W, H = 24, 16


def _consume_all(
    ring: FrameRing, stop: threading.Event, delays: list[float], newest: bool
) -> list[tuple[int, bool]]:
    """Read until the producer is done and the ring is empty; (frame_id, checksum ok)."""
    got: list[tuple[int, bool]] = []
    i = 0
    while True:
        lease = ring.acquire_read(0.02, newest=newest)
        if lease is None:
            if stop.is_set():
                return got
            continue
        with lease:
            ok = frame_checksum(lease) == int(lease.header["checksum"])
            time.sleep(delays[i % len(delays)])
            # read again after the pause: a producer writing into a held slot would show
            ok = ok and frame_checksum(lease) == int(lease.header["checksum"])
            got.append((int(lease.header["frame_id"]), ok))
        i += 1


@settings(
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    producer_delays=st.lists(st.floats(0, 0.004), min_size=1, max_size=8),
    consumer_delays=st.lists(st.floats(0, 0.006), min_size=1, max_size=8),
    slots=st.integers(2, 4),
    mode=st.sampled_from([RingMode.REALTIME, RingMode.LOSSLESS]),
    newest=st.booleans(),
    frames=st.integers(1, 40),
)
def test_stress_threads(
    ring_name: str,
    producer_delays: list[float],
    consumer_delays: list[float],
    slots: int,
    mode: RingMode,
    newest: bool,
    frames: int,
) -> None:
    ring = create_render_ring(ring_name, Size(W, H), slots=slots, mode=mode)
    consumer = attach_render_ring(ring_name)  # its own handle and lock, as another process
    stop = threading.Event()
    result: list[list[tuple[int, bool]]] = []
    reader = threading.Thread(
        target=lambda: result.append(_consume_all(consumer, stop, consumer_delays, newest))
    )
    reader.start()
    committed = 0
    try:
        for i in range(frames):
            lease = ring.acquire_write(2.0)
            assert lease is not None, "producer starved"
            fill_frame(lease, i, W, H)
            time.sleep(producer_delays[i % len(producer_delays)])
            lease.commit()
            committed += 1
    finally:
        stop.set()
        reader.join(30)
    got = result[0]
    ids = [fid for fid, _ in got]
    assert all(ok for _, ok in got), "torn frame: checksum changed while held"
    assert len(ids) == len(set(ids)), "a frame was delivered twice"
    assert ids == sorted(ids), "frames delivered out of order"
    counters = ring.counters()
    assert counters.committed == committed == frames
    assert len(ids) + counters.dropped == frames, "a frame neither delivered nor counted dropped"
    if mode == RingMode.LOSSLESS and not newest:
        assert ids == list(range(frames))
    consumer.close()
    ring.close()
    ring.unlink()


def test_stress_across_processes(ring_name: str) -> None:
    frames = 300
    ring = create_render_ring(ring_name, Size(W, H), slots=3)
    ring.attach_as_consumer()
    child = mp.get_context("spawn").Process(
        target=child_produce, args=(ring_name, frames, W, H, 0.001)
    )
    child.start()
    got: list[int] = []
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        lease = ring.acquire_read(0.2)
        if lease is None:
            if not child.is_alive() and ring.counters().committed == frames:
                break
            continue
        with lease:
            assert frame_checksum(lease) == int(lease.header["checksum"])
            got.append(int(lease.header["frame_id"]))
            if len(got) % 7 == 0:
                time.sleep(0.004)  # fall behind now and then
    child.join(10)
    counters = ring.counters()
    assert counters.committed == frames
    assert len(got) == len(set(got)) and got == sorted(got)
    assert len(got) + counters.dropped == frames
    ring.close()
