"""Run-time control of a worker: JSON datagrams on a Unix socket.

A Unix datagram socket is reachable by name from any process and language,
needs no broker, and one message is one datagram (no framing). The worker
polls it between frames, so a control message never races a frame.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import tempfile
import uuid
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, Field, TypeAdapter, ValidationError

log = logging.getLogger(__name__)

MAX_MESSAGE_BYTES = 4096


class SetUpscaler(BaseModel):
    op: Literal["set_upscaler"] = "set_upscaler"
    name: str


class SetCachePolicy(BaseModel):
    """Run another layer-cache policy in the current method (upscalers/cache)."""

    op: Literal["set_cache_policy"] = "set_cache_policy"
    policy: str = Field(max_length=64)


class GetStatus(BaseModel):
    op: Literal["status"] = "status"


ControlMessage = Annotated[SetUpscaler | SetCachePolicy | GetStatus, Field(discriminator="op")]
_MESSAGE = TypeAdapter(ControlMessage)


def parse_message(data: bytes) -> SetUpscaler | SetCachePolicy | GetStatus:
    """Decode one datagram; raises ValueError naming what is wrong."""
    if len(data) > MAX_MESSAGE_BYTES:
        raise ValueError(f"control message of {len(data)} bytes exceeds {MAX_MESSAGE_BYTES}")
    try:
        return _MESSAGE.validate_json(data)
    except ValidationError as exc:
        raise ValueError(f"bad control message: {exc.errors(include_url=False)}") from None


class ControlServer:
    """The worker's end: bound socket, non-blocking receive, reply to the sender."""

    def __init__(self, path: Path) -> None:
        self.path = path
        path.unlink(missing_ok=True)
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.bind(str(path))
        self._sock.setblocking(False)

    def poll(self) -> list[tuple[bytes, str | None]]:
        """All datagrams waiting now, with the sender's address (None if unbound)."""
        out: list[tuple[bytes, str | None]] = []
        while True:
            try:
                data, addr = self._sock.recvfrom(MAX_MESSAGE_BYTES + 1)
            except BlockingIOError:
                return out
            out.append((data, addr or None))

    def reply(self, addr: str | None, payload: dict[str, Any]) -> None:
        if not addr:
            return
        try:
            self._sock.sendto(json.dumps(payload).encode(), addr)
        except OSError as exc:  # the asker went away: nothing to do
            log.debug("control reply to %s failed: %s", addr, exc)

    def close(self) -> None:
        self._sock.close()
        self.path.unlink(missing_ok=True)


def send_control(path: Path, message: BaseModel, timeout_s: float = 2.0) -> dict[str, Any]:
    """Send one message and wait for the worker's JSON reply."""
    reply_path = Path(tempfile.gettempdir()) / f"upcast-ctl-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        sock.bind(str(reply_path))
        sock.settimeout(timeout_s)
        sock.sendto(message.model_dump_json().encode(), str(path))
        data = sock.recv(65536)
        result: dict[str, Any] = json.loads(data)
        return result
    except TimeoutError:
        raise TimeoutError(f"no reply from worker control socket {path} in {timeout_s}s") from None
    finally:
        sock.close()
        reply_path.unlink(missing_ok=True)
