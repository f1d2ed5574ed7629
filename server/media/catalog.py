"""The hang catalog (``catalog.json`` track) of a game broadcast.

Mirrors the zod schema of @moq/hang 0.3.5 (``catalog/root.js``, ``video.js``,
``container.js``), which @moq/watch 0.4.6 validates every catalog against:

- root: loose object, ``video`` optional.
- ``video.renditions``: record of *track name* -> rendition config; we publish
  one rendition on track ``video``. ``video.display`` ({width, height}) optional.
- rendition: ``codec`` (string, required), ``container`` (for CMAF
  ``{"kind": "cmaf", "init": <base64 ftyp+moov>}``, both required: a cmaf
  container without ``init`` is rejected), optional integers (u53)
  ``codedWidth``, ``codedHeight``, ``bitrate``, ``jitter`` (ms), optional
  number ``framerate``, optional boolean ``optimizeForLatency``.
- ``description`` (hex avcC) is left out on purpose: for CMAF the player reads
  the avcC from ``init``, and one source of truth cannot disagree with itself.
- ``audio.renditions`` (``catalog/audio.js``): track name -> ``codec`` ("opus"),
  ``container`` (we use ``{"kind": "legacy"}``: each frame is a varint timestamp in
  microseconds then the raw Opus packet, the container @moq/watch prefers for audio),
  ``sampleRate`` and ``numberOfChannels`` (required), optional ``bitrate`` and
  ``jitter`` (ms, one frame: a packet is published the moment it is encoded). Opus
  needs no ``description``.
"""

from __future__ import annotations

import base64
import math
from typing import TYPE_CHECKING, Literal

from pydantic import BaseModel, ConfigDict, Field
from pydantic.alias_generators import to_camel

if TYPE_CHECKING:
    from server.media.encode import EncodedConfig, VideoEncoder

VIDEO_TRACK = "video"
AUDIO_TRACK = "audio"


class _CatalogModel(BaseModel):
    # Python names in snake_case, JSON in the schema's camelCase; unknown fields refused
    # so a typo cannot silently vanish from the catalog.
    model_config = ConfigDict(
        alias_generator=to_camel, populate_by_name=True, extra="forbid", frozen=True
    )


class CmafContainer(_CatalogModel):
    kind: Literal["cmaf"] = "cmaf"
    init: str  # base64 of the init segment (ftyp + moov)


class VideoRendition(_CatalogModel):
    codec: str  # WebCodecs codec string, e.g. avc1.42c01f
    container: CmafContainer
    coded_width: int = Field(ge=0)
    coded_height: int = Field(ge=0)
    framerate: float = Field(gt=0)
    bitrate: int | None = Field(default=None, ge=0)
    optimize_for_latency: bool = True
    # Longest wait (ms) between frames the player should expect: one frame interval,
    # as every frame is published the moment it is encoded.
    jitter: int | None = Field(default=None, ge=0)


class Display(_CatalogModel):
    width: int = Field(ge=0)
    height: int = Field(ge=0)


class VideoSection(_CatalogModel):
    renditions: dict[str, VideoRendition]
    display: Display | None = None


class LegacyContainer(_CatalogModel):
    kind: Literal["legacy"] = "legacy"


class AudioRendition(_CatalogModel):
    codec: str  # WebCodecs codec string: "opus"
    container: LegacyContainer
    sample_rate: int = Field(gt=0)
    number_of_channels: int = Field(gt=0)
    bitrate: int | None = Field(default=None, ge=0)
    jitter: int | None = Field(default=None, ge=0)


class AudioSection(_CatalogModel):
    renditions: dict[str, AudioRendition]


class Catalog(_CatalogModel):
    video: VideoSection
    audio: AudioSection | None = None

    def to_json(self) -> bytes:
        """The catalog frame: compact UTF-8 JSON, optional fields left out when unset."""
        return self.model_dump_json(by_alias=True, exclude_none=True).encode()


