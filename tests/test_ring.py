"""FrameRing: layout, fences, modes, timeouts, dead peers."""

from __future__ import annotations

import itertools
import multiprocessing as mp
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from server.frames.frame import Camera, FrameFlags, FrameMeta, Size
from server.frames.ring import (
    DISPLAY_PLANES,
    MAGIC,
    RENDER_PLANES,
    RING_HEADER_SIZE,
    SLOT_HEADER,
    SLOT_HEADER_SIZE,
    FrameRing,
    RingError,
    RingMode,
    SlotState,
)
from server.frames.ring_frames import (
    attach_display_ring,
    attach_render_ring,
    create_render_ring,
    read_meta,
    render_frame_of,
    write_meta,
)
from server.frames.timing import Stage
from tests.ringutil import (
    child_hold_read_then_hang,
    child_write_half_then_hang,
    fill_frame,
    frame_checksum,
)

SPAWN = mp.get_context("spawn")


def test_layout_is_as_documented(ring_name: str) -> None:
    ring = FrameRing.create(ring_name, RENDER_PLANES, (640, 360), slots=3)
    raw = Path(f"/dev/shm/{ring_name}").read_bytes()
    assert raw[:8] == MAGIC
    assert int.from_bytes(raw[8:12], "little") == 1
    assert int.from_bytes(raw[12:16], "little") == 3  # slot_count
    assert int.from_bytes(raw[16:20], "little") == 4  # plane_count
    assert int.from_bytes(raw[24:28], "little") == 640
    assert int.from_bytes(raw[28:32], "little") == 360
    stride = int.from_bytes(raw[32:40], "little")
    assert stride % 4096 == 0
    assert int.from_bytes(raw[40:48], "little") == RING_HEADER_SIZE
    assert len(raw) == RING_HEADER_SIZE + 3 * stride
    # plane table entry 1 (depth): name, dtype code 2 (float32), 1 channel, aligned offset
    entry = raw[256 + 64 : 256 + 128]
    assert entry[:16].rstrip(b"\0") == b"depth"
    assert int.from_bytes(entry[16:20], "little") == 2
    assert int.from_bytes(entry[20:24], "little") == 1
    depth_off = int.from_bytes(entry[24:32], "little")
    assert depth_off % 64 == 0 and depth_off >= SLOT_HEADER_SIZE + 640 * 360 * 3
    # a committed frame's bytes sit exactly where the table says
    lease = ring.acquire_write(1.0)
    assert lease is not None
    views = lease.views(320, 180)
    views["depth"][...] = np.arange(320 * 180, dtype=np.float32).reshape(180, 320)
    lease.header["input_seq"] = 77
    lease.header["game_time_us"] = -(2**40) - 3  # i64: the sign and high bits survive
    lease.commit()
    raw = Path(f"/dev/shm/{ring_name}").read_bytes()
    slot0 = RING_HEADER_SIZE
    assert int.from_bytes(raw[slot0 : slot0 + 4], "little") == SlotState.READY
    assert int.from_bytes(raw[slot0 + 8 : slot0 + 16], "little") == 1  # seq
    assert int.from_bytes(raw[slot0 + 16 : slot0 + 20], "little") == 320
    assert int.from_bytes(raw[slot0 + 544 : slot0 + 552], "little", signed=True) == 77
    assert int.from_bytes(raw[slot0 + 552 : slot0 + 560], "little", signed=True) == -(2**40) - 3
    plane = np.frombuffer(raw, np.float32, 320 * 180, slot0 + depth_off)
    assert plane[12345] == 12345.0
    ring.close()


def test_slot_header_fields_neither_overlap_nor_overflow() -> None:
    """A field added to the header (or a stage added to the stamps) must not run into
    the next one: numpy accepts overlapping fields silently."""
    fields = SLOT_HEADER.fields
    assert fields is not None
    spans = sorted((off, off + dt.itemsize, name) for name, (dt, off, *_) in fields.items())
    for (_, end, name), (start, _, nxt) in itertools.pairwise(spans):
        assert end <= start, f"{name} runs into {nxt}"
    assert spans[-1][1] <= SLOT_HEADER_SIZE
    assert spans[-1][2] == "game_time_us" and spans[-1][0] == 552


