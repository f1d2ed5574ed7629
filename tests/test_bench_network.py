"""``upcast bench network``: its pieces without a stack (the short real run is in
test_bench_network_e2e.py)."""

from __future__ import annotations

import pytest

from server.bench.network.page import ShownFrames, counter_deltas
from server.bench.network.series import RateSeries, capacity_bps
from server.cli import main
from server.net import PROFILES


def test_capacity_follows_the_schedule() -> None:
    drop = PROFILES["drop"]
    assert [capacity_bps(drop, i) for i in range(3)] == [20e6, 2e6, 20e6]
    blackout = PROFILES["blackout"]
    assert [capacity_bps(blackout, i) for i in range(3)] == [20e6, 0.0, 20e6]
    assert capacity_bps(PROFILES["lan"], 0) is None


def test_rate_series_takes_rates_over_each_span() -> None:
    series = RateSeries(PROFILES["drop"], t0=100.0)
    series.sample(100.0, target_bps=3_000_000, step=0, link_bytes=0, page_bytes=None)
    series.sample(100.5, target_bps=3_000_000, step=0, link_bytes=125_000, page_bytes=1000)
    series.sample(
        101.0, target_bps=1_000_000, step=1, link_bytes=250_000, page_bytes=63_500, frame_divisor=2
    )
    data = series.as_dict()
    assert data["t_s"] == [0.5, 1.0]
    assert data["capacity_bps"] == [20e6, 2e6]
    assert data["link_delivered_bps"] == [2e6, 2e6]
    assert data["page_received_bps"] == [None, 1e6]
    assert data["bitrate_target_bps"] == [3_000_000, 1_000_000]
    assert data["frame_divisor"] == [None, 2]
    assert series.means()["capacity_bps"] == 11e6


def test_freezes_between_drawn_frames() -> None:
    shown = ShownFrames()
    shown.start([0.0, 33.0])  # before the window: only the last draw counts
    shown.add([66.0, 99.0, 400.0, 433.0])  # one gap of 301 ms
    shown.add([466.0])
    shown.finish(1000.0)  # still frozen at the end: 534 ms
    assert shown.shown == 5
    s = shown.summary()
    assert s["count"] == 2
    assert s["total_ms"] == pytest.approx(301 + 534)
    assert s["longest_ms"] == pytest.approx(534)


def test_page_counters_are_differences_of_what_the_page_has() -> None:
    start = {"framesLost": 2, "groupsSkipped": 1, "late": 0, "recovery": {"keyframeRequests": 1}}
    end: dict[str, object] = {"framesLost": 5, "groupsSkipped": 1, "late": 4}
    end |= {"longestFreezeMs": 250.0, "recovery": {"keyframeRequests": 3}}
    deltas = counter_deltas(start, end)
    assert deltas == {
        "framesLost": 3,
        "groupsSkipped": 0,
        "late": 4,
        "longestFreezeMs_since_start": 250.0,
        "recovery_keyframeRequests": 2,
    }
    assert counter_deltas({}, {}) == {}


def test_bad_arguments_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "network", "--profile", "moon"]) == 2
    assert "unknown profile 'moon'" in capsys.readouterr().err
    assert main(["bench", "network", "--seconds", "0"]) == 2
