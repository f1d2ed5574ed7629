"""Binds the quality controller to a live session: measurements in, switches out.

Every ``CHECK_INTERVAL_S`` on the session's loop it reads the session's monitor (the
published frame rate and each stage's p50/p95 over its window), the scene class of
the frames published meanwhile and the host's busy cores, and hands them to the
controller. A decision goes out the way a person's control request does (the input
router: the game renders at the new scale from its next frame, the worker switches
method on its control socket), as the source ``quality-auto``, so it is refused and
logged the same way; it is one log line with its reason, and the stream state (the
timing track: the page's overlay, ``upcast bench``) carries the choice and why.

The encoded size goes through the same router (``encode_scale``: the session's
encoder scales the picture down and the viewers follow a new catalog).

A person's accepted control request pins what it set (``quality: "auto"`` in a later
request lets go); ``--quality fixed`` never switches anything.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Mapping
from dataclasses import replace
from typing import Protocol

from prometheus_client import CollectorRegistry, Gauge

from server.frames.frame import FrameMeta, Size
from server.frames.monitor import FrameRateMonitor
from server.ops.host_load import HostLoad
from server.session.input_router import InputRouter
from server.session.quality.calibrate import load_machine_figures
from server.session.quality.controller import (
    Decision,
    Measurement,
    QualityController,
    QualityGoal,
    SourceLimits,
)
from server.session.quality.figures import FiguresError
from server.session.quality.model import QualityModel, Setting
from server.session.quality.peers import HostPeers
from server.session.quality.scene import SceneTracker
from server.session.session_control import ControlResult

log = logging.getLogger(__name__)


class StreamSettingsLike(Protocol):
    """What the adapter reads of the session's settings (runner.StreamSettings)."""

    @property
    def fps(self) -> float: ...
    @property
    def upscaler(self) -> str | None: ...
    @property
    def scale(self) -> float | None: ...
    @property
    def frame_generation(self) -> bool | None: ...
    @property
    def source(self) -> str: ...
    @property
    def quality(self) -> str: ...
    @property
    def quality_preference(self) -> str: ...
    @property
    def min_scale(self) -> float: ...
    @property
    def max_scale(self) -> float: ...
    @property
    def quality_methods(self) -> tuple[str, ...]: ...


CHECK_INTERVAL_S = 0.5
# Frame rates closer than this are one rate (the stream state holds it rounded).
SAME_RATE_FPS = 0.01
AUTO_SOURCE = "quality-auto"


class QualityMetrics:
    def __init__(self, registry: CollectorRegistry) -> None:
        self.expected = Gauge(
            "upcast_quality_expected_psnr_db",
            "PSNR the current setting is expected to give (speed-against-error table)",
            registry=registry,
        )
        self.scale = Gauge("upcast_quality_render_scale", "Render scale chosen", registry=registry)
        self.encode_scale = Gauge(
            "upcast_quality_encode_scale",
            "Encoded scale chosen (display / encoded size)",
            registry=registry,
        )
        self.headroom = Gauge(
            "upcast_quality_host_idle_cores", "Host cores idle at the last check", registry=registry
        )
        self.switches = Gauge(
            "upcast_quality_switches", "Settings switched by the controller", registry=registry
        )
        self.frame_rate = Gauge(
            "upcast_quality_frame_rate",
            "Frame rate chosen (frames per second the game renders)",
            registry=registry,
        )


