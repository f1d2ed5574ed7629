"""H.264 encoder for the stream: RGB frames in, one CMAF fragment per frame out.

Tuned for latency the way low-latency game streamers (Sunshine, Selkies) tune
x264: ``zerolatency`` (no frame threads, no lookahead, no B-frames), a VBV one
frame deep (``vbv-bufsize = bitrate / fps``) so no frame can take more than
about one frame interval to transmit, scene cuts off (keyframes only when we
want a new MoQ group), IDRs on demand, and either periodic IDRs or periodic
intra refresh.

Periodic IDRs come every ``gop_seconds`` of stream time, whatever the frame rate: x264's
keyint counts frames at the configured rate, so a stream sent at a fraction of it (the
rate control's every other frame, a frame rate the quality controller lowered) would
otherwise stretch its groups, and every viewer that joins or skips a group, the time it
waits for a keyframe, by that fraction.

Intra refresh (``intra_refresh=True``) sweeps a column of intra blocks across
the picture once per ``gop_seconds`` instead of sending a whole IDR: every frame
costs about the same, so a lossy or narrow link sees no keyframe spike, and a
decoder that lost something is whole again after one sweep. IDRs then come only
at the start and on demand (a new subscriber, a player that lost a group).

The bitrate can change while streaming (:meth:`VideoEncoder.set_bitrate`, for
the session's rate control): libavcodec's libx264 wrapper reconfigures x264 when
the context's ``bit_rate`` changes between frames. The VBV ceiling stays the one
the encoder opened with (``bitrate``), so the rate can go down from it and back
up to it, not above.

The encoded size can change while streaming too (:meth:`VideoEncoder.set_encoded_size`,
for the session's quality control when nothing cheaper holds the frame rate): the
frames keep arriving at the display size and swscale scales them down in the pass
that converts them to YUV, so a smaller size costs no extra pass. A new size needs a
new SPS, so x264 is reopened: the next frame is an IDR, the stream gets a new init
segment (:class:`EncodedConfig`, on that frame) and the session publishes it as a new
video track in a new catalog. Timestamps run on across the switch; fragment numbers
(mfhd) start over at 1 on the new track, as a new encoder's do, so a viewer that joins
the new track some frames after its first counts nothing lost.

The fragment of a frame is returned by the call that encodes that frame: x264
in this mode returns every access unit immediately, and the fMP4 boxes are
written by :mod:`server.media.cmaf` without a muxer that would hold a frame back.

One instance per stream, used by one thread at a time (the asyncio pipeline
runs :meth:`VideoEncoder.encode` in an executor). PyAV drops the GIL inside
swscale and x264, so the event loop keeps running while a frame encodes.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from fractions import Fraction

import av
import numpy as np
import numpy.typing as npt
from av.codec.context import Flags
from av.video.codeccontext import VideoCodecContext
from av.video.frame import PictureType, VideoFrame
from av.video.reformatter import ColorRange, Colorspace, Interpolation, VideoReformatter

from server.frames.frame import Size
from server.media.cmaf import (
    MOOF_SIZE,
    AvcConfig,
    annexb_to_avcc,
    init_segment,
    media_fragment,
    split_annexb,
)
from server.media.filler import pad_sample

TIMESCALE = 1_000_000  # fMP4 and encoder clock in microseconds, so pts_us is written as-is

# Reference point for the default bitrate: 6 Mbit/s at 1280x720, 60 fps.
_REFERENCE_BITS_PER_PIXEL_FRAME = 6_000_000 / (1280 * 720 * 60)

# The lowest rate set_bitrate goes to: below this x264 at its highest QP still
# overshoots at 360p, and the picture is no longer worth sending.
MIN_BITRATE = 100_000

# libavutil AVColorSpace / primaries / transfer / range codes for BT.709 limited range.
_BT709 = 1
_RANGE_MPEG = 1


def default_bitrate(width: int, height: int, fps: float) -> int:
    """Bits per second scaled with pixels per second from 6 Mbit/s at 720p60."""
    return round(_REFERENCE_BITS_PER_PIXEL_FRAME * width * height * fps)


def encoded_size(display: Size, scale: float) -> tuple[int, int]:
    """The encoded size for ``display`` / ``scale`` (scale >= 1): even, rounded down,
    and at least 16x16."""
    if not (math.isfinite(scale) and scale >= 1.0):
        raise ValueError(f"encode scale must be a finite number >= 1, got {scale}")
    width = max(16, int(display.width / scale) // 2 * 2)
    height = max(16, int(display.height / scale) // 2 * 2)
    return min(width, display.width), min(height, display.height)


@dataclass(frozen=True)
class EncoderConfig:
    """Encoder settings; the constructor checks them and names the bad field."""

    width: int
    height: int
    fps: float = 60.0
    bitrate: int | None = None  # bits/s; None: default_bitrate(width, height, fps)
    preset: str = "ultrafast"
    gop_seconds: float = 2.0  # periodic IDR interval (with intra_refresh: the sweep period)
    vbv_frames: float = 1.0  # VBV buffer in frame intervals (1 = one-frame VBV)
    keyframe_min_interval_ms: float = 250.0  # no forced IDR sooner than this after any IDR
    threads: int = 0  # x264 threads, 0 = x264 chooses (sliced threads under zerolatency)
    convert_threads: int = 1  # swscale slice threads for RGB->YUV (the game shares the cores)
    intra_refresh: bool = False  # refresh sweeps instead of periodic IDRs (see the module doc)

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if value <= 0 or value % 2:
                raise ValueError(
                    f"{name} must be a positive even number for yuv420p (x264), got {value};"
                    " pad or crop the frame to an even size"
                )
        if self.fps <= 0:
            raise ValueError(f"fps must be positive, got {self.fps}")
        if self.bitrate is not None and self.bitrate < 10_000:
            raise ValueError(f"bitrate must be at least 10000 bit/s, got {self.bitrate}")
        if self.gop_seconds <= 0:
            raise ValueError(f"gop_seconds must be positive, got {self.gop_seconds}")
        if self.vbv_frames <= 0:
            raise ValueError(f"vbv_frames must be positive, got {self.vbv_frames}")
        if self.keyframe_min_interval_ms < 0:
            raise ValueError(
                f"keyframe_min_interval_ms must be >= 0, got {self.keyframe_min_interval_ms}"
            )
        if self.threads < 0:
            raise ValueError(f"threads must be >= 0, got {self.threads}")
        if self.convert_threads < 1:
            raise ValueError(f"convert_threads must be >= 1, got {self.convert_threads}")
        if self.preset not in _X264_PRESETS:
            raise ValueError(
                f"preset must be one of {', '.join(_X264_PRESETS)}, got {self.preset!r}"
            )

    @property
    def target_bitrate(self) -> int:
        return self.bitrate or default_bitrate(self.width, self.height, self.fps)

    @property
    def gop_frames(self) -> int:
        return max(1, round(self.gop_seconds * self.fps))

    @property
    def frame_duration_us(self) -> int:
        return round(1e6 / self.fps)


_X264_PRESETS = (
    "ultrafast",
    "superfast",
    "veryfast",
    "faster",
    "fast",
    "medium",
    "slow",
    "slower",
    "veryslow",
    "placebo",
)


@dataclass(frozen=True)
class EncodedConfig:
    """What a decoder needs for the frames from one IDR on: a new one per size change."""

    generation: int  # 0 for the size the encoder opened with, +1 per change
    width: int
    height: int
    codec: str  # WebCodecs codec string of the SPS
    init_segment: bytes  # ftyp + moov with this SPS/PPS


@dataclass(frozen=True)
class EncodedFrame:
    """One encoded frame: a complete CMAF fragment (moof + mdat), one MoQ frame."""

    frame_id: int
    pts_us: int
    keyframe: bool
    fragment: bytes
    encode_ms: float  # whole call on this thread: RGB->YUV + x264 + boxing
    convert_ms: float  # of which RGB->YUV420 (swscale)
    x264_ms: float  # of which x264
    # The size the session asked every frame to reach while it probes the link (0: not
    # probing), and how many bytes of filler data this frame carries to reach it.
    padded_to: int = 0
    filler_bytes: int = 0
    # Set on the first frame (an IDR) of a new encoded size: publish it before the frame.
    new_config: EncodedConfig | None = None


class VideoEncoder:
    """libx264 via PyAV, producing CMAF fragments with zero frames of delay."""

    def __init__(self, config: EncoderConfig, encoded: tuple[int, int] | None = None) -> None:
        """``encoded``: the (width, height) to encode at from the first frame, when smaller
        than the input's (``config.width`` x ``config.height``): the frames are scaled
        down in the YUV conversion pass, as after :meth:`set_encoded_size`. A rendition
        ladder's rungs open this way, so their init segment is known before any frame."""
        self.config = config
        width, height = encoded or (config.width, config.height)
        opened = config
        if encoded is not None:
            _check_encoded_size(config, width, height)
            opened = replace(config, width=width, height=height, bitrate=config.target_bitrate)
        self._codec = _open_x264(opened)
        extradata = self._codec.extradata
        if not extradata:
            raise RuntimeError("libx264 returned no global header (SPS/PPS)")
        # One reformatter for the stream: it keeps its swscale context, which a fresh
        # frame.reformat() would rebuild for every frame (about 1 ms at 360p).
        self._reformatter = VideoReformatter()
        self.avc = AvcConfig.from_annexb(extradata)
        self.init_segment = init_segment(width, height, TIMESCALE, self.avc)
        self.encoded_config = EncodedConfig(
            0, width, height, self.avc.codec_string(), self.init_segment
        )
        self._pending_size: tuple[int, int] | None = None
        # The last frame x264 was given (yuv420p at the encoded size). x264 copies its
        # input, so another thread may read it afterwards: a rendition ladder scales its
        # rungs from it instead of converting the RGB frame a second time.
        self.last_yuv: VideoFrame | None = None
        self.size_changes = 0
        self._sequence = 0
        self._last_pts_us: int | None = None
        self._keyframe_requested = False
        self._last_keyframe_pts_us: int | None = None
        self._last_idr_pts_us: int | None = None  # any IDR, for the periodic ones
        self.periodic_keyframes = 0  # forced by stream time (see the module doc)
        self._bitrate = config.target_bitrate
        self._pending_bitrate: int | None = None
        self._min_fragment_bytes = 0
        self.bitrate_changes = 0
        self.frames_in = 0
        self.fragments_out = 0
        self.forced_keyframes = 0

    def codec_string(self) -> str:
        """WebCodecs/RFC 6381 codec string from the SPS, e.g. ``avc1.42c01f``."""
        return self.avc.codec_string()

    def request_keyframe(self) -> None:
        """Make a coming frame an IDR: the next one, or, if an IDR (periodic or forced)
        was made less than ``keyframe_min_interval_ms`` of stream time ago, the first
        one after that interval.

        A storm of requests (many viewers joining, a client retrying) thus costs at
        most one IDR per interval, and no request is lost. Safe to call from the event
        loop while another thread encodes: it only sets a flag.
        """
        self._keyframe_requested = True

    @property
    def bitrate(self) -> int:
        """The bitrate x264 aims at now (bit/s), after any :meth:`set_bitrate` applied."""
        return self._pending_bitrate or self._bitrate

    def set_bitrate(self, bits_per_second: int) -> int:
        """Aim at a new bitrate from the next frame on; returns the rate that will be
        used: clamped to ``MIN_BITRATE`` .. the configured bitrate (the VBV ceiling;
        it wins where it is lower than ``MIN_BITRATE``).

        Safe to call from the event loop while another thread encodes: the encoding
        thread applies it before its next frame.
        """
        rate = min(self.config.target_bitrate, max(MIN_BITRATE, int(bits_per_second)))
        self._pending_bitrate = rate
        return rate

    @property
    def encoded_size(self) -> tuple[int, int]:
        """(width, height) of the frames x264 encodes now (the input size until a change)."""
        cfg = self.encoded_config
        return cfg.width, cfg.height

    def set_encoded_size(self, width: int, height: int) -> None:
        """Encode at ``width`` x ``height`` from the next frame on (that frame an IDR
        with a new :class:`EncodedConfig`); the input size is the input's size again.

        The frames still arrive at the input size and are scaled down while converted.
        A size no larger than the input, even and at least 16x16 (what x264 and the
        browsers' decoders take), or ValueError naming it. Asking for the size already
        encoded changes nothing. Safe to call from the event loop while another thread
        encodes: the encoding thread applies it before its next frame.
        """
        _check_encoded_size(self.config, width, height)
        self._pending_size = (width, height)

    def pad_frames_to(self, fragment_bytes: int) -> None:
        """Make every coming fragment at least ``fragment_bytes`` long with filler data
        (server/media/filler.py), 0 to stop: the session's link probe. Safe to call from
        the event loop while another thread encodes: it only sets a number."""
        self._min_fragment_bytes = max(0, int(fragment_bytes))

    def encode(
        self,
        rgb: npt.NDArray[np.uint8],
        frame_id: int,
        pts_us: int,
        *,
        force_keyframe: bool = False,
    ) -> EncodedFrame:
        """Encode one (H, W, 3) uint8 RGB frame; ``pts_us`` must increase.

        ``force_keyframe``: make this frame an IDR whatever the cooldown of
        :meth:`request_keyframe` (a rendition ladder keeps its rungs' IDRs on the same
        frames this way). The array may be a read-only view of shared memory; it is
        only read, and only during this call.
        """
        cfg = self.config
        if rgb.shape != (cfg.height, cfg.width, 3) or rgb.dtype != np.uint8:
            raise ValueError(
                f"frame must be uint8 ({cfg.height}, {cfg.width}, 3), got {rgb.dtype} {rgb.shape}"
            )
        return self._encode(lambda: self._to_yuv(rgb), frame_id, pts_us, force_keyframe)

    def encode_yuv(
        self, yuv: VideoFrame, frame_id: int, pts_us: int, *, force_keyframe: bool = False
    ) -> EncodedFrame:
        """Encode a frame already converted: yuv420p, BT.709 limited range, at the
        encoded size (a rendition ladder converts the display frame once and scales
        the planes down rung by rung; see server/media/ladder.py). Else as :meth:`encode`."""

        def checked() -> VideoFrame:
            if yuv.format.name != "yuv420p" or (yuv.width, yuv.height) != self.encoded_size:
                width, height = self.encoded_size
                raise ValueError(
                    f"frame must be yuv420p {width}x{height},"
                    f" got {yuv.format.name} {yuv.width}x{yuv.height}"
                )
            return yuv

        return self._encode(checked, frame_id, pts_us, force_keyframe)

    def _encode(
        self, convert: Callable[[], VideoFrame], frame_id: int, pts_us: int, force_keyframe: bool
    ) -> EncodedFrame:
        start = time.perf_counter_ns()
        cfg = self.config
        if self._last_pts_us is not None and pts_us <= self._last_pts_us:
            raise ValueError(f"pts_us must increase: {pts_us} after {self._last_pts_us}")
        self._last_pts_us = pts_us
        self.frames_in += 1

        pending = self._pending_bitrate
        if pending is not None:
            self._pending_bitrate = None
            if pending != self._bitrate:
                self._codec.bit_rate = pending  # libx264 reconfigures before this frame
                self._bitrate = pending
                self.bitrate_changes += 1

        new_config = self._take_size_change()

        t_convert = time.perf_counter_ns()
        yuv = convert()
        self.last_yuv = yuv
        t_x264 = time.perf_counter_ns()
        yuv.pts = pts_us
        forced = self._take_keyframe_request(pts_us) or force_keyframe
        periodic = not forced and self._periodic_idr_due(pts_us)
        if forced or periodic:
            yuv.pict_type = PictureType.I
        packets = self._codec.encode(yuv)
        t_box = time.perf_counter_ns()
        # zerolatency + no B-frames + no lookahead: exactly one packet per frame in.
        if len(packets) != 1:
            raise RuntimeError(f"x264 returned {len(packets)} packets for one frame (delay?)")
        packet = packets[0]
        annexb = bytes(packet)
        # An IDR, not the packet's key flag: under intra refresh x264 flags the first
        # frame of each sweep as a key (a recovery point), which a decoder cannot
        # start from; only an IDR may open a MoQ group.
        keyframe = packet.is_keyframe and _has_idr(annexb)
        if keyframe:
            # Any IDR serves a pending request and restarts the cooldown.
            self._keyframe_requested = False
            self._last_keyframe_pts_us = pts_us
            self._last_idr_pts_us = pts_us
        if forced:
            self.forced_keyframes += 1
        if periodic and keyframe:
            self.periodic_keyframes += 1
        if new_config is not None:
            if not keyframe:
                raise RuntimeError("x264 reopened at a new size but its first frame is no IDR")
            # Nobody subscribes to the new track before its catalog went out, so this IDR
            # reaches no viewer: the first request for the new track is served at once,
            # not after the cooldown this IDR would start (measured: 250-300 ms freezes).
            self._last_keyframe_pts_us = None

        self._sequence += 1
        floor = self._min_fragment_bytes
        sample = annexb_to_avcc(annexb)
        padded = pad_sample(sample, floor - MOOF_SIZE - 8) if floor else sample
        fragment = media_fragment(self._sequence, pts_us, cfg.frame_duration_us, padded, keyframe)
        self.fragments_out += 1
        end = time.perf_counter_ns()
        return EncodedFrame(
            frame_id=frame_id,
            pts_us=pts_us,
            keyframe=keyframe,
            fragment=fragment,
            encode_ms=(end - start) / 1e6,
            convert_ms=(t_x264 - t_convert) / 1e6,
            x264_ms=(t_box - t_x264) / 1e6,
            padded_to=floor,
            filler_bytes=len(padded) - len(sample),
            new_config=new_config,
        )

    def _take_size_change(self) -> EncodedConfig | None:
        size = self._pending_size
        if size is None:
            return None
        self._pending_size = None
        if size == self.encoded_size:
            return None
        width, height = size
        # The VBV ceiling stays the one the encoder opened with and the rate stays the
        # one the rate control chose: the link did not change, only the picture's size.
        reopened = replace(
            self.config, width=width, height=height, bitrate=self.config.target_bitrate
        )
        codec = _open_x264(reopened)
        codec.bit_rate = self._bitrate
        extradata = codec.extradata
        if not extradata:
            raise RuntimeError("libx264 returned no global header (SPS/PPS)")
        self._codec = codec
        self.avc = AvcConfig.from_annexb(extradata)
        self.init_segment = init_segment(width, height, TIMESCALE, self.avc)
        self.encoded_config = EncodedConfig(
            self.encoded_config.generation + 1,
            width,
            height,
            self.avc.codec_string(),
            self.init_segment,
        )
        # A fresh x264 starts with an IDR: the switch serves any pending request.
        self._keyframe_requested = False
        self._sequence = 0  # a new track: its fragments count from 1
        self.size_changes += 1
        return self.encoded_config

    def _periodic_idr_due(self, pts_us: int) -> bool:
        """A GOP of stream time has passed since the last IDR (half a frame early, so at
        the configured rate x264's own keyint and this pick the same frame)."""
        cfg = self.config
        last = self._last_idr_pts_us
        if cfg.intra_refresh or last is None:
            return False
        return pts_us - last >= cfg.gop_seconds * 1e6 - cfg.frame_duration_us / 2

    def _take_keyframe_request(self, pts_us: int) -> bool:
        if not self._keyframe_requested:
            return False
        last = self._last_keyframe_pts_us
        if last is not None and pts_us - last < self.config.keyframe_min_interval_ms * 1000:
            return False  # stays requested: served by the first frame after the interval
        self._keyframe_requested = False
        return True

    def _to_yuv(self, rgb: npt.NDArray[np.uint8]) -> VideoFrame:
        width, height = self.encoded_size
        return rgb_to_yuv420(self._reformatter, rgb, width, height, self.config.convert_threads)


