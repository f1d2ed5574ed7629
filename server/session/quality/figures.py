"""The speed-against-error table adaptive quality rests on, derived from measurements.

Three committed reports are its source: ``docs/reports/eval_upscalers.json`` (every
upscaler's time and PSNR against the game's ground truth at 1.5x, 2x and 3x, per
scene), ``docs/reports/framegen.json`` (the frame predictor's time and PSNR per
scene) and ``docs/reports/encode_scale.json`` (encoding below the display size: the
encoder's time against the display size's, and the decoded picture's PSNR lost, per
render scale). ``python -m server.session.quality.figures`` rewrites ``figures.json`` beside
this file from them; ``tests/test_quality_figures.py`` fails when the two disagree,
so the table is never typed in and cannot drift from the reports. The table ships in
the package (the reports do not: the Docker build context leaves docs/reports out).

Quality does not depend on the machine; time does. The times here were measured on
the machine named in the table, and the controller rescales them online from the
stage times it measures (model.py), so a faster or slower host, or one loaded by
other sessions, corrects them within seconds.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

FIGURES_PATH = Path(__file__).with_name("figures.json")
ROOT = Path(__file__).resolve().parents[3]
EVAL_REPORT = ROOT / "docs" / "reports" / "eval_upscalers.json"
FRAMEGEN_REPORT = ROOT / "docs" / "reports" / "framegen.json"
ENCODE_REPORT = ROOT / "docs" / "reports" / "encode_scale.json"
PREDICTOR = "mpe16"  # the worker's default predictor (server/worker/prediction.py)
# PSNR of a prediction that is exact (a still scene predicts itself): the report
# writes 100 dB there; any finite cap far above the upscalers' figures serves.
EXACT_PSNR_DB = 100.0


class FiguresError(ValueError):
    """The figures file or a report it is made from is missing or malformed."""


@dataclass(frozen=True)
class MethodFigures:
    """One upscaler at the evaluation's scales (ascending), display-size frames."""

    scales: tuple[float, ...]
    median_ms: tuple[float, ...]
    p95_ms: tuple[float, ...]
    psnr_db: Mapping[str, tuple[float, ...]]  # scene -> PSNR at each scale


@dataclass(frozen=True)
class EncodeFigures:
    """Encoding below the display size: per encoded scale (display / encoded, ascending,
    1 first) the encoder's time against scale 1's, and per render scale the PSNR lost
    against scale 1 (None where not measured: encoded smaller than rendered)."""

    scales: tuple[float, ...]
    ms_ratio: tuple[float, ...]
    render_scales: tuple[float, ...]
    loss_db: tuple[tuple[float | None, ...], ...]  # [render scale][encoded scale]


@dataclass(frozen=True)
class SpeedErrorFigures:
    display_pixels: int  # the size the times were measured at
    machine: str
    methods: Mapping[str, MethodFigures]
    predict_ms: float  # the frame predictor, per predicted frame at predict_pixels
    predict_pixels: int
    predict_psnr_db: Mapping[str, float]  # scene -> PSNR of predicted frames
    render_ms: float  # the built-in renderer, median, at predict_pixels
    scenes: tuple[str, ...]
    encode: EncodeFigures | None = None  # None: the encoded size stays the display's


def _floats(values: Any, what: str) -> tuple[float, ...]:
    if not isinstance(values, list) or not values:
        raise FiguresError(f"{what}: expected a non-empty list of numbers")
    out = tuple(float(v) for v in values)
    if not all(math.isfinite(v) and v >= 0 for v in out):
        raise FiguresError(f"{what}: every value must be finite and >= 0")
    return out