def test_round_trip_zero_copy_read_only(ring_name: str) -> None:
    producer = create_render_ring(ring_name, Size(64, 48))
    consumer = attach_render_ring(ring_name)
    lease = producer.acquire_write(1.0)
    assert lease is not None
    views = lease.views(63, 47)
    views["color"][...] = 200
    views["depth"][...] = 0.5
    cam = Camera.identity()
    meta = FrameMeta(
        frame_id=42,
        camera=cam,
        jitter=(0.25, -0.125),
        flags=FrameFlags.RESET,
        input_seq=5,
        game_time_us=3_600_000_123,  # an hour in: beyond 32 bits
    )
    meta.stamps[Stage.RENDER_START] = (111, 222)
    write_meta(lease.header, meta)
    seq = lease.commit(stamp_stage=Stage.RING_R_READY)
    assert seq == 1

    read = consumer.acquire_read(1.0)
    assert read is not None
    frame = render_frame_of(read)
    assert frame.size == Size(63, 47)
    assert frame.meta.frame_id == 42 and frame.meta.jitter == (0.25, -0.125)
    assert frame.meta.flags == FrameFlags.RESET
    assert frame.meta.input_seq == 5 and frame.meta.game_time_us == 3_600_000_123
    assert tuple(frame.meta.stamps[Stage.RENDER_START]) == (111, 222)
    assert frame.meta.stamps[Stage.RING_R_READY, 0] > 0
    assert (frame.color == 200).all() and (frame.depth == 0.5).all()
    # views, not copies: they point into the shared mapping and cannot be written
    assert not frame.color.flags.writeable and not frame.color.flags.owndata
    with pytest.raises(ValueError):
        frame.depth[0, 0] = 1.0
    # the producer's next write into the same slot shows through the held view
    # only after a new commit: here the slot is READING, so the producer gets another
    states = producer.states()
    assert states.count(SlotState.READING) == 1
    read.release()
    assert producer.states() == [SlotState.FREE] * 3
    producer.close()
    consumer.close()


def test_meta_round_trip_preserves_camera(ring_name: str) -> None:
    ring = create_render_ring(ring_name, Size(8, 8))
    rng = np.random.default_rng(3)
    mats = rng.standard_normal((4, 4, 4)).astype(np.float32)
    cam = Camera(mats[0], mats[1], mats[2], mats[3], 0.05, 500.0, 70.0)
    lease = ring.acquire_write(1.0)
    assert lease is not None
    write_meta(lease.header, FrameMeta(frame_id=7, camera=cam))
    back = read_meta(lease.header)
    lease.abort()
    assert np.array_equal(back.camera.proj, mats[1]) and back.camera.far == 500.0
    ring.close()


def test_every_known_flag_crosses_the_ring_and_unknown_bits_do_not(ring_name: str) -> None:
    """The worker sees the flags the game set (AREA_SAMPLES changes what temporal does);
    a bit this version does not know is dropped, not passed on as an invalid flag."""
    ring = create_render_ring(ring_name, Size(8, 8))
    lease = ring.acquire_write(1.0)
    assert lease is not None
    for flags in FrameFlags:
        write_meta(lease.header, FrameMeta(frame_id=1, camera=Camera.identity(), flags=flags))
        assert read_meta(lease.header).flags == flags
    every = FrameFlags.RESET | FrameFlags.COLOR_ONLY | FrameFlags.AREA_SAMPLES
    write_meta(lease.header, FrameMeta(frame_id=2, camera=Camera.identity(), flags=every))
    lease.header["flags"] = int(every) | 1 << 20
    assert read_meta(lease.header).flags == every
    lease.abort()
    ring.close()


def test_realtime_overwrites_oldest_and_counts_drops(ring_name: str) -> None:
    ring = create_render_ring(ring_name, Size(16, 16), slots=3)
    for i in range(5):
        lease = ring.acquire_write(0.1)
        assert lease is not None, "real-time producer must never wait for the consumer"
        lease.header["frame_id"] = i
        lease.views(16, 16)
        lease.commit()
    counters = ring.counters()
    assert counters.committed == 5 and counters.dropped_overwritten == 2
    got = []
    while (lease := ring.acquire_read(0.01)) is not None:
        got.append(int(lease.header["frame_id"]))
        lease.release()
    assert got == [2, 3, 4]  # the newest three, in order
    ring.close()


def test_lossless_waits_then_times_out(ring_name: str) -> None:
    ring = create_render_ring(ring_name, Size(16, 16), slots=2, mode=RingMode.LOSSLESS)
    for _ in range(2):
        lease = ring.acquire_write(0.1)
        assert lease is not None
        lease.views(16, 16)
        lease.commit()
    t0 = time.monotonic()
    cpu0 = time.process_time()
    assert ring.acquire_write(0.3) is None
    waited = time.monotonic() - t0
    assert 0.28 <= waited < 1.0
    assert time.process_time() - cpu0 < 0.1, "waiting must block, not spin"
    assert ring.counters().dropped == 0
    ring.close()


def test_read_timeout_blocks_without_spinning(ring_name: str) -> None:
    ring = create_render_ring(ring_name, Size(16, 16))
    cpu0 = time.process_time()
    t0 = time.monotonic()
    assert ring.acquire_read(0.4) is None
    assert time.monotonic() - t0 >= 0.39
    assert time.process_time() - cpu0 < 0.1
    ring.close()


