"""A local session: rings, the game process and the upscaler worker process.

Each part is its own OS process started from the ``upcast`` CLI, so the
worker shares nothing with the game but the ring names, exactly as an engine
written in another language would. The stack restarts a worker that dies; the
game keeps rendering meanwhile (ring R is real-time: it overwrites, never
waits).
"""

from __future__ import annotations

import logging
import os
import shlex
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from server.config_types import CachePolicyName, PredictorName, SizeText, UpscalerName
from server.frames.frame import Size
from server.frames.ring import SHM_DIR, FrameRing
from server.frames.ring_frames import create_display_ring, create_render_ring
from server.ops import orphan_guard
from server.session.gamepad_keys import GamepadKeyMap
from upscalers import registry
from upscalers.names import TEMPORAL_UPSCALERS, UPSCALERS

log = logging.getLogger(__name__)


# The game process's exit codes of source x11 besides the application's own: its X
# display died (server/game/x11/source.py), the source could not start (bad command,
# no Xvfb, no display: server/commands/game_x11.py). Not imported: those modules need
# the X11 libraries.
DISPLAY_GONE_CODE = 70
SOURCE_FAILED_CODE = 78


def _x11_end(code: int) -> str:
    if code == DISPLAY_GONE_CODE:
        return "the X display is gone; the session stops"
    if code == SOURCE_FAILED_CODE:
        return "the X11 source could not start (the game's log above says why)"
    return f"the application exited (code {code}); the session stops"


