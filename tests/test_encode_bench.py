"""``upcast bench encode`` runs end to end on a few small frames and reports zero delay."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from server.bench import encode as bench


def test_bench_encode_smoke(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    out = tmp_path / "encode.json"
    args = parser.parse_args(
        ["--json", str(out), "--sizes", "320x180", "--frames", "20", "--warmup", "2",
         "--force-keyframe-every", "8", "--psnr-every", "1"]
    )  # fmt: skip
    assert bench.run(args) == 0
    report = json.loads(out.read_text())
    assert report["benchmark"] == "encode"
    (case,) = report["cases"]
    assert case["name"] == "encode_320x180"
    assert case["median_ms"] > 0 and case["p95_ms"] >= case["median_ms"]
    assert case["mux_delay_frames_max"] == 0
    assert case["pictures_per_fragment"] == [1]
    # Requested at frame 8 (133 ms), held by the 250 ms cooldown after the IDR at
    # frame 0, made at frame 15 (250 ms); the request at 16 is within 250 ms of that.
    assert case["keyframes"]["count"] == 1
    assert case["all"]["psnr_frames"] == 20