class SessionQuality:
    def __init__(
        self,
        controller: QualityController | None,
        router: InputRouter,
        monitor: FrameRateMonitor,
        stream_state: dict[str, str | float | bool],
        *,
        enabled: bool = True,
        host: HostLoad | None = None,
        peers: HostPeers | None = None,
        registry: CollectorRegistry | None = None,
        unavailable: str | None = None,
    ) -> None:
        self.controller = controller
        self.router = router
        self.monitor = monitor
        self.enabled = enabled and controller is not None
        # Why auto cannot run here (no figures for the method, an unknown start).
        self.unavailable = unavailable
        self.scene = SceneTracker()
        self.host = host if host is not None else HostLoad()
        self.peers = peers if peers is not None else HostPeers.from_environment()
        self._state = stream_state
        self._metrics = QualityMetrics(registry) if registry is not None else None
        self.decisions: list[Decision] = []
        self._pending: dict[int, Decision] = {}  # our requests' seq -> what they asked
        self._sending: Decision | None = None
        self._publish()

    def frame(self, meta: FrameMeta) -> None:
        if self.enabled:  # fixed: nothing to judge, so nothing to track
            self.scene.frame(meta, time.monotonic())

    def control_outcome(self, result: ControlResult) -> None:
        """Every control result. Our own: a refused one is rolled back. A person's
        accepted one: its goal fields change the controller's goal, ``quality`` turns it
        on or off, and an upscaler, scale or frame generation is pinned (``quality:
        "auto"`` lets go of every pin)."""
        if result.source == AUTO_SOURCE:
            self._own_outcome(result)
            return
        if not result.accepted:
            return
        if self.controller is None:
            if result.requested.get("quality") == "auto":
                log.warning("quality: auto asked by %s but unavailable: %s", result.source,
                            self.unavailable)  # fmt: skip
            return
        req = result.requested
        frame_rate = req.get("frame_rate")
        self._set_goal(req, result.source)
        mode = req.get("quality")
        if mode == "auto":
            self.enabled = True
            self.controller.unpin()
            log.info("quality: auto (set by %s), nothing pinned", result.source)
        elif mode == "fixed":
            self.enabled = False
            log.info("quality: fixed (set by %s)", result.source)
        method, scale, fg = req.get("upscaler"), req.get("scale"), req.get("frame_generation")
        encode = req.get("encode_scale")
        rate = (
            float(frame_rate) / self.controller.goal.target_fps
            if isinstance(frame_rate, int | float)
            else None
        )
        asked = (method, scale, fg, encode, rate)
        if any(x is not None for x in asked):
            self.controller.pin(
                method=method if isinstance(method, str) else None,
                scale=float(scale) if isinstance(scale, int | float) else None,
                frame_generation=fg if isinstance(fg, bool) else None,
                encode_scale=float(encode) if isinstance(encode, int | float) else None,
                rate=rate,
            )
            if self.enabled:
                pinned = ("upscaler", "scale", "frame_generation", "encode_scale", "frame_rate")
                log.info(
                    "quality: %s pinned by a control request from %s (auto adapts the rest)",
                    ", ".join(k for k in pinned if k in req),
                    result.source,
                )
        self._publish()

    def _own_outcome(self, result: ControlResult) -> None:
        decision = self._pending.pop(result.seq, None)
        if decision is None and self._sending is not None:
            decision, self._sending = self._sending, None
        if decision is None or result.accepted or self.controller is None:
            return
        # The worker (or the router) refused part of it: what went through before the
        # refusal (the game's scale and frame generation) is set back too.
        target = decision.target_fps
        log.warning("quality: %s refused (%s); back to %s", decision.setting.describe(target),
                    result.reason, decision.previous.describe(target))  # fmt: skip
        self.controller.refused(decision, result.reason or "refused")
        self._send(decision.previous, decision.setting)

    def _set_goal(self, req: Mapping[str, object], source: str) -> None:
        assert self.controller is not None
        goal = self.controller.goal
        changes: dict[str, object] = {}
        for key in ("target_fps", "preference", "min_scale", "max_scale"):
            if req.get(key) is not None:
                changes[key] = req[key]
        methods = req.get("methods")
        if isinstance(methods, list):
            changes["methods"] = tuple(str(m) for m in methods)
        if not changes:
            return
        try:
            self.controller.set_goal(replace(goal, **changes))  # type: ignore[arg-type]
        except ValueError as exc:
            log.warning("quality goal from %s not applied: %s", source, exc)
            return
        log.info("quality goal set by %s: %s", source, changes)
        if "target_fps" in changes:
            self._follow_target()

    def _follow_target(self) -> None:
        """A new target: the game ticks at it times the current rate's fraction (a rate
        off the new target's ladder is conformed at the next check)."""
        assert self.controller is not None
        wanted = self.controller.goal.target_fps * self.controller.setting.rate
        running = self._running_frame_rate()
        if running is None or abs(wanted - running) > SAME_RATE_FPS:
            self.router.apply_setting(AUTO_SOURCE, frame_rate=wanted)

    def _running_frame_rate(self) -> float | None:
        """The frame rate the game runs at: what the session last set it to (its stream
        state, written for every accepted request), the goal's target before that."""
        rate = self._state.get("frame_rate")
        if isinstance(rate, int | float) and not isinstance(rate, bool):
            return float(rate)
        return None if self.controller is None else self.controller.goal.target_fps

    def step(self, now: float) -> Decision | None:
        if self.controller is None or not self.enabled:
            return None
        snap = self.monitor.snapshot()
        peer = self.peers.waiting()
        p50: Mapping[str, float] = {k: f.p50_ms for k, f in snap.stages.items()}
        p95: Mapping[str, float] = {k: f.p95_ms for k, f in snap.stages.items()}
        measurement = Measurement(
            now=now,
            fps=snap.fps if math.isfinite(snap.fps) else math.nan,
            frames=snap.window_frames,
            p50=p50,
            p95=p95,
            scene=self.scene.scene(now),
            host_busy_cores=self.host.busy_cores(),
            host_cores=self.host.cores,
            peer_waiting_rate=peer.rate if peer is not None else None,
            peer_cores_short=peer.cores_short if peer is not None else 0.0,
        )
        log.debug(
            "quality check: %.1f fps (%d frames), p50 %s, p95 %s, scene %s, host busy %s of %g",
            measurement.fps, measurement.frames,
            {k: round(v, 1) for k, v in p50.items()}, {k: round(v, 1) for k, v in p95.items()},
            measurement.scene, measurement.host_busy_cores, measurement.host_cores,
        )  # fmt: skip
        decision = None
        if self.enabled and self.controller is not None:
            decision = self.controller.update(measurement)
        if decision is not None:
            self._apply(decision)
        self._publish()
        return decision

    def _apply(self, decision: Decision) -> None:
        log.info("%s", decision.log_line())
        self.decisions.append(decision)
        # A request refused at once (by the router) is answered inside the send.
        self._sending = decision
        seq = self._send(decision.setting, decision.previous)
        answered = self._sending is None
        self._sending = None
        if seq is not None and not answered:
            self._pending[seq] = decision
            while len(self._pending) > 16:  # answers that never came
                self._pending.pop(next(iter(self._pending)))

    def _send(self, new: Setting, old: Setting) -> int | None:
        assert self.controller is not None
        frame_rate = self.controller.goal.target_fps * new.rate
        running = self._running_frame_rate()
        if running is not None and abs(frame_rate - running) < SAME_RATE_FPS:
            frame_rate_asked: float | None = None
        else:
            frame_rate_asked = frame_rate
        return self.router.apply_setting(
            AUTO_SOURCE,
            upscaler=new.method if new.method != old.method else None,
            scale=new.scale if abs(new.scale - old.scale) > 1e-6 else None,
            frame_generation=(
                new.frame_generation if new.frame_generation != old.frame_generation else None
            ),
            encode_scale=(
                new.encode_scale if abs(new.encode_scale - old.encode_scale) > 1e-6 else None
            ),
            frame_rate=frame_rate_asked,
        )

    def _publish(self) -> None:
        self._state["quality"] = "auto" if self.enabled else "fixed"
        if self.controller is None:
            self._state["quality_reason"] = self.unavailable or "fixed"
            return
        st = self.controller.state
        self._state["quality_reason"] = st.reason if self.enabled else "fixed"
        self._state["quality_at_floor"] = bool(self.enabled and st.at_floor)
        short = st.cores_short if self.enabled else None
        if short is None:
            self._state.pop("quality_cores_short", None)
        else:
            self._state["quality_cores_short"] = round(short, 3)
        if math.isfinite(st.expected_psnr_db):
            self._state["expected_psnr_db"] = round(st.expected_psnr_db, 2)
        if st.headroom_cores is not None:
            self._state["host_idle_cores"] = round(st.headroom_cores, 2)
        if self._metrics is not None:
            if math.isfinite(st.expected_psnr_db):
                self._metrics.expected.set(st.expected_psnr_db)
            self._metrics.scale.set(st.setting.scale)
            self._metrics.encode_scale.set(st.setting.encode_scale)
            self._metrics.switches.set(st.switches)
            running = self._running_frame_rate()
            if running is not None:
                self._metrics.frame_rate.set(running)
            if st.headroom_cores is not None:
                self._metrics.headroom.set(st.headroom_cores)

    async def run(self, stop: asyncio.Event) -> None:
        while not stop.is_set():
            await asyncio.sleep(CHECK_INTERVAL_S)
            try:
                self.step(time.monotonic())
            except Exception:  # a controller bug must never end the stream
                log.exception("quality check failed; the setting stays")


