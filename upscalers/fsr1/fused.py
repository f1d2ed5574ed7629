"""FSR 1 EASU (+ RCAS) as one pure function of whole tensors, for ``torch.compile``.

Same math as ``fsr1_easu`` / ``fsr1_rcas`` (see their docstrings), written the
other way round: no scratch buffers, no ``out=``, no bands, every tap an
indexed read of the padded input. Eager torch would run this as dozens of full
passes over display-size temporaries, which is why the eager classes are
written with bands and in-place ops; the CPU profile of those shows the time
spread over ~200 small elementwise kernels per frame (addcmul, copy, mul, add,
min/max, clamp), i.e. memory passes. Inductor fuses this function's
per-output-pixel work into a few loops over the output (taps as indirect
loads), which removes those passes.

Only the compiled path (``EasuUpscaler(compile=True)`` and friends) calls it;
it also runs eagerly, slowly, which is how the tests compare it.
"""

from __future__ import annotations

import torch

from upscalers.fsr1.easu import DIR_ZERO, PAD, TAP_ROWS, TINY
from upscalers.fsr1.rcas import RCAS_LIMIT


def easu_fused(
    padded: torch.Tensor,
    row_f: torch.Tensor,
    col_f: torch.Tensor,
    phase_y: torch.Tensor,
    phase_x: torch.Tensor,
) -> torch.Tensor:
    """(3, H_out, W_out) EASU of a (3, H + 2 PAD, W + 2 PAD) edge-padded image in [0, 1].

    ``row_f`` (H_out, 1) and ``col_f`` (1, W_out) are the padded indices of texel 'f'
    of each output pixel, ``phase_y`` (H_out, 1) and ``phase_x`` (1, W_out) its phase.
    """
    lum = (padded[0] + padded[2]) * 0.5 + padded[1]
    centre = lum[1:-1, 1:-1]
    # Per-texel direction and length of texels -1 .. n (field index = padded index - 1).
    lengths = []
    diffs = []
    for before, after in ((lum[1:-1, :-2], lum[1:-1, 2:]), (lum[:-2, 1:-1], lum[2:, 1:-1])):
        diff = after - before
        one_sided = torch.maximum((after - centre).abs(), (centre - before).abs())
        ratio = (diff.abs() / one_sided.clamp_min(TINY)).clamp_max(1.0)
        diffs.append(diff)
        lengths.append(ratio * ratio)
    fields = torch.stack((diffs[0], diffs[1], lengths[0] + lengths[1]))
    r, c = row_f - 1, col_f - 1
    top = torch.lerp(fields[:, r, c], fields[:, r, c + 1], phase_x)
    bottom = torch.lerp(fields[:, r + 1, c], fields[:, r + 1, c + 1], phase_x)
    dx, dy, length = torch.lerp(top, bottom, phase_y).unbind(0)

    r2 = dx * dx + dy * dy
    keep = (r2 >= DIR_ZERO).to(dx.dtype)
    inv = r2.clamp_min(DIR_ZERO).rsqrt() * keep + (1.0 - keep)
    dx = (dx * keep + (1.0 - keep)) * inv
    dy = dy * inv
    ln = (length * 0.5).square()
    dx2, dy2 = dx * dx, dy * dy
    stretch = (dx2 + dy2) / torch.maximum(dx.abs(), dy.abs())
    lx2 = ((stretch - 1.0) * ln + 1.0).square()
    ly2 = (ln * -0.5 + 1.0).square()
    clip_s = 1.0 / (ln * ((0.25 - 0.04) - 0.5) + 0.5) - 2.5
    a = dx2 * lx2 + dy2 * ly2
    cc = dy2 * lx2 + dx2 * ly2
    b = dx * dy * (lx2 - ly2) * 2.0

    # One (H_out, W_out) accumulator per channel: every term then has the same shape and
    # inductor fuses the 12 taps into one loop over the output instead of realizing
    # each tap's weight as a display-size buffer.
    acc = [torch.zeros_like(a) for _ in range(3)]
    weight_sum = torch.zeros_like(a)
    for ty, txs in TAP_ROWS:
        oy = ty - phase_y
        c_row = cc * (oy * oy) - 2.5
        b_row = b * oy
        for tx in txs:
            ox = tx - phase_x
            d2s = c_row + a * (ox * ox) + b_row * ox
            e = (d2s - clip_s).clamp_max(0.0)
            w = (d2s * d2s - 2.25) * e * e
            weight_sum = weight_sum + w
            for ch in range(3):
                acc[ch] = acc[ch] + padded[ch, row_f + ty, col_f + tx] * w
    norm = weight_sum.clamp_min(TINY).reciprocal()
    out = []
    for ch in range(3):
        quad = [padded[ch, row_f + ty, col_f + tx] for ty in (0, 1) for tx in (0, 1)]
        lo = torch.minimum(torch.minimum(quad[0], quad[1]), torch.minimum(quad[2], quad[3]))
        hi = torch.maximum(torch.maximum(quad[0], quad[1]), torch.maximum(quad[2], quad[3]))
        out.append(torch.minimum(torch.maximum(acc[ch] * norm, lo), hi))
    return torch.stack(out)


def rcas_fused(image: torch.Tensor, scale: float) -> torch.Tensor:
    """RCAS of a (3, H, W) image in [0, 1] (edges repeated), lobe scaled by ``scale``."""
    # Edge repeat by clamped neighbour indices: a load each, no padded copy.
    _, h, w = image.shape
    rows = torch.arange(h, device=image.device).view(-1, 1)
    cols = torch.arange(w, device=image.device).view(1, -1)
    up, down = (rows - 1).clamp_min(0), (rows + 1).clamp_max(h - 1)
    left, right = (cols - 1).clamp_min(0), (cols + 1).clamp_max(w - 1)
    north, south = image[:, up, cols], image[:, down, cols]
    west, east = image[:, rows, left], image[:, rows, right]
    centre = image
    mn = torch.minimum(torch.minimum(north, south), torch.minimum(west, east))
    mx = torch.maximum(torch.maximum(north, south), torch.maximum(west, east))
    one = 1.0 + 2.0 * TINY
    ratio = torch.minimum((mn + TINY) / (mx + TINY), (one - (mx + TINY)) / (one - (mn + TINY)))
    lobe = (torch.amin(ratio, dim=0) * -0.25).clamp_min(-RCAS_LIMIT) * scale
    gain = lobe / (lobe * 4.0 + 1.0)
    ring = (north + west) + (east + south) - centre * 4.0
    return (centre + ring * gain).clamp(0.0, 1.0)


def easu_rcas_fused(
    padded: torch.Tensor,
    row_f: torch.Tensor,
    col_f: torch.Tensor,
    phase_y: torch.Tensor,
    phase_x: torch.Tensor,
    scale: float,
) -> torch.Tensor:
    return rcas_fused(easu_fused(padded, row_f, col_f, phase_y, phase_x), scale)


__all__ = ["PAD", "easu_fused", "easu_rcas_fused", "rcas_fused"]
