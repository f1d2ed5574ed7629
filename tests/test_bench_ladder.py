"""``upcast bench ladder`` runs the real ladder on a short clip and writes its report."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path


def test_the_report_has_each_rung_against_the_players_track(tmp_path: Path) -> None:
    out = tmp_path / "ladder.json"
    subprocess.run(
        [sys.executable, "-m", "server.cli", "bench", "ladder", "--json", str(out),
         "--display-size", "640x360", "--frames", "40", "--warmup", "2", "--psnr-every", "5"],
        check=True, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    report = json.loads(out.read_text())
    cases = {c["name"]: c for c in report["cases"]}
    assert set(cases) == {"ladder conversion", "player", "video.320x180", "video.160x90"}
    # Shared with the player's encoder, as in the session: no second conversion.
    assert cases["ladder conversion"]["cpu_ms_per_frame"] == 0
    for name in ("video.320x180", "video.160x90"):
        rung = cases[name]
        assert rung["frames"] == 40 and rung["keyframes"] >= 1  # one a second (30 fps)
        assert rung["cpu_vs_player"] > 0
        assert 0 < rung["achieved_bitrate"] <= 1.5 * rung["bitrate_cap"]
        # The rung shows the frame it was given (a wrong or stale picture is far below).
        assert rung["psnr_own_size_db"] > 18
    ratios = {r["name"]: r["ratio"] for r in report["ratios"]}
    assert ratios["ladder_cpu"] > 0
    assert "of one core" in report["notes"][-1]
