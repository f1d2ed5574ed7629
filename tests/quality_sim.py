"""A simulated host for the quality controller: sessions whose stages cost CPU time that
depends on their setting, sharing a number of cores (and a hog that takes some).

A session runs at its setting's frame rate (``rate`` of the host's ``fps``) and costs
CPU in proportion to it. When the sessions (and the hog) ask more CPU than the host
has, every stage stretches by the same factor and the frame rate falls by it: the
first-order behaviour of processes sharing cores under a fair scheduler. The true
costs are the simulator's own, not the controller's table, so the controller has to
learn them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from server.session.quality.controller import Measurement, QualityController
from server.session.quality.model import Setting
from server.session.quality.scene import SceneClass

DISPLAY_PIXELS = 1280 * 720
# What a stage costs on the simulated host, ms per frame, idle.
UPSCALE_MS = {
    "bilinear": 2.5,
    "bicubic": 3.0,
    "lanczos2": 18.0,
    "easu": 6.0,
    "easu_rcas": 6.5,
    "temporal": 12.0,
}


def true_times(
    setting: Setting, temporal_ms: float | None = None, fg_render_share: float = 0.6
) -> dict[str, float]:
    render_px = DISPLAY_PIXELS / setting.scale**2
    render = 6.0 + 22.0 * render_px / (480 * 270)  # a fixed part plus a per-pixel part
    upscale = UPSCALE_MS[setting.method]
    if setting.method == "temporal" and temporal_ms is not None:
        upscale = temporal_ms
    if setting.frame_generation:
        render *= fg_render_share
        upscale += 2.0
    # The encoder reads the whole display-size frame (a fixed part) and codes the
    # encoded pixels (the rest): the simulator's own split, not the benchmark's.
    encode = 10.0 * (0.35 + 0.65 / setting.encode_scale**2)
    return {"render": render, "upscale": upscale, "encode": encode}


@dataclass
class SimulatedHost:
    cores: float
    controllers: list[QualityController]
    fps: float = 30.0
    scene: SceneClass = "slow"
    hog_cores: Callable[[float], float] = lambda t: 0.0
    temporal_ms: float | None = None
    fg_render_share: float = 0.6
    step_s: float = 0.5
    # Whether each session hears of the others waiting for cores (as under upcast serve:
    # server/session/quality/peers.py), and what it heard at each step.
    peers: bool = False
    now: float = 0.0
    waiting: list[tuple[float, list[bool]]] = field(default_factory=list)
    log: list[tuple[float, int, str]] = field(default_factory=list)
    delivered: list[list[tuple[float, float]]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.delivered = [[] for _ in self.controllers]

    def run(self, seconds: float) -> None:
        end = self.now + seconds
        while self.now < end:
            self.step()

    def step(self) -> None:
        times = [
            true_times(c.setting, self.temporal_ms, self.fg_render_share) for c in self.controllers
        ]
        rates = [self.fps * c.setting.rate for c in self.controllers]
        demand = sum(sum(t.values()) * r / 1000.0 for t, r in zip(times, rates, strict=True))
        demand += self.hog_cores(self.now)
        stretch = max(1.0, demand / self.cores)
        busy = min(self.cores, demand)
        waiting = [c.state.waiting_for_cores for c in self.controllers]
        self.waiting.append((self.now, waiting))
        peers = [self._peer_wait(i) for i in range(len(self.controllers))]
        for i, (controller, t) in enumerate(zip(self.controllers, times, strict=True)):
            peer = peers[i]
            fps = rates[i] / stretch
            # A stage whose own median passes the frame period caps the rate too.
            slowest = max(t.values()) * stretch
            fps = min(fps, 1000.0 / slowest)
            self.delivered[i].append((self.now, fps))
            measurement = Measurement(
                now=self.now,
                fps=fps,
                frames=int(fps * 2),
                p50={k: v * stretch for k, v in t.items()},
                p95={k: v * stretch * 1.3 for k, v in t.items()},
                scene=self.scene,
                host_busy_cores=busy,
                host_cores=self.cores,
                peer_waiting_rate=peer[0] if peer is not None else None,
                peer_cores_short=peer[1] if peer is not None else 0.0,
            )
            decision = controller.update(measurement)
            if decision is not None:
                self.log.append((self.now, i, decision.log_line()))
        self.now += self.step_s

    def _peer_wait(self, i: int) -> tuple[float, float] | None:
        """As upcast serve's host file tells session ``i``: the other session waiting
        for cores at the lowest rate, and how many it lacks (peers.py)."""
        if not self.peers:
            return None
        waits = [
            (c.setting.rate, c.state.cores_short)
            for j, c in enumerate(self.controllers)
            if j != i and c.state.cores_short is not None
        ]
        return min(waits) if waits else None

    def fps_between(self, session: int, start: float, end: float) -> list[float]:
        return [fps for t, fps in self.delivered[session] if start <= t < end]

    def switches_between(self, start: float, end: float, session: int | None = None) -> int:
        return sum(
            1 for t, i, _ in self.log if start <= t < end and (session is None or i == session)
        )
