"""An offline multi-frame least-squares reconstruction of the photograph sequences.

``upcast eval upscalers --real-content DIR --multiframe-ls`` answers, for the still
camera and the pan: what does a plain solve of every jittered sample seen so far
reach, and what is left of it within temporal's output clamp (each display pixel
within the 3x3 range of its render pixel's neighbourhood, issue 19's halo limit)?
Where temporal misses a margin that this reference reaches within the clamp, the
clamp is not what stops it: the samples hold the detail and temporal does not yet
recover it. It is a reference, not a bound: it has no prior beyond stopping early,
and on smooth pictures temporal (EASU's start, accumulation) can beat it.

At a measured frame F, every frame t <= F is one set of equations: each render
sample is the box average of the display-resolution picture over its footprint
(the render pixel's box, shifted by the frame's jitter and, for a pan, by the
camera's move since frame t, on frame F's display grid). The picture is the
least-squares solution of all of them, found by conjugate gradients on the
least-squares problem (CGLS), started from frame F's own bicubic upscale and
stopped once the samples are matched to within their rounding (the discrepancy
principle): the system is ill-conditioned near the display's Nyquist frequency (a
box two pixels wide passes almost nothing there), and run to convergence it
amplifies the rounding into noise; stopping early regularises, as a truncated SVD
does. No truth enters the solution.

Not an upscaler: it keeps every frame and costs seconds per frame, and it uses the
sequences' own model (box samples, exact motion), which a renderer's point samples
do not follow.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import torch

from server.eval.real_content import load_rgb
from server.eval.real_content_sequences import View, build_sequence, views
from server.eval.real_content_sources import image_source
from server.frames.frame import Size
from server.ops.progress import elapsed_and_left, progress
from upscalers import metrics
from upscalers.temporal import ops
from upscalers.temporal.params import TemporalParams

F32 = npt.NDArray[np.float32]
U8 = npt.NDArray[np.uint8]

# When to stop (Morozov's discrepancy principle): once the samples are matched to
# within what their rounding to 8 bits explains, further iterations fit the rounding
# (and the box model's own error), amplified near Nyquist. Uniform rounding error has
# a variance of 1/12 level^2; DISCREPANCY is the usual safety factor over it. At most
# MAX_ITERATIONS where the model's error keeps the misfit above that. On 2 training
# photographs per source (480x270, 2x, still camera, frame 31) the best of 5, 7, 10,
# 14 and 20 iterations varied from 5 to 20, and 40 iterations were 0.7-6.2 dB below
# it; this rule (4 to 15 iterations) came within 0.1 dB of each photograph's best, a
# fixed 10 within 0.8 dB, a fixed 20 within 2.9 dB.
ROUNDING_VARIANCE = 1.0 / 12.0
DISCREPANCY = 1.1
MAX_ITERATIONS = 15
KINDS_COVERED = ("still", "pan")
# Measured frames per sequence: one solve each, spread over the measured span.
FRAMES_MEASURED = 4


def footprint_matrix(n_render: int, n_canvas: int, scale: float, start: float) -> F32:
    """(n_render, n_canvas) weights: render pixel r averages the canvas pixels under
    [start + scale * r, start + scale * (r + 1)), each by its overlap over ``scale``;
    parts beyond the canvas count for its edge pixel (the edge is replicated)."""
    if n_render < 1 or n_canvas < 1 or scale <= 0:
        raise ValueError(f"need positive sizes and scale, got {n_render}, {n_canvas}, {scale}")
    lo = start + scale * np.arange(n_render, dtype=np.float64)
    hi = lo + scale
    k = np.floor(lo)[:, None] + np.arange(math.ceil(scale) + 1)[None, :]
    overlap = np.clip(np.minimum(hi[:, None], k + 1.0) - np.maximum(lo[:, None], k), 0.0, None)
    cols = np.clip(k, 0, n_canvas - 1).astype(np.int64)
    out = np.zeros((n_render, n_canvas), np.float64)
    rows = np.broadcast_to(np.arange(n_render)[:, None], k.shape)
    np.add.at(out, (rows.ravel(), cols.ravel()), (overlap / scale).ravel())
    return out.astype(np.float32)


@dataclass(frozen=True)
class Samples:
    """One frame's samples on the canvas: colour (h, w, 3) and, per axis, where render
    pixel 0's footprint starts in canvas pixels."""

    color: U8
    start_x: float
    start_y: float


