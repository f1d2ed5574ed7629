"""The local preview: ring U as an MJPEG stream, stats and controls over plain HTTP.

``upcast preview`` serves this page so a person can watch, steer and switch
upscalers without the streaming server (``upcast up`` runs the real one). It is deliberately
small: the standard library's threading HTTP server plus Pillow for JPEG.

One consumer thread owns ring U. It always takes the newest frame (never
waiting on or holding back the worker) and only JPEG-encodes it when somebody
watches (an MJPEG viewer or a snapshot request), at most ``max_fps`` times a
second, releasing the slot right after the encode. HTTP handler threads only
read the latest JPEG from a locked holder.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image
from pydantic import BaseModel, ConfigDict, ValidationError

from server.config_types import UpscalerName
from server.frames.ring import FrameRing
from server.frames.timing import STAGE_SPANS, Stage, span_ms
from server.game.input import InputMessage, send_input
from server.stack.preview_page import PAGE_HTML
from server.worker.control import GetStatus, SetUpscaler, send_control
from upscalers import registry

log = logging.getLogger(__name__)

MAX_BODY_BYTES = 4096
MAX_DRAIN_BYTES = 1 << 20  # larger refused bodies are not read: the connection closes
JPEG_QUALITY = 80
STATUS_CACHE_S = 1.0
STATUS_TIMEOUT_S = 0.5
CONTROL_TIMEOUT_S = 3.0
SNAPSHOT_WAIT_S = 2.0
FPS_WINDOW_S = 2.0
STAGE_WINDOW = 30  # frames averaged for the stage latencies
BOUNDARY = "upcastframe"
# Stages a frame has been through when the preview encodes it; later ones are
# the streaming server's and would always be missing here.
PREVIEW_SPANS = ("render", "ring_r_handoff", "upscale", "ring_u_handoff", "encode")


class ControlRequest(BaseModel):
    """``POST /control`` body."""

    model_config = ConfigDict(extra="forbid")

    upscaler: UpscalerName


class _RateMeter:
    """Events per second over a sliding window."""

    def __init__(self, window_s: float = FPS_WINDOW_S) -> None:
        self._window_s = window_s
        self._born = time.monotonic()
        self._events: deque[tuple[float, int]] = deque()

    def add(self, now: float, count: int = 1) -> None:
        if count > 0:
            self._events.append((now, count))
        self._trim(now)

    def _trim(self, now: float) -> None:
        while self._events and now - self._events[0][0] > self._window_s:
            self._events.popleft()

    def rate(self, now: float) -> float:
        self._trim(now)
        span = min(self._window_s, now - self._born)
        if span <= 0:
            return 0.0
        return sum(c for _, c in self._events) / span


class PreviewState:
    """Thread-safe holder of the latest JPEG and the figures shown in the overlay."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.jpeg: bytes | None = None
        self.jpeg_seq = 0  # +1 per encoded frame
        self.jpeg_frame_id: int | None = None
        self.frame_id: int | None = None  # newest frame seen on ring U
        self.frames_seen = 0
        self.viewers = 0
        self.snapshot_waiters = 0
        self.closed = False
        self._ring_fps = _RateMeter()
        self._preview_fps = _RateMeter()
        self._stages: dict[str, deque[float]] = {
            name: deque(maxlen=STAGE_WINDOW) for name in (*PREVIEW_SPANS, "total")
        }

    # Called with ``cond`` held by the consumer.
    def _record_stages(self, stamps: np.ndarray[Any, Any]) -> None:
        for name, start, end in STAGE_SPANS:
            if name in self._stages:
                value = span_ms(stamps, start, end)
                if value is not None:
                    self._stages[name].append(value)
        total = span_ms(stamps, Stage.RENDER_START, Stage.ENCODE_END)
        if total is not None:
            self._stages["total"].append(total)

    def wait_jpeg(self, after_seq: int, timeout_s: float) -> tuple[int, bytes | None]:
        """Wait until a JPEG newer than ``after_seq`` exists (or timeout/close)."""
        with self.cond:
            self.cond.wait_for(lambda: self.jpeg_seq != after_seq or self.closed, timeout_s)
            return self.jpeg_seq, self.jpeg

    def wanted(self) -> bool:
        with self.cond:
            return self.viewers > 0 or self.snapshot_waiters > 0

    def snapshot(self) -> dict[str, Any]:
        now = time.monotonic()
        with self.cond:
            stages = {
                name: round(sum(v) / len(v), 2) if v else None for name, v in self._stages.items()
            }
            return {
                "fps": round(self._ring_fps.rate(now), 2),
                "preview_fps": round(self._preview_fps.rate(now), 2),
                "frame_id": self.frame_id,
                "jpeg_frame_id": self.jpeg_frame_id,
                "frames_seen": self.frames_seen,
                "viewers": self.viewers,
                "stages_ms": stages,
            }


