"""The control API's models: what a control request may ask, and what a session answers.

Control rides MoQ (the lead's decision for issue 7): a request is a ``control``
frame on a viewer input track ``<broadcast>/input/<id>`` (the page's controls
and ``upcast control`` send the same thing), and the answer is the session's
``status`` track. A session may sit behind any moq-lite relay or CDN with no
inbound HTTP route to it, the browser already holds that connection, and the
relay's token model covers publishing there. ``docs/control.schema.json`` is
generated from these models (``python -m server.serve.control_schema``).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from server.config_types import CachePolicyName

STATUS_TRACK = "status"


class SessionControl(BaseModel):
    """What a control request may change; fields left out stay as they are."""

    upscaler: str | None = Field(
        default=None, max_length=64, description="upscaler method to switch the worker to"
    )
    scale: float | None = Field(
        default=None,
        ge=1.0,
        le=4.0,
        allow_inf_nan=False,
        description="display / render size; the game renders smaller from its next frame",
    )
    cache_policy: CachePolicyName | None = Field(
        default=None,
        max_length=64,
        description="layer-cache policy of the upscaler (unet_cached): delta_l, delta_h, "
        "budget, budget@DB, every_N, deepcache, motion, delta@SMAPE; refused for a method "
        "without a cache",
    )
    frame_generation: bool | None = Field(
        default=None,
        description="render every other frame and predict the rest from the last render "
        "(the stream keeps its frame rate; the game's render rate halves)",
    )
    encode_scale: float | None = Field(
        default=None,
        ge=1.0,
        le=4.0,
        allow_inf_nan=False,
        description="display / encoded size: the encoder scales the upscaled picture down "
        "(1: the display size); the viewers follow a new catalog and video track",
    )
    frame_rate: float | None = Field(
        default=None,
        ge=1.0,
        le=240.0,
        allow_inf_nan=False,
        description="frames per second the game renders and the stream carries, at most "
        "the session's configured rate; game time keeps its pace (fewer pictures show it)",
    )

    quality: Literal["auto", "fixed"] | None = Field(
        default=None,
        description="auto: the session chooses upscaler, scale, frame generation, encoded "
        "size and, last, the frame rate to hold its target with the best picture (and lets "
        "go of what earlier requests pinned); fixed: it keeps what it runs. A request that "
        "sets upscaler, scale, frame_generation, encode_scale or frame_rate pins that field "
        "under auto",
    )
    target_fps: float | None = Field(
        default=None,
        ge=1.0,
        le=240.0,
        allow_inf_nan=False,
        description="the frame rate auto holds (at most the session's configured rate); "
        "it lowers the frame rate below this only when no cheaper picture holds it",
    )
    preference: Literal["framerate", "resolution", "balanced"] | None = Field(
        default=None,
        description="what auto gives up first: framerate trades picture and lowers the "
        "frame rate only when the cheapest picture misses; resolution lowers the frame rate "
        "before the picture goes below the start; balanced lets the rate sag to 3/4 of the "
        "target and lowers it before the encoded size",
    )
    min_scale: float | None = Field(
        default=None, ge=1.0, le=4.0, allow_inf_nan=False, description="auto's lowest scale"
    )
    max_scale: float | None = Field(
        default=None, ge=1.0, le=4.0, allow_inf_nan=False, description="auto's highest scale"
    )
    methods: list[str] | None = Field(
        default=None,
        max_length=16,
        description="the upscalers auto may choose from (empty or absent: every method "
        "with speed-against-error figures)",
    )

    def requested(self) -> dict[str, object]:
        """The fields this request sets."""
        return self.model_dump(exclude_none=True, include=set(SessionControl.model_fields))


class ControlResult(BaseModel):
    """The outcome of one control request, as the status track reports it."""

    model_config = ConfigDict(extra="forbid")

    seq: int = Field(description="the request's seq (the sender picks it)")
    source: str = Field(description="the input broadcast that sent the request")
    accepted: bool
    reason: str | None = Field(default=None, description="why it was refused")
    requested: dict[str, object] = Field(default_factory=dict, description="what it asked")


class StatusRecord(BaseModel):
    """One frame of the ``status`` track: a new group per change, so a late
    subscriber gets the current state at once."""

    model_config = ConfigDict(extra="forbid")

    broadcast: str
    upscaler: str | None = Field(description="the method the worker runs now")
    scale: float | None = Field(description="display / render size now")
    frame_generation: bool | None = Field(
        default=None, description="whether every other frame is predicted now"
    )
    cache_policy: str | None = Field(
        default=None,
        description="the layer-cache policy the worker runs, as configured at start or "
        "reported at the last switch (null: the method has no cache)",
    )
    encoded: str | None = Field(
        default=None, description="the size the encoder sends now, WIDTHxHEIGHT"
    )
    quality: str | None = Field(
        default=None, description="auto (adaptive quality chooses) or fixed"
    )
    quality_reason: str | None = Field(
        default=None, description="why adaptive quality chose the current setting"
    )
    quality_at_floor: bool | None = Field(
        default=None,
        description="adaptive quality runs the cheapest setting it may and the frame rate "
        "still misses the target: the host cannot carry more (upcast serve admits no "
        "further session while one says so)",
    )
    quality_cores_short: float | None = Field(
        default=None,
        description="adaptive quality runs below the target frame rate and its next rate "
        "up lacks only this many idle cores (None: not waiting); upcast serve's other "
        "sessions at a higher rate leave it their idle cores, and free them when they can",
    )
    expected_psnr_db: float | None = Field(
        default=None,
        description="PSNR the current setting is expected to give against the game's "
        "ground truth (the speed-against-error table; a model figure, not a measurement)",
    )
    frame_rate: float | None = Field(
        default=None,
        description="frames per second the game renders now (below the configured rate "
        "when adaptive quality or a control request lowered it)",
    )
    fps: float = Field(description="frames per second the session publishes (rolling)")
    frames: int = Field(description="frames published since the session started")
    last_control: ControlResult | None = Field(
        default=None, description="the result of the last control request"
    )