def rgb_to_yuv420(
    reformatter: VideoReformatter,
    rgb: npt.NDArray[np.uint8],
    width: int,
    height: int,
    threads: int = 1,
) -> VideoFrame:
    """An (H, W, 3) uint8 RGB array as a yuv420p frame of ``width`` x ``height``, BT.709
    limited range (the VUI written into the SPS, so the browser converts back with the
    same matrix). ``reformatter`` keeps its swscale context between calls."""
    # from_numpy_buffer wraps the array's memory (no copy); padded rows (a crop)
    # become the frame's linesize. Only pixel-strided views need a copy.
    if rgb.strides[1:] == (3, 1):
        frame = VideoFrame.from_numpy_buffer(rgb, format="rgb24")
    else:
        frame = VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
    scaled = (width, height) != (rgb.shape[1], rgb.shape[0])
    return reformatter.reformat(
        frame,
        width=width,
        height=height,
        # Area averaging when scaling down: no aliasing of thin detail.
        interpolation=Interpolation.AREA if scaled else None,
        format="yuv420p",
        src_colorspace=Colorspace.ITU709,
        dst_colorspace=Colorspace.ITU709,
        dst_color_range=ColorRange.MPEG,
        threads=threads,
    )


def _check_encoded_size(cfg: EncoderConfig, width: int, height: int) -> None:
    if not (16 <= width <= cfg.width and 16 <= height <= cfg.height):
        raise ValueError(
            f"encoded size {width}x{height} must lie within 16x16 .. the input's"
            f" {cfg.width}x{cfg.height}"
        )
    if width % 2 or height % 2:
        raise ValueError(f"encoded size {width}x{height} must be even for yuv420p (x264)")