def _encode_jpeg(color: np.ndarray[Any, Any], quality: int) -> bytes:
    image = Image.fromarray(color, "RGB")
    out = io.BytesIO()
    image.save(out, "JPEG", quality=quality)
    return out.getvalue()


class _HTTPServer(ThreadingHTTPServer):
    daemon_threads = True
    request_queue_size = 16

    def __init__(self, host: str, port: int, preview: PreviewServer) -> None:
        self.address_family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.preview = preview
        super().__init__((host, port), _Handler)

    def server_bind(self) -> None:
        if self.address_family == socket.AF_INET6:
            # "::" also serves IPv4 where the system allows dual-stack sockets.
            with contextlib.suppress(OSError):  # a platform without dual stack
                self.socket.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 0)
        super().server_bind()

    def handle_error(self, request: Any, client_address: Any) -> None:
        log.warning("preview: error serving %s", client_address, exc_info=True)


class PreviewServer:
    """HTTP preview of ring U with stats, upscaler switching and input forwarding."""

    def __init__(
        self,
        ring_u: FrameRing,
        control_path: Path,
        input_path: Path,
        host: str = "127.0.0.1",
        port: int = 8080,
        max_fps: float = 30.0,
        *,
        jpeg_quality: int = JPEG_QUALITY,
        session_info: Callable[[], dict[str, Any]] | None = None,
        on_upscaler_set: Callable[[str], None] | None = None,
    ) -> None:
        if max_fps <= 0:
            raise ValueError(f"max_fps must be positive, got {max_fps}")
        self.ring_u = ring_u
        self.control_path = control_path
        self.input_path = input_path
        self.host = host
        self.port = port
        self.max_fps = max_fps
        self.jpeg_quality = jpeg_quality
        self.session_info = session_info
        # Told of every switch the worker accepted, so a restarted worker resumes it.
        self.on_upscaler_set = on_upscaler_set
        self.state = PreviewState()
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._httpd: _HTTPServer | None = None
        self._threads: list[threading.Thread] = []
        self._status_lock = threading.Lock()
        self._status: dict[str, Any] = {}
        self._status_at = -1e9

    # ----------------------------------------------------------------- lifecycle

    @property
    def bound_port(self) -> int:
        if self._httpd is None:
            return self.port
        return int(self._httpd.server_address[1])

    @property
    def url(self) -> str:
        """Where a browser on this machine opens the page."""
        host = self.host
        if host in ("", "0.0.0.0"):
            host = "127.0.0.1"
        elif host == "::":
            host = "::1"
        if ":" in host:
            host = f"[{host}]"
        return f"http://{host}:{self.bound_port}/"

    def start(self) -> None:
        """Bind (OSError if the port is taken) and start the HTTP and consumer threads."""
        self._httpd = _HTTPServer(self.host, self.port, self)
        self.ring_u.attach_as_consumer()
        self._threads = [
            threading.Thread(target=self._consume, name="preview-consumer", daemon=True),
            threading.Thread(
                target=self._httpd.serve_forever,
                kwargs={"poll_interval": 0.2},
                name="preview-http",
                daemon=True,
            ),
        ]
        for t in self._threads:
            t.start()
        log.info(
            "preview serving %s on %s (max %.0f fps, JPEG quality %d)",
            self.ring_u.name,
            self.url,
            self.max_fps,
            self.jpeg_quality,
        )

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        with self.state.cond:
            self.state.closed = True
            self.state.cond.notify_all()
        if self._httpd is not None:
            self._httpd.shutdown()
            self._httpd.server_close()
        for t in self._threads:
            t.join(5.0)
        self._threads = []
        self._httpd = None

    def __enter__(self) -> PreviewServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ consumer

    def _consume(self) -> None:
        state = self.state
        period = 1.0 / self.max_fps
        next_encode = 0.0
        last_committed = self.ring_u.counters().committed
        while not self._stop.is_set():
            try:
                wanted = state.wanted()
                now = time.monotonic()
                if wanted and now < next_encode:
                    self._stop.wait(next_encode - now)
                    continue
                if not wanted:
                    # Nobody watches: keep the figures fresh a few times a second only.
                    self._wake.wait(0.25)
                    self._wake.clear()
                    wanted = state.wanted()
                lease = self.ring_u.acquire_read(0.5, newest=True)
                committed = self.ring_u.counters().committed
                now = time.monotonic()
                with state.cond:
                    state._ring_fps.add(now, committed - last_committed)
                last_committed = committed
                if lease is None:
                    continue
                jpeg: bytes | None = None
                with lease:
                    stamps = np.array(lease.header["stamps"], dtype=np.int64)
                    frame_id = int(lease.header["frame_id"])
                    stamps[Stage.ENCODE_START] = (time.monotonic_ns(), time.time_ns())
                    if wanted:
                        next_encode = now + period
                        jpeg = _encode_jpeg(lease.planes["color"], self.jpeg_quality)
                        stamps[Stage.ENCODE_END] = (time.monotonic_ns(), time.time_ns())
                with state.cond:
                    state.frame_id = frame_id
                    state.frames_seen += 1
                    if jpeg is not None:
                        state.jpeg = jpeg
                        state.jpeg_seq += 1
                        state.jpeg_frame_id = frame_id
                        state._preview_fps.add(time.monotonic())
                        state._record_stages(stamps)
                        state.cond.notify_all()
            except Exception:
                log.exception("preview consumer error; continuing")
                self._stop.wait(0.5)

    def request_frame(self, timeout_s: float = SNAPSHOT_WAIT_S) -> bytes | None:
        """A JPEG encoded after this call (or the latest one if none comes in time)."""
        state = self.state
        with state.cond:
            seq = state.jpeg_seq
            state.snapshot_waiters += 1
        self._wake.set()
        try:
            with state.cond:
                state.cond.wait_for(lambda: state.jpeg_seq > seq or state.closed, timeout_s)
                return state.jpeg
        finally:
            with state.cond:
                state.snapshot_waiters -= 1

    # ------------------------------------------------------------------- worker

    def worker_status(self) -> dict[str, Any]:
        """The worker's GetStatus reply, cached for about a second."""
        with self._status_lock:
            now = time.monotonic()
            if now - self._status_at >= STATUS_CACHE_S:
                try:
                    self._status = send_control(self.control_path, GetStatus(), STATUS_TIMEOUT_S)
                except (OSError, TimeoutError, ValueError) as exc:
                    self._status = {"ok": False, "error": f"worker unreachable: {exc}"}
                self._status_at = time.monotonic()
            return dict(self._status)

    def set_upscaler(self, name: str) -> dict[str, Any]:
        reply = send_control(self.control_path, SetUpscaler(name=name), CONTROL_TIMEOUT_S)
        if reply.get("ok") and self.on_upscaler_set is not None:
            self.on_upscaler_set(name)
        with self._status_lock:
            self._status_at = -1e9  # the next /stats asks the worker again
        return reply

    def stats(self) -> dict[str, Any]:
        out = self.state.snapshot()
        worker = self.worker_status()
        out["upscaler"] = worker.get("upscaler")
        out["worker"] = worker
        out["upscalers"] = registry.available()
        out["max_fps"] = self.max_fps
        if self.session_info is not None:
            out["session"] = self.session_info()
        return out


