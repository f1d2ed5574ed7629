"""``upcast bench relay`` end to end, small: both relays (ours and moq-rs's Rust core)
each as a process, a 640x360 synthetic publisher, 2 load-test viewers for 3 s, through
``run(args)`` into a JSON report. Timing is not asserted (a loaded 2-core machine runs
this): only that the report has its shape and every viewer on both relays got frames.

Outside CI the test skips when moq-rs is not installed; under ``CI=true`` (the dev
extras install it) a missing package fails instead.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import pytest

from server.bench.relay import bench
from server.bench.relay.profile import own_time, own_time_by_file

if os.environ.get("CI"):
    import moq  # noqa: F401
else:
    pytest.importorskip("moq", reason="moq-rs not installed: pip install -e '.[dev]'")

CASE_NUMBERS = (
    "relay_cpu_percent",
    "relay_cpu_percent_idle",
    "cpu_per_viewer_percent",
    "fps_min",
    "fps_mean",
    "relay_rss_mb",
)


def parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    return parser.parse_args(argv)


def test_both_relays_measured_with_two_viewers(tmp_path: Path) -> None:
    out = tmp_path / "relay.json"
    small = ["--viewers", "2", "--duration", "3", "--idle-s", "1", "--warmup", "1"]
    args = parse(
        [*small, "--size", "640x360", "--json", str(out), "--profile", str(tmp_path / "profile")]
    )
    assert bench.run(args) == 0
    report = json.loads(out.read_text())
    assert report["benchmark"] == "relay"
    assert report["config"]["viewers"] == [2]
    assert report["config"]["bitrate_kbps"] > 0  # one bitrate, for both engines
    cases = {c["name"]: c for c in report["cases"]}
    assert set(cases) == {"upcast 2 viewers", "moq-rs 2 viewers"}
    for name, case in cases.items():
        assert "error" not in case, case
        for key in CASE_NUMBERS:
            assert isinstance(case[key], int | float), (name, key)
        assert case["relay_cpu_percent"] > 0 and case["relay_rss_mb"] > 0, case
        assert case["connected"] == 2 and case["failed"] == 0, case
        assert len(case["viewer_fps"]) == 2 and min(case["viewer_fps"]) > 0, case
        assert case["lost_frames"] == sum(case["lost_per_viewer"]) >= 0
        assert case["median_ms"] is not None and case["p95_ms"] is not None
    # py-spy ran on ours (or says why not, where ptrace is not allowed); never on Rust.
    profile = cases["upcast 2 viewers"]["profile"]
    assert "top_own_time" in profile or profile["error"], profile
    assert "profile" not in cases["moq-rs 2 viewers"]
    for ratio in report["ratios"]:
        assert (ratio["numerator"], ratio["denominator"]) == ("upcast", "moq-rs")


def test_without_moq_rs_only_upcast_may_run(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(bench, "moq_rs_available", lambda: False)
    assert bench.run(parse(["--engines", "upcast,moq-rs"])) == 2
    assert "pip install" in capsys.readouterr().err


def test_own_time_sums_the_leaf_of_each_stack() -> None:
    raw = "main;run;send (q.py:1) 5\nmain;run;encrypt (c.py:9) 6\nmain;send (q.py:1) 2\n"
    total, top = own_time(raw + "not a stack line\n")
    assert total == 13
    assert top == [("send (q.py:1)", 7), ("encrypt (c.py:9)", 6)]
    assert own_time_by_file(raw) == [("q.py", 7), ("c.py", 6)]
