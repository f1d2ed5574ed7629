"""The quality controller: the best picture a session's target frame rate allows.

Sans-IO, like the rate controller: ``update`` takes one window's measurements (the
monitor's frame rate and stage times, the scene class, the host's busy cores) and
returns a ``Decision`` with its reason, or None to keep the setting. It learns as it
goes (model.py) and never touches a process.

In the manner of libwebrtc's CPU adaptation and a game engine's dynamic resolution:

- **Down fast.** ``DOWN_CHECKS`` checks in a row that miss the target (the frame
  rate under ``HOLD_FRACTION`` of it while the host is busy, or a stage's median over
  its one-period budget) switch at once to the best-looking setting predicted to
  fit: every stage's median within ``DOWN_MARGIN`` of its budget and the whole
  session's CPU within what the frame rate shows it gets (``fps / target`` of what
  it needs now, times ``DOWN_MARGIN``). When none fits, the cheapest, if it is
  predicted to take under ``FLOOR_GAIN`` of the CPU the current one takes (else the
  session is at its floor). A step down never switches to a method the table says is
  slower than the running one, nor encodes a larger picture.
- **Up carefully.** After ``UP_HOLD_S`` without a miss, one small step (the render
  scale by at most one ladder step, or straight back to the scale that held before the
  last step down, and/or another method or frame generation) to a
  setting predicted to look at least ``UP_MIN_GAIN_DB`` better, with every stage's
  median within ``UP_MARGIN`` of its budget and its extra CPU inside the host's idle cores
  less a ``HOST_RESERVE`` (on a host shared by sessions, the idle cores are what
  the others leave). A switch that restarts a temporal method's history (any
  change of scale or method while one runs) must gain ``RESET_COST_DB`` more.
- **Probation.** A step up that misses within ``PROBATION_S`` goes back at once,
  and that setting is not tried again for ``BLOCK_S`` (doubling each time it fails
  again, up to ``BLOCK_MAX_S``): a host on the edge settles instead of hunting.
- **Settle.** After any switch, ``SETTLE_S`` passes before the next judgement, so
  the monitor's window holds only frames of the new setting; nothing is judged in
  the first ``WARMUP_S`` (start-up: kernels compile, caches fill).

The encoded size is the last resort before the frame rate: a step down lowers it
only when no setting at the current encoded size fits, and any change of it must
gain ``ENCODE_SWITCH_COST_DB`` more (every viewer moves to a new track and waits for
its first keyframe). A step up moves it one step of the benchmark's ladder at a time.

**The frame rate** is a knob too (``Setting.rate``, a fraction of the target on
``RATE_LADDER``: 30, 20, 15, 10 fps of 30): the game ticks slower, keeping game time,
so every stage costs that much less CPU. It goes down only to a rate the measured one
is nearer to than to the current (26 of 30 fps stays, ragged, rather than become a
steady 20: fewer frames is no cure for a few late ones). A lower rate is judged against
itself (the miss, the budgets, the CPU), and a step up tries the next rate up before any
better picture at the same rate: a rate below the target is a debt, paid back first, so
no step up improves the picture until the rate is back.

**Sessions on one host** (``upcast serve``, peers.py): a session below its target rate
whose next rate up lacks only idle cores says so (``ControllerState.cores_short``), and
the supervisor tells the others. While one waits at a lower rate than ours for cores we
could free, we take no step up that costs CPU, and when the idle cores fall short we step
our picture down by what it lacks (``_yield_to_peer``, one step per ``UP_HOLD_S``); a
shortfall all we could free would not cover holds nothing.

Degradation preference (WebRTC's ``degradationPreference``) says when the rate goes
down: ``framerate`` (games) only when the cheapest setting at the full rate still
misses, the picture gives first; ``balanced`` before the encoded size goes down, and
the rate may sag to ``BALANCED_FRACTION`` of the target before anything is judged a
miss; ``resolution`` before the picture falls below the one it started with.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Literal

from server.session.quality.model import (
    STAGES,
    QualityModel,
    Setting,
    StageTimes,
    rate_ladder,
    scale_ladder,
    settings_grid,
)
from server.session.quality.scene import SceneClass

Preference = Literal["framerate", "resolution", "balanced"]
PREFERENCES: tuple[Preference, ...] = ("framerate", "resolution", "balanced")

HOLD_FRACTION = 0.9  # a window under this share of the target misses it
BALANCED_FRACTION = 0.75
HOST_BUSY_FRACTION = 0.85  # the host counts as busy from this share of its cores
DOWN_CHECKS = 2
DOWN_MARGIN = 0.85
UP_MARGIN = 0.75
UP_HOLD_S = 4.0
UP_MIN_GAIN_DB = 0.2
RESET_COST_DB = 0.15
ENCODE_SWITCH_COST_DB = 0.3
FLOOR_GAIN = 0.85  # "nothing fits": the cheapest, only if below this share of the CPU now
HOST_RESERVE = 0.1  # of the host's cores, never planned for
PROBATION_S = 10.0
BLOCK_S = 20.0
BLOCK_MAX_S = 160.0
SETTLE_S = 2.0
WARMUP_S = 5.0
SCALE_STEP = 0.25
MIN_FRAMES = 5  # a window with fewer frames says nothing about the rate
YIELD_SAVING = 0.1  # a step down for a waiting session frees this share of our CPU or more


@dataclass(frozen=True)
class QualityGoal:
    """What the session is asked for (the control API may change it at run time)."""

    target_fps: float
    preference: Preference = "framerate"
    min_scale: float = 1.0
    max_scale: float = 4.0
    methods: tuple[str, ...] = ()  # empty: every method with figures
    frame_generation: bool = True  # whether the controller may predict frames
    encode_size: bool = True  # whether it may encode below the display size

    def __post_init__(self) -> None:
        if not (math.isfinite(self.target_fps) and self.target_fps > 0):
            raise ValueError(f"target_fps must be positive, got {self.target_fps}")
        if self.preference not in PREFERENCES:
            raise ValueError(f"preference must be one of {', '.join(PREFERENCES)}")
        if not 1.0 <= self.min_scale <= self.max_scale <= 4.0:
            raise ValueError("need 1 <= min_scale <= max_scale <= 4")


@dataclass(frozen=True)
class SourceLimits:
    """What the source lets change: a captured application (colour only) has a fixed
    size, no depth or motion for a temporal method, and nothing to predict from."""

    scale: bool = True
    temporal: bool = True
    frame_generation: bool = True
    encode_size: bool = True  # the session can change its encoder's size


@dataclass(frozen=True)
class Measurement:
    now: float
    fps: float  # frames published per second over the window
    frames: int  # frames in the window
    p50: Mapping[str, float]  # stage -> ms
    p95: Mapping[str, float]
    scene: SceneClass = "unknown"
    host_busy_cores: float | None = None  # every process on the host
    host_cores: float = 1.0
    # Another session on the host waiting for cores to raise its rate (peers.py): the
    # lowest such rate (a fraction of its target) and the idle cores it is short of;
    # None: none waits, or the session runs alone.
    peer_waiting_rate: float | None = None
    peer_cores_short: float = 0.0


@dataclass(frozen=True)
class Decision:
    setting: Setting
    previous: Setting
    direction: Literal["down", "up", "back", "goal"]
    reason: str
    expected_psnr_db: float
    predicted: StageTimes
    target_fps: float | None = None  # the goal's, to say a setting's frame rate in fps

    def log_line(self) -> str:
        before = self.previous.describe(self.target_fps)
        after = self.setting.describe(self.target_fps)
        return (
            f"quality {self.direction}: {before} -> {after} "
            f"(expected {self.expected_psnr_db:.2f} dB; {self.reason})"
        )


@dataclass
class ControllerState:
    """What the controller shows (the status track, /sessions, Prometheus)."""

    setting: Setting
    expected_psnr_db: float = math.nan
    reason: str = "starting"
    headroom_cores: float | None = None
    switches: int = 0
    last_change_at: float | None = None
    at_floor: bool = False  # nothing cheaper is left and the target is still missed
    # Below the target rate with a rate step up that only the host's spare cores stop,
    # and by how many cores (None: not waiting): what the host's other sessions leave
    # idle should come here first (peers.py).
    cores_short: float | None = None

    @property
    def waiting_for_cores(self) -> bool:
        return self.cores_short is not None


@dataclass
class _Block:
    until: float
    backoff_s: float


@dataclass
class _Pins:
    method: str | None = None
    scale: float | None = None
    frame_generation: bool | None = None
    encode_scale: float | None = None
    rate: float | None = None


@dataclass
class QualityController:
    model: QualityModel
    goal: QualityGoal
    start: Setting
    limits: SourceLimits = field(default_factory=SourceLimits)

    def __post_init__(self) -> None:
        self.state = ControllerState(self.start)
        self._floor_psnr = self.model.expected_psnr(self.start, "unknown")
        self._misses = 0
        self._last_miss_at: float | None = None
        self._last_up: tuple[float, Setting] | None = None  # (when, from what)
        self._blocked: dict[Setting, _Block] = {}
        self._pins = _Pins()
        self._said_floor = False
        self._first_at: float | None = None
        self._last_good: Setting | None = None  # what held before the last step down

    # -- the control API's side ------------------------------------------------------

    @property
    def setting(self) -> Setting:
        return self.state.setting

    def set_goal(self, goal: QualityGoal) -> None:
        self.goal = goal

    def pin(
        self,
        *,
        method: str | None = None,
        scale: float | None = None,
        frame_generation: bool | None = None,
        encode_scale: float | None = None,
        rate: float | None = None,
    ) -> None:
        """Hold the given fields where a person set them (a control request did): the
        controller adapts only the others. The setting takes them at once. ``rate`` is
        a fraction of the goal's target frame rate."""
        if method is not None:
            self._pins.method = method
        if scale is not None:
            self._pins.scale = scale
        if frame_generation is not None:
            self._pins.frame_generation = frame_generation
        if encode_scale is not None:
            self._pins.encode_scale = encode_scale
        if rate is not None:
            if not (math.isfinite(rate) and rate > 0):
                raise ValueError(f"rate must be a positive fraction of the target, got {rate}")
            self._pins.rate = rate
        now = self.state.setting
        self.state.setting = Setting(
            method if method is not None else now.method,
            scale if scale is not None else now.scale,
            frame_generation if frame_generation is not None else now.frame_generation,
            encode_scale if encode_scale is not None else now.encode_scale,
            rate if rate is not None else now.rate,
        )

    def unpin(self) -> None:
        self._pins = _Pins()

    def refused(self, decision: Decision, why: str) -> None:
        """A switch did not go through (the worker refused the method): the setting is
        what it was, and the refused one is not asked for again for a while."""
        block = self._blocked.get(decision.setting)
        backoff = BLOCK_S if block is None else min(BLOCK_MAX_S, block.backoff_s * 2)
        until = (self.state.last_change_at or 0.0) + backoff
        self._blocked[decision.setting] = _Block(until, backoff)
        self._last_up = None
        self.state.setting = decision.previous
        self.state.reason = f"{decision.setting.describe(self.goal.target_fps)} refused: {why}"

    # -- judging ---------------------------------------------------------------------

    def update(self, m: Measurement) -> Decision | None:
        current = self.state.setting
        if self._first_at is None:
            self._first_at = m.now  # a step up waits for measurements, not priors
        settled = self.state.last_change_at is None or m.now - self.state.last_change_at >= SETTLE_S
        if not settled:
            return None
        p50 = _finite(m.p50)
        p95 = _finite(m.p95)
        self.model.learn(current, p50, p95)
        self.state.expected_psnr_db = self.model.expected_psnr(current, m.scene)
        self.state.headroom_cores = _idle(m)
        if not self._within_goal(current):
            return self._conform(m)  # a new goal or pin applies at once, warm or not
        if m.now - self._first_at < WARMUP_S:
            return None  # the first seconds are start-up: kernels, caches, a cold encoder
        miss = self._miss(m, p50)
        if miss is not None:
            self._misses += 1
            self._last_miss_at = m.now
            self.state.cores_short = None  # a session missing its rate is not held by cores
        else:
            self._misses = 0
            if self._holding(m):
                # At the cheapest but holding now (the hog left): the host can carry it.
                self.state.at_floor = False
                self._said_floor = False
        if miss is not None and self._misses >= DOWN_CHECKS:
            return self._down(m, miss, p50)
        if miss is None and self._quiet_for(m.now) >= UP_HOLD_S:
            yielded = self._yield_to_peer(m)
            if yielded is not None:
                return yielded
        if miss is None and self._holding(m) and self._quiet_for(m.now) >= UP_HOLD_S:
            return self._up(m)
        return None

    def _holding(self, m: Measurement) -> bool:
        """A measured rate at the target: no step up on a window that says nothing."""
        return (
            m.frames >= MIN_FRAMES
            and math.isfinite(m.fps)
            and m.fps >= self._judged_fps() * HOLD_FRACTION
        )

    def _within_goal(self, setting: Setting) -> bool:
        """Whether the goal, the pins and the source allow this setting. Every candidate
        passes; so does an off-ladder scale inside the bounds (the start's 2.667, say).
        Checked on every update: no walk over the candidates."""
        g, p = self.goal, self._pins
        methods_ok = (not g.methods or setting.method in g.methods) and setting.method in set(
            self.model.methods()
        )
        if p.method is not None:
            methods_ok = setting.method == p.method
        if not self.limits.temporal and _is_temporal(setting.method):
            methods_ok = False
        if p.scale is not None or not self.limits.scale:
            scale_ok = True
        else:
            scale_ok = g.min_scale - 1e-6 <= setting.scale <= g.max_scale + 1e-6
        fg_ok = (
            setting.frame_generation == p.frame_generation
            if p.frame_generation is not None
            else (
                not setting.frame_generation
                or (g.frame_generation and self.limits.frame_generation)
            )
        )
        if p.encode_scale is not None:
            encode_ok = abs(setting.encode_scale - p.encode_scale) < 1e-6
        elif setting.encode_scale == 1.0:
            encode_ok = True
        else:
            encode_ok = (
                g.encode_size
                and self.limits.encode_size
                and setting.encode_scale in self.model.encode_scales()
                and setting.encode_scale <= setting.scale + 1e-6
            )
        return methods_ok and scale_ok and fg_ok and encode_ok and self._allowed_rate(setting.rate)

    def _conform(self, m: Measurement) -> Decision | None:
        """The goal changed under the current setting (another method list, bounds, a
        pin): the best allowed setting predicted to cost no more CPU than this one."""
        current = self.state.setting
        here_cpu = self.model.predict(current).cpu_cores(self._fps_of(current))
        rate = current.rate if self._allowed_rate(current.rate) else self._rates()[0]
        best: tuple[float, Setting] | None = None
        cheapest: tuple[float, Setting] | None = None
        for cand in self._candidates([rate]):
            times = self.model.predict(cand)
            cpu = times.cpu_cores(self._fps_of(cand))
            if cheapest is None or cpu < cheapest[0]:
                cheapest = (cpu, cand)
            budget = 1000.0 / self._fps_of(cand)
            if cpu > here_cpu * 1.05 or any(times.p50[s] > budget * DOWN_MARGIN for s in STAGES):
                continue
            quality = self.model.expected_psnr(cand, m.scene)
            if best is None or quality > best[0]:
                best = (quality, cand)
        chosen = best[1] if best is not None else (cheapest[1] if cheapest is not None else None)
        if chosen is None or chosen == current:
            return None
        return self._switch(m, chosen, "goal", "the goal allows this setting no more")

    def _quiet_for(self, now: float) -> float:
        marks = (self._last_miss_at, self.state.last_change_at, self._first_at)
        since = [t for t in marks if t is not None]
        return math.inf if not since else now - max(since)

    def _fps_of(self, setting: Setting) -> float:
        """The frame rate a setting runs at."""
        return self.goal.target_fps * setting.rate

    def _allowed_rate(self, rate: float) -> bool:
        return any(abs(rate - r) < 1e-6 for r in self._rates())

    def _judged_fps(self) -> float:
        """The rate a window must reach: the current setting's (a lowered rate is judged
        against itself), less the sag ``balanced`` allows."""
        fps = self._fps_of(self.state.setting)
        if self.goal.preference == "balanced":
            return fps * BALANCED_FRACTION
        return fps

    def _miss(self, m: Measurement, p50: Mapping[str, float]) -> str | None:
        """Why this window misses the target, or None. The frame rate decides: a stage's
        p95 past its period on a shared host is often a preemption, not a cost, while a
        median past it caps the rate for sure."""
        budget = 1000.0 / self._fps_of(self.state.setting)
        over = [s for s in STAGES if p50.get(s, 0.0) > budget]
        if over:
            s = over[0]
            return f"{s} p50 {p50[s]:.1f} ms over its {budget:.1f} ms budget"
        fps = m.fps if math.isfinite(m.fps) else math.nan
        wanted = self._judged_fps() * HOLD_FRACTION
        if m.frames >= MIN_FRAMES and fps < wanted and self._host_busy(m):
            slowest = max(STAGES, key=lambda s: p50.get(s, 0.0))
            return f"{fps:.1f} fps under {wanted:.1f} ({slowest} p50 {p50.get(slowest, 0):.1f} ms)"
        return None

    def _host_busy(self, m: Measurement) -> bool:
        """A low rate on an idle host is the source's pace (an application that draws
        slower), not a cost this controller can cut."""
        busy = m.host_busy_cores
        if busy is None or not math.isfinite(busy):
            return True
        return busy >= HOST_BUSY_FRACTION * m.host_cores

    # -- choosing --------------------------------------------------------------------

    def _rates(self) -> list[float]:
        """The frame-rate fractions allowed, highest first."""
        if self._pins.rate is not None:
            return [self._pins.rate]
        return rate_ladder(self.goal.target_fps)

    def _candidates(self, rates: list[float] | None = None) -> list[Setting]:
        """Every allowed setting at ``rates`` (default: the current rate)."""
        if rates is None:
            rates = [self.state.setting.rate]
        table = self.model.methods()
        methods = [x for x in table if not self.goal.methods or x in self.goal.methods]
        if not self.limits.temporal:
            methods = [x for x in methods if not _is_temporal(x)]
        current = self.state.setting
        if self._pins.method is not None:
            methods = [self._pins.method]
        if self.limits.scale and self._pins.scale is None:
            scales = scale_ladder(self.goal.min_scale, self.goal.max_scale, SCALE_STEP)
        else:
            scales = [current.scale if self._pins.scale is None else self._pins.scale]
        if self._pins.frame_generation is not None:
            fgs = [self._pins.frame_generation]
        elif self.goal.frame_generation and self.limits.frame_generation:
            fgs = [False, True]
        else:
            fgs = [False]
        if self._pins.encode_scale is not None:
            encodes = [self._pins.encode_scale]
        elif self.goal.encode_size and self.limits.encode_size:
            encodes = self.model.encode_scales()
        else:
            encodes = [1.0]
        grid = settings_grid(methods, scales, fgs, encodes, rates)
        return [s for s in grid if s.method in table]

    def _blocked_now(self, setting: Setting, now: float) -> bool:
        block = self._blocked.get(setting)
        return block is not None and now < block.until

    def _costlier_method(self, cand: Setting, current: Setting) -> bool:
        """A step down never moves to a method the table says is slower than the one
        running, at the candidate's scale: its cost is a guess (a method's slowdown on a
        busy host is its own: temporal's torch threads suffer more than a resampler),
        and a guess is no way out of a miss."""
        if cand.method == current.method:
            return False
        scale = cand.scale
        return (
            self.model.table_upscale_ms(cand.method, scale)[0]
            > self.model.table_upscale_ms(current.method, scale)[0] * 1.001
        )

    def _switch_cost(self, a: Setting, b: Setting) -> float:
        """dB a switch from ``a`` to ``b`` must gain beyond the picture it buys."""
        cost = RESET_COST_DB if self._resets_history(a, b) else 0.0
        if abs(a.encode_scale - b.encode_scale) > 1e-6:
            cost += ENCODE_SWITCH_COST_DB
        return cost

    def _encode_step(self, a: Setting, b: Setting) -> int:
        """How many steps of the encoded-scale ladder lie between ``a`` and ``b``."""
        ladder = self.model.encode_scales()
        if a.encode_scale not in ladder or b.encode_scale not in ladder:
            return 0 if abs(a.encode_scale - b.encode_scale) < 1e-6 else len(ladder)
        return abs(ladder.index(a.encode_scale) - ladder.index(b.encode_scale))

    def _resets_history(self, a: Setting, b: Setting) -> bool:
        if not (_is_temporal(a.method) or _is_temporal(b.method)):
            return False
        return a.method != b.method or abs(a.scale - b.scale) > 1e-6

    def _down(self, m: Measurement, miss: str, p50: Mapping[str, float]) -> Decision | None:
        current = self.state.setting
        self._misses = 0
        if self._last_up is not None and m.now - self._last_up[0] <= PROBATION_S:
            # The last step up did not hold: back, and leave that setting alone a while.
            _, before = self._last_up
            block = self._blocked.get(current)
            backoff = BLOCK_S if block is None else min(BLOCK_MAX_S, block.backoff_s * 2)
            self._blocked[current] = _Block(m.now + backoff, backoff)
            self._last_up = None
            reason = f"{miss}; the step up did not hold, not tried again for {backoff:.0f} s"
            return self._switch(m, before, "back", reason)
        now_times = self.model.predict(current)
        fps = m.fps if math.isfinite(m.fps) and m.fps > 0 else self._judged_fps()
        share = min(1.0, fps / self._judged_fps())
        here_cpu = now_times.cpu_cores(self._fps_of(current))
        cpu_allowed = here_cpu * share * DOWN_MARGIN
        fitting, cheapest = self._fitting(m, [current.rate], cpu_allowed)
        # The encoded size goes down last: only when nothing at the current size fits.
        keep = [f for f in fitting if f[1].encode_scale <= current.encode_scale + 1e-6]
        if keep:
            return self._switch(m, _best(keep), "down", miss)
        preference = self.goal.preference
        if preference == "balanced":
            slower = self._slower(m, fps, cpu_allowed, here_cpu, same_encode=True)
            if slower is not None:
                why = f"{miss}; a lower frame rate before a smaller encoded size"
                return self._switch(m, slower, "down", why)
        if fitting:
            return self._switch(m, _best(fitting), "down", miss)
        # The cheapest only when it is clearly cheaper: settings within a few percent of
        # each other are all "the floor", and hopping between them costs frames.
        if (
            cheapest is not None
            and cheapest[0] < here_cpu * FLOOR_GAIN
            and cheapest[1] != current
            and preference != "resolution"
        ):
            return self._switch(m, cheapest[1], "down", f"{miss}; nothing fits: the cheapest")
        # Nothing cheaper at this frame rate: the rate gives.
        slower = self._slower(m, fps, cpu_allowed, here_cpu)
        if slower is not None:
            why = f"{miss}; nothing cheaper holds {self._fps_of(current):.3g} fps: a lower rate"
            return self._switch(m, slower, "down", why)
        self.state.at_floor = True
        if not self._said_floor:
            self._said_floor = True
            self.state.reason = f"{miss}; nothing cheaper is allowed: at the lowest setting"
        return None

    def _fitting(
        self, m: Measurement, rates: list[float], cpu_allowed: float
    ) -> tuple[list[tuple[float, Setting, StageTimes]], tuple[float, Setting, StageTimes] | None]:
        """The candidates at ``rates`` a step down may take, predicted to fit (every
        stage's median within ``DOWN_MARGIN`` of its period, the session's CPU within
        ``cpu_allowed``), each with its score (picture less the switch's cost); and the
        cheapest candidate, fitting or not."""
        current = self.state.setting
        fitting: list[tuple[float, Setting, StageTimes]] = []
        cheapest: tuple[float, Setting, StageTimes] | None = None
        for cand in self._candidates(rates):
            if cand != current and (
                self._costlier_method(cand, current)
                or cand.encode_scale < current.encode_scale - 1e-6
            ):
                continue  # a step down encodes no larger and runs no slower a method
            quality = self.model.expected_psnr(cand, m.scene)
            if self.goal.preference == "resolution" and quality < self._floor_psnr - 0.05:
                continue
            times = self.model.predict(cand)
            cpu = times.cpu_cores(self._fps_of(cand))
            if cheapest is None or cpu < cheapest[0]:
                cheapest = (cpu, cand, times)
            if cand == current:
                continue
            budget = 1000.0 / self._fps_of(cand)
            fits_stages = all(times.p50[s] <= budget * DOWN_MARGIN for s in STAGES)
            if fits_stages and cpu <= cpu_allowed:
                fitting.append((quality - self._switch_cost(current, cand), cand, times))
        return fitting, cheapest

    def _slower(
        self,
        m: Measurement,
        fps: float,
        cpu_allowed: float,
        here_cpu: float,
        *,
        same_encode: bool = False,
    ) -> Setting | None:
        """The best setting at the highest lower frame rate that fits; where none fits at
        any, the cheapest at the lowest rate if it is clearly cheaper; else None. Only
        rates the measured ``fps`` is closer to than to the current one: a session that
        shows 26 of 30 fps keeps its 26 rather than hold a steady 20 (it is at its floor)."""
        current = self.state.setting
        here = self._fps_of(current)
        lower = [
            r
            for r in self._rates()
            if r < current.rate - 1e-6 and fps < (here + self.goal.target_fps * r) / 2.0
        ]
        for rate in lower:
            fitting, _ = self._fitting(m, [rate], cpu_allowed)
            if same_encode:
                fitting = [f for f in fitting if f[1].encode_scale <= current.encode_scale + 1e-6]
            if fitting:
                return _best(fitting)
        if not lower or same_encode:
            return None
        _, cheapest = self._fitting(m, [lower[-1]], cpu_allowed)
        if cheapest is None or cheapest[0] >= here_cpu * FLOOR_GAIN:
            return None
        return cheapest[1]

    def _up(self, m: Measurement) -> Decision | None:
        current = self.state.setting
        here = self.model.predict(current)
        here_cpu = here.cpu_cores(self._fps_of(current))
        here_q = self.model.expected_psnr(current, m.scene)
        idle = _idle(m)
        # Without a host reading, a step may add a tenth of what the session takes.
        spare = (idle - HOST_RESERVE * m.host_cores) if idle is not None else 0.1 * here_cpu
        spare_text = f"{idle:.2f} idle cores" if idle is not None else "no host reading"
        if self._peer_claims(m):
            # Another session on the host waits at a lower rate than ours, for cores we
            # could leave it: the idle cores are its. Only a step costing nothing goes.
            self.state.cores_short = None
            spare = min(spare, 0.0)
            spare_text = (
                f"{spare_text}, held for a session waiting at "
                f"{m.peer_waiting_rate or 0.0:.0%} of its rate"
            )
            faster = None
        else:
            faster = self._faster(m, here_cpu, spare)
        if faster is not None:
            cand, extra = faster
            reason = f"{self._fps_of(cand):.3g} fps again for {extra:+.2f} cores ({spare_text})"
            self._last_up = (m.now, current)
            return self._switch(m, cand, "up", reason)
        if any(r > current.rate + 1e-6 for r in self._rates()):
            # Below the target rate the idle cores are kept for the rate: a better picture
            # now would take what the next rate up needs (here, or in another session).
            return None
        budget = 1000.0 / self._fps_of(current)
        best: tuple[float, Setting, float] | None = None
        for cand in self._candidates():
            if cand == current or self._blocked_now(cand, m.now):
                continue
            if abs(cand.scale - current.scale) > self._up_reach(current) + 1e-6:
                continue
            if self._encode_step(current, cand) > 1:
                continue
            times = self.model.predict(cand)
            if any(times.p50[s] > budget * UP_MARGIN for s in STAGES):
                continue
            extra = times.cpu_cores(self._fps_of(cand)) - here_cpu
            if extra > 0 and extra > spare:
                continue
            gain = (
                self.model.expected_psnr(cand, m.scene) - here_q - self._switch_cost(current, cand)
            )
            if gain >= UP_MIN_GAIN_DB and (best is None or gain > best[0]):
                best = (gain, cand, extra)
        if best is None:
            return None
        gain, cand, extra = best
        reason = f"+{gain:.2f} dB expected for {extra:+.2f} cores ({spare_text})"
        self._last_up = (m.now, current)
        return self._switch(m, cand, "up", reason)

    def _yield_options(
        self, m: Measurement, lower_rate: bool = False
    ) -> list[tuple[float, Setting, float]]:
        """(score, setting, cores freed) of each cheaper setting at our encoded size (a
        yield moves no viewer to a new track): at our rate, or with ``lower_rate`` at the
        next rate down, if that stays above the waiting session's (max-min: we never go
        below the one we yield to)."""
        current = self.state.setting
        here_cpu = self.model.predict(current).cpu_cores(self._fps_of(current))
        rates = [current.rate]
        if lower_rate:
            peer = m.peer_waiting_rate if m.peer_waiting_rate is not None else 1.0
            lower = [r for r in self._rates() if peer + 1e-6 < r < current.rate - 1e-6]
            if not lower:
                return []
            rates = [max(lower)]
        out: list[tuple[float, Setting, float]] = []
        for cand in self._candidates(rates):
            if cand == current or self._blocked_now(cand, m.now):
                continue
            if abs(cand.encode_scale - current.encode_scale) > 1e-6:
                continue
            freed = here_cpu - self.model.predict(cand).cpu_cores(self._fps_of(cand))
            if freed <= 0:
                continue
            score = self.model.expected_psnr(cand, m.scene) - self._switch_cost(current, cand)
            out.append((score, cand, freed))
        return out

    def _peer_claims(self, m: Measurement) -> bool:
        """Another session waits at a lower rate than ours for cores we could free (its
        shortfall already counts the host's idle cores): a claim on our spare. One that
        all we could free would not meet is none, or a session would give its picture
        for nothing."""
        peer = m.peer_waiting_rate
        if peer is None or peer >= self.state.setting.rate - 1e-6:
            return False
        options = self._yield_options(m) + self._yield_options(m, lower_rate=True)
        freeable = max((f for _, _, f in options), default=0.0)
        return freeable >= m.peer_cores_short

    def _yield_to_peer(self, m: Measurement) -> Decision | None:
        """Another session on the host waits for cores at a lower rate than ours, which
        the idle cores do not cover but a cheaper setting of ours would: the best-looking
        cheaper picture at our rate that frees what it lacks (and ``YIELD_SAVING`` of our
        CPU at least), else the best-looking at the next rate down if it stays above the
        other's (the picture gives before the rate, as in ``framerate``). None when
        nobody waits lower, or we cannot free enough."""
        current = self.state.setting
        peer = m.peer_waiting_rate
        if peer is None or peer >= current.rate - 1e-6:
            return None
        here_cpu = self.model.predict(current).cpu_cores(self._fps_of(current))
        need = max(m.peer_cores_short, YIELD_SAVING * here_cpu)
        options = [o for o in self._yield_options(m) if o[2] >= need - 1e-9]
        if not options:
            options = [o for o in self._yield_options(m, True) if o[2] >= need - 1e-9]
        if not options:
            return None
        _, cand, freed = max(options, key=lambda o: o[0])
        self._last_up = None  # not a step up: a miss after it is not a failed probation
        reason = (
            f"another session on the host waits for cores at {peer:.0%} of its rate; "
            f"frees {freed:.2f} cores"
        )
        return self._switch(m, cand, "down", reason)

    def _faster(
        self, m: Measurement, here_cpu: float, spare: float
    ) -> tuple[Setting, float] | None:
        """Below the target rate: the best-looking setting at the next rate up predicted
        to fit there (``UP_MARGIN``) within the spare cores, and the cores it adds."""
        current = self.state.setting
        higher = [r for r in self._rates() if r > current.rate + 1e-6]
        self.state.cores_short = None
        if not higher:
            return None
        rate = min(higher)
        best: tuple[float, Setting, float] | None = None
        short: float | None = None  # the fewest cores a candidate lacked
        for cand in self._candidates([rate]):
            if self._blocked_now(cand, m.now) or self._encode_step(current, cand) > 1:
                continue
            quality = self.model.expected_psnr(cand, m.scene)
            if self.goal.preference == "resolution" and quality < self._floor_psnr - 0.05:
                continue
            times = self.model.predict(cand)
            budget = 1000.0 / self._fps_of(cand)
            if any(times.p50[s] > budget * UP_MARGIN for s in STAGES):
                continue
            extra = times.cpu_cores(self._fps_of(cand)) - here_cpu
            if extra > 0 and extra > spare:
                lack = extra - spare  # the host's idle cores already count in spare
                short = lack if short is None else min(short, lack)
                continue
            score = quality - self._switch_cost(current, cand)
            if best is None or score > best[0]:
                best = (score, cand, extra)
        self.state.cores_short = short if best is None else None
        return None if best is None else (best[1], best[2])

    def _up_reach(self, current: Setting) -> float:
        """How far one step up may move the scale: one ladder step, or straight back to
        the setting that held before the last step down (the last known good, as GCC
        returns to the rate before a transient loss)."""
        good = self._last_good
        if good is None or good.scale >= current.scale:
            return SCALE_STEP
        return max(SCALE_STEP, current.scale - good.scale)

    def _switch(
        self,
        m: Measurement,
        setting: Setting,
        direction: Literal["down", "up", "back", "goal"],
        why: str,
    ) -> Decision:
        previous = self.state.setting
        if direction != "up":
            self._last_up = None
        if direction == "down" and self._last_good is None:
            self._last_good = previous
        elif (
            direction == "up"
            and self._last_good is not None
            and (setting.scale <= self._last_good.scale)
        ):
            self._last_good = None  # back where it was: the next climb is careful again
        self.state = replace(
            self.state,
            setting=setting,
            expected_psnr_db=self.model.expected_psnr(setting, m.scene),
            reason=why,
            switches=self.state.switches + 1,
            last_change_at=m.now,
            at_floor=False,
        )
        self._said_floor = False
        return Decision(
            setting=setting,
            previous=previous,
            direction=direction,
            reason=why,
            expected_psnr_db=self.state.expected_psnr_db,
            predicted=self.model.predict(setting),
            target_fps=self.goal.target_fps,
        )


def _best(scored: list[tuple[float, Setting, StageTimes]]) -> Setting:
    """The highest score; between equals, the cheaper."""
    return max(scored, key=lambda x: (x[0], -x[2].cpu_cores(1.0)))[1]


def _finite(values: Mapping[str, float]) -> dict[str, float]:
    """Stage times a window can trust: finite and not negative (NaN, Inf or a missing
    stage means "not measured", never zero)."""
    out: dict[str, float] = {}
    for k, v in values.items():
        try:
            f = float(v)
        except (TypeError, ValueError):
            continue
        if math.isfinite(f) and f >= 0.0:
            out[k] = f
    return out


def _idle(m: Measurement) -> float | None:
    busy = m.host_busy_cores
    if busy is None or not math.isfinite(busy) or not math.isfinite(m.host_cores):
        return None
    return max(0.0, m.host_cores - busy)


def _is_temporal(method: str) -> bool:
    from upscalers import registry

    return registry.is_temporal(method)
