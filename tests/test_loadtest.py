"""upcast loadtest against a real in-process Relay and the synthetic publisher.

One event loop (asyncio.run) holds the Relay on port 0, the synthetic publisher
at 320x180/30 fps and the load test's viewers, so the test needs no free port
and nothing outlives it. Frame rate and latency are checked loosely: the CI
machine has two cores shared with other tests.
"""

from __future__ import annotations

import asyncio
import json
import socket
import time
from collections.abc import Coroutine
from pathlib import Path
from typing import Any

import pytest

from server.cli import main
from server.frames.frame import Size
from server.loadtest.findmax import FindMaxResult, find_max, ladder
from server.loadtest.plan import LoadConfig, make_plan, parse_relay_url
from server.loadtest.relay_probe import parse_cpu_seconds
from server.loadtest.results import build_report, table, verdict
from server.loadtest.run import LoadResult, LoadTestError, run_load
from server.loadtest.synthetic import FrameSource, SyntheticPublisher, SyntheticSettings
from server.loadtest.viewer_stats import ViewerStats
from server.quic.certs import CertBundle, generate_cert
from server.relay.relay import Relay, RelayConfig

SMALL = Size(320, 180)


@pytest.fixture(scope="module")
def cert(tmp_path_factory: pytest.TempPathFactory) -> CertBundle:
    return generate_cert(directory=tmp_path_factory.mktemp("cert"))


def run(coro: Coroutine[Any, Any, Any], timeout: float = 30.0) -> Any:
    async def bounded() -> Any:
        async with asyncio.timeout(timeout):
            return await coro

    return asyncio.run(bounded())


async def with_relay_and_publisher(cert: CertBundle, body: Any, *, fps: float = 30.0) -> Any:
    relay = Relay(RelayConfig(host="127.0.0.1", port=0), cert)
    await relay.start()
    url = f"http://127.0.0.1:{relay.port}/"
    stop = asyncio.Event()
    publisher = SyntheticPublisher(SyntheticSettings(url, SMALL, fps, gop_seconds=1.0))
    task = asyncio.create_task(publisher.run(stop))
    try:
        return await body(url)
    finally:
        stop.set()
        await task
        await relay.close()


def test_three_viewers_get_every_frame_with_latency(cert: CertBundle, tmp_path: Path) -> None:
    async def body(url: str) -> LoadResult:
        config = LoadConfig(url, viewers=3, duration_s=3.0, warmup_s=1.0)
        return await run_load(config, progress=False)

    result: LoadResult = run(with_relay_and_publisher(cert, body))
    assert len(result.stats) == 3
    for s in result.stats:
        assert s.connected and s.error is None and s.catalog
        assert s.fps() == pytest.approx(30.0, abs=3.0), s.summary()
        assert s.lost == 0
        assert s.bad_fragments == 0
        assert len(s.publish_to_receive_ms) >= 60
        assert min(s.publish_to_receive_ms) > 0
        assert min(s.render_end_to_receive_ms) >= min(s.publish_to_receive_ms)
    assert result.relay_cpu_percent is not None and result.relay_cpu_percent > 0
    assert result.loadtest_cpu_percent is not None

    path = tmp_path / "report.json"
    build_report(result).write(path)
    report = json.loads(path.read_text())
    assert {"machine", "config", "cases", "verdict", "benchmark"} <= set(report)
    names = [c["name"] for c in report["cases"]]
    assert names == ["viewer 0", "viewer 1", "viewer 2", "summary"]
    summary = report["cases"][-1]
    for key in ("fps_min", "fps_median", "lost_total", "median_ms", "p95_ms", "relay_cpu_percent"):
        assert summary[key] is not None, key
    assert summary["publish_to_receive_ms"]["p99"] > 0
    assert report["config"]["processes"] == 1
    assert report["verdict"]["viewers"] == 3
    text = table(result)
    assert "relay CPU" in text and "verdict" in text


def test_worker_processes(cert: CertBundle) -> None:
    async def body(url: str) -> LoadResult:
        config = LoadConfig(url, viewers=2, duration_s=2.0, warmup_s=1.0, processes=2)
        return await run_load(config, progress=False)

    result: LoadResult = run(with_relay_and_publisher(cert, body), timeout=40.0)
    assert result.processes == 2
    assert [s.viewer for s in result.stats] == [0, 1]
    for s in result.stats:
        assert s.connected and s.frames > 30 and s.lost == 0, s.summary()
    assert len(result.worker_cpu_percent) == 2


def test_bad_arguments_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    base = ["loadtest", "--relay", "http://localhost:4443/"]
    cases = [
        ([*base, "--viewers", "0", "--duration", "5"], "--viewers"),
        ([*base, "--viewers", "1001", "--duration", "5"], "--viewers"),
        ([*base, "--viewers", "3", "--duration", "0"], "--duration"),
        ([*base, "--viewers", "3", "--duration", "99999"], "--duration"),
        (["loadtest", "--relay", "ftp://x/", "--viewers", "1", "--duration", "1"], "--relay"),
        (["loadtest", "--relay", "not a url", "--viewers", "1", "--duration", "1"], "--relay"),
        ([*base, "--viewers", "2", "--duration", "1", "--processes", "3"], "--processes"),
    ]
    for argv, word in cases:
        assert main(argv) == 2, argv
        assert word in capsys.readouterr().err, argv


