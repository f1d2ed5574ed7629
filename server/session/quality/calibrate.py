"""This machine's times for the adaptive-quality table, measured once and cached per machine.

The shipped table (figures.json) holds every upscaler's PSNR, which does not depend on the
machine, and times measured on the machine named in it. A host that is faster, slower or
has a vector unit the table's machine lacked starts its controller from wrong times, which
the controller corrects online only for the setting it runs. ``upcast calibrate`` times
every method of the table at every scale on this machine, through the worker's own code
path (UpscalerHost, one frame at a time, the worker's thread count), together with the
frame predictor and the renderer, and writes a table with the shipped quality and these
times to a per-machine cache file. ``load_machine_figures`` prefers that file when its
machine key matches this host. ``--from-eval`` takes the times from an ``upcast eval
upscalers`` report run on this machine instead of measuring again.
"""

from __future__ import annotations

import copy
import hashlib
import importlib.metadata
import json
import math
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from server.ops.machine import cpu_model, usable_cores
from server.session.quality.figures import (
    FIGURES_PATH,
    PREDICTOR,
    FiguresError,
    SpeedErrorFigures,
    derive_figures,
    parse_figures,
)

CACHE_ENV = "UPCAST_CACHE_DIR"  # where calibrations live; else $XDG_CACHE_HOME/upcast
WARMUP_CALLS = 2  # first calls allocate (and a temporal method has no history yet)


def machine_description() -> str:
    """What the times depend on: the CPU, how many cores this process may use, torch
    (its version read from the package's metadata: a session need not import torch)."""
    try:
        torch_version = importlib.metadata.version("torch")
    except importlib.metadata.PackageNotFoundError:
        torch_version = "none"
    return f"{cpu_model() or 'unknown CPU'}, {usable_cores()} cores, torch {torch_version}"


def machine_key(description: str | None = None) -> str:
    text = description if description is not None else machine_description()
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def cache_dir() -> Path:
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "upcast"


def calibration_path(key: str | None = None) -> Path:
    return cache_dir() / f"quality-figures-{key or machine_key()}.json"


@dataclass(frozen=True)
class MachineFigures:
    figures: SpeedErrorFigures
    source: str  # where the times come from, for the session's log line


def load_machine_figures(shipped: Path = FIGURES_PATH) -> MachineFigures:
    """This machine's calibration where one exists and loads, else the shipped table.
    A calibration that does not load is named in ``source`` and left alone (the user
    may want to look at it); the shipped table serves."""
    description = machine_description()
    path = calibration_path(machine_key(description))
    note = ""
    if path.exists():
        try:
            raw = json.loads(path.read_text())
            calibrated = raw["calibration"]
            if calibrated.get("machine") != description:
                raise FiguresError(f"it was measured on {calibrated.get('machine')!r}")
            return MachineFigures(
                parse_figures(raw),
                f"this machine's calibration {path} ({calibrated.get('from')}, "
                f"{calibrated.get('at')})",
            )
        except (OSError, ValueError, KeyError, AttributeError, FiguresError) as exc:
            note = f"; the calibration {path} was not used: {exc}"
    try:
        figures = parse_figures(json.loads(shipped.read_text()))
    except (OSError, ValueError) as exc:
        raise FiguresError(f"cannot read {shipped}: {exc}") from None
    return MachineFigures(
        figures,
        f"the shipped table ({figures.machine}; `upcast calibrate` measures this one){note}",
    )


def _display_of(pixels: int) -> tuple[int, int]:
    """A 16:9 size of ``pixels`` (the shipped table's 1280x720 exactly), even sides."""
    width = math.sqrt(pixels * 16 / 9)
    w, h = round(width / 2) * 2, round(width * 9 / 16 / 2) * 2
    return max(2, w), max(2, h)


def _summary(samples: list[float]) -> tuple[float, float]:
    values = np.asarray(samples, dtype=np.float64)
    return round(float(np.median(values)), 3), round(float(np.percentile(values, 95)), 3)


Progress = Callable[[str], None]


def measure_times(
    base: Mapping[str, Any],
    *,
    methods: list[str] | None = None,
    display: tuple[int, int] | None = None,
    frames: int = 12,
    scene: str = "default",
    on_progress: Progress = lambda _: None,
) -> dict[str, Any]:
    """``base`` (the shipped table's JSON form) with this machine's times: every method
    (or only ``methods``, the others keeping the shipped times, named in
    ``calibration_kept``) at each of its scales, the frame predictor and the renderer.
    The PSNR columns stay the shipped ones: quality does not depend on the machine."""
    from server.frames.frame import Size
    from server.game.render.renderer import Renderer, RenderTargets
    from upscalers import registry
    from upscalers.host import UpscalerHost
    from upscalers.output import to_uint8

    if frames < 1:
        raise ValueError("frames must be at least 1")
    names = list(methods) if methods else list(base["methods"])
    unknown = [m for m in names if m not in base["methods"]]
    if unknown:
        raise FiguresError(f"not in the table: {', '.join(unknown)} (it has "
                           f"{', '.join(sorted(base['methods']))})")  # fmt: skip
    w, h = display or _display_of(int(base["display_pixels"]))
    display_size = Size(w, h)
    table = copy.deepcopy(dict(base))
    # Kept times are per pixel of the shipped display: rescale them to this one's.
    ratio = w * h / int(base["display_pixels"])
    kept: list[str] = []
    for name, entry in table["methods"].items():
        if name not in names:
            entry["median_ms"] = [round(v * ratio, 3) for v in entry["median_ms"]]
            entry["p95_ms"] = [round(v * ratio, 3) for v in entry["p95_ms"]]
            kept += [f"{name}@{s:g}" for s in entry["scales"]]
    table["calibration_kept"] = kept
    calls = WARMUP_CALLS + frames
    for n, name in enumerate(names, 1):
        entry = table["methods"][name]
        entry["median_ms"], entry["p95_ms"] = [], []
        for scale in entry["scales"]:
            render = Size(max(2, round(w / scale)), max(2, round(h / scale)))
            renderer = Renderer(scene, render, scale=scale, jitter=registry.is_temporal(name))
            host = UpscalerHost(name, display_size)
            samples: list[float] = []
            for i in range(calls):
                frame = renderer.render(i, 0.25 + i / 30, RenderTargets.allocate(render))
                t0 = time.perf_counter_ns()
                to_uint8(host.upscale(frame))
                if i >= WARMUP_CALLS:
                    samples.append((time.perf_counter_ns() - t0) / 1e6)
            median, p95 = _summary(samples)
            entry["median_ms"].append(median)
            entry["p95_ms"].append(p95)
        times = ", ".join(f"{s:g}x {m:.1f} ms" for s, m in zip(entry["scales"],
                          entry["median_ms"], strict=True))  # fmt: skip
        on_progress(f"calibrate: {n}/{len(names)} {name}: {times}")
    table["predict_ms"], table["render_ms"] = _predictor_and_render_ms(
        int(base["predict_pixels"]), frames, scene
    )
    on_progress(
        f"calibrate: renderer {table['render_ms']:.1f} ms, predictor {PREDICTOR} "
        f"{table['predict_ms']:.1f} ms a frame at {_display_of(int(base['predict_pixels']))}"
    )
    table["display_pixels"] = w * h
    return table


