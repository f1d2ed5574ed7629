"""``upcast serve --config FILE``: per-session overrides, validated with errors that
name the session and the field.

The file is JSON (a list, or ``{"sessions": [...]}``) or TOML (``[[sessions]]``
tables). Each entry overrides the command-line session flags for one session;
entry ``i`` is session ``i + 1``.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from server.config_types import CachePolicyName, PredictorName, SizeText, UpscalerName
from server.stack.local import SessionConfig
from server.stream_config import StreamConfig


class ConfigFileError(ValueError):
    """The config file is unreadable or invalid; the message names session and field."""


class SessionOverride(BaseModel):
    """One session's overrides of the command-line flags (all optional)."""

    model_config = ConfigDict(extra="forbid")

    broadcast: str | None = Field(default=None, description="broadcast name (default: prefix-i)")
    scene: str | None = Field(default=None, description="scene preset")
    render_size: SizeText | None = Field(default=None, description="render size WIDTHxHEIGHT")
    display_size: SizeText | None = Field(default=None, description="display size WIDTHxHEIGHT")
    fps: float | None = Field(default=None, gt=0, le=240, description="game and stream fps")
    upscaler: UpscalerName | None = Field(default=None, description="initial upscaler")
    frame_generation: bool | None = Field(
        default=None, description="start with frame generation on (renders every other frame)"
    )
    predictor: PredictorName | None = Field(default=None, description="frame predictor")
    cache_policy: CachePolicyName | None = Field(
        default=None, description="layer-cache policy of unet_cached"
    )
    seed: int | None = Field(default=None, description="scene seed")
    source: Literal["game", "x11"] | None = Field(
        default=None, description="game (built-in renderer) or x11 (a real application)"
    )
    app: str | None = Field(default=None, description="x11: the application's command line")
    app_exit: Literal["stop", "restart"] | None = Field(
        default=None, description="x11: stop the session or restart the application when it exits"
    )
    x11_display: str | None = Field(
        default=None, description="x11: capture this X server (:N) instead of a new Xvfb"
    )
    gamepad: dict[str, str] | None = Field(
        default=None, description='gamepad -> keys map, e.g. {"button:0": "z"}'
    )
    bitrate_kbps: int | None = Field(default=None, description="video bitrate")
    gop_seconds: float | None = Field(default=None, description="keyframe interval (seconds)")


def _entries(path: Path) -> list[Any]:
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigFileError(f"cannot read {path}: {exc}") from None
    try:
        data: Any = tomllib.loads(text) if path.suffix == ".toml" else json.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as exc:
        kind = "TOML" if path.suffix == ".toml" else "JSON"
        raise ConfigFileError(f"{path} is not valid {kind}: {exc}") from None
    if isinstance(data, dict) and set(data) == {"sessions"}:
        data = data["sessions"]
    if not isinstance(data, list):
        raise ConfigFileError(f"{path}: expected a list of sessions (or a 'sessions' key)")
    return data


def _problem(index: int, exc: ValidationError) -> str:
    lines = [f"session {index}:"]
    for err in exc.errors(include_url=False):
        field = ".".join(str(p) for p in err["loc"]) or "(entry)"
        lines.append(f"  {field}: {err['msg']}")
    return "\n".join(lines)


def load_overrides(path: Path) -> list[SessionOverride]:
    problems: list[str] = []
    out: list[SessionOverride] = []
    for i, entry in enumerate(_entries(path), start=1):
        try:
            out.append(SessionOverride.model_validate(entry))
        except ValidationError as exc:
            problems.append(_problem(i, exc))
    if problems:
        raise ConfigFileError(f"invalid {path}:\n" + "\n".join(problems))
    return out


def session_configs(
    base: SessionConfig,
    stream: StreamConfig,
    overrides: list[SessionOverride],
    count: int,
    prefix: str,
) -> list[tuple[SessionConfig, StreamConfig]]:
    """The configs of ``count`` sessions: the flags, then each session's overrides."""
    if len(overrides) > count:
        raise ConfigFileError(f"the config file has {len(overrides)} sessions, --sessions {count}")
    problems: list[str] = []
    out: list[tuple[SessionConfig, StreamConfig]] = []
    base_fields = base.model_dump(exclude={"name"})
    stream_fields = stream.model_dump()
    for i in range(1, count + 1):
        o: dict[str, Any] = {}
        if i <= len(overrides):
            o = overrides[i - 1].model_dump(exclude_none=True)
        s_over = {k: o.pop(k) for k in ("broadcast", "bitrate_kbps", "gop_seconds") if k in o}
        s_over.setdefault("broadcast", f"{prefix}-{i}")
        try:
            config = SessionConfig.model_validate(base_fields | o)
            session_stream = StreamConfig.model_validate(stream_fields | s_over)
        except ValidationError as exc:
            problems.append(_problem(i, exc))
            continue
        out.append((config, session_stream))
    names = [s.broadcast for _, s in out]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        problems.append(f"broadcast names must differ between sessions: {', '.join(dupes)}")
    if problems:
        raise ConfigFileError("invalid session configuration:\n" + "\n".join(problems))
    return out
