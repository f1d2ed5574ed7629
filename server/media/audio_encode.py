"""Opus encoding with PyAV (libopus), one packet per 10 ms frame, no lookahead queue.

libopus returns each frame's packet from the same ``encode`` call (checked: packets
come out one for one), so a frame's packet exists as soon as the frame is encoded.
The ``lowdelay`` application keeps the codec's own delay at 2.5 ms (120 samples at
48 kHz, the pre-skip). A packet is stamped with its input frame's time, not libopus's
pre-skip-shifted pts (negative for the first packet, which a varint cannot carry):
the decoded sound plays 2.5 ms late, a constant well inside any sync tolerance.

A packet travels in hang's ``legacy`` container: a QUIC varint of its timestamp in
microseconds, then the raw Opus packet (what @moq/watch's audio path reads).
"""

from __future__ import annotations

from dataclasses import dataclass

import av
import numpy as np
import numpy.typing as npt
from av.audio.codeccontext import AudioCodecContext

SAMPLE_RATE = 48_000
# 10 ms at 48 kHz. Why not Opus's usual 20 ms: a frame's first sample waits for the
# frame to fill before it can be sent, and the sound must reach the page before its
# picture (which is shown as soon as it is decoded); 10 ms more of margin was worth the
# few percent of bitrate. The catalog's ``jitter`` tells @moq/watch the frame length.
FRAME_SAMPLES = 480
CODEC = "opus"  # WebCodecs codec string


@dataclass(frozen=True)
class AudioEncoderConfig:
    sample_rate: int = SAMPLE_RATE
    channels: int = 1
    bitrate: int = 64_000
    frame_samples: int = FRAME_SAMPLES

    @property
    def frame_us(self) -> int:
        return self.frame_samples * 1_000_000 // self.sample_rate


@dataclass(frozen=True)
class AudioPacket:
    pts_us: int  # media clock of the packet's first decoded sample (the video's clock)
    duration_us: int
    payload: bytes  # one raw Opus packet


class OpusEncoder:
    def __init__(self, config: AudioEncoderConfig | None = None) -> None:
        self.config = config or AudioEncoderConfig()
        cfg = self.config
        context = av.CodecContext.create("libopus", "w")
        assert isinstance(context, AudioCodecContext)
        context.sample_rate = cfg.sample_rate
        context.layout = "mono" if cfg.channels == 1 else "stereo"
        context.format = "flt"
        context.bit_rate = cfg.bitrate
        context.options = {
            "application": "lowdelay",
            "frame_duration": str(cfg.frame_samples * 1000 // cfg.sample_rate),
        }
        context.open()
        self._context = context
        self.frames = 0

    def encode(self, samples: npt.NDArray[np.float32], pts_samples: int) -> list[AudioPacket]:
        """Encode one frame of ``frame_samples`` mono samples whose first sample is at
        ``pts_samples`` on the media clock (samples since the clock's origin)."""
        cfg = self.config
        if samples.shape != (cfg.frame_samples,):
            raise ValueError(f"expected {cfg.frame_samples} samples, got {samples.shape}")
        planes = np.ascontiguousarray(np.tile(samples[None, :], (cfg.channels, 1)))
        # Packed float: (1, samples * channels), channel-interleaved.
        packed = planes.T.reshape(1, -1) if cfg.channels > 1 else planes
        frame = av.AudioFrame.from_ndarray(packed, format="flt", layout=self._context.layout.name)
        frame.sample_rate = cfg.sample_rate
        frame.pts = pts_samples
        self.frames += 1
        out = []
        for packet in self._context.encode(frame):
            duration = packet.duration or cfg.frame_samples
            out.append(
                AudioPacket(
                    pts_us=pts_samples * 1_000_000 // cfg.sample_rate,
                    duration_us=duration * 1_000_000 // cfg.sample_rate,
                    payload=bytes(packet),
                )
            )
        return out


def encode_varint(value: int) -> bytes:
    """QUIC variable-length integer (RFC 9000 16): hang's legacy timestamp prefix."""
    if value < 0:
        raise ValueError("varint must be non-negative")
    if value < 1 << 6:
        return value.to_bytes(1, "big")
    if value < 1 << 14:
        return (value | 0x4000).to_bytes(2, "big")
    if value < 1 << 30:
        return (value | 0x8000_0000).to_bytes(4, "big")
    if value < 1 << 62:
        return (value | 0xC000_0000_0000_0000).to_bytes(8, "big")
    raise ValueError("varint too large")


def legacy_frame(packet: AudioPacket) -> bytes:
    """The packet as a hang ``legacy`` frame: varint pts (us) + Opus packet."""
    return encode_varint(packet.pts_us) + packet.payload