def _predictor_and_render_ms(pixels: int, frames: int, scene: str) -> tuple[float, float]:
    """The worker's frame predictor (observe a rendered frame, predict the next camera's)
    and the renderer, both at ``pixels``: the model scales them by pixels."""
    from server.frames.frame import Size
    from server.game.render.renderer import Renderer, RenderTargets
    from upscalers.framegen import MeshProjectionPredictor, MpeOptions

    w, h = _display_of(pixels)
    size = Size(w, h)
    renderer = Renderer(scene, size, jitter=False)
    predictor = MeshProjectionPredictor(MpeOptions(tile=int(PREDICTOR.removeprefix("mpe"))), "cpu")
    render_ms: list[float] = []
    predict_ms: list[float] = []
    prev_t: float | None = None
    for i in range(WARMUP_CALLS + frames):
        t = 0.25 + i / 30
        t0 = time.perf_counter_ns()
        rendered = renderer.render(2 * i, t, RenderTargets.allocate(size), prev_t=prev_t)
        t1 = time.perf_counter_ns()
        nxt = renderer.render(2 * i + 1, t + 1 / 60, prev_t=t)
        t2 = time.perf_counter_ns()
        predictor.observe(rendered)
        predictor.predict(nxt.meta.camera.view, nxt.meta.camera.proj, nxt.meta.flags)
        t3 = time.perf_counter_ns()
        prev_t = t
        if i >= WARMUP_CALLS:
            render_ms += [(t1 - t0) / 1e6, (t2 - t1) / 1e6]
            predict_ms.append((t3 - t2) / 1e6)
    return _summary(predict_ms)[0], _summary(render_ms)[0]


def times_from_eval(base: Mapping[str, Any], report: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with the upscalers' times of an ``upcast eval upscalers`` report (run on
    this machine); the predictor's and renderer's stay the shipped ones. A method or scale
    the report lacks keeps the shipped time, named in ``calibration.kept``."""
    if str(report.get("benchmark")) != "eval_upscalers":
        raise FiguresError("not an `upcast eval upscalers` report")
    # derive_figures needs a frame-generation report only for its predictor figures:
    # hand it the shipped ones in that report's form.
    predictions = [
        {"method": PREDICTOR, "median_ms": base["predict_ms"], "scene": scene, "psnr_db": db}
        for scene, db in base["predict_psnr_db"].items()
    ]
    w, h = _display_of(int(base["predict_pixels"]))
    framegen = {
        "cases": [{"kind": "render", "median_ms": base["render_ms"]}, *predictions],
        "config": {"size": f"{w}x{h}"},
    }
    try:
        measured = derive_figures(report, framegen)
    except (KeyError, TypeError, ValueError) as exc:
        raise FiguresError(f"malformed eval report: {exc!r}") from None
    ratio = int(base["display_pixels"]) / int(measured["display_pixels"])
    table = copy.deepcopy(dict(base))
    kept: list[str] = []
    for name, entry in table["methods"].items():
        got = measured["methods"].get(name)
        for i, scale in enumerate(entry["scales"]):
            if got is None or scale not in got["scales"]:
                kept.append(f"{name}@{scale:g}")
                continue
            j = got["scales"].index(scale)
            # Per pixel of display: the report may have run at another display size.
            entry["median_ms"][i] = round(got["median_ms"][j] * ratio, 3)
            entry["p95_ms"][i] = round(got["p95_ms"][j] * ratio, 3)
    table["calibration_kept"] = kept
    return table


def stamp(table: dict[str, Any], how: str, description: str | None = None) -> dict[str, Any]:
    """Mark ``table`` as this machine's calibration (what load_machine_figures checks)."""
    machine = description if description is not None else machine_description()
    table["machine"] = machine
    table["source"] = [*table.get("source", []), f"upcast calibrate ({how})"]
    kept = table.pop("calibration_kept", [])
    table["calibration"] = {
        "machine": machine,
        "key": machine_key(machine),
        "from": how,
        "at": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "kept_shipped_times": kept,
    }
    parse_figures(table)  # what we write must load
    return table