def parse_figures(raw: Mapping[str, Any]) -> SpeedErrorFigures:
    """The table from its JSON form; raises FiguresError naming what is wrong."""
    try:
        methods: dict[str, MethodFigures] = {}
        for name, entry in raw["methods"].items():
            scales = _floats(entry["scales"], f"{name}.scales")
            if list(scales) != sorted(set(scales)):
                raise FiguresError(f"{name}.scales must be ascending without repeats")
            psnr = {s: _floats(v, f"{name}.psnr_db.{s}") for s, v in entry["psnr_db"].items()}
            columns = [_floats(entry["median_ms"], f"{name}.median_ms"),
                       _floats(entry["p95_ms"], f"{name}.p95_ms"), *psnr.values()]  # fmt: skip
            if any(len(c) != len(scales) for c in columns):
                raise FiguresError(f"{name}: one figure per scale expected")
            methods[name] = MethodFigures(scales, columns[0], columns[1], psnr)
        predict = {str(k): float(v) for k, v in raw["predict_psnr_db"].items()}
        figures = SpeedErrorFigures(
            display_pixels=int(raw["display_pixels"]),
            machine=str(raw["machine"]),
            methods=methods,
            predict_ms=float(raw["predict_ms"]),
            predict_pixels=int(raw["predict_pixels"]),
            predict_psnr_db=predict,
            render_ms=float(raw["render_ms"]),
            scenes=tuple(str(s) for s in raw["scenes"]),
            encode=_parse_encode(raw["encode"]) if raw.get("encode") is not None else None,
        )
    except (KeyError, TypeError, AttributeError) as exc:
        raise FiguresError(f"malformed speed-against-error figures: {exc!r}") from None
    if not methods:
        raise FiguresError("no method in the figures")
    return figures


def _parse_encode(raw: Mapping[str, Any]) -> EncodeFigures:
    scales = _floats(raw["scales"], "encode.scales")
    if list(scales) != sorted(set(scales)) or scales[0] != 1.0:
        raise FiguresError("encode.scales must be ascending from 1 without repeats")
    ratio = _floats(raw["ms_ratio"], "encode.ms_ratio")
    render = _floats(raw["render_scales"], "encode.render_scales")
    rows = raw["loss_db"]
    if len(ratio) != len(scales) or not isinstance(rows, list) or len(rows) != len(render):
        raise FiguresError("encode: one time ratio per scale and one loss row per render scale")
    loss: list[tuple[float | None, ...]] = []
    for row in rows:
        if not isinstance(row, list) or len(row) != len(scales):
            raise FiguresError("encode.loss_db: one figure (or null) per encoded scale")
        values = tuple(None if v is None else float(v) for v in row)
        if any(v is not None and not (math.isfinite(v) and v >= 0) for v in values):
            raise FiguresError("encode.loss_db: finite and >= 0, or null")
        loss.append(values)
    return EncodeFigures(scales, ratio, render, tuple(loss))


def load_figures(path: Path = FIGURES_PATH) -> SpeedErrorFigures:
    try:
        raw = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise FiguresError(f"cannot read {path}: {exc}") from None
    return parse_figures(raw)


def _size_pixels(text: str) -> int:
    w, h = text.lower().split("x")
    return int(w) * int(h)


def derive_figures(
    eval_report: Mapping[str, Any], framegen_report: Mapping[str, Any]
) -> dict[str, Any]:
    """The table's JSON form from the two reports (plain methods only: the ``+torch``
    and ``+compiled`` variants are the same method on another backend)."""
    config = eval_report["config"]
    scenes = [str(s) for s in config["scenes"]]
    by_method: dict[str, dict[float, Mapping[str, Any]]] = {}
    for case in eval_report["cases"]:
        method = str(case["method"])
        if "+" in method:
            continue
        by_method.setdefault(method, {})
        by_method[method].setdefault(float(case["scale"]), {})
        by_method[method][float(case["scale"])][str(case["scene"])] = case  # type: ignore[index]
    methods: dict[str, Any] = {}
    for method, per_scale in sorted(by_method.items()):
        scales = sorted(per_scale)
        entry: dict[str, Any] = {"scales": scales, "median_ms": [], "p95_ms": [],
                                 "psnr_db": {s: [] for s in scenes}}  # fmt: skip
        for scale in scales:
            cases = per_scale[scale]
            # One time per method and scale: the median over scenes of each scene's figure.
            entry["median_ms"].append(round(_median([c["median_ms"] for c in cases.values()]), 3))
            entry["p95_ms"].append(round(_median([c["p95_ms"] for c in cases.values()]), 3))
            for scene in scenes:
                entry["psnr_db"][scene].append(round(float(cases[scene]["psnr_db"]), 3))
        methods[method] = entry
    predict_ms: list[float] = []
    predict_psnr: dict[str, float] = {}
    render_ms = None
    for case in framegen_report["cases"]:
        if case.get("kind") == "render":
            render_ms = float(case["median_ms"])
        elif case.get("method") == PREDICTOR:
            predict_ms.append(float(case["median_ms"]))
            predict_psnr[str(case["scene"])] = round(min(EXACT_PSNR_DB, float(case["psnr_db"])), 3)
    if render_ms is None or not predict_ms:
        raise FiguresError(f"the frame-generation report has no render case or no {PREDICTOR}")
    machine = eval_report.get("machine", {})
    return {
        "source": ["docs/reports/eval_upscalers.json", "docs/reports/framegen.json"],
        "machine": f"{machine.get('cpu', '?')}, {machine.get('cpu_count', '?')} cores",
        "display_pixels": _size_pixels(str(config["display_size"])),
        "scenes": scenes,
        "methods": methods,
        "predict_ms": round(_median(predict_ms), 3),
        "predict_pixels": _size_pixels(str(framegen_report["config"]["size"])),
        "predict_psnr_db": predict_psnr,
        "render_ms": round(render_ms, 3),
    }