def session_quality(
    settings: StreamSettingsLike,
    display: Size,
    router: InputRouter,
    monitor: FrameRateMonitor,
    stream_state: dict[str, str | float | bool],
    registry: CollectorRegistry | None,
) -> SessionQuality:
    """The session's quality adapter; fixed (with the reason logged) where auto cannot
    run: the start is unknown, or the method has no speed-against-error figures."""
    controller, why = _controller_for(settings, display)
    enabled = settings.quality == "auto"
    if controller is None and enabled:
        log.warning("quality: auto unavailable, the settings stay fixed: %s", why)
    adapter = SessionQuality(
        controller,
        router,
        monitor,
        stream_state,
        enabled=enabled,
        registry=registry,
        unavailable=why,
    )
    if adapter.enabled and controller is not None:
        goal = controller.goal
        log.info(
            "quality: auto from %s, holding %.0f fps (%s preferred, scale %g-%g, methods %s)",
            controller.setting.describe(), goal.target_fps, goal.preference, goal.min_scale,
            goal.max_scale, ", ".join(goal.methods) or "all with figures",
        )  # fmt: skip
    return adapter


def _controller_for(
    settings: StreamSettingsLike, display: Size
) -> tuple[QualityController | None, str | None]:
    if settings.upscaler is None or settings.scale is None:
        return None, "the starting upscaler and render scale are not known to this session"
    try:
        machine = load_machine_figures()
    except FiguresError as exc:
        return None, str(exc)
    figures = machine.figures
    log.info("quality: figures from %s", machine.source)
    if settings.upscaler not in figures.methods:
        return None, (
            f"no speed-against-error figures for {settings.upscaler!r} (auto chooses among "
            f"{', '.join(sorted(figures.methods))})"
        )
    color_only = settings.source != "game"
    limits = SourceLimits(
        scale=not color_only, temporal=not color_only, frame_generation=not color_only
    )
    try:
        goal = QualityGoal(
            target_fps=settings.fps,
            preference=settings.quality_preference,  # type: ignore[arg-type]
            min_scale=settings.min_scale,
            max_scale=settings.max_scale,
            methods=tuple(settings.quality_methods),
        )
    except ValueError as exc:
        return None, str(exc)
    start = Setting(settings.upscaler, float(settings.scale), bool(settings.frame_generation))
    model = QualityModel(figures, display.width * display.height)
    return QualityController(model, goal, start, limits), None
