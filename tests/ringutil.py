"""Helpers shared by ring tests: deterministic frame contents with checksums."""

from __future__ import annotations

import zlib

import numpy as np

from server.frames.ring import ReadLease, WriteLease


def fill_frame(lease: WriteLease, seq_hint: int, width: int, height: int) -> int:
    """Fill every plane from a seed and store a CRC of all bytes in the header."""
    rng = np.random.default_rng(seq_hint)
    crc = 0
    for name, view in lease.views(width, height).items():
        if view.dtype == np.uint8:
            view[...] = rng.integers(0, 256, size=view.shape, dtype=np.uint8)
        else:
            view[...] = rng.standard_normal(size=view.shape, dtype=np.float32)
        crc = zlib.crc32(view.tobytes(), crc)
        del name
    lease.header["frame_id"] = seq_hint
    lease.header["checksum"] = crc
    return crc


def frame_checksum(lease: ReadLease) -> int:
    crc = 0
    for view in lease.planes.values():
        crc = zlib.crc32(view.tobytes(), crc)
    return crc


# ---- child process bodies (module level so the "spawn" start method can import them)


def child_hold_read_then_hang(name: str, held: object) -> None:
    """Attach as consumer, take a frame, say so, then hang until killed."""
    import time

    from server.frames.ring import FrameRing

    ring = FrameRing.attach(name)
    ring.attach_as_consumer()
    lease = ring.acquire_read(5.0)
    assert lease is not None
    held.set()  # type: ignore[attr-defined]
    time.sleep(60)


def child_write_half_then_hang(name: str, held: object, width: int, height: int) -> None:
    """Attach as producer, write half a frame, say so, then hang until killed."""
    import time

    from server.frames.ring import FrameRing

    ring = FrameRing.attach(name)
    ring.attach_as_producer()
    lease = ring.acquire_write(5.0)
    assert lease is not None
    views = lease.views(width, height)
    first = next(iter(views.values()))
    first[: height // 2] = 255
    held.set()  # type: ignore[attr-defined]
    time.sleep(60)


def child_produce(name: str, count: int, width: int, height: int, period_s: float) -> None:
    """Produce ``count`` checksummed frames at a steady period."""
    import time

    from server.frames.ring import FrameRing

    ring = FrameRing.attach(name)
    ring.attach_as_producer()
    for i in range(count):
        lease = ring.acquire_write(5.0)
        if lease is None:
            continue
        fill_frame(lease, i, width, height)
        lease.commit()
        time.sleep(period_s)
    ring.close()
