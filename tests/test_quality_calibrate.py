"""``upcast calibrate``: this machine's times for adaptive quality, and which table a
session uses."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from server.cli import main
from server.session.quality.calibrate import (
    CACHE_ENV,
    calibration_path,
    load_machine_figures,
    machine_description,
    measure_times,
    stamp,
    times_from_eval,
)
from server.session.quality.figures import (
    EVAL_REPORT,
    FIGURES_PATH,
    FiguresError,
    derive_figures,
    parse_figures,
)


def _shipped() -> dict[str, Any]:
    raw: dict[str, Any] = json.loads(FIGURES_PATH.read_text())
    return raw


@pytest.fixture
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv(CACHE_ENV, str(tmp_path))
    return tmp_path


def test_measured_times_replace_the_shipped_ones_and_keep_the_quality() -> None:
    base = _shipped()
    table = measure_times(base, methods=["bilinear"], display=(128, 72), frames=2)
    measured = table["methods"]["bilinear"]
    assert len(measured["median_ms"]) == len(base["methods"]["bilinear"]["scales"])
    assert all(v > 0 for v in measured["median_ms"])
    assert all(p >= m for p, m in zip(measured["p95_ms"], measured["median_ms"], strict=True))
    # 128x72 is 100x fewer pixels than the shipped 1280x720: the kept times say so.
    assert table["display_pixels"] == 128 * 72
    kept = table["methods"]["bicubic"]["median_ms"]
    assert kept == pytest.approx(
        [v * 128 * 72 / base["display_pixels"] for v in base["methods"]["bicubic"]["median_ms"]],
        abs=1e-3,
    )
    assert (
        "bicubic@2" in table["calibration_kept"] and "bilinear@2" not in table["calibration_kept"]
    )
    for name, entry in table["methods"].items():  # quality does not depend on the machine
        assert entry["psnr_db"] == base["methods"][name]["psnr_db"]
    assert table["predict_ms"] > 0 and table["render_ms"] > 0
    figures = parse_figures(stamp(table, "measured"))
    assert figures.display_pixels == 128 * 72


def test_measuring_an_unknown_method_names_the_known_ones() -> None:
    with pytest.raises(FiguresError, match=r"not in the table: nope.*bilinear"):
        measure_times(_shipped(), methods=["nope"], frames=1)


def test_times_from_an_eval_report_are_the_reports() -> None:
    base = _shipped()
    report = json.loads(EVAL_REPORT.read_text())
    table = times_from_eval(base, report)
    framegen = {"cases": [{"kind": "render", "median_ms": 1.0},
                          {"method": "mpe16", "median_ms": 1.0, "scene": "x", "psnr_db": 30}],
                "config": {"size": "640x360"}}  # fmt: skip
    expected = derive_figures(report, framegen)["methods"]
    for name, entry in table["methods"].items():
        assert entry["median_ms"] == expected[name]["median_ms"]
    assert table["calibration_kept"] == []
    assert table["predict_ms"] == base["predict_ms"]  # not in an eval report: kept
    with pytest.raises(FiguresError, match="eval upscalers"):
        times_from_eval(base, {"benchmark": "serve"})


def test_a_session_uses_this_machines_calibration_and_falls_back_with_the_reason(
    cache: Path,
) -> None:
    shipped = load_machine_figures()
    assert shipped.source.startswith("the shipped table")
    table = stamp(_shipped(), "measured")
    table["methods"]["bilinear"]["median_ms"] = [1.0, 1.0, 1.0]
    path = calibration_path()
    assert path.parent == cache
    path.write_text(json.dumps(table))
    mine = load_machine_figures()
    assert str(path) in mine.source and "measured" in mine.source
    assert mine.figures.methods["bilinear"].median_ms == (1.0, 1.0, 1.0)
    # Another machine's file under this key (copied over, or the CPU changed): not used.
    table["calibration"]["machine"] = "another CPU, 64 cores"
    path.write_text(json.dumps(table))
    other = load_machine_figures()
    assert other.source.startswith("the shipped table") and "another CPU" in other.source
    path.write_text("{ truncated")
    broken = load_machine_figures()
    assert broken.source.startswith("the shipped table") and "not used" in broken.source
    assert broken.figures.methods == shipped.figures.methods


def test_the_command_writes_a_table_sessions_load(
    cache: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["calibrate", "--methods", "bilinear", "--frames", "2", "--display-size", "128x72"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "bilinear" in out and f"wrote {calibration_path()}" in out
    written = json.loads(calibration_path().read_text())
    assert written["calibration"]["machine"] == machine_description()
    assert main(["calibrate", "--show"]) == 0
    assert str(calibration_path()) in capsys.readouterr().out


def test_the_command_refuses_bad_input_clearly(
    cache: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    garbage = tmp_path / "report.json"
    garbage.write_text("[1, 2")
    assert main(["calibrate", "--from-eval", str(garbage)]) == 2
    assert "cannot read" in capsys.readouterr().err
    garbage.write_text(json.dumps({"benchmark": "serve", "cases": []}))
    assert main(["calibrate", "--from-eval", str(garbage)]) == 2
    assert "eval upscalers" in capsys.readouterr().err
    assert main(["calibrate", "--frames", "0"]) == 2
    assert main(["calibrate", "--methods", "nope", "--frames", "1"]) == 2
    assert "not in the table" in capsys.readouterr().err
    assert not calibration_path().exists()