def test_newest_read_skips_and_counts(ring_name: str) -> None:
    ring = create_render_ring(ring_name, Size(16, 16))
    for i in range(3):
        lease = ring.acquire_write(0.1)
        assert lease is not None
        lease.header["frame_id"] = i
        lease.views(16, 16)
        lease.commit()
    lease = ring.acquire_read(0.1, newest=True)
    assert lease is not None and int(lease.header["frame_id"]) == 2
    lease.release()
    assert ring.counters().dropped_skipped == 2
    assert ring.acquire_read(0.01) is None
    ring.close()


def test_exception_in_write_block_frees_slot(ring_name: str) -> None:
    ring = create_render_ring(ring_name, Size(16, 16))
    with pytest.raises(RuntimeError), ring.acquire_write(0.1) as lease:  # type: ignore[union-attr]
        lease.views(16, 16)
        raise RuntimeError("renderer crashed")
    assert ring.states() == [SlotState.FREE] * 3
    ring.close()


def test_oversized_header_is_rejected_not_fatal(ring_name: str) -> None:
    ring = create_render_ring(ring_name, Size(16, 16))
    lease = ring.acquire_write(0.1)
    assert lease is not None
    lease.header["width"] = 10_000  # a buggy producer writes a size beyond capacity
    lease.header["height"] = 16
    lease.commit()
    good = ring.acquire_write(0.1)
    assert good is not None
    good.views(16, 16)
    good.commit()
    got = ring.acquire_read(0.1)
    assert got is not None and got.width == 16
    got.release()
    assert ring.counters().rejected == 1
    ring.close()


def test_attach_errors_are_clear(ring_name: str) -> None:
    with pytest.raises(RingError, match="no ring named"):
        FrameRing.attach(ring_name)
    with open(f"/dev/shm/{ring_name}", "wb") as f:
        f.write(b"\0" * 8192)
    with pytest.raises(RingError, match="bad magic"):
        FrameRing.attach(ring_name)
    os.unlink(f"/dev/shm/{ring_name}")
    FrameRing.create(ring_name, DISPLAY_PLANES, (8, 8)).close()
    with pytest.raises(RingError, match="not a render"):
        attach_render_ring(ring_name)
    attach_display_ring(ring_name).close()
    with pytest.raises(ValueError, match="plain file name"):
        FrameRing.attach("../etc/passwd")


def test_consumer_killed_mid_read_is_recovered_by_restart(ring_name: str) -> None:
    ring = create_render_ring(ring_name, Size(32, 16))
    lease = ring.acquire_write(0.1)
    assert lease is not None
    crc = fill_frame(lease, 99, 32, 16)
    lease.commit()
    held = SPAWN.Event()
    child = SPAWN.Process(target=child_hold_read_then_hang, args=(ring_name, held))
    child.start()
    assert held.wait(20), "child consumer never took the frame"
    assert ring.states().count(SlotState.READING) == 1
    os.kill(child.pid, signal.SIGKILL)  # type: ignore[arg-type]
    child.join(10)
    # The producer is not stalled meanwhile: it keeps getting slots.
    for _ in range(3):
        w = ring.acquire_write(0.2)
        assert w is not None
        w.abort()
    # A restarted consumer re-attaches by name and gets the interrupted frame.
    restarted = attach_render_ring(ring_name)
    restarted.attach_as_consumer()
    again = restarted.acquire_read(1.0)
    assert again is not None and frame_checksum(again) == crc
    again.release()
    assert ring.counters().recovered == 1
    restarted.close()
    ring.close()


def test_producer_killed_mid_write_never_delivers_half_frame(ring_name: str) -> None:
    ring = create_render_ring(ring_name, Size(32, 16))
    ring.attach_as_consumer()
    held = SPAWN.Event()
    child = SPAWN.Process(target=child_write_half_then_hang, args=(ring_name, held, 32, 16))
    child.start()
    assert held.wait(20), "child producer never started writing"
    os.kill(child.pid, signal.SIGKILL)  # type: ignore[arg-type]
    child.join(10)
    assert ring.acquire_read(0.2) is None, "a half-written slot must not be delivered"
    assert ring.states().count(SlotState.WRITING) == 1
    # A restarted producer takes the slot back and the ring works at full size again.
    producer = attach_render_ring(ring_name)
    producer.attach_as_producer()
    assert producer.states() == [SlotState.FREE] * 3
    for i in range(3):
        w = producer.acquire_write(0.2)
        assert w is not None
        fill_frame(w, i, 32, 16)
        w.commit()
    assert producer.counters().dropped == 0
    producer.close()
    ring.close()
