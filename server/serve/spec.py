"""What the supervisor tells one session process: a JSON file it reads at start."""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict

from server.stack.local import SessionConfig
from server.stream_config import StreamConfig


class SessionSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")

    index: int  # 1-based
    config: SessionConfig  # its name is unique per start: rings and sockets never collide
    stream: StreamConfig
    relay_url: str
    token: str | None = None  # the publisher's JWT when the supervisor minted one
    cert_hash_hex: str | None = None
    metrics_port: int = 0
    frame_tap_port: int = 0  # 0: off (server/serve/frame_tap.py)
    frame_tap_host: str = "127.0.0.1"
    status_path: Path  # the session writes its state here (atomically, twice a second)
