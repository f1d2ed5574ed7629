"""``upcast bench network`` for real: 5 s of ``lan`` and 5 s of ``lte`` (4 Mbit/s)
through the emulator in headless Chromium with one load-test viewer beside it, at
small sizes. Checked: the report's shape (every figure is there), the page's traffic
went through the emulator, and the shaped profile's series carries its capacity.
Then 5 s of ``lan`` with two spectators (``--spectators lan,lte``), each behind its own
emulator: each has a first picture, a delivered ratio and freezes. Figures themselves
are not judged: the machine is shared and the session's rate control is changing.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from server.bench.network.table import table
from server.cli import main
from server.ops.browser_paths import WEB_ROOT
from tests.chromium import browser_marks

pytestmark = [*browser_marks(WEB_ROOT / "index.html"), pytest.mark.timeout(300)]


def test_short_run_reports_every_figure(tmp_path: Path) -> None:
    report_path, plot_path = tmp_path / "network.json", tmp_path / "network.png"
    argv = ["bench", "network", "--profile", "lan", "--profile", "lte", "--seconds", "5"]
    argv += ["--warmup", "2", "--render-size", "160x90", "--viewers", "1"]
    argv += ["--json", str(report_path), "--plot", str(plot_path)]
    assert main(argv) == 0
    report = json.loads(report_path.read_text())
    assert {"benchmark", "machine", "config", "cases", "notes"} <= set(report)
    assert report["benchmark"] == "network"
    lan, lte = report["cases"]
    assert (lan["name"], lte["name"]) == ("lan", "lte")
    for case in (lan, lte):
        assert case["frames_published"] > 0 and case["frames_shown"] > 0, case
        assert 0 < case["delivered_ratio"] <= 1.2
        assert {"count", "total_ms", "longest_ms"} <= set(case["freezes"])
        assert 0 <= case["probes"]["proved"] <= case["probes"]["started"]
        assert case["glass_to_glass"]["count"] > 0
        assert case["median_ms"] is not None and case["p95_ms"] >= case["median_ms"]
        assert case["received_psnr_db"]["count"] + case["received_psnr_db"]["unknown"] > 0
        assert case["link"]["down"]["bytes_delivered"] > 0  # the page played through it
        series = case["series"]
        n = len(series["t_s"])
        assert n >= 6  # 5 s at 0.5 s
        for key in ("bitrate_target_bps", "capacity_bps", "link_delivered_bps"):
            assert len(series[key]) == n
        assert any(v is not None for v in series["bitrate_target_bps"])
        viewers = case["viewers"]
        assert viewers["count"] == 1 and "delivery" in viewers["viewers"][0]
    assert set(lan["series"]["capacity_bps"]) == {None}
    assert set(lte["series"]["capacity_bps"]) == {4e6}
    assert [r["name"] for r in report["ratios"]] == ["lan: delivered fps", "lte: delivered fps"]
    assert "lte" in table(report["cases"])
    assert plot_path.stat().st_size > 0


def test_short_run_with_spectators_on_their_own_links(tmp_path: Path) -> None:
    """One profile for the player and two tokenless spectators, lan and lte, each behind
    its own emulator, joining as the window opens."""
    report_path = tmp_path / "network.json"
    argv = ["bench", "network", "--profile", "lan", "--spectators", "lan,lte", "--seconds", "5"]
    argv += ["--warmup", "2", "--render-size", "160x90", "--json", str(report_path)]
    assert main(argv) == 0
    report = json.loads(report_path.read_text())
    assert report["config"]["spectators"] == ["lan", "lte"]
    (case,) = report["cases"]
    assert case["frames_shown"] > 0 and case["delivered_ratio"] is not None  # the player
    spectators = case["spectators"]
    assert [s["profile"] for s in spectators] == ["lan", "lte"]
    for s in spectators:
        assert isinstance(s["first_picture_ms"], float) and s["first_picture_ms"] > 0, s
        # As the player's: frames in flight at the window's edges can put it a little over 1.
        assert 0 <= s["delivered_ratio"] <= 1.2, s
        assert {"count", "total_ms", "longest_ms"} <= set(s["freezes"])
        assert s["link_down_bytes"] > 0  # it played through its own emulator
        assert "rendition_seconds" in s and "rendition_switches" in s  # null: an older page
        assert s["glass_to_glass"]["count"] >= 0
    summary = report["spectators"]
    assert summary["count"] == 2 and summary["without_picture"] == []
    for key in ("worst_first_picture_ms", "worst_delivered_ratio", "worst_longest_freeze_ms"):
        assert summary[key]["player_profile"] == "lan"
    assert [r["name"] for r in report["ratios"]] == [
        "lan: delivered fps",
        "lan: spectator lan: delivered fps",
        "lan: spectator lte: delivered fps",
    ]