def derive_encode(report: Mapping[str, Any]) -> dict[str, Any]:
    """The encoded-size part of the table from ``upcast bench encode_scale``'s report:
    time ratios averaged over its cases, PSNR lost averaged over scenes (never below 0:
    a smaller size never adds detail; a negative figure is the codec's noise)."""
    cases = [c for c in report["cases"] if "encode_scale" in c]
    ref = {(c["scene"], float(c["render_scale"])): c for c in cases if c["encode_scale"] == 1.0}
    scales = sorted({float(c["encode_scale"]) for c in cases})
    render = sorted({float(c["render_scale"]) for c in cases})
    if not ref or scales[:1] != [1.0]:
        raise FiguresError("the encode_scale report has no encoded scale 1 to compare with")
    ratios: list[float] = []
    loss: list[list[float | None]] = [[] for _ in render]
    for e in scales:
        pairs = [(c, ref[k]) for c in cases if c["encode_scale"] == e
                 and (k := (c["scene"], float(c["render_scale"]))) in ref]  # fmt: skip
        ratios.append(round(_median([c["median_ms"] / r["median_ms"] for c, r in pairs]), 3))
        for row, s in zip(loss, render, strict=True):
            lost = [r["psnr_db"] - c["psnr_db"] for c, r in pairs if float(c["render_scale"]) == s]
            row.append(round(max(0.0, sum(lost) / len(lost)), 3) if lost else None)
    return {"scales": scales, "ms_ratio": ratios, "render_scales": render, "loss_db": loss}


def _median(values: list[Any]) -> float:
    ordered = sorted(float(v) for v in values)
    mid = len(ordered) // 2
    return ordered[mid] if len(ordered) % 2 else (ordered[mid - 1] + ordered[mid]) / 2


def derive_from_reports(
    eval_path: Path = EVAL_REPORT,
    framegen_path: Path = FRAMEGEN_REPORT,
    encode_path: Path = ENCODE_REPORT,
) -> dict[str, Any]:
    try:
        eval_report = json.loads(eval_path.read_text())
        framegen_report = json.loads(framegen_path.read_text())
        encode_report = json.loads(encode_path.read_text())
    except (OSError, ValueError) as exc:
        raise FiguresError(f"cannot read the reports: {exc}") from None
    table = derive_figures(eval_report, framegen_report)
    table["source"].append("docs/reports/encode_scale.json")
    table["encode"] = derive_encode(encode_report)
    return table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m server.session.quality.figures",
        description="Rewrite the adaptive-quality speed-against-error table from the "
        "evaluation reports.",
    )
    parser.add_argument("--eval-report", type=Path, default=EVAL_REPORT)
    parser.add_argument("--framegen-report", type=Path, default=FRAMEGEN_REPORT)
    parser.add_argument("--encode-report", type=Path, default=ENCODE_REPORT)
    parser.add_argument("--out", type=Path, default=FIGURES_PATH)
    args = parser.parse_args(argv)
    table = derive_from_reports(args.eval_report, args.framegen_report, args.encode_report)
    parse_figures(table)  # what we write must load
    args.out.write_text(json.dumps(table, indent=1) + "\n")
    print(f"wrote {args.out} ({len(table['methods'])} methods)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
