"""The real-content suite of ``upcast eval upscalers --real-content DIR``.

Held-out photographs (``real_content_sources``) become the sequences of
``real_content_sequences``; every method runs over each sequence frame by frame,
interleaved like the game scenes, through one UpscalerHost per method (each
sequence starts with RESET, so temporal history never crosses sequences).
Temporal methods get the jittered frames, spatial ones the unjittered frames; both
are area averages of the photograph and flagged AREA_SAMPLES, as a user's photographs
and video would be (``upscalers.upscale_sequence(..., area_samples=True)``).

Per scale, method and kind the report keeps the mean PSNR over the measured
frames and the photographs, the per-frame PSNR curve (mean over photographs),
SSIM, flicker and the time. Measured frames: ``first`` its one frame; ``pan``,
``zoom`` and ``still`` from ``measure_from`` on (history has built up); ``cut``
from the cut on (the recovery is what it shows).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from PIL import Image

from server.eval.methods import MethodSpec
from server.eval.real_content_sequences import (
    KINDS,
    PAD,
    Sequence,
    build_sequence,
    source_scale,
)
from server.eval.real_content_sources import image_source
from server.frames.frame import Size
from server.ops.progress import elapsed_and_left, progress
from server.ops.report import summarize_ms
from upscalers import metrics
from upscalers.host import UpscalerHost
from upscalers.output import to_uint8

U8 = npt.NDArray[np.uint8]
SUITE = "real_content"
# Untimed first calls per method and scale (allocation, first reset), as in the game eval.
WARMUP_CALLS = 2


@dataclass
class KindResult:
    """One method on one kind: PSNR per photograph per frame, SSIM and flicker per
    photograph over its measured frames."""

    psnr: list[list[float]] = field(default_factory=list)
    ssim: list[float] = field(default_factory=list)
    flicker: list[float] = field(default_factory=list)


def load_rgb(path: Path) -> U8:
    with Image.open(path) as image:
        return np.asarray(image.convert("RGB"), dtype=np.uint8)


def large_enough(images: list[Path], display: Size) -> tuple[list[Path], list[str]]:
    """(the images that cover the display crop and its padding at one source pixel per
    display pixel or more, why each other one is left out): a smaller picture's
    "truth" would be an upsample of it, which flatters every method; a file that is
    not a picture is left out too, named, rather than ending the run."""
    kept: list[Path] = []
    left_out: list[str] = []
    for path in images:
        try:
            with Image.open(path) as image:  # reads the header only
                size = Size(*image.size)
        except (OSError, ValueError) as e:  # PIL's UnidentifiedImageError is an OSError
            left_out.append(f"{path}: not a picture this can read ({e})")
            continue
        if source_scale(size, display) >= 1.0:
            kept.append(path)
        else:
            need = Size(display.width + 2 * PAD, display.height + 2 * PAD)
            left_out.append(
                f"{path} ({size}): smaller than the {display} crop with its padding ({need})"
            )
    return kept, left_out


def run_suite(
    images: list[Path],
    methods: list[MethodSpec],
    display: Size,
    scales: list[float],
    frames: int,
    measure_from: int,
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Run every method over every held-out image's sequences at each scale; returns
    report cases (``suite: real_content``) and the report's ``real_content`` section."""
    pictures = [load_rgb(p) for p in images]
    cases: list[dict[str, Any]] = []
    section: dict[str, Any] = {
        "images": [f"{image_source(p)}/{p.name}" for p in images],
        "display_size": str(display),
        "frames": frames,
        "measure_from": measure_from,
        "kinds": list(KINDS),
        "reference": "box average of the photograph over each display pixel "
        "(render pixels: over their jittered footprint)",
        "scales": {},
    }
    started = time.monotonic()
    total, step = len(scales) * len(pictures), 0
    for scale in scales:
        hosts = {m.label: UpscalerHost(m.name, display, m.options) for m in methods}
        times: dict[str, list[float]] = {m.label: [] for m in methods}
        results = {m.label: {k: KindResult() for k in KINDS} for m in methods}
        render = display.scaled(1 / scale)
        for i, (path, src) in enumerate(zip(images, pictures, strict=True)):
            # The picture before the cut: the next photograph (itself turned over if alone).
            other = pictures[(i + 1) % len(pictures)] if len(pictures) > 1 else src[::-1, ::-1]
            for kind in KINDS:
                seq = build_sequence(kind, path.name, src, other, display, scale, frames)
                _run_sequence(seq, methods, hosts, times, results, measure_from)
            step += 1
            elapsed, eta = elapsed_and_left(step, total, started)
            progress(
                f"[real {step}/{total}] {path.name} {scale:g}x done "
                f"({elapsed:.0f} s elapsed, ~{eta:.0f} s left)"
            )
        per_method: dict[str, Any] = {}
        for m in methods:
            t = summarize_ms(times[m.label][WARMUP_CALLS:])
            per_kind: dict[str, Any] = {}
            for kind in KINDS:
                r = results[m.label][kind]
                curve = np.mean(np.asarray(r.psnr, dtype=np.float64), axis=0)
                span = measured_span(kind, len(curve), measure_from)
                psnr = float(np.mean(curve[span[0] : span[1]]))
                flicker = float(np.mean(r.flicker)) if kind != "first" else None
                per_kind[kind] = {
                    "psnr_db": psnr,
                    "psnr_per_frame": [float(v) for v in curve],
                    "measured_frames": list(span),
                    "worst_image_psnr_db": float(np.min(_image_means(r.psnr, span))),
                    "psnr_by_source": _by_source(images, r.psnr, span),
                    "psnr_by_image": _by_image(images, r.psnr, span),
                }
                cases.append(
                    {
                        "name": f"real/{kind}/{scale:g}x/{m.label}",
                        "suite": SUITE,
                        "scene": f"photo_{kind}",
                        "scale": scale,
                        "method": m.label,
                        "render_size": str(render),
                        "median_ms": t["median_ms"],
                        "p95_ms": t["p95_ms"],
                        "warmup_ms": max(times[m.label][:WARMUP_CALLS]),
                        "psnr_db": psnr,
                        "ssim": float(np.mean(r.ssim)),
                        "flip": None,
                        "flicker": flicker,
                        "images": len(images),
                    }
                )
            per_method[m.label] = {
                "temporal": m.temporal,
                "median_ms": t["median_ms"],
                "p95_ms": t["p95_ms"],
                "kinds": per_kind,
            }
        section["scales"][f"{scale:g}"] = {"render_size": str(render), "methods": per_method}
    return cases, section


