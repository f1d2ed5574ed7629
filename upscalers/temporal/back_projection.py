"""Back-projection of the temporal history onto each frame's own samples.

Accumulating jittered samples gives each display pixel the average of the samples
that landed near it; but every sample is an average itself, over its render
pixel's footprint (a box of S x S display pixels at a scale S, shifted by the
jitter). So the accumulated history converges to the picture blurred by that box,
not to the picture, and a sharpening filter afterwards can only guess the
difference (and rings where it guesses wrong).

Back-projection (iterative back-projection, Irani and Peleg 1991; a Landweber step
of the least-squares problem) instead asks the history to explain the samples: it
predicts each sample of this frame from the history (the box over the sample's
footprint, at its jittered position), and adds the prediction error back to the
display pixels the footprint covers, each display pixel by the error of the
samples that cover it, weighted by how much they cover it. A still camera's
jitter moves the footprints over the sub-pixel positions, so over a few frames the
history approaches a picture whose box averages are the samples: detail the box
hid, recovered from the overlap of the shifted boxes rather than guessed. Under
motion the same step corrects what resampling the history blurred.

Each frame corrects with a fraction ``step`` of its error: samples of a real
renderer are not exact box averages (a point-sampled edge aliases, and differs
from frame to frame), and a full step would follow each frame's aliasing; a
fraction averages it over frames as the accumulation does.

The operator is separable: per axis, a render sample covers a run of display
pixels (weights: overlap / footprint width, edges replicated), and a display pixel
is covered by a few samples (its back weights: their coverage over the total).
The tables depend on the size and the jitter only and are shared by the torch
path (here) and the numba kernel (``temporal_cpu_kernels.back_project``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import numpy.typing as npt
import torch
import torch.nn.functional as F

I64Array = npt.NDArray[np.int64]
F32Array = npt.NDArray[np.float32]


@dataclass(frozen=True)
class AxisTaps:
    """One axis of the operator: sample r predicted as sum_t forward_weight[r, t] *
    history[forward_index[r, t]]; display pixel k corrected by sum_u back_weight[k, u] *
    error[back_index[k, u]]. Unused taps have weight 0 and index 0."""

    forward_index: I64Array  # (n_render, T)
    forward_weight: F32Array
    back_index: I64Array  # (n_display, U)
    back_weight: F32Array


def axis_taps(n_render: int, n_display: int, jitter: float) -> AxisTaps:
    """Taps of one axis: render pixel r's footprint is the box of width n_display /
    n_render display pixels centred on its sample, at (r + 0.5 + jitter) render pixels;
    display pixel k spans [k, k + 1). Footprint parts beyond the image count for the
    edge pixel (the edge is replicated)."""
    if n_render < 1 or n_display < 1:
        raise ValueError(f"axis sizes must be positive, got {n_render} -> {n_display}")
    scale = n_display / n_render
    centre = scale * (np.arange(n_render, dtype=np.float64) + 0.5 + jitter)
    lo, hi = centre - scale / 2, centre + scale / 2
    # Display pixels a footprint can touch: from floor(lo), ceil(scale) + 1 of them.
    k = np.floor(lo)[:, None] + np.arange(math.ceil(scale) + 1)[None, :]
    overlap = np.minimum(hi[:, None], k + 1.0) - np.maximum(lo[:, None], k)
    rows = np.broadcast_to(np.arange(n_render)[:, None], k.shape)[overlap > 0.0]
    cols = np.clip(k, 0, n_display - 1).astype(np.int64)[overlap > 0.0]
    # Parts clipped onto the same edge pixel add up: one entry per (row, column).
    pairs, which = np.unique(rows * n_display + cols, return_inverse=True)
    coverage = np.bincount(which, weights=overlap[overlap > 0.0] / scale).astype(np.float64)
    rows, cols = pairs // n_display, pairs % n_display
    forward_index, forward_weight = _rows_as_taps(rows, cols, coverage, n_render)
    # A display pixel no footprint covers (the last one at a jitter of -0.5, where every
    # footprint moved half a render pixel back) gets no correction.
    total = np.bincount(cols, weights=coverage, minlength=n_display)
    by_column = np.lexsort((rows, cols))
    back_index, back_weight = _rows_as_taps(
        cols[by_column],
        rows[by_column],
        coverage[by_column] / total[cols[by_column]],
        n_display,
    )
    return AxisTaps(forward_index, forward_weight, back_index, back_weight)


@dataclass(frozen=True)
class Regular2x:
    """At 2x, away from the edges every render pixel's footprint has the same taps and
    every display pixel of a parity the same back taps: render column r reads display
    columns 2 r + base + t (t < len(forward)) for r in [r_lo, r_hi); display column 2 q + a
    reads samples q + offsets[a, u] for q in [q_lo, q_hi). The same terms in the same
    order as the tables (a shorter parity is padded with weight 0), so a kernel can use
    contiguous runs there and the tables elsewhere."""

    base: int
    forward: F32Array  # (n,)
    r_lo: int
    r_hi: int
    offsets: I64Array  # (2, m)
    back: F32Array  # (2, m)
    q_lo: int
    q_hi: int


def regular_2x(taps: AxisTaps) -> Regular2x | None:
    """The interior pattern of a 2x axis's tables; None for any other scale."""
    fi, fw = taps.forward_index, taps.forward_weight
    bi, bw = taps.back_index, taps.back_weight
    n_render, n_display = fi.shape[0], bi.shape[0]
    if n_display != 2 * n_render or n_render < 4:
        return None
    mid = n_render // 2
    n = int(np.count_nonzero(fw[mid]))
    base = int(fi[mid, 0]) - 2 * mid
    forward = fw[mid, :n].copy()
    r = np.arange(n_render)
    fits = (
        (np.count_nonzero(fw, axis=1) == n)
        & np.all(fi[:, :n] == 2 * r[:, None] + base + np.arange(n)[None, :], axis=1)
        & np.all(fw[:, :n] == forward[None, :], axis=1)
    )
    r_lo, r_hi = _run_around(fits, mid)
    q = np.arange(n_render)
    counts = [int(np.count_nonzero(bw[2 * mid + a])) for a in (0, 1)]
    m = max(counts)
    offsets = np.zeros((2, m), np.int64)
    back = np.zeros((2, m), np.float32)
    q_fits = np.ones(n_render, bool)
    for a in (0, 1):
        k = counts[a]
        offsets[a, :k] = bi[2 * mid + a, :k] - mid
        back[a, :k] = bw[2 * mid + a, :k]
        rows = 2 * q + a
        q_fits &= (
            (np.count_nonzero(bw[rows], axis=1) == k)
            & np.all(bi[rows, :k] == q[:, None] + offsets[a, :k][None, :], axis=1)
            & np.all(bw[rows, :k] == back[a, :k][None, :], axis=1)
        )
    q_lo, q_hi = _run_around(q_fits, mid)
    return Regular2x(base, forward, r_lo, r_hi, offsets, back, q_lo, q_hi)


