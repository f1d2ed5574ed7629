"""``upcast bench capture`` runs end to end on a small screen: every grabber exact, notes made."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from server.bench.app import capture as bench
from server.game.x11.grabbers import GRABBERS


def test_bench_capture_smoke(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    out = tmp_path / "capture.json"
    args = parser.parse_args(
        ["--json", str(out), "--sizes", "64x36", "--rounds", "2", "--frames", "3"]
    )
    assert bench.run(args) == 0
    report = json.loads(out.read_text())
    assert report["benchmark"] == "bench_capture"
    cases = {c["name"]: c for c in report["cases"]}
    assert set(cases) == {"64x36/memcpy"} | {f"64x36/{g}" for g in GRABBERS}
    for grabber in GRABBERS:
        case = cases[f"64x36/{grabber}"]
        assert case["pixels_exact"] and case["pixels_exact_after"], case
        assert case["count"] == 6 and case["p95_ms"] >= case["median_ms"] > 0
    assert len(report["ratios"]) == len(GRABBERS)
    assert any(n.startswith("PASS: at 64x36 the fastest") or "FAIL: at 64x36" in n
               for n in report["notes"])  # fmt: skip
