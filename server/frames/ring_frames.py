"""Typed frames on top of ring slots: FrameMeta <-> slot header, planes <-> frames."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from server.frames.frame import Camera, DisplayFrame, FrameFlags, FrameMeta, RenderFrame, Size
from server.frames.ring import (
    DISPLAY_PLANES,
    RENDER_PLANES,
    FrameRing,
    PlaneSpec,
    ReadLease,
    RingError,
    RingMode,
    WriteLease,
)

SlotHeader = np.ndarray  # a 0-d structured view of SLOT_HEADER

# Bits a producer may set that mean something here; unknown bits are dropped.
KNOWN_FLAGS = (
    FrameFlags.RESET | FrameFlags.PREDICTED | FrameFlags.COLOR_ONLY | FrameFlags.AREA_SAMPLES
)


def write_meta(header: SlotHeader, meta: FrameMeta) -> None:
    """Copy ``meta`` into a slot header (stamps included)."""
    cam = meta.camera
    header["frame_id"] = meta.frame_id
    header["flags"] = int(meta.flags)
    header["jitter"] = meta.jitter
    header["near"] = cam.near
    header["far"] = cam.far
    header["fov_y_deg"] = cam.fov_y_deg
    mats = header["matrices"]
    mats[0] = cam.view
    mats[1] = cam.proj
    mats[2] = cam.prev_view
    mats[3] = cam.prev_proj
    header["stamps"] = meta.stamps
    header["input_seq"] = meta.input_seq
    header["game_time_us"] = meta.game_time_us


def read_meta(header: SlotHeader) -> FrameMeta:
    """A FrameMeta that owns copies of the header's values (safe after release)."""
    mats = np.array(header["matrices"], dtype=np.float32)
    camera = Camera(
        view=mats[0],
        proj=mats[1],
        prev_view=mats[2],
        prev_proj=mats[3],
        near=float(header["near"]),
        far=float(header["far"]),
        fov_y_deg=float(header["fov_y_deg"]),
    )
    jitter = header["jitter"]
    return FrameMeta(
        frame_id=int(header["frame_id"]),
        camera=camera,
        jitter=(float(jitter[0]), float(jitter[1])),
        flags=FrameFlags(int(header["flags"]) & int(KNOWN_FLAGS)),
        stamps=np.array(header["stamps"], dtype=np.int64),
        input_seq=int(header["input_seq"]),
        game_time_us=int(header["game_time_us"]),
    )


def render_frame_of(lease: ReadLease) -> RenderFrame:
    """Read-only G-buffer views of a ring R slot plus a copy of its metadata."""
    p = lease.planes
    return RenderFrame(
        color=p["color"],
        depth=p["depth"],
        motion=p["motion"],
        dynamic_mask=p["dynamic_mask"],
        meta=read_meta(lease.header),
    )


def put_render_frame(ring: FrameRing, frame: RenderFrame, timeout_s: float) -> bool:
    """Copy a frame that already exists into the next ring R slot (False: no slot in time).

    The game renders straight into its slot instead; this is for frames made
    elsewhere (tests, replays, an engine that keeps its own G-buffers)."""
    lease = ring.acquire_write(timeout_s)
    if lease is None:
        return False
    views = lease.views(*frame.size)
    for key in ("color", "depth", "motion", "dynamic_mask"):
        views[key][...] = getattr(frame, key)
    write_meta(lease.header, frame.meta)
    lease.commit()
    return True


def display_frame_of(lease: ReadLease) -> DisplayFrame:
    return DisplayFrame(color=lease.planes["color"], meta=read_meta(lease.header))


def _check_planes(ring: FrameRing, expected: Sequence[PlaneSpec], role: str) -> None:
    if tuple(ring.planes) != tuple(expected):
        names = [p.name for p in ring.planes]
        raise RingError(f"ring {ring.name!r} has planes {names}, not a {role} ring")


def create_render_ring(
    name: str, max_size: Size, *, slots: int = 3, mode: RingMode = RingMode.REALTIME
) -> FrameRing:
    return FrameRing.create(name, RENDER_PLANES, max_size, slots=slots, mode=mode, replace=True)


def create_display_ring(
    name: str, max_size: Size, *, slots: int = 3, mode: RingMode = RingMode.REALTIME
) -> FrameRing:
    return FrameRing.create(name, DISPLAY_PLANES, max_size, slots=slots, mode=mode, replace=True)


def attach_render_ring(name: str, wait_s: float = 0.0) -> FrameRing:
    ring = FrameRing.attach(name, wait_s=wait_s)
    _check_planes(ring, RENDER_PLANES, "render (G-buffer)")
    return ring


def attach_display_ring(name: str, wait_s: float = 0.0) -> FrameRing:
    ring = FrameRing.attach(name, wait_s=wait_s)
    _check_planes(ring, DISPLAY_PLANES, "display")
    return ring


def render_targets_of(lease: WriteLease, size: Size) -> dict[str, np.ndarray]:
    """Writable plane views of a ring R slot sized for this frame."""
    return lease.views(size.width, size.height)
