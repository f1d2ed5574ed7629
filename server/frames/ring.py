"""FrameRing: a shared-memory ring of frame slots with a fence per slot.

One producer writes frames straight into a slot, one consumer reads them as
read-only views: no copy, no pickling. The same ring type carries G-buffers
(ring R: game -> upscaler worker) and display frames (ring U: worker ->
encoder); only the plane list differs.

Byte layout (version 1)
=======================

The ring is one POSIX shared-memory object, ``/dev/shm/<name>`` on Linux (what
``shm_open("/<name>")`` opens in C). All integers are little-endian; offsets
are bytes from the start of the object.

Ring header, ``RING_HEADER_SIZE`` = 4096 bytes::

    off  type      field
    0    char[8]   magic = "UPCRING\\x01"
    8    u32       layout_version = 1
    12   u32       slot_count
    16   u32       plane_count
    20   u32       mode: 0 = real-time (overwrite oldest READY), 1 = lossless (wait)
    24   u32       max_width   (plane capacity, pixels)
    28   u32       max_height
    32   u64       slot_stride (bytes from one slot to the next, multiple of 4096)
    40   u64       slots_offset (= 4096)
    48   u32       ready_futex: +1 each time a slot becomes READY
    52   u32       free_futex:  +1 each time a slot becomes FREE
    56   i32       producer_pid (last producer to attach, 0 = none)
    60   i32       consumer_pid (last consumer to attach, 0 = none)
    64   u64       next_seq: sequence number of the next committed frame (from 1)
    72   u64       committed: frames marked READY
    80   u64       delivered: frames handed to the consumer
    88   u64       dropped_overwritten: READY frames the producer overwrote
    96   u64       dropped_skipped: READY frames the consumer skipped ("newest" reads)
    104  u64       recovered: slots taken back from dead processes
    112  u64       rejected: READY frames whose header was invalid (size beyond capacity)
    256  plane table, plane_count entries of 64 bytes:
           +0  char[16] name (ASCII, NUL padded)
           +16 u32      dtype: 1 = uint8, 2 = float32
           +20 u32      channels
           +24 u64      offset of the plane inside a slot (64-byte aligned)
           +32 u64      capacity in bytes (max_width * max_height * channels * itemsize)

Slot ``i`` starts at ``slots_offset + i * slot_stride``. Slot header, 1024 bytes::

    0    u32       state: 0 FREE, 1 WRITING, 2 READY, 3 READING
    4    i32       owner_pid (process holding it WRITING or READING)
    8    u64       seq (set when it becomes READY)
    16   u32       width   (of this frame; <= max_width)
    20   u32       height
    24   i64       frame_id
    32   u32       flags (bits: 0 RESET, 1 PREDICTED, 2 COLOR_ONLY, 3 AREA_SAMPLES; frame.py)
    36   f32[2]    jitter (render pixels)
    44   f32       near
    48   f32       far
    52   f32       fov_y_deg
    56   u64       checksum (optional, 0 = none; tests use it)
    64   f32[4][4][4]  view, proj, prev_view, prev_proj (row-major)
    320  i64[14][2]    timing stamps (monotonic ns, wall ns) in server.frames.timing.Stage order
    544  i64       input_seq: sequence number of the last player input the game applied
                   before rendering this frame (0 = none); lets a client measure
                   input-to-photon latency
    552  i64       game_time_us: game time the frame was rendered at, microseconds
                   (0 = unknown: a source without a game clock); a predicted frame
                   keeps its tick's time. Lets a benchmark re-render the ground
                   truth of a received frame

Planes follow at their table offsets. Each holds ``height * width * channels``
elements of its dtype, packed row-major (no row padding) for the slot's own
width and height, so a frame smaller than the capacity needs no reallocation.

Fences and the protocol
=======================

``state`` is the per-slot fence. Transitions FREE -> WRITING -> READY ->
READING -> FREE (and WRITING -> FREE on abort, READY -> WRITING when a real-time
producer overwrites) are made while holding ``flock(LOCK_EX)`` on the
shared-memory object's file descriptor: held for microseconds, released by
the kernel if its holder dies, and a full memory barrier on both sides.
Waiting uses the two futex words: read the word under the lock, find nothing
to do, release, ``FUTEX_WAIT`` on (word, value read) with a timeout. Whoever
changes a slot bumps the word under the lock and ``FUTEX_WAKE`` s after.

A dead peer cannot deadlock the other: every wait has a timeout, and slots
held by a process that no longer exists are recovered (WRITING -> FREE: a
half-written frame is never delivered; READING -> READY: the frame is handed
to the next consumer that attaches).
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import mmap
import os
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path
from types import TracebackType
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt

from server.frames.futex import FutexWord
from server.frames.timing import STAGE_COUNT, Stage
from server.ops.process import pid_alive

log = logging.getLogger(__name__)

MAGIC = b"UPCRING\x01"
LAYOUT_VERSION = 1
RING_HEADER_SIZE = 4096
SLOT_HEADER_SIZE = 1024
PLANE_TABLE_OFFSET = 256
PLANE_ENTRY_SIZE = 64
MAX_PLANES = (RING_HEADER_SIZE - PLANE_TABLE_OFFSET) // PLANE_ENTRY_SIZE
PLANE_ALIGN = 64
PAGE = 4096
SHM_DIR = Path("/dev/shm")


class SlotState(IntEnum):
    FREE = 0
    WRITING = 1
    READY = 2
    READING = 3


class RingMode(IntEnum):
    REALTIME = 0  # the producer never waits: it overwrites the oldest READY frame
    LOSSLESS = 1  # the producer waits for a FREE slot


_DTYPE_CODES: dict[int, np.dtype[Any]] = {1: np.dtype(np.uint8), 2: np.dtype(np.float32)}
_CODE_OF_DTYPE = {v: k for k, v in _DTYPE_CODES.items()}

RING_HEADER = np.dtype(
    {
        "names": [
            "magic", "version", "slot_count", "plane_count", "mode", "max_width", "max_height",
            "slot_stride", "slots_offset", "ready_futex", "free_futex", "producer_pid",
            "consumer_pid", "next_seq", "committed", "delivered", "dropped_overwritten",
            "dropped_skipped", "recovered", "rejected",
        ],
        "formats": [
            "S8", "<u4", "<u4", "<u4", "<u4", "<u4", "<u4", "<u8", "<u8", "<u4", "<u4", "<i4",
            "<i4", "<u8", "<u8", "<u8", "<u8", "<u8", "<u8", "<u8",
        ],
        "offsets": [
            0, 8, 12, 16, 20, 24, 28, 32, 40, 48, 52, 56, 60, 64, 72, 80, 88, 96, 104, 112,
        ],
        "itemsize": PLANE_TABLE_OFFSET,
    }
)  # fmt: skip

PLANE_ENTRY = np.dtype(
    {
        "names": ["name", "dtype", "channels", "offset", "capacity"],
        "formats": ["S16", "<u4", "<u4", "<u8", "<u8"],
        "offsets": [0, 16, 20, 24, 32],
        "itemsize": PLANE_ENTRY_SIZE,
    }
)

SLOT_HEADER = np.dtype(
    {
        "names": [
            "state", "owner_pid", "seq", "width", "height", "frame_id", "flags", "jitter",
            "near", "far", "fov_y_deg", "checksum", "matrices", "stamps", "input_seq",
            "game_time_us",
        ],
        "formats": [
            "<u4", "<i4", "<u8", "<u4", "<u4", "<i8", "<u4", ("<f4", (2,)), "<f4", "<f4", "<f4",
            "<u8", ("<f4", (4, 4, 4)), ("<i8", (STAGE_COUNT, 2)), "<i8", "<i8",
        ],
        "offsets": [0, 4, 8, 16, 20, 24, 32, 36, 44, 48, 52, 56, 64, 320, 544, 552],
        "itemsize": SLOT_HEADER_SIZE,
    }
)  # fmt: skip


def field_offset(dtype: np.dtype[Any], name: str) -> int:
    """Byte offset of a field of one of the layout dtypes above."""
    fields = dtype.fields
    assert fields is not None
    return int(fields[name][1])


@dataclass(frozen=True)
class PlaneSpec:
    """A named image plane of a slot: ``channels`` values of ``dtype`` per pixel."""

    name: str
    dtype: np.dtype[Any]
    channels: int

    def nbytes(self, width: int, height: int) -> int:
        return width * height * self.channels * self.dtype.itemsize

    def shape(self, width: int, height: int) -> tuple[int, ...]:
        return (height, width) if self.channels == 1 else (height, width, self.channels)


RENDER_PLANES: tuple[PlaneSpec, ...] = (
    PlaneSpec("color", np.dtype(np.uint8), 3),
    PlaneSpec("depth", np.dtype(np.float32), 1),
    PlaneSpec("motion", np.dtype(np.float32), 2),
    PlaneSpec("dynamic_mask", np.dtype(np.uint8), 1),
)
DISPLAY_PLANES: tuple[PlaneSpec, ...] = (PlaneSpec("color", np.dtype(np.uint8), 3),)


class RingError(RuntimeError):
    """The shared-memory object is missing, not a ring, or of another layout."""


@dataclass
class RingCounters:
    committed: int
    delivered: int
    dropped_overwritten: int
    dropped_skipped: int
    recovered: int
    rejected: int

    @property
    def dropped(self) -> int:
        return self.dropped_overwritten + self.dropped_skipped + self.rejected


def _align(value: int, to: int) -> int:
    return (value + to - 1) // to * to


def _shm_path(name: str) -> Path:
    if not name or "/" in name or name.startswith("."):
        raise ValueError(f"ring name must be a plain file name, got {name!r}")
    return SHM_DIR / name


class FrameRing:
    """A handle on one ring; ``create`` makes the object, ``attach`` opens it by name.

    Any number of handles may exist; the protocol assumes one producer and one
    consumer at a time. A handle is safe to share between threads.
    """

    def __init__(self, name: str, fd: int, owner: bool) -> None:
        self.name = name
        self._fd = fd
        self._created = owner
        size = os.fstat(fd).st_size
        if size < RING_HEADER_SIZE:
            os.close(fd)
            raise RingError(f"ring {name!r}: shared memory object too small ({size} bytes)")
        self._mm = mmap.mmap(fd, size, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
        self._thread_lock = threading.Lock()
        self.header = np.ndarray((), dtype=RING_HEADER, buffer=self._mm, offset=0)
        if bytes(self.header["magic"]) != MAGIC:
            self._close_mapping()
            raise RingError(f"ring {name!r}: not an upcast ring (bad magic)")
        if int(self.header["version"]) != LAYOUT_VERSION:
            version = int(self.header["version"])
            self._close_mapping()
            raise RingError(f"ring {name!r}: layout version {version}, expected {LAYOUT_VERSION}")
        self.slot_count = int(self.header["slot_count"])
        self.mode = RingMode(int(self.header["mode"]))
        self.max_width = int(self.header["max_width"])
        self.max_height = int(self.header["max_height"])
        self._slot_stride = int(self.header["slot_stride"])
        self._slots_offset = int(self.header["slots_offset"])
        table = np.ndarray(
            (int(self.header["plane_count"]),),
            dtype=PLANE_ENTRY,
            buffer=self._mm,
            offset=PLANE_TABLE_OFFSET,
        )
        self.planes: tuple[PlaneSpec, ...] = tuple(
            PlaneSpec(e["name"].decode(), _DTYPE_CODES[int(e["dtype"])], int(e["channels"]))
            for e in table
        )
        self._plane_offsets = [int(e["offset"]) for e in table]
        self.slots = [
            np.ndarray((), dtype=SLOT_HEADER, buffer=self._mm, offset=self._slot_offset(i))
            for i in range(self.slot_count)
        ]
        self._view_cache: dict[tuple[int, int, int, bool], dict[str, npt.NDArray[Any]]] = {}
        self._u32 = memoryview(self._mm).cast("I")
        self._i32 = memoryview(self._mm).cast("i")
        self._u64 = memoryview(self._mm).cast("Q")
        n = self.slot_count
        self._state_idx = [
            self._word_index(i, field_offset(SLOT_HEADER, "state"), 4) for i in range(n)
        ]
        self._owner_idx = [
            self._word_index(i, field_offset(SLOT_HEADER, "owner_pid"), 4) for i in range(n)
        ]
        self._seq_idx = [self._word_index(i, field_offset(SLOT_HEADER, "seq"), 8) for i in range(n)]
        self._checksum_idx = [
            self._word_index(i, field_offset(SLOT_HEADER, "checksum"), 8) for i in range(n)
        ]
        self._producer_pid_idx = field_offset(RING_HEADER, "producer_pid") // 4
        self._consumer_pid_idx = field_offset(RING_HEADER, "consumer_pid") // 4
        self._counter_idx = {
            name: field_offset(RING_HEADER, name) // 8
            for name in (
                "next_seq", "committed", "delivered", "dropped_overwritten",
                "dropped_skipped", "recovered", "rejected",
            )
        }  # fmt: skip
        self._ready = FutexWord(self._mm, field_offset(RING_HEADER, "ready_futex"))
        self._free = FutexWord(self._mm, field_offset(RING_HEADER, "free_futex"))
        self._pid = os.getpid()

    # ----------------------------------------------------------------- lifecycle

    @classmethod
    def create(
        cls,
        name: str,
        planes: Sequence[PlaneSpec],
        max_size: tuple[int, int],
        *,
        slots: int = 3,
        mode: RingMode = RingMode.REALTIME,
        replace: bool = False,
    ) -> FrameRing:
        """Create the shared-memory object (fails if it exists unless ``replace``)."""
        if slots < 2:
            raise ValueError(f"a ring needs at least 2 slots, got {slots}")
        if not 1 <= len(planes) <= MAX_PLANES:
            raise ValueError(f"a ring holds 1 to {MAX_PLANES} planes, got {len(planes)}")
        width, height = max_size
        if width <= 0 or height <= 0:
            raise ValueError(f"ring capacity must be positive, got {width}x{height}")
        path = _shm_path(name)
        if replace:
            path.unlink(missing_ok=True)
        offsets: list[int] = []
        cursor = SLOT_HEADER_SIZE
        for plane in planes:
            cursor = _align(cursor, PLANE_ALIGN)
            offsets.append(cursor)
            cursor += plane.nbytes(width, height)
        stride = _align(cursor, PAGE)
        total = RING_HEADER_SIZE + stride * slots
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_RDWR, 0o600)
        try:
            os.ftruncate(fd, total)
            with mmap.mmap(fd, RING_HEADER_SIZE) as mm:
                hdr = np.ndarray((), dtype=RING_HEADER, buffer=mm, offset=0)
                hdr["version"] = LAYOUT_VERSION
                hdr["slot_count"] = slots
                hdr["plane_count"] = len(planes)
                hdr["mode"] = int(mode)
                hdr["max_width"] = width
                hdr["max_height"] = height
                hdr["slot_stride"] = stride
                hdr["slots_offset"] = RING_HEADER_SIZE
                hdr["next_seq"] = 1
                table = np.ndarray(
                    (len(planes),), dtype=PLANE_ENTRY, buffer=mm, offset=PLANE_TABLE_OFFSET
                )
                for entry, plane, off in zip(table, planes, offsets, strict=True):
                    entry["name"] = plane.name.encode()
                    entry["dtype"] = _CODE_OF_DTYPE[plane.dtype]
                    entry["channels"] = plane.channels
                    entry["offset"] = off
                    entry["capacity"] = plane.nbytes(width, height)
                # Magic last: a reader never sees a half-initialised header as valid.
                hdr["magic"] = MAGIC
                del hdr, table
        except BaseException:
            os.close(fd)
            path.unlink(missing_ok=True)
            raise
        log.debug("created ring %s: %d slots of %d bytes", name, slots, stride)
        return cls(name, fd, owner=True)

    @classmethod
    def attach(cls, name: str, *, wait_s: float = 0.0) -> FrameRing:
        """Open an existing ring by name, waiting up to ``wait_s`` for it to appear."""
        path = _shm_path(name)
        deadline = time.monotonic() + wait_s
        while True:
            try:
                fd = os.open(path, os.O_RDWR)
                break
            except FileNotFoundError:
                if time.monotonic() >= deadline:
                    raise RingError(f"no ring named {name!r} (looked for {path})") from None
                time.sleep(0.02)
        return cls(name, fd, owner=False)

    def close(self) -> None:
        """Drop this handle's mapping (views handed out keep their pages alive)."""
        self._close_mapping()

    def unlink(self) -> None:
        """Remove the shared-memory object's name; mappings stay valid until closed."""
        _shm_path(self.name).unlink(missing_ok=True)

    def _close_mapping(self) -> None:
        for attr in ("_ready", "_free"):
            word = getattr(self, attr, None)
            if word is not None:
                word.release()
        self.header = None  # type: ignore[assignment]
        self.slots = []
        self._view_cache = {}
        for attr in ("_u32", "_i32", "_u64"):
            view = getattr(self, attr, None)
            if view is not None:
                view.release()
        # Views still exported (a caller kept a frame): the mapping goes when they do.
        with contextlib.suppress(BufferError, AttributeError):
            self._mm.close()
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> FrameRing:
        return self

    def __exit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -------------------------------------------------------------------- locking

    @contextmanager
    def _locked(self) -> Iterator[None]:
        with self._thread_lock:
            fcntl.flock(self._fd, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(self._fd, fcntl.LOCK_UN)

    # ---------------------------------------------------------------- inspection

    def _slot_offset(self, index: int) -> int:
        return self._slots_offset + index * self._slot_stride

    def require_fits(self, width: int, height: int, what: str) -> None:
        """Refuse, at start, frames this ring's planes cannot hold."""
        if width > self.max_width or height > self.max_height:
            raise ValueError(
                f"{what} {width}x{height} exceeds ring {self.name!r} capacity "
                f"{self.max_width}x{self.max_height}"
            )

    def counters(self) -> RingCounters:
        h = self.header
        return RingCounters(
            committed=int(h["committed"]),
            delivered=int(h["delivered"]),
            dropped_overwritten=int(h["dropped_overwritten"]),
            dropped_skipped=int(h["dropped_skipped"]),
            recovered=int(h["recovered"]),
            rejected=int(h["rejected"]),
        )

    def states(self) -> list[SlotState]:
        return [SlotState(self._state(i)) for i in range(self.slot_count)]

    def plane_views(
        self, index: int, width: int, height: int, *, writable: bool
    ) -> dict[str, npt.NDArray[Any]]:
        if not (0 < width <= self.max_width and 0 < height <= self.max_height):
            raise RingError(
                f"ring {self.name!r}: frame {width}x{height} outside capacity "
                f"{self.max_width}x{self.max_height}"
            )
        key = (index, width, height, writable)
        cached = self._view_cache.get(key)
        if cached is not None:
            return cached
        base = self._slot_offset(index)
        views: dict[str, npt.NDArray[Any]] = {}
        for plane, off in zip(self.planes, self._plane_offsets, strict=True):
            arr: npt.NDArray[Any] = np.ndarray(
                plane.shape(width, height), dtype=plane.dtype, buffer=self._mm, offset=base + off
            )
            arr.flags.writeable = writable
            views[plane.name] = arr
        # Building ndarrays is the slowest part of a handoff; sizes rarely change.
        if len(self._view_cache) > 8 * self.slot_count:
            self._view_cache.clear()
        self._view_cache[key] = views
        return views

    # ------------------------------------------------------- control words
    # The protocol touches a few integers per slot many times per frame; plain
    # memoryview casts read and write them ~20x faster than numpy structured
    # fields, which matters right after a wake-up when caches are cold.

    def _word_index(self, slot: int, byte_offset: int, size: int) -> int:
        return (self._slot_offset(slot) + byte_offset) // size

    def _state(self, i: int) -> int:
        return int(self._u32[self._state_idx[i]])

    def _set_state(self, i: int, state: SlotState, owner: int = 0) -> None:
        self._i32[self._owner_idx[i]] = owner
        self._u32[self._state_idx[i]] = int(state)

    def _owner(self, i: int) -> int:
        return int(self._i32[self._owner_idx[i]])

    def _seq(self, i: int) -> int:
        return int(self._u64[self._seq_idx[i]])

    def _bump(self, counter: str, by: int = 1) -> None:
        idx = self._counter_idx[counter]
        self._u64[idx] = self._u64[idx] + by

    # ------------------------------------------------------------------ recovery

    def recover_dead_holders(self) -> int:
        """Take back slots held by processes that no longer exist. Returns the count."""
        with self._locked():
            return self._recover_locked()

    def _recover_locked(self) -> int:
        recovered = 0
        for i in range(self.slot_count):
            state = self._state(i)
            if state not in (SlotState.WRITING, SlotState.READING) or pid_alive(self._owner(i)):
                continue
            if state == SlotState.WRITING:
                self._set_state(i, SlotState.FREE)
                self._free.increment()
            else:
                self._set_state(i, SlotState.READY)
                self._ready.increment()
            recovered += 1
        if recovered:
            self._bump("recovered", recovered)
            log.warning("ring %s: recovered %d slot(s) from dead processes", self.name, recovered)
        return recovered

    # ------------------------------------------------------------------ producer

    def acquire_write(self, timeout_s: float) -> WriteLease | None:
        """A slot to write, or None after ``timeout_s`` (lossless mode, consumer behind).

        In real-time mode this only waits when every slot is held, which needs a
        ring of 2 slots or a consumer holding more than one.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            with self._locked():
                seen = self._free.value
                index = self._pick_for_write()
                if index is None and self._recover_locked():
                    # A dead consumer or producer was holding slots: look again.
                    index = self._pick_for_write()
                if index is not None:
                    self._set_state(index, SlotState.WRITING, self._pid)
                    self._u64[self._checksum_idx[index]] = 0
                    self._i32[self._producer_pid_idx] = self._pid
                    return WriteLease(self, index)
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            # Wake at least every 100 ms to notice a consumer that died holding a slot.
            self._free.wait(seen, min(remaining, 0.1))

    def _pick_for_write(self) -> int | None:
        oldest: tuple[int, int] | None = None
        for i in range(self.slot_count):
            state = self._state(i)
            if state == SlotState.FREE:
                return i
            if state == SlotState.READY and (oldest is None or self._seq(i) < oldest[0]):
                oldest = (self._seq(i), i)
        if self.mode == RingMode.REALTIME and oldest is not None:
            self._bump("dropped_overwritten")
            return oldest[1]
        return None

    def _commit(self, index: int, stamp_stage: Stage | None) -> int:
        if stamp_stage is not None:
            self.slots[index]["stamps"][stamp_stage] = (time.monotonic_ns(), time.time_ns())
        with self._locked():
            if self._state(index) != SlotState.WRITING or self._owner(index) != self._pid:
                raise RingError(f"ring {self.name!r}: commit of slot {index} not held for writing")
            seq = int(self._u64[self._counter_idx["next_seq"]])
            self._u64[self._counter_idx["next_seq"]] = seq + 1
            self._u64[self._seq_idx[index]] = seq
            self._set_state(index, SlotState.READY)
            self._bump("committed")
            self._ready.increment()
        self._ready.wake_all()
        return seq

    def _abort_write(self, index: int) -> None:
        with self._locked():
            if self._state(index) == SlotState.WRITING and self._owner(index) == self._pid:
                self._set_state(index, SlotState.FREE)
                self._free.increment()
        self._free.wake_all()

    # ------------------------------------------------------------------ consumer

    def acquire_read(self, timeout_s: float, *, newest: bool = False) -> ReadLease | None:
        """The next READY frame as read-only views, or None after ``timeout_s``.

        ``newest=False`` delivers frames in sequence order; ``newest=True`` takes
        the latest and frees (and counts as skipped) the older READY ones.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            with self._locked():
                seen = self._ready.value
                index = self._pick_for_read(newest)
                if index is not None:
                    try:
                        lease = ReadLease(self, index)
                    except RingError as exc:
                        # A producer wrote a size the planes cannot hold: refuse that
                        # frame, free its slot, keep serving the next ones.
                        self._set_state(index, SlotState.FREE)
                        self._bump("rejected")
                        self._free.increment()
                        log.error(
                            "ring %s: rejected frame seq %d: %s", self.name, self._seq(index), exc
                        )
                        continue
                    self._set_state(index, SlotState.READING, self._pid)
                    self._i32[self._consumer_pid_idx] = self._pid
                    self._bump("delivered")
                    return lease
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not self._ready.wait(seen, remaining):
                return None

    def _pick_for_read(self, newest: bool) -> int | None:
        ready = sorted(
            (self._seq(i), i) for i in range(self.slot_count) if self._state(i) == SlotState.READY
        )
        if not ready:
            return None
        if not newest:
            return ready[0][1]
        for _, older in ready[:-1]:
            self._set_state(older, SlotState.FREE)
            self._bump("dropped_skipped")
            self._free.increment()
        return ready[-1][1]

    def _release_read(self, index: int) -> None:
        with self._locked():
            if self._state(index) == SlotState.READING and self._owner(index) == self._pid:
                self._set_state(index, SlotState.FREE)
                self._free.increment()
        self._free.wake_all()

    def attach_as_consumer(self) -> None:
        """Register as the consumer and give back what a dead predecessor held."""
        with self._locked():
            self._recover_locked()
            self._i32[self._consumer_pid_idx] = self._pid

    def attach_as_producer(self) -> None:
        """Register as the producer and free what a dead predecessor was writing."""
        with self._locked():
            self._recover_locked()
            self._i32[self._producer_pid_idx] = self._pid

    def peer_alive(self, role: str) -> bool:
        """Whether the last registered producer/consumer process still exists."""
        idx = self._producer_pid_idx if role == "producer" else self._consumer_pid_idx
        pid = int(self._i32[idx])
        return pid != 0 and pid_alive(pid)


class _Lease:
    kind: ClassVar[str] = "lease"

    def __init__(self, ring: FrameRing, index: int) -> None:
        self.ring = ring
        self.index = index
        self.header = ring.slots[index]
        self._open = True

    @property
    def seq(self) -> int:
        return int(self.header["seq"])


class WriteLease(_Lease):
    """A slot held WRITING: fill ``views(width, height)`` and the header, then commit."""

    kind = "write"

    def views(self, width: int, height: int) -> dict[str, npt.NDArray[Any]]:
        self.header["width"] = width
        self.header["height"] = height
        return self.ring.plane_views(self.index, width, height, writable=True)

    def commit(self, stamp_stage: Stage | None = None) -> int:
        """Mark READY (the fence), after stamping ``stamp_stage`` if given. Returns seq."""
        if not self._open:
            raise RingError("lease already closed")
        self._open = False
        return self.ring._commit(self.index, stamp_stage)

    def abort(self) -> None:
        if self._open:
            self._open = False
            self.ring._abort_write(self.index)

    def __enter__(self) -> WriteLease:
        return self

    def __exit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        # Leaving the block without commit (an exception, an early return) frees the slot.
        self.abort()


class ReadLease(_Lease):
    """A slot held READING: read-only views valid until ``release``."""

    kind = "read"

    def __init__(self, ring: FrameRing, index: int) -> None:
        super().__init__(ring, index)
        self.width = int(self.header["width"])
        self.height = int(self.header["height"])
        self.planes = ring.plane_views(index, self.width, self.height, writable=False)

    def release(self) -> None:
        if self._open:
            self._open = False
            self.planes = {}
            self.ring._release_read(self.index)

    def __enter__(self) -> ReadLease:
        return self

    def __exit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.release()