def video_rendition(config: EncodedConfig, fps: float, bitrate: int | None) -> VideoRendition:
    """The catalog entry of one encoded configuration."""
    return VideoRendition(
        codec=config.codec,
        container=CmafContainer(init=base64.b64encode(config.init_segment).decode("ascii")),
        coded_width=config.width,
        coded_height=config.height,
        framerate=fps,
        bitrate=bitrate,
        jitter=math.ceil(1000 / fps),
    )


def video_catalog(
    *,
    codec: str,
    init_segment: bytes,
    width: int,
    height: int,
    fps: float,
    bitrate: int | None = None,
    track: str = VIDEO_TRACK,
) -> Catalog:
    """A catalog with one CMAF H.264 rendition published on ``track``."""
    rendition = VideoRendition(
        codec=codec,
        container=CmafContainer(init=base64.b64encode(init_segment).decode("ascii")),
        coded_width=width,
        coded_height=height,
        framerate=fps,
        bitrate=bitrate,
        jitter=math.ceil(1000 / fps),
    )
    return Catalog(video=VideoSection(renditions={track: rendition}))


def audio_section(
    *, sample_rate: int, channels: int, bitrate: int, frame_ms: int, track: str = AUDIO_TRACK
) -> AudioSection:
    """One Opus rendition in the legacy container on ``track``."""
    rendition = AudioRendition(
        codec="opus",
        container=LegacyContainer(),
        sample_rate=sample_rate,
        number_of_channels=channels,
        bitrate=bitrate,
        jitter=frame_ms,
    )
    return AudioSection(renditions={track: rendition})


def catalog_for(
    encoder: VideoEncoder, track: str = VIDEO_TRACK, audio: AudioSection | None = None
) -> Catalog:
    """The catalog describing what ``encoder`` produces now (and the audio, if any)."""
    cfg = encoder.config
    return catalog_of(encoder.encoded_config, cfg.fps, cfg.target_bitrate, track, audio)


def catalog_of(
    config: EncodedConfig,
    fps: float,
    bitrate: int | None,
    track: str = VIDEO_TRACK,
    audio: AudioSection | None = None,
    rungs: dict[str, VideoRendition] | None = None,
) -> Catalog:
    """The catalog of one encoded configuration published on ``track``, then the
    rendition ladder's ``rungs`` (server/media/ladder.py) in order: a viewer that takes
    the first rendition (the player's page, older pages) plays the player's track."""
    renditions = {track: video_rendition(config, fps, bitrate)}
    renditions.update(rungs or {})
    return Catalog(video=VideoSection(renditions=renditions), audio=audio)


def video_track_name(generation: int) -> str:
    """The track of one encoded configuration: ``video``, then ``video.1``, ``video.2``...

    A new size is a new track, not new data on the old one: a viewer reads the catalog
    before it subscribes, so it never meets a frame its decoder was not configured for,
    and a relay never serves a group of the old size under the new name."""
    return VIDEO_TRACK if generation == 0 else f"{VIDEO_TRACK}.{generation}"


def is_video_track(name: str) -> bool:
    """Whether ``name`` is one of the names :func:`video_track_name` gives."""
    if name == VIDEO_TRACK:
        return True
    prefix, _, number = name.partition(".")
    return prefix == VIDEO_TRACK and number.isdigit() and not number.startswith("0")


# The rendition ladder's tracks (server/media/ladder.py): a size in the name, as a
# rung's size never changes.
RUNG_PREFIX = "video."


def rung_track_name(width: int, height: int) -> str:
    """``video.640x360``: the size in the name, as a rung's size never changes."""
    return f"{RUNG_PREFIX}{width}x{height}"


def is_rung_track(name: str) -> bool:
    """Whether ``name`` is a name :func:`rung_track_name` gives."""
    if not name.startswith(RUNG_PREFIX):
        return False
    width, sep, height = name[len(RUNG_PREFIX) :].partition("x")
    return bool(sep) and width.isdigit() and height.isdigit()