_NAL_IDR = 5


def _has_idr(annexb: bytes) -> bool:
    return any(nal and nal[0] & 0x1F == _NAL_IDR for nal in split_annexb(annexb))


def _open_x264(cfg: EncoderConfig) -> VideoCodecContext:
    codec = av.CodecContext.create("libx264", "w")
    codec.width = cfg.width
    codec.height = cfg.height
    codec.pix_fmt = "yuv420p"
    codec.time_base = Fraction(1, TIMESCALE)
    codec.framerate = Fraction(cfg.fps).limit_denominator(1001)
    # SPS/PPS once in extradata (for avcC), not repeated in every IDR.
    codec.flags |= Flags.global_header
    codec.thread_count = cfg.threads
    codec.colorspace = _BT709
    codec.color_primaries = _BT709
    codec.color_trc = _BT709
    codec.color_range = _RANGE_MPEG
    # The rate through the context (not x264-params): libavcodec compares the
    # context's bit_rate with x264's before each frame and reconfigures x264 when
    # it changed, which is how set_bitrate works while streaming.
    codec.bit_rate = cfg.target_bitrate
    vbv_bits = max(1000, round(cfg.target_bitrate * cfg.vbv_frames / cfg.fps))
    params: dict[str, int] = {
        "keyint": cfg.gop_frames,
        "scenecut": 0,  # IDRs only when we decide: each one starts a MoQ group
        "bframes": 0,
        "rc-lookahead": 0,
        "sync-lookahead": 0,
    }
    if cfg.intra_refresh:
        params["intra-refresh"] = 1  # keyint is then the sweep's period, not an IDR's
    codec.options = {
        "preset": cfg.preset,
        "tune": "zerolatency",
        "forced-idr": "1",  # pict_type I -> IDR, not a recovery-point I-frame
        "maxrate": str(cfg.target_bitrate),
        "bufsize": str(vbv_bits),
        "x264-params": ":".join(f"{k}={v}" for k, v in params.items()),
    }
    codec.open()
    return codec
