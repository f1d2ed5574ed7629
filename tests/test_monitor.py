"""Frame-rate monitor: fps, jitter, stage percentiles, budget warnings, Prometheus."""

from __future__ import annotations

import logging
import re

import pytest
from prometheus_client import CollectorRegistry, generate_latest

from server.frames.monitor import FrameRateMonitor
from server.frames.timing import Stage, new_stamps


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _stamps(render_ms: float, upscale_ms: float) -> object:
    s = new_stamps()
    t0 = 1_000_000_000
    s[Stage.RENDER_START, 0] = t0
    s[Stage.RENDER_END, 0] = t0 + int(render_ms * 1e6)
    s[Stage.UPSCALE_START, 0] = t0 + int(render_ms * 1e6) + 100_000
    s[Stage.UPSCALE_END, 0] = s[Stage.UPSCALE_START, 0] + int(upscale_ms * 1e6)
    return s


def test_fps_and_jitter_follow_the_frame_times() -> None:
    clock = FakeClock()
    mon = FrameRateMonitor("session", 30.0, clock=clock, window_s=2.0)
    for i in range(60):
        clock.t = 100.0 + i / 30.0
        mon.frame()
    snap = mon.snapshot()
    assert snap.fps == pytest.approx(30.0, rel=1e-6)
    assert snap.jitter_ms == pytest.approx(0.0, abs=1e-6)
    # Alternating 20 ms / 46.7 ms intervals: same 30 fps on average, visible jitter.
    mon2 = FrameRateMonitor("session", 30.0, clock=clock, window_s=10.0)
    t = 200.0
    for i in range(60):
        t += 0.020 if i % 2 else 0.0467
        clock.t = t
        mon2.frame()
    assert mon2.snapshot().jitter_ms == pytest.approx(13.35, abs=0.2)


def test_window_forgets_old_frames() -> None:
    clock = FakeClock()
    mon = FrameRateMonitor("relay", 60.0, clock=clock, window_s=1.0)
    for i in range(10):
        clock.t = 100.0 + i * 0.01
        mon.frame()
    clock.t = 105.0
    assert mon.snapshot().fps == 0.0
    assert mon.frames == 10


def test_stage_percentiles_and_budget_warning(caplog: pytest.LogCaptureFixture) -> None:
    clock = FakeClock()
    registry = CollectorRegistry()
    mon = FrameRateMonitor("session", 60.0, clock=clock, registry=registry)
    for i in range(40):
        clock.t = 100.0 + i / 60.0
        mon.frame(_stamps(render_ms=10.0, upscale_ms=30.0 if i % 2 else 5.0), dropped=i % 10 == 0)  # type: ignore[arg-type]
    snap = mon.snapshot()
    assert snap.stages["render"].p50_ms == pytest.approx(10.0)
    assert snap.stages["upscale"].p95_ms == pytest.approx(30.0)
    assert snap.dropped == 4
    with caplog.at_level(logging.WARNING):
        missed = mon.check_budgets()
        again = mon.check_budgets()
    assert missed == ["upscale"] == again  # 30 ms > one 60 fps period; render is fine
    assert sum("upscale" in r.message for r in caplog.records) == 1  # rate-limited
    text = generate_latest(registry).decode()
    assert 'upcast_frames_total{component="session"} 40.0' in text
    assert 'upcast_dropped_frames_total{component="session"} 4.0' in text
    assert 'upcast_stage_latency_seconds_count{component="session",stage="render"} 40.0' in text
    assert 'upcast_stage_budget_misses_total{component="session",stage="upscale"} 2.0' in text


def test_bad_target_is_refused() -> None:
    with pytest.raises(ValueError, match="target_fps"):
        FrameRateMonitor("x", 0.0)


def test_a_new_target_moves_the_default_budgets_and_keeps_given_ones() -> None:
    mon = FrameRateMonitor("session", 30.0)
    mon.set_target_fps(15.0)
    assert mon.target_fps == 15.0
    assert mon.budgets_ms["render"] == pytest.approx(1000 / 15)
    given = FrameRateMonitor("session", 30.0, budgets_ms={"render": 5.0})
    given.set_target_fps(15.0)
    assert given.budgets_ms == {"render": 5.0}
    with pytest.raises(ValueError, match="target_fps"):
        mon.set_target_fps(float("nan"))


def test_monitors_share_one_registry_by_component() -> None:
    registry = CollectorRegistry()
    a = FrameRateMonitor("relay/a", None, registry=registry)
    b = FrameRateMonitor("relay/b", None, registry=registry, budgets_ms={"relay": 1.0})
    again = FrameRateMonitor("relay/a", None, registry=registry)  # a broadcast came back
    for mon in (a, b, again):
        mon.frame()
    b.record_stage("relay", 3.0)
    assert b.check_budgets() == ["relay"] and a.check_budgets() == []
    text = generate_latest(registry).decode()
    assert 'upcast_frames_total{component="relay/a"} 2.0' in text
    assert 'upcast_frames_total{component="relay/b"} 1.0' in text


def test_budget_warnings_are_summarised_not_repeated(caplog: pytest.LogCaptureFixture) -> None:
    """A stack that cannot hold its target: 90 s of one check a second, every stage and the
    rate over budget, gives one line at the first miss and then one per WARN_EVERY_S."""
    from server.frames.monitor import WARN_EVERY_S

    clock = FakeClock()
    mon = FrameRateMonitor("session", 60.0, clock=clock)
    frame = 0
    with caplog.at_level(logging.WARNING, logger="server.frames.monitor"):
        for second in range(90):
            for _ in range(20):  # 20 fps against a 60 fps target
                clock.t = 100.0 + frame / 20.0
                frame += 1
                mon.frame(_stamps(render_ms=40.0, upscale_ms=30.0))  # type: ignore[arg-type]
            assert set(mon.check_budgets()) == {"fps", "render", "upscale"}, second
    lines = [r.getMessage() for r in caplog.records]
    assert 3 <= len(lines) <= 1 + 90 / WARN_EVERY_S, lines
    # Each line names every missed budget and how often it was missed since the last one.
    assert all("fps target" in line and "render" in line and "upscale" in line for line in lines)
    counts = re.findall(r"\[(\d+)/(\d+) checks\]", lines[1])
    assert counts and all(a == b and int(a) >= WARN_EVERY_S - 1 for a, b in counts)