def _by_source(
    images: list[Path], psnr: list[list[float]], span: tuple[int, int]
) -> dict[str, float]:
    """Mean PSNR over the measured frames per content source (``image_source``:
    mate-nature, plasma-photos, ..., or the folder of your own pictures), in the order
    first met."""
    sources: dict[str, list[float]] = {}
    for path, value in zip(images, _image_means(psnr, span), strict=True):
        sources.setdefault(image_source(path), []).append(float(value))
    return {name: float(np.mean(values)) for name, values in sources.items()}


def _by_image(
    images: list[Path], psnr: list[list[float]], span: tuple[int, int]
) -> dict[str, float]:
    """Mean PSNR over the measured frames per photograph, keyed ``source/name`` like
    the section's ``images``: the issue's margins hold on every held-out sequence, and
    a mean over sources can hide one that misses."""
    return {
        f"{image_source(path)}/{path.name}": float(value)
        for path, value in zip(images, _image_means(psnr, span), strict=True)
    }


def _image_means(psnr: list[list[float]], span: tuple[int, int]) -> npt.NDArray[np.float64]:
    """Each image's mean PSNR over the measured frames ``[start, end)``."""
    per_frame = np.asarray(psnr, dtype=np.float64)[:, span[0] : span[1]]
    means: npt.NDArray[np.float64] = per_frame.mean(axis=1)
    return means


def measured_span(kind: str, length: int, measure_from: int) -> tuple[int, int]:
    """[start, end) of the measured frames of a kind's sequence (module docstring)."""
    if kind == "first":
        return 0, 1
    if kind == "cut":
        return length // 2, length  # build_sequence cuts in the middle
    return min(measure_from, length - 1), length


def _run_sequence(
    seq: Sequence,
    methods: list[MethodSpec],
    hosts: dict[str, UpscalerHost],
    times: dict[str, list[float]],
    results: dict[str, dict[str, KindResult]],
    measure_from: int,
) -> None:
    labels = [m.label for m in methods]
    temporal = {m.label: m.temporal for m in methods}
    measured = range(*measured_span(seq.kind, len(seq.truth), measure_from))
    psnr: dict[str, list[float]] = {m: [] for m in labels}
    ssim: dict[str, list[float]] = {m: [] for m in labels}
    errors: dict[str, list[npt.NDArray[np.float32]]] = {m: [] for m in labels}
    for i, truth in enumerate(seq.truth):
        # Rotate the order each frame so no method always runs with warm or cold caches.
        for m in labels[i % len(labels) :] + labels[: i % len(labels)]:
            frame = seq.frames_for(temporal[m])[i]
            t0 = time.perf_counter_ns()
            image = to_uint8(hosts[m].upscale(frame))
            times[m].append((time.perf_counter_ns() - t0) / 1e6)
            psnr[m].append(metrics.psnr(truth, image))
            if i in measured:
                ssim[m].append(metrics.ssim(truth, image))
                errors[m].append(metrics.signed_error(truth, image))
    for m in labels:
        r = results[m][seq.kind]
        r.psnr.append(psnr[m])
        r.ssim.append(float(np.mean(ssim[m])))
        if len(errors[m]) >= 2:
            r.flicker.append(metrics.flicker(errors[m]))
