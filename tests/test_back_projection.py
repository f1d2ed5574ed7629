"""Back-projection of the temporal history (upscalers/temporal/back_projection.py): the footprint
tables, and that its steps recover what the render pixels' boxes average away."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from server.game.render.transforms import jitter_offset, jitter_phase_count
from upscalers.temporal.back_projection import (
    AxisTaps,
    axis_taps,
    back_project,
    precondition_filter,
    predict,
    regular_2x,
)


def _dense(index: np.ndarray, weight: np.ndarray, n_cols: int) -> np.ndarray:
    out = np.zeros((index.shape[0], n_cols))
    for row in range(index.shape[0]):
        np.add.at(out[row], index[row], weight[row])
    return out


@pytest.mark.parametrize(
    ("n_render", "n_display"), [(40, 80), (41, 123), (30, 45), (64, 32), (7, 7)]
)
@pytest.mark.parametrize("jitter", [-0.5, -0.17, 0.0, 0.31, 0.49])
def test_every_sample_and_every_display_pixel_has_weights_summing_to_one(
    n_render: int, n_display: int, jitter: float
) -> None:
    taps = axis_taps(n_render, n_display, jitter)
    forward = _dense(taps.forward_index, taps.forward_weight, n_display)
    back = _dense(taps.back_index, taps.back_weight, n_render)
    np.testing.assert_allclose(forward.sum(axis=1), 1.0, atol=1e-6)
    # The back weights are the forward coverage, per display pixel, over its total; a
    # pixel no footprint covers (the last one, at a jitter of -0.5) is not corrected.
    coverage = forward.T
    total = coverage.sum(axis=1, keepdims=True)
    covered = total[:, 0] > 0
    assert covered.sum() >= n_display - 1
    np.testing.assert_allclose(back.sum(axis=1)[covered], 1.0, atol=1e-6)
    np.testing.assert_allclose(back[~covered], 0.0)
    np.testing.assert_allclose(
        back[covered], (coverage / np.where(total > 0, total, 1))[covered], atol=1e-6
    )


def test_a_sample_is_the_box_over_its_jittered_footprint() -> None:
    # 2x: render pixel r spans display [2r, 2r + 2) unjittered.
    centred = _dense(*_forward(axis_taps(4, 8, 0.0)), 8)
    np.testing.assert_allclose(centred[1], [0, 0, 0.5, 0.5, 0, 0, 0, 0], atol=1e-7)
    # A quarter of a render pixel to the right: [2.5, 4.5).
    shifted = _dense(*_forward(axis_taps(4, 8, 0.25)), 8)
    np.testing.assert_allclose(shifted[1], [0, 0, 0.25, 0.5, 0.25, 0, 0, 0], atol=1e-7)
    # The last footprint leaves the image: its part beyond counts for the edge pixel.
    np.testing.assert_allclose(shifted[3], [0, 0, 0, 0, 0, 0, 0.25, 0.75], atol=1e-7)


def _forward(taps: AxisTaps) -> tuple[np.ndarray, np.ndarray]:
    return taps.forward_index, taps.forward_weight


def _samples(
    truth: torch.Tensor, n_render: tuple[int, int], jitter: tuple[float, float]
) -> torch.Tensor:
    """What a renderer with one box-filtered sample per pixel gives at this jitter."""
    h, w = n_render
    _, big_h, big_w = truth.shape
    return predict(truth, axis_taps(w, big_w, jitter[0]), axis_taps(h, big_h, jitter[1]))


def test_a_history_that_explains_its_samples_is_left_alone() -> None:
    gen = torch.Generator().manual_seed(1)
    truth = torch.rand((3, 24, 40), generator=gen)
    jitter = (0.3, -0.2)
    samples = _samples(truth, (12, 20), jitter)
    history = truth.clone()
    back_project(history, samples, axis_taps(20, 40, jitter[0]), axis_taps(12, 24, jitter[1]), 1.0)
    torch.testing.assert_close(history, truth, rtol=0.0, atol=1e-6)


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(10.0 * torch.log10(1.0 / torch.mean((a - b) ** 2)))


@pytest.mark.parametrize("step", [0.3, 1.0])
def test_steps_over_the_jitter_sequence_recover_the_detail_the_boxes_hide(step: float) -> None:
    """A still camera at 2x: each frame's samples are boxes over 2x2 display pixels at
    that frame's jitter. Accumulation converges at best to the mean of the samples
    spread over their footprints, the box-blurred picture; steps of back-projection over
    the same frames, from the first frame's spread samples, come far closer to the truth
    and stay finite."""
    gen = torch.Generator().manual_seed(7)
    # Detail at every scale: noise plus a smooth ramp, in [0, 1].
    truth = (0.6 * torch.rand((3, 32, 48), generator=gen) + torch.linspace(0, 0.4, 48)).clamp(0, 1)
    phases = jitter_phase_count(2.0)
    history: torch.Tensor | None = None
    spread = []
    for t in range(4 * phases):
        j = jitter_offset(t, phases)
        tx, ty = axis_taps(24, 48, j[0]), axis_taps(16, 32, j[1])
        samples = predict(truth, tx, ty)
        alone = torch.zeros_like(truth)
        back_project(alone, samples, tx, ty, 1.0)  # the samples spread over their footprints
        spread.append(alone)
        if history is None:
            history = alone.clone()
        else:
            back_project(history, samples, tx, ty, step)
    assert history is not None and torch.isfinite(history).all()
    accumulated = _psnr(torch.stack(spread).mean(0), truth)
    projected = _psnr(history, truth)
    assert projected > accumulated + 3.0, f"{projected:.1f} dB against {accumulated:.1f} dB"


@pytest.mark.parametrize("n_render", [4, 5, 41, 640])
@pytest.mark.parametrize("jitter", [-0.5, -0.375, 0.0, 0.125, 0.49])
def test_the_2x_pattern_is_the_tables_away_from_the_edges(n_render: int, jitter: float) -> None:
    """The numba kernel reads the interior of a 2x row through ``regular_2x``: it must say
    exactly what the tables say there, and cover all but a pixel or two at each edge."""
    taps = axis_taps(n_render, 2 * n_render, jitter)
    reg = regular_2x(taps)
    assert reg is not None
    forward = _dense(taps.forward_index, taps.forward_weight, 2 * n_render)
    back = _dense(taps.back_index, taps.back_weight, n_render)
    for r in range(reg.r_lo, reg.r_hi):
        row = np.zeros(2 * n_render)
        row[2 * r + reg.base + np.arange(len(reg.forward))] = reg.forward
        np.testing.assert_array_equal(forward[r], row)
    for q in range(reg.q_lo, reg.q_hi):
        for a in (0, 1):
            row = np.zeros(n_render)
            np.add.at(row, q + reg.offsets[a], reg.back[a])
            np.testing.assert_array_equal(back[2 * q + a], row)
    assert reg.r_lo <= 2 and reg.r_hi >= n_render - 2
    assert reg.q_lo <= 2 and reg.q_hi >= n_render - 2
    assert regular_2x(axis_taps(n_render, 3 * n_render, jitter)) is None


def test_the_preconditioning_filter_keeps_the_mean_and_lifts_nyquist() -> None:
    """[-c, 1 + 2c, -c] per axis: a constant correction passes as it is, a checkerboard
    (the display's Nyquist frequency on both axes) comes out (1 + 4c)^2 times larger
    inside, and the edges replicate (no pull towards zero at the border)."""
    c = 0.5
    flat = torch.full((3, 6, 8), 0.25)
    assert torch.allclose(precondition_filter(flat, c), flat)
    yy, xx = torch.meshgrid(torch.arange(6), torch.arange(8), indexing="ij")
    board = ((yy + xx) % 2 * 2 - 1).float().expand(3, 6, 8)
    out = precondition_filter(board, c)
    assert torch.allclose(out[:, 1:-1, 1:-1], board[:, 1:-1, 1:-1] * (1 + 4 * c) ** 2)
    ramp = torch.arange(8.0).expand(3, 6, 8)
    assert torch.allclose(precondition_filter(ramp, c)[:, :, 1:-1], ramp[:, :, 1:-1])


def test_a_preconditioned_step_matches_the_filtered_correction() -> None:
    """back_project with ``precondition`` adds the step times the filtered correction of
    the plain step, nothing else."""
    rng = np.random.default_rng(3)
    history = torch.from_numpy(rng.random((3, 16, 20), np.float32))
    samples = torch.from_numpy(rng.random((3, 8, 10), np.float32))
    tx, ty = axis_taps(10, 20, 0.2), axis_taps(8, 16, -0.3)
    plain, pre = history.clone(), history.clone()
    back_project(plain, samples, tx, ty, 1.0)
    back_project(pre, samples, tx, ty, 0.4, precondition=0.5)
    expected = history + 0.4 * precondition_filter(plain - history, 0.5)
    assert torch.allclose(pre, expected, atol=1e-5)


def test_a_map_of_preconditionings_filters_each_pixel_with_its_own() -> None:
    """Still and moving pixels take different strengths; each output pixel is what the
    whole image filtered with its own c gives there."""
    rng = np.random.default_rng(5)
    correction = torch.from_numpy(rng.standard_normal((3, 10, 12)).astype(np.float32))
    moving = torch.zeros(10, 12, dtype=torch.bool)
    moving[3:7, 4:] = True
    c_map = torch.where(moving, 0.35, 0.5)
    expected = torch.where(
        moving, precondition_filter(correction, 0.35), precondition_filter(correction, 0.5)
    )
    assert torch.allclose(precondition_filter(correction, c_map), expected, atol=1e-6)