def least_squares(
    samples: list[Samples],
    scale: tuple[float, float],
    canvas: Size,
    init: F32,
    max_iterations: int = MAX_ITERATIONS,
) -> tuple[F32, int]:
    """The (H, W, 3) canvas whose footprint averages best match every frame's samples,
    and the iterations it took: CGLS (conjugate gradients on the least-squares problem)
    from ``init``, stopped by the discrepancy principle (``DISCREPANCY``)."""
    ops_y, ops_x, residual = [], [], []
    x = torch.from_numpy(np.ascontiguousarray(init, dtype=np.float32)).permute(2, 0, 1).clone()
    for s in samples:
        h, w = s.color.shape[:2]
        ay = torch.from_numpy(footprint_matrix(h, canvas.height, scale[1], s.start_y))
        ax = torch.from_numpy(footprint_matrix(w, canvas.width, scale[0], s.start_x))
        ops_y.append(ay)
        ops_x.append(ax)
        observed = torch.from_numpy(s.color.astype(np.float32)).permute(2, 0, 1)
        residual.append(observed - ay @ x @ ax.T)
    count = sum(r.numel() for r in residual)

    def back(parts: list[torch.Tensor]) -> torch.Tensor:  # A^T applied to every frame's part
        out = torch.zeros_like(x)
        for ay, ax, part in zip(ops_y, ops_x, parts, strict=True):
            out += ay.T @ part @ ax
        return out

    def misfit() -> float:  # mean squared residual per sample
        return sum(float((r * r).sum()) for r in residual) / count

    gradient = back(residual)
    direction = gradient.clone()
    gamma = float((gradient * gradient).sum())
    done = 0
    while done < max_iterations and gamma > 0.0 and misfit() > DISCREPANCY * ROUNDING_VARIANCE:
        forward = [ay @ direction @ ax.T for ay, ax in zip(ops_y, ops_x, strict=True)]
        alpha = gamma / sum(float((q * q).sum()) for q in forward)
        x += alpha * direction
        for r, q in zip(residual, forward, strict=True):
            r -= alpha * q
        gradient = back(residual)
        gamma_next = float((gradient * gradient).sum())
        direction = gradient + (gamma_next / gamma) * direction
        gamma = gamma_next
        done += 1
    return x.permute(1, 2, 0).numpy(), done


def clamp_to_samples(image: F32, color: U8) -> F32:
    """Each display pixel within the 3x3 range of its render pixel's neighbourhood in
    ``color``, widened as temporal widens it: temporal's output clamp
    (``TemporalUpscaler._finish_output``)."""
    c = torch.from_numpy(color.astype(np.float32)).permute(2, 0, 1)
    slack = TemporalParams().output_clamp_slack
    lo, hi = ops.render_range_at_display(c, image.shape[0], image.shape[1], slack)
    x = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)
    return torch.minimum(torch.maximum(x, lo), hi).permute(1, 2, 0).numpy()


def measured_frames(frames: int, measure_from: int) -> list[int]:
    """``FRAMES_MEASURED`` frames spread over [measure_from, frames)."""
    first = min(measure_from, frames - 1)
    picks = np.linspace(first, frames - 1, FRAMES_MEASURED)
    return sorted({int(np.rint(v)) for v in picks})


@dataclass
class FrameReference:
    frame: int
    iterations: int  # CGLS iterations the discrepancy principle allowed
    psnr: float  # the reconstruction, rounded to uint8
    psnr_clamped: float  # the same within temporal's output clamp