class _BadRequest(Exception):
    def __init__(self, status: HTTPStatus, message: str, **extra: Any) -> None:
        super().__init__(message)
        self.status = status
        self.payload = {"error": message, **extra}


class _Handler(BaseHTTPRequestHandler):
    server: _HTTPServer
    server_version = "upcast-preview/0.1"
    protocol_version = "HTTP/1.1"
    timeout = 15.0  # a stalled client frees its thread

    @property
    def preview(self) -> PreviewServer:
        return self.server.preview

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("preview %s: %s", self.address_string(), format % args)

    # ------------------------------------------------------------------ replies

    def _send(self, status: HTTPStatus, body: bytes, content_type: str) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, status: HTTPStatus, payload: dict[str, Any]) -> None:
        self._send(status, json.dumps(payload).encode(), "application/json")

    def _refuse(self, exc: _BadRequest) -> None:
        log.warning(
            "preview: refused %s %s from %s: %s",
            self.command,
            self.path,
            self.client_address[0],
            exc,
        )
        self._json(exc.status, exc.payload)

    def _body(self) -> bytes:
        if "chunked" in self.headers.get("Transfer-Encoding", "").lower():
            self.close_connection = True
            raise _BadRequest(HTTPStatus.LENGTH_REQUIRED, "chunked bodies are not accepted")
        raw = self.headers.get("Content-Length")
        try:
            length = int(raw) if raw is not None else 0
        except ValueError:
            self.close_connection = True
            raise _BadRequest(HTTPStatus.BAD_REQUEST, "bad Content-Length") from None
        if length < 0:
            self.close_connection = True
            raise _BadRequest(HTTPStatus.BAD_REQUEST, "bad Content-Length")
        if length > MAX_BODY_BYTES:
            if length <= MAX_DRAIN_BYTES:
                # Read what was sent so the client sees the 413 rather than a reset.
                self.rfile.read(length)
            else:
                self.close_connection = True
            raise _BadRequest(
                HTTPStatus.REQUEST_ENTITY_TOO_LARGE,
                f"body of {length} bytes exceeds {MAX_BODY_BYTES}",
            )
        return self.rfile.read(length) if length else b""

    def _json_body(self) -> Any:
        body = self._body()
        try:
            return json.loads(body)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise _BadRequest(HTTPStatus.BAD_REQUEST, f"body is not JSON: {exc}") from None

    # ------------------------------------------------------------------- routes

    def do_HEAD(self) -> None:
        self.do_GET()

    def do_GET(self) -> None:
        path = self.path.split("?", 1)[0]
        if path in ("/", "/index.html"):
            self._send(HTTPStatus.OK, PAGE_HTML.encode(), "text/html; charset=utf-8")
        elif path == "/stream.mjpg":
            self._stream()
        elif path == "/snapshot.jpg":
            jpeg = self.preview.request_frame()
            if jpeg is None:
                self._send(
                    HTTPStatus.SERVICE_UNAVAILABLE,
                    b"no frame yet: the game and the upscaler worker are still starting\n",
                    "text/plain; charset=utf-8",
                )
            else:
                self._send(HTTPStatus.OK, jpeg, "image/jpeg")
        elif path == "/stats":
            self._json(HTTPStatus.OK, self.preview.stats())
        else:
            self._send(HTTPStatus.NOT_FOUND, b"not found\n", "text/plain; charset=utf-8")

    def do_POST(self) -> None:
        path = self.path.split("?", 1)[0]
        try:
            if path == "/control":
                self._post_control()
            elif path == "/input":
                self._post_input()
            else:
                self._body()  # drain it so keep-alive stays in sync
                raise _BadRequest(HTTPStatus.NOT_FOUND, f"no POST route {path}")
        except _BadRequest as exc:
            self._refuse(exc)

    def _post_control(self) -> None:
        allowed = registry.available()
        try:
            request = ControlRequest.model_validate(self._json_body())
        except ValidationError as exc:
            msgs = "; ".join(
                f"{'.'.join(str(p) for p in e['loc']) or 'body'}: {e['msg']}"
                for e in exc.errors(include_url=False)
            )
            raise _BadRequest(HTTPStatus.BAD_REQUEST, msgs, allowed=allowed) from None
        try:
            reply = self.preview.set_upscaler(request.upscaler)
        except (OSError, TimeoutError) as exc:
            log.warning("preview: upscaler switch to %s failed: %s", request.upscaler, exc)
            self._json(HTTPStatus.GATEWAY_TIMEOUT, {"error": f"worker did not answer: {exc}"})
            return
        if not reply.get("ok"):
            log.warning("preview: worker refused upscaler %s: %s", request.upscaler, reply)
            self._json(HTTPStatus.BAD_GATEWAY, {"error": reply.get("error", "worker refused")})
            return
        log.info("preview: upscaler switched to %s", reply.get("upscaler"))
        self._json(HTTPStatus.OK, {"ok": True, "upscaler": reply.get("upscaler")})

    def _post_input(self) -> None:
        try:
            message = InputMessage.model_validate(self._json_body())
        except ValidationError as exc:
            msgs = "; ".join(
                f"{'.'.join(str(p) for p in e['loc']) or 'body'}: {e['msg']}"
                for e in exc.errors(include_url=False)
            )
            raise _BadRequest(HTTPStatus.BAD_REQUEST, msgs) from None
        try:
            send_input(self.preview.input_path, message)
        except OSError as exc:
            self._json(HTTPStatus.SERVICE_UNAVAILABLE, {"error": f"game unreachable: {exc}"})
            return
        self._json(HTTPStatus.OK, {"ok": True})

    def _stream(self) -> None:
        preview = self.preview
        state = preview.state
        self.close_connection = True
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        if self.command == "HEAD":
            return
        with state.cond:
            state.viewers += 1
        preview._wake.set()
        seq = 0
        try:
            while True:
                new_seq, jpeg = state.wait_jpeg(seq, 1.0)
                if state.closed:
                    return
                if new_seq == seq or jpeg is None:
                    continue
                seq = new_seq
                self.wfile.write(
                    f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\n"
                    f"Content-Length: {len(jpeg)}\r\n\r\n".encode()
                )
                self.wfile.write(jpeg)
                self.wfile.write(b"\r\n")
                self.wfile.flush()
        except (ConnectionError, TimeoutError, OSError):
            return  # the viewer went away
        finally:
            with state.cond:
                state.viewers -= 1
