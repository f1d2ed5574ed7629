"""The rendition ladder: smaller copies of the stream for spectators on narrower links.

The player's track (``video``) follows the player's link (rate control, intra refresh,
IDRs only on demand). A spectator cannot ask for anything (no token, no input track),
so a link narrower than the player's would leave it with a stream it cannot carry and
groups seconds apart to join at. The ladder adds *rungs*: the same upscaled frame at
the display size / a divisor (2: half, 4: a quarter), converted to YUV once and scaled
down rung by rung (a scaler, not a second render), each with a fixed bitrate cap and
its own track ``video.<W>x<H>`` in the same hang catalog, so a viewer picks the one its
link carries and switches at any group.

Keyframes, and so groups, are decided for all rungs at once:

- every ``gop_seconds`` of stream time (1 s by default): a spectator joins, or rejoins
  after a skipped group, within that long, with no keyframe request (it cannot send
  one); the relay replays the latest group, so a join shows a picture at once;
- on every frame where the player's track has an IDR, so a viewer that moves between
  the player's track and a rung meets a group boundary at the same frame;
- on request (a new subscriber of a rung, the relay's nudge), at most once per
  ``keyframe_min_interval_ms``, as the player's encoder does.

Only the rungs someone watches are encoded (the session passes the rungs with a
subscriber, :meth:`RenditionLadder.set_wanted`; the relay holds one upstream
subscription per track while it has viewers), so a ladder nobody watches costs nothing.

Rung IDRs stay on the same frames (the same pts on every rung), so a switch between
rungs lands on a group boundary. A rung whose encoder fails is dropped (logged, the
catalog republished without it); the other rungs and the player's track go on.

Cost: one RGB -> YUV pass over the display frame, then per rung a plane scaling and
x264 at the rung's size (``upcast bench ladder`` measures each against the player's
track).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from av.video.frame import VideoFrame
from av.video.reformatter import Interpolation, VideoReformatter

from server.frames.frame import Size
from server.media.catalog import VideoRendition, rung_track_name, video_rendition
from server.media.encode import (
    MIN_BITRATE,
    EncodedFrame,
    EncoderConfig,
    VideoEncoder,
    default_bitrate,
    encoded_size,
    rgb_to_yuv420,
)
from server.stream_config import DEFAULT_DIVISORS, DEFAULT_GOP_S, check_divisors

log = logging.getLogger(__name__)

# No periodic IDR of the rung's own: the ladder decides every rung's IDRs (module doc).
_NO_PERIODIC_IDR_S = 3600.0


@dataclass(frozen=True)
class RungFrame:
    track: str
    encoded: EncodedFrame


@dataclass
class Rung:
    track: str
    width: int
    height: int
    bitrate: int
    encoder: VideoEncoder
    scaler: VideoReformatter = field(default_factory=VideoReformatter)
    frames: int = 0
    cpu_s_total: float = 0.0  # this thread's CPU in the rung's calls (not its neighbours')


@dataclass
class LadderStats:
    frames: int = 0  # frames given to the ladder
    keyframes: int = 0  # ladder IDRs (one per rung each)
    aligned_keyframes: int = 0  # of which on a player-track IDR
    requested_keyframes: int = 0  # of which on a request
    convert_cpu_s: float = 0.0  # the one RGB -> YUV pass per frame, shared by the rungs
    idle_frames: int = 0  # frames given while no rung was watched (nothing encoded)
    failed_rungs: list[str] = field(default_factory=list)


class RenditionLadder:
    """Encodes the rungs of one stream; one thread at a time calls :meth:`encode`."""

    def __init__(
        self,
        display: Size,
        fps: float,
        divisors: Sequence[int] = DEFAULT_DIVISORS,
        *,
        gop_seconds: float = DEFAULT_GOP_S,
        keyframe_min_interval_ms: float = 250.0,
        threads: int = 1,
    ) -> None:
        if gop_seconds <= 0:
            raise ValueError(f"ladder gop_seconds must be positive, got {gop_seconds}")
        self.display = display
        self.fps = fps
        self.gop_us = gop_seconds * 1e6
        self._half_frame_us = 1e6 / fps / 2
        self._min_interval_us = keyframe_min_interval_ms * 1000
        self.stats = LadderStats()
        self.rungs: list[Rung] = []
        seen: set[tuple[int, int]] = set()
        for divisor in check_divisors(divisors):
            width, height = encoded_size(display, float(divisor))
            if (width, height) in seen or (width, height) == (display.width, display.height):
                continue  # a tiny display: two divisors round to one size
            seen.add((width, height))
            # The rate cap: default_bitrate's bits per pixel (6 Mbit/s at 720p60), no
            # more: rungs are for links that cannot carry the player's rate.
            bitrate = max(MIN_BITRATE, default_bitrate(width, height, fps))
            config = EncoderConfig(
                width=display.width,
                height=display.height,
                fps=fps,
                bitrate=bitrate,
                gop_seconds=_NO_PERIODIC_IDR_S,
                keyframe_min_interval_ms=keyframe_min_interval_ms,
                threads=threads,
                intra_refresh=False,
            )
            encoder = VideoEncoder(config, encoded=(width, height))
            self.rungs.append(Rung(rung_track_name(width, height), width, height, bitrate, encoder))
        self._convert = VideoReformatter()
        self._wanted: frozenset[str] | None = None
        self._last_idr_us: int | None = None
        self._requested = False

    @property
    def tracks(self) -> tuple[str, ...]:
        return tuple(rung.track for rung in self.rungs)

    def renditions(self) -> dict[str, VideoRendition]:
        """The rungs' catalog entries, largest first, each with its rate cap."""
        return {
            rung.track: video_rendition(rung.encoder.encoded_config, self.fps, rung.bitrate)
            for rung in self.rungs
        }

    @property
    def idle(self) -> bool:
        """Whether no rung is watched now (see :meth:`set_wanted`): nothing to encode."""
        wanted = self._wanted
        return wanted is not None and not any(r.track in wanted for r in self.rungs)

    def set_wanted(self, tracks: frozenset[str] | None) -> None:
        """Encode only the rungs in ``tracks`` (the ones someone subscribed to; None:
        every rung). A rung nobody watches costs nothing, so a ladder on a host without
        spectators is free; a rung that gets a subscriber again starts at the IDR its
        subscription asks for. Safe to call from the event loop while another thread
        encodes: it swaps one reference."""
        self._wanted = tracks

    def request_keyframe(self) -> None:
        """A rung IDR soon (a new subscriber, a relay's nudge): the next frame, or the
        first one ``keyframe_min_interval_ms`` after the last ladder IDR. Safe to call
        from the event loop while another thread encodes: it only sets a flag."""
        self._requested = True

    def encode(
        self,
        frame: npt.NDArray[np.uint8] | VideoFrame,
        frame_id: int,
        pts_us: int,
        *,
        align: bool = False,
    ) -> tuple[list[RungFrame], list[str]]:
        """Encode one display-size frame on every rung: (the rungs' frames, the tracks
        of rungs that failed on it and are now gone). ``frame``: RGB, or the yuv420p
        frame the player's encoder converted (its ``last_yuv`` at the display size),
        which saves the conversion. ``align``: the player's track made this frame (or
        one the ladder was not given) an IDR."""
        self.stats.frames += 1
        idr = self._idr_due(pts_us, align)
        out: list[RungFrame] = []
        failed: list[str] = []
        wanted = self._wanted
        rungs = list(self.rungs)
        if wanted is not None:
            # Down to the smallest rung someone watches: the ones above it only scale.
            last = max((i for i, r in enumerate(rungs) if r.track in wanted), default=-1)
            rungs = rungs[: last + 1]
            if not rungs:
                self.stats.idle_frames += 1
                return out, failed
        source = self._display_yuv(frame)
        for rung in rungs:
            start = time.thread_time()
            if wanted is not None and rung.track not in wanted:
                source = rung.scaler.reformat(
                    source, width=rung.width, height=rung.height, interpolation=Interpolation.AREA
                )
                continue
            try:
                source = rung.scaler.reformat(
                    source, width=rung.width, height=rung.height, interpolation=Interpolation.AREA
                )
                encoded = rung.encoder.encode_yuv(source, frame_id, pts_us, force_keyframe=idr)
            except Exception:
                log.exception("ladder rung %s failed: dropped, the others go on", rung.track)
                self.rungs.remove(rung)
                self.stats.failed_rungs.append(rung.track)
                failed.append(rung.track)
                continue
            rung.frames += 1
            rung.cpu_s_total += time.thread_time() - start
            out.append(RungFrame(rung.track, encoded))
        return out, failed

    def _display_yuv(self, frame: npt.NDArray[np.uint8] | VideoFrame) -> VideoFrame:
        """The frame as yuv420p at the display size. Each rung is then scaled from the
        one above it (planes only, about 0.3 ms at 720p), where converting RGB inside
        each rung's encoder cost 2-3 ms a rung (``upcast bench ladder``)."""
        width, height = self.display.width, self.display.height
        if isinstance(frame, VideoFrame):
            if frame.format.name != "yuv420p" or (frame.width, frame.height) != (width, height):
                raise ValueError(
                    f"ladder frame must be yuv420p {width}x{height},"
                    f" got {frame.format.name} {frame.width}x{frame.height}"
                )
            return frame
        start = time.thread_time()
        converted = rgb_to_yuv420(self._convert, frame, width, height)
        self.stats.convert_cpu_s += time.thread_time() - start
        return converted

    def _idr_due(self, pts_us: int, aligned: bool) -> bool:
        last = self._last_idr_us
        periodic = last is None or pts_us - last >= self.gop_us - self._half_frame_us
        requested = self._requested and (last is None or pts_us - last >= self._min_interval_us)
        if not (periodic or aligned or requested):
            return False
        self._last_idr_us = pts_us
        self._requested = False
        self.stats.keyframes += 1
        if aligned:
            self.stats.aligned_keyframes += 1
        elif requested and not periodic:
            self.stats.requested_keyframes += 1
        return True
