"""``upcast bench framegen`` end to end at a tiny size: the report a user reads."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from server.bench import framegen


def test_report_scores_every_method_against_the_rendered_truth(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    framegen.add_arguments(parser)
    out = tmp_path / "fg.json"
    args = parser.parse_args(
        [
            "--json",
            str(out),
            "--plot",
            str(tmp_path / "fg.png"),
            "--scenes",
            "slow_pan,static",
            "--size",
            "160x90",
            "--frames",
            "3",
            "--tiles",
            "16",
            "--flip-frames",
            "1",
        ]
    )
    assert framegen.run(args) == 0
    report = json.loads(out.read_text())
    assert (tmp_path / "fg.png").stat().st_size > 0
    cases = {c["name"]: c for c in report["cases"]}
    render = cases["render"]["median_ms"]
    assert render > 0
    for scene in ("slow_pan", "static"):
        for method in ("repeat", "splat", "backward_warp", "mpe16", "mpe16_torch", "mpe16_none"):
            c = cases[f"{scene}/{method}"]
            assert c["predicted"] == 3 and c["refused"] == 0
            # Both yardsticks of cost, each the median cost over its render median.
            assert abs(c["cost_over_size_render"] - c["median_ms"] / render) < 1e-9
            scene_render = c["scene_render_median_ms"]
            assert abs(c["cost_over_render"] - c["median_ms"] / scene_render) < 1e-9
            assert 0.0 <= c["sky_share"] <= 1.0
    # A still camera: every method reproduces the frame exactly (PSNR capped).
    assert cases["static/mpe16"]["psnr_db"] == framegen.PSNR_CAP_DB
    # A moving camera: MPE beats repeating the frame, and both backends agree.
    pan = {m: cases[f"slow_pan/{m}"]["psnr_db"] for m in ("repeat", "mpe16", "mpe16_torch")}
    assert pan["mpe16"] > pan["repeat"] + 1.0  # at 160x90 the pan moves ~1 px a frame
    assert abs(pan["mpe16"] - pan["mpe16_torch"]) < 0.5
    assert any("mpe16 over repeat" in n for n in report["notes"])
