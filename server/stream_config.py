"""Streaming settings of ``upcast up`` (relay, broadcast, encoder), validated at the edge."""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

# The rendition ladder for spectators (server/media/ladder.py): rungs at the display
# size / each divisor, a group every DEFAULT_GOP_S.
DEFAULT_DIVISORS = (2, 4)
DEFAULT_GOP_S = 1.0
MAX_RUNGS = 4


def parse_divisors(text: str) -> tuple[int, ...]:
    """``"2,4"`` -> (2, 4); ``"off"``, ``"none"`` or ``""`` -> () (no ladder).

    ValueError naming the problem: not integers, a divisor under 2 (a rung the size of
    the player's track would only double its cost), repeats, more than MAX_RUNGS."""
    text = text.strip().lower()
    if text in ("", "off", "none"):
        return ()
    try:
        divisors = tuple(int(part) for part in text.split(","))
    except ValueError:
        raise ValueError(f"ladder must be divisors like 2,4 or 'off', got {text!r}") from None
    return check_divisors(divisors)


def check_divisors(divisors: Sequence[int]) -> tuple[int, ...]:
    """The divisors, checked (see :func:`parse_divisors`), largest rung first."""
    if any(d < 2 for d in divisors):
        raise ValueError(f"ladder divisors must be at least 2, got {list(divisors)}")
    if len(set(divisors)) != len(divisors):
        raise ValueError(f"ladder divisors must differ, got {list(divisors)}")
    if len(divisors) > MAX_RUNGS:
        raise ValueError(f"at most {MAX_RUNGS} ladder rungs, got {len(divisors)}")
    return tuple(sorted(divisors))


_BROADCAST = re.compile(r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*$")


class StreamConfig(BaseModel):
    """What ``upcast up`` streams and where; errors name the field."""

    model_config = ConfigDict(extra="forbid")

    host: str = Field(default="::", description="relay bind address (`::` = all, dual stack)")
    port: int = Field(default=4443, ge=1, le=65535, description="relay port, UDP (QUIC) and TCP")
    broadcast: str = Field(default="game", description="broadcast name of the game session")
    bitrate_kbps: int | None = Field(
        default=None,
        ge=100,
        le=200_000,
        description="video bitrate (default: 6 Mbit/s at 720p60, scaled)",
    )
    gop_seconds: float = Field(
        default=2.0,
        gt=0,
        le=60,
        description="periodic keyframe interval (with intra_refresh: the refresh sweep period)",
    )
    audio: bool = Field(default=True, description="publish the game's sound (Opus track `audio`)")
    rate_control: bool = Field(
        default=True,
        description="the bitrate follows the player's link (its feedback); the configured"
        " bitrate is the ceiling. Off: the bitrate stays fixed",
    )
    intra_refresh: bool = Field(
        default=True,
        description="refresh the picture in sweeps of intra blocks instead of periodic"
        " keyframes (no keyframe spikes on a narrow link); keyframes on demand",
    )
    ladder: list[int] = Field(
        default_factory=lambda: list(DEFAULT_DIVISORS),
        max_length=MAX_RUNGS,
        description="spectator renditions: the display size divided by each (>= 2, distinct);"
        " empty: the player's stream only",
    )
    quality: Literal["auto", "fixed"] = Field(
        default="auto",
        description="auto: upscaler, render scale, frame generation, encoded size and, last,"
        " the frame rate follow the host's load and the scene to hold the frame rate with"
        " the best picture; fixed: the settings stay as started",
    )
    quality_preference: Literal["framerate", "resolution", "balanced"] = Field(
        default="framerate",
        description="what auto gives up first: the picture, the frame rate only when the"
        " cheapest picture misses (framerate); the frame rate before the picture goes below"
        " the start (resolution); the rate sags to 3/4 of the target and is lowered before"
        " the encoded size (balanced)",
    )
    min_scale: float = Field(default=1.0, ge=1.0, le=4.0, description="auto's lowest render scale")
    max_scale: float = Field(default=4.0, ge=1.0, le=4.0, description="auto's highest render scale")
    quality_methods: list[str] = Field(
        default_factory=list,
        max_length=16,
        description="upscalers auto may choose from (empty: every method with figures)",
    )
    metrics_port: int | None = Field(
        default=None,
        ge=0,
        le=65535,
        description="session Prometheus port (default: port + 1; 0 = off)",
    )

    @field_validator("ladder")
    @classmethod
    def _ladder(cls, v: list[int]) -> list[int]:
        return list(check_divisors(v))

    @field_validator("broadcast")
    @classmethod
    def _broadcast(cls, v: str) -> str:
        if not _BROADCAST.match(v) or v.endswith("/input") or "/input/" in v:
            raise ValueError(
                f"broadcast {v!r} must be path segments of letters, digits, '_', '.', '-'"
                " joined by '/', and not contain an 'input' segment (viewers publish there)"
            )
        return v

    @model_validator(mode="after")
    def _scale_bounds(self) -> StreamConfig:
        if self.min_scale > self.max_scale:
            raise ValueError(f"min_scale {self.min_scale:g} is above max_scale {self.max_scale:g}")
        return self

    @property
    def bitrate_bps(self) -> int | None:
        """The encoder's bitrate in bit/s (None: its default, scaled by size and fps)."""
        return None if self.bitrate_kbps is None else self.bitrate_kbps * 1000

    @property
    def session_metrics_port(self) -> int:
        return self.port + 1 if self.metrics_port is None else self.metrics_port