class SourceStopped(RuntimeError):
    """The session's source ended for good (an X11 application exited)."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


def color_only_upscalers() -> list[str]:
    return [m for m in UPSCALERS if m not in TEMPORAL_UPSCALERS]


class SessionConfig(BaseModel):
    """One game session; validated at start with errors that name the field."""

    model_config = ConfigDict(extra="forbid")

    scene: str = Field(default="default", description="scene preset of the reference game")
    render_size: SizeText = Field(default="640x360", description="game render size WIDTHxHEIGHT")
    display_size: SizeText = Field(default="1280x720", description="upscaled size WIDTHxHEIGHT")
    fps: float = Field(
        default=60.0,
        gt=0,
        le=240,
        description="game logic and stream frame rate (with frame generation the game "
        "renders every other frame and the worker predicts the rest)",
    )
    upscaler: UpscalerName = Field(default="bilinear", description="initial upscaler")
    frame_generation: bool = Field(
        default=False, description="start with frame generation on (switchable at run time)"
    )
    predictor: PredictorName = Field(
        default="mpe", description="frame predictor the worker uses for predicted frames"
    )
    cache_policy: CachePolicyName | None = Field(
        default=None,
        description="layer-cache policy of unet_cached (delta_l, delta_h, budget, budget@DB, "
        "every_N, deepcache, motion; None: delta_l); switchable at run time",
    )
    seed: int = Field(default=0, description="scene seed")
    source: Literal["game", "x11"] = Field(
        default="game",
        description="game: the built-in renderer; x11: an application on an X11 display, "
        "captured at render_size (colour only: spatial upscalers, no frame generation)",
    )
    app: str | None = Field(
        default=None,
        description="x11: the application to start, one shell-quoted command line",
    )
    app_exit: Literal["stop", "restart"] = Field(
        default="stop",
        description="x11: when the application exits, stop the session or restart it",
    )
    x11_display: str | None = Field(
        default=None, description="x11: capture this existing X server (:N) instead of a new Xvfb"
    )
    gamepad: GamepadKeyMap | None = Field(
        default=None,
        description='gamepad buttons and sticks -> keys, e.g. {"button:0": "z", '
        '"axis:0-": "arrowleft"} (None: the standard layout\'s default: d-pad and left '
        "stick = arrows, A space, B control, X shift, Y alt, start enter, back escape)",
    )
    game_threads: int = Field(default=1, ge=1, description="torch threads in the game")
    worker_threads: int = Field(
        default=1, ge=1, description="CPU threads in the worker (torch and numba's kernels)"
    )
    slots: int = Field(default=3, ge=2, le=16, description="slots per ring")
    name: str = Field(
        default_factory=lambda: f"upcast-{os.getpid()}-{uuid.uuid4().hex[:6]}",
        description="session name: prefix of its rings and sockets",
    )

    @field_validator("scene")
    @classmethod
    def _scene(cls, v: str) -> str:
        from server.game.render.scenes import SCENE_NAMES

        if v not in SCENE_NAMES:
            raise ValueError(f"unknown scene {v!r}; allowed: {', '.join(SCENE_NAMES)}")
        return v

    @model_validator(mode="after")
    def _source_fits(self) -> SessionConfig:
        if self.source == "game":
            for name in ("app", "x11_display"):
                if getattr(self, name) is not None:
                    raise ValueError(f"{name} applies to source 'x11' only (source is 'game')")
            return self
        if self.app is None and self.x11_display is None:
            raise ValueError("source 'x11' needs app (a program to start) or x11_display")
        if self.app is not None:
            try:
                if not shlex.split(self.app):
                    raise ValueError("app is empty")
            except ValueError as exc:
                raise ValueError(f"app {self.app!r} is not a command line: {exc}") from None
        if self.upscaler in TEMPORAL_UPSCALERS:
            raise ValueError(
                f"upscaler {self.upscaler!r} needs depth, motion and jitter, which source "
                f"'x11' does not give; use one of {', '.join(color_only_upscalers())}"
            )
        if self.frame_generation:
            raise ValueError("frame_generation needs depth and motion: not with source 'x11'")
        return self

    @model_validator(mode="after")
    def _render_not_larger(self) -> SessionConfig:
        r, d = Size.parse(self.render_size), Size.parse(self.display_size)
        if r.width > d.width or r.height > d.height:
            raise ValueError(f"render_size {r} is larger than display_size {d}")
        return self

    @property
    def scale(self) -> float:
        return Size.parse(self.display_size).width / Size.parse(self.render_size).width


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "server.cli", *args]


# glibc hands large frees back to the kernel at once, so every frame's big
# temporaries fault in fresh pages again (~3000 faults, ~1 ms per frame in the
# renderer). Keeping them in the heap bounds memory by the peak of one frame.
_CHILD_ENV = {"MALLOC_MMAP_THRESHOLD_": str(512 << 20), "MALLOC_TRIM_THRESHOLD_": str(1 << 30)}


def _child_env() -> dict[str, str]:
    return {**os.environ, **_CHILD_ENV}


def session_files(name: str) -> list[Path]:
    """Every file a session called ``name`` creates: its two rings and two sockets.
    ``upcast serve`` removes them after a session process was killed (no cleanup ran)."""
    tmp = Path(tempfile.gettempdir())
    return [
        SHM_DIR / f"{name}-r",
        SHM_DIR / f"{name}-u",
        tmp / f"{name}.ctl",
        tmp / f"{name}.input",
    ]


class LocalStack:
    """Owns the rings and the child processes of one session."""

    def __init__(
        self,
        config: SessionConfig,
        *,
        game_duration_s: float | None = None,
        metrics_ports: tuple[int, int] = (0, 0),
        app_sound: bool = False,
    ) -> None:
        """``metrics_ports``: the game's and the worker's Prometheus ports (0: off);
        ``app_sound``: source x11 gets a PulseAudio server for the program's sound (only
        worth running when the session streams audio)."""
        self.config = config
        self.game_metrics_port, self.worker_metrics_port = metrics_ports
        self.ring_r_name = f"{config.name}-r"
        self.ring_u_name = f"{config.name}-u"
        self.control_path = Path(tempfile.gettempdir()) / f"{config.name}.ctl"
        self.input_path = Path(tempfile.gettempdir()) / f"{config.name}.input"
        # source x11: the application's PulseAudio server (socket ``native`` inside).
        self.pulse_dir = Path(tempfile.gettempdir()) / f"{config.name}.pulse"
        self.app_sound = app_sound
        self._game_duration_s = game_duration_s
        self.ring_r: FrameRing | None = None
        self.ring_u: FrameRing | None = None
        self.game: subprocess.Popen[bytes] | None = None
        self.worker: subprocess.Popen[bytes] | None = None
        self.worker_restarts = 0
        # The method the worker runs now; a restarted worker starts with it.
        self.upscaler = config.upscaler

    def start(self) -> None:
        c = self.config
        display = Size.parse(c.display_size)
        # Removed, and the children ended, by this process's reaper should it die
        # without stop() (SIGKILL): registered before they exist.
        for path in session_files(c.name):
            orphan_guard.watch_path(path)
        # Ring R holds up to display size, so the render scale can change without
        # recreating it.
        self.ring_r = create_render_ring(self.ring_r_name, display, slots=c.slots)
        self.ring_u = create_display_ring(self.ring_u_name, display, slots=c.slots)
        self.worker = self._spawn_worker()
        game_args = self._game_args() if c.source == "game" else self._x11_args()
        if self._game_duration_s is not None:
            game_args += ["--duration", f"{self._game_duration_s:g}"]
        if self.game_metrics_port:
            game_args += ["--metrics-port", str(self.game_metrics_port)]
        self.game = subprocess.Popen(_cli(*game_args), env=_child_env())
        orphan_guard.watch_process(self.game.pid)
        log.info("session %s: game pid %d, worker pid %d", c.name, self.game.pid, self.worker.pid)

    def _x11_args(self) -> list[str]:
        c = self.config
        args = [
            "game", "--source", "x11", "--ring", self.ring_r_name, "--size", c.render_size,
            "--fps", f"{c.fps:g}", "--input", str(self.input_path), "--app-exit", c.app_exit,
        ]  # fmt: skip
        if c.app is not None:
            args += ["--app", c.app]
        if c.x11_display is not None:
            args += ["--x11-display", c.x11_display]
        return [*args, "--pulse-dir", str(self.pulse_dir)] if self.app_sound else args

    def _game_args(self) -> list[str]:
        c = self.config
        return [
            "game", "--ring", self.ring_r_name, "--scene", c.scene, "--size", c.render_size,
            "--scale", f"{c.scale:.6g}", "--fps", f"{c.fps:g}", "--seed", str(c.seed),
            "--threads", str(c.game_threads), "--input", str(self.input_path),
            "--jitter" if registry.is_temporal(c.upscaler) else "--no-jitter",
            "--frame-generation" if c.frame_generation else "--no-frame-generation",
        ]  # fmt: skip

    def _spawn_worker(self) -> subprocess.Popen[bytes]:
        c = self.config
        worker = subprocess.Popen(
            _cli(
                "worker",
                "--ring-in",
                self.ring_r_name,
                "--ring-out",
                self.ring_u_name,
                "--upscaler",
                self.upscaler,
                "--display-size",
                c.display_size,
                "--control",
                str(self.control_path),
                "--threads",
                str(c.worker_threads),
                "--metrics-port",
                str(self.worker_metrics_port),
                "--predictor",
                c.predictor,
                *(["--cache-policy", c.cache_policy] if c.cache_policy else []),
            )
        )
        orphan_guard.watch_process(worker.pid)
        return worker

    def remember_upscaler(self, name: str) -> None:
        """Record a run-time switch the worker accepted (see server/worker/control.py)."""
        self.upscaler = name

    def wait_ready(self, timeout_s: float = 60.0) -> None:
        """Block until the worker's control socket exists (the worker has attached)."""
        deadline = time.monotonic() + timeout_s
        while not self.control_path.exists():
            self.check_children()
            if time.monotonic() > deadline:
                raise TimeoutError(f"worker did not come up in {timeout_s:.0f}s")
            time.sleep(0.05)

    def check_children(self) -> None:
        """Restart a dead worker; raise if the game died."""
        if self.worker is not None and self.worker.poll() is not None:
            code = self.worker.returncode
            self.worker_restarts += 1
            log.warning(
                "worker exited (code %s); restarting (restart #%d)", code, self.worker_restarts
            )
            self.control_path.unlink(missing_ok=True)
            orphan_guard.forget_process(self.worker.pid)
            self.worker = self._spawn_worker()
        if self.game is None or self.game.poll() is None:
            return
        code = self.game.returncode
        if self.config.source == "x11":
            # The game process ends when the application does (or its display died):
            # the session has nothing left to stream, whatever the code.
            raise SourceStopped(_x11_end(code), code)
        if code != 0:
            raise RuntimeError(f"game process exited with code {code}")

    def stop(self) -> None:
        for proc in (self.game, self.worker):
            if proc is not None and proc.poll() is None:
                proc.terminate()
        for proc in (self.game, self.worker):
            if proc is None:
                continue
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)
            orphan_guard.forget_process(proc.pid)
        for ring in (self.ring_r, self.ring_u):
            if ring is not None:
                ring.unlink()
                ring.close()
        self.ring_r = self.ring_u = None
        self.control_path.unlink(missing_ok=True)
        self.input_path.unlink(missing_ok=True)
        for path in session_files(self.config.name):
            orphan_guard.forget_path(path)

    def __enter__(self) -> LocalStack:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