def _closed_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_unreachable_relay_fails_fast(capsys: pytest.CaptureFixture[str]) -> None:
    port = _closed_port()
    start = time.monotonic()
    argv = ["loadtest", "--relay", f"http://127.0.0.1:{port}/", "--viewers", "2"]
    assert main([*argv, "--duration", "5", "--quiet"]) == 1
    assert time.monotonic() - start < 6.0
    assert "unreachable" in capsys.readouterr().err


def test_no_broadcast_is_a_clear_error(cert: CertBundle) -> None:
    async def body() -> None:
        relay = Relay(RelayConfig(host="127.0.0.1", port=0), cert)
        await relay.start()
        try:
            url = f"http://127.0.0.1:{relay.port}/"
            config = LoadConfig(url, viewers=1, duration_s=1.0, wait_broadcast_s=0.3)
            with pytest.raises(LoadTestError, match="no broadcast 'game'"):
                await run_load(config, progress=False)
        finally:
            await relay.close()

    run(body())


def test_loop_source_restamps_fragments() -> None:
    from server.media.cmaf_read import parse_fragment

    source = FrameSource(SyntheticSettings("http://x/", SMALL, 30.0, gop_seconds=0.5))
    frames = [source.next(i, 1_000_000 + i * 33_333) for i in range(40)]
    infos = [parse_fragment(f.fragment) for f in frames]
    assert [i.decode_time for i in infos] == [1_000_000 + i * 33_333 for i in range(40)]
    assert [f.keyframe for f in frames[:16]] == [True] + [False] * 14 + [True]
    sequences = [i.sequence for i in infos]
    assert sequences == sorted(set(sequences))
    source.want_keyframe()  # a new viewer: the loop restarts at its IDR (after 250 ms)
    time.sleep(0.26)
    assert source.next(40, 3_000_000).keyframe


def test_stats_window_loss_and_matching() -> None:
    stats = ViewerStats(0, window=(10.0, 11.0))
    wall = 1_000_000_000

    def frame(n: int, now: float, *, timing_first: bool = False) -> None:
        record = {"n": n, "pts_us": n * 1000, "stamps": {"publish": wall + n * 1000 - 5000}}
        if timing_first:
            stats.on_timing(record, now)
        stats.on_video(n * 1000, 100, now, wall + n * 1000)
        if not timing_first:
            stats.on_timing(record, now)

    frame(0, 9.9)  # before the window: not counted
    for n in range(1, 10):
        if n != 5:  # frame 5 never arrives
            frame(n, 10.0 + n / 10, timing_first=n == 3)
    stats.on_timing({"n": 5, "pts_us": 5000, "stamps": {}}, 10.5)
    assert stats.frames == 8
    assert stats.lost == 1
    assert stats.published == 9
    assert stats.publish_to_receive_ms == [5.0] * 8
    assert stats.fps() == pytest.approx(8.0)


def test_plan_and_parsing() -> None:
    config = LoadConfig("http://[::1]:4443/", viewers=41, duration_s=10, ramp_per_s=20)
    assert config.problem() is None
    plan = make_plan(config, 100.0)
    assert plan.connect_at(40) == pytest.approx(102.0)
    assert plan.window == pytest.approx((104.0, 114.0))
    assert parse_relay_url("http://[::1]:4443/").authority == "[::1]:4443"
    text = "# HELP x\nprocess_cpu_seconds_total 12.5\nprocess_open_fds 9.0\n"
    assert parse_cpu_seconds(text) == 12.5
    assert parse_cpu_seconds("nothing") is None
    assert ladder(100) == [10, 20, 30, 50, 75, 100]
    assert ladder(45) == [10, 20, 30, 45]


def test_find_max_bisects_between_pass_and_fail(monkeypatch: pytest.MonkeyPatch) -> None:
    capacity = 42
    tried: list[int] = []

    async def fake_run(cfg: LoadConfig, label: str) -> LoadResult:
        tried.append(cfg.viewers)
        plan = make_plan(cfg, 0.0)
        good = cfg.viewers <= capacity
        stats = []
        for i in range(cfg.viewers):
            s = ViewerStats(i, window=plan.window, connected=True)
            s.frames = round(30 * cfg.duration_s) if good else 10
            s.publish_to_receive_ms = [5.0] * 10
            stats.append(s)
        return LoadResult(cfg, plan, stats, 1, [None], None, None, None, (0, 0, 0), (0, 0, 0))

    async def go() -> FindMaxResult:
        config = LoadConfig("http://localhost:1/", viewers=100, duration_s=2.0)
        return await find_max(config, 2.0, fake_run)

    monkeypatch.setattr("server.loadtest.findmax.PAUSE_S", 0.0)
    found = run(go())
    assert tried[:4] == [10, 20, 30, 50]
    assert found.largest_held <= capacity < (found.smallest_failed or 0)
    assert found.smallest_failed is not None
    assert found.smallest_failed - found.largest_held <= max(2, found.largest_held // 10)
    assert verdict(found.steps[0][2])["all_held"]