@lru_cache(maxsize=512)
def cached_regular_2x(n_render: int, n_display: int, jitter: float) -> Regular2x | None:
    """``regular_2x`` of ``cached_axis_taps`` with the same arguments, kept the same way."""
    return regular_2x(cached_axis_taps(n_render, n_display, jitter))


def _run_around(fits: npt.NDArray[np.bool_], mid: int) -> tuple[int, int]:
    """[lo, hi) of the run of True around ``mid``; empty if ``mid`` itself is False."""
    if not fits[mid]:
        return 0, 0
    misses = np.flatnonzero(~fits)
    before, after = misses[misses < mid], misses[misses > mid]
    lo = int(before[-1]) + 1 if len(before) else 0
    hi = int(after[0]) if len(after) else len(fits)
    return lo, hi


@lru_cache(maxsize=512)
def cached_axis_taps(n_render: int, n_display: int, jitter: float) -> AxisTaps:
    """``axis_taps``, kept per size and jitter (a jitter sequence repeats: 8 phases at 2x,
    72 at 3x); callers share the arrays and only read them."""
    return axis_taps(n_render, n_display, jitter)


def _rows_as_taps(
    rows: I64Array, cols: I64Array, values: npt.NDArray[np.float64], n_rows: int
) -> tuple[I64Array, F32Array]:
    """Sparse entries, sorted by row then column, as (index, weight) tables of n_rows
    rows padded to the widest row."""
    counts = np.bincount(rows, minlength=n_rows)
    width = max(1, int(counts.max(initial=0)))
    starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
    slot = np.arange(len(rows)) - starts[rows]
    index = np.zeros((n_rows, width), np.int64)
    weight = np.zeros((n_rows, width), np.float32)
    index[rows, slot] = cols
    weight[rows, slot] = values
    return index, weight