def sequence_reference(
    kind: str,
    src: U8,
    display: Size,
    scale: float,
    frames: int,
    measure_from: int,
    max_iterations: int = MAX_ITERATIONS,
) -> list[FrameReference]:
    """The reconstruction at each measured frame of ``kind`` over ``src`` (a still
    camera or a pan: one magnification, so every frame is a shift of the others)."""
    if kind not in KINDS_COVERED:
        raise ValueError(f"the reference covers {', '.join(KINDS_COVERED)}, not {kind!r}")
    seq = build_sequence(kind, "reference", src, src, display, scale, frames)
    cams = views(kind, frames, Size(src.shape[1], src.shape[0]), display)
    jittered = seq.frames_for(True)
    render = Size(jittered[0].color.shape[1], jittered[0].color.shape[0])
    sx, sy = display.width / render.width, display.height / render.height
    out = []
    for f in measured_frames(frames, measure_from):
        # Camera moves since each frame, in frame f's display pixels.
        moves = [_move(cams[t], cams[f]) for t in range(f + 1)]
        mx = math.ceil(max(abs(m[0]) for m in moves) + sx) + 1
        my = math.ceil(max(abs(m[1]) for m in moves) + sy) + 1
        canvas = Size(display.width + 2 * mx, display.height + 2 * my)
        samples = [
            Samples(
                jittered[t].color,
                mx + moves[t][0] + sx * jittered[t].meta.jitter[0],
                my + moves[t][1] + sy * jittered[t].meta.jitter[1],
            )
            for t in range(f + 1)
        ]
        init = _bicubic_canvas(jittered[f].color, display, mx, my)
        big, iterations = least_squares(samples, (sx, sy), canvas, init, max_iterations)
        crop = big[my : my + display.height, mx : mx + display.width]
        truth = seq.truth[f]
        out.append(
            FrameReference(
                f,
                iterations,
                metrics.psnr(truth, _to_u8(crop)),
                metrics.psnr(truth, _to_u8(clamp_to_samples(crop, jittered[f].color))),
            )
        )
    return out


def _move(at: View, to: View) -> tuple[float, float]:
    """Where frame ``at``'s display origin lies on frame ``to``'s display grid."""
    return (at.bx - to.bx) / to.a, (at.by - to.by) / to.a


def _bicubic_canvas(color: U8, display: Size, mx: int, my: int) -> F32:
    up = cv2.resize(color, (display.width, display.height), interpolation=cv2.INTER_CUBIC)
    padded = cv2.copyMakeBorder(up, my, my, mx, mx, cv2.BORDER_REPLICATE)
    return np.asarray(padded, dtype=np.float32)


def _to_u8(image: F32) -> U8:
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def reference_section(
    images: list[Path],
    display: Size,
    scales: list[float],
    frames: int,
    measure_from: int,
) -> dict[str, Any]:
    """The report's ``real_content.multiframe_ls``: per scale and kind, the mean PSNR
    of the reconstruction (and within the output clamp) over the images and their
    measured frames, and per image."""
    started = time.monotonic()
    total, step = len(scales) * len(images), 0
    out: dict[str, Any] = {
        "method": "least squares over every jittered sample so far (CGLS, discrepancy stop), "
        "offline; clamped: within temporal's output clamp",
        "max_iterations": MAX_ITERATIONS,
        "discrepancy": DISCREPANCY,
        "scales": {},
    }
    for scale in scales:
        per_kind: dict[str, dict[str, Any]] = {}
        runs: dict[str, dict[str, list[FrameReference]]] = {k: {} for k in KINDS_COVERED}
        for path in images:
            src = load_rgb(path)
            name = f"{image_source(path)}/{path.name}"
            for kind in KINDS_COVERED:
                runs[kind][name] = sequence_reference(
                    kind, src, display, scale, frames, measure_from
                )
            step += 1
            elapsed, eta = elapsed_and_left(step, total, started)
            progress(
                f"[least squares {step}/{total}] {path.name} {scale:g}x done "
                f"({elapsed:.0f} s elapsed, ~{eta:.0f} s left)"
            )
        for kind, by_image in runs.items():
            raw = {n: float(np.mean([b.psnr for b in bs])) for n, bs in by_image.items()}
            clamped = {
                n: float(np.mean([b.psnr_clamped for b in bs])) for n, bs in by_image.items()
            }
            first = next(iter(by_image.values()))
            per_kind[kind] = {
                "psnr_db": float(np.mean(list(raw.values()))),
                "psnr_clamped_db": float(np.mean(list(clamped.values()))),
                "frames": [b.frame for b in first],
                "iterations_mean": float(
                    np.mean([b.iterations for bs in by_image.values() for b in bs])
                ),
                "psnr_by_image": raw,
                "psnr_clamped_by_image": clamped,
            }
        out["scales"][f"{scale:g}"] = per_kind
    return out