def _index(a: I64Array, like: torch.Tensor) -> torch.Tensor:
    return torch.from_numpy(a).to(like.device)


def _weight(a: F32Array, like: torch.Tensor) -> torch.Tensor:
    return torch.from_numpy(a).to(device=like.device, dtype=like.dtype)


def predict(history: torch.Tensor, taps_x: AxisTaps, taps_y: AxisTaps) -> torch.Tensor:
    """The (3, h, w) samples the (3, H, W) history predicts: the box over each sample's
    footprint, along the columns ((3, H, w)), then along the rows."""
    fx = _weight(taps_x.forward_weight, history)
    across = (history[:, :, _index(taps_x.forward_index, history)] * fx).sum(-1)
    fy = _weight(taps_y.forward_weight, history).unsqueeze(-1)
    return (across[:, _index(taps_y.forward_index, history), :] * fy).sum(2)


def back_project(
    history: torch.Tensor,
    samples: torch.Tensor,
    taps_x: AxisTaps,
    taps_y: AxisTaps,
    step: float | torch.Tensor,
    precondition: float | torch.Tensor = 0.0,
) -> None:
    """One step on the (3, H, W) history in place, towards explaining the (3, h, w)
    samples (same colour space); ``step`` a number or an (H, W) map of them;
    ``precondition`` (a number or an (H, W) map) filters the correction first
    (``precondition_filter``; 0: not)."""
    error = samples - predict(history, taps_x, taps_y)
    # The error back to the display pixels, along the rows ((3, H, w)), then the columns.
    by = _weight(taps_y.back_weight, history).unsqueeze(-1)
    down = (error[:, _index(taps_y.back_index, history), :] * by).sum(2)
    bx = _weight(taps_x.back_weight, history)
    correction = (down[:, :, _index(taps_x.back_index, history)] * bx).sum(-1)
    if isinstance(precondition, torch.Tensor) or precondition > 0.0:
        correction = precondition_filter(correction, precondition)
    if isinstance(step, torch.Tensor):
        history.addcmul_(correction, step.to(history.dtype))
    else:
        history.add_(correction, alpha=step)


def precondition_filter(correction: torch.Tensor, c: float | torch.Tensor) -> torch.Tensor:
    """The (3, H, W) correction filtered per axis by [-c, 1 + 2c, -c], edges replicated:
    gain 1 at zero frequency, 1 + 4c at Nyquist. A correction has passed the footprint's
    box twice (prediction, then back), which leaves little of the detail near the
    display's Nyquist frequency; this gives that part back its weight, as the inverse
    of the averaged normal operator would (``TemporalParams.area_precondition``). ``c``
    a number or an (H, W) map: each output pixel is filtered with its own c, along both
    axes. The numba kernel ``precondition_add`` computes the same sums in the same
    order."""
    h = correction.shape[1]
    padded = F.pad(correction.unsqueeze(0), (1, 1, 1, 1), mode="replicate")[0]
    centre, side = 1.0 + 2.0 * c, -c
    # Rows y - 1, y and y + 1 of the padding, each along the row with output row y's c.
    above, here, below = (
        padded[:, r : r + h, 1:-1] * centre
        + (padded[:, r : r + h, :-2] + padded[:, r : r + h, 2:]) * side
        for r in range(3)
    )
    return here * centre + (above + below) * side
