"""The real-content suite's offline multi-frame least-squares reference: a solve of
every frame's jittered box samples (server/eval/multiframe_ls.py)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from server.cli import main
from server.eval import multiframe_ls
from server.eval.multiframe_ls import (
    Samples,
    clamp_to_samples,
    footprint_matrix,
    least_squares,
    measured_frames,
    sequence_reference,
)
from server.eval.real_content_sequences import build_sequence
from server.frames.frame import Size
from server.game.render.transforms import jitter_offset
from upscalers import metrics
from upscalers.temporal.params import TemporalParams


def _texture(seed: int, shape: tuple[int, int]) -> np.ndarray:
    """Detail at every scale: noise blurred at two radii (uint8 RGB)."""
    rng = np.random.default_rng(seed)
    noise = rng.random((*shape, 3)).astype(np.float32)
    img = 0.6 * cv2.GaussianBlur(noise, (0, 0), 4) + 0.4 * cv2.GaussianBlur(noise, (0, 0), 0.8)
    img = (img - img.min()) / (img.max() - img.min())
    return (img * 255).astype(np.uint8)


def test_footprint_rows_average_the_pixels_under_the_box() -> None:
    aligned = footprint_matrix(3, 6, 2.0, 0.0)
    assert aligned[1].tolist() == [0.0, 0.0, 0.5, 0.5, 0.0, 0.0]
    half = footprint_matrix(3, 6, 2.0, 0.5)
    assert half[0].tolist() == [0.25, 0.5, 0.25, 0.0, 0.0, 0.0]
    # Parts beyond the canvas count for the edge pixel: every row still averages.
    for start in (-1.3, 0.0, 0.7, 2.4):
        np.testing.assert_allclose(footprint_matrix(5, 9, 1.7, start).sum(axis=1), 1.0, atol=1e-6)
    with pytest.raises(ValueError, match="positive"):
        footprint_matrix(0, 4, 2.0, 0.0)


def _as_u8(image: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def _jittered_samplings(truth: np.ndarray, frames: int, offset: float) -> list[Samples]:
    """Box samplings of ``truth`` (H, W, 3 float) at 2x with the game's Halton jitter,
    the footprints shifted by ``offset`` display pixels, rounded to 8 bits as a renderer
    stores them."""
    h, w = truth.shape[0] // 2, truth.shape[1] // 2
    out = []
    for t in range(frames):
        jx, jy = jitter_offset(t, 32)
        sx, sy = 2.0 * jx + offset, 2.0 * jy + offset
        ay = footprint_matrix(h, truth.shape[0], 2.0, sy)
        ax = footprint_matrix(w, truth.shape[1], 2.0, sx)
        color = np.stack([ay @ truth[..., c] @ ax.T for c in range(3)], axis=-1)
        out.append(Samples(_as_u8(color), sx, sy))
    return out


def _bicubic(samples: Samples, canvas: Size) -> np.ndarray:
    up = cv2.resize(samples.color, tuple(canvas), interpolation=cv2.INTER_CUBIC)
    return np.asarray(up, np.float32)


def test_least_squares_recovers_detail_no_single_frame_holds() -> None:
    """Eight jittered 2x box samplings of a textured picture: the reconstruction from
    all of them is far closer to the picture than the bicubic upscale of one."""
    truth = _texture(1, (36, 60)).astype(np.float32)
    samples = _jittered_samplings(truth, 8, 0.5)
    init = _bicubic(samples[0], Size(60, 36))
    out, iterations = least_squares(samples, (2.0, 2.0), Size(60, 36), init)
    gain = metrics.psnr(_as_u8(truth), _as_u8(out)) - metrics.psnr(_as_u8(truth), _as_u8(init))
    assert gain > 4.0, gain
    assert 1 <= iterations <= multiframe_ls.MAX_ITERATIONS


def test_the_discrepancy_stop_keeps_rounding_from_being_amplified() -> None:
    """Run on (no stop, many iterations), the ill-conditioned system turns rounding
    into noise; the discrepancy principle stops before that."""
    truth = _texture(2, (36, 60)).astype(np.float32)
    samples = _jittered_samplings(truth, 6, 0.0)
    init = _bicubic(samples[0], Size(60, 36))
    stopped, _ = least_squares(samples, (2.0, 2.0), Size(60, 36), init)
    old = multiframe_ls.DISCREPANCY
    try:
        multiframe_ls.DISCREPANCY = 0.0
        unstopped, iterations = least_squares(samples, (2.0, 2.0), Size(60, 36), init, 200)
    finally:
        multiframe_ls.DISCREPANCY = old
    assert iterations == 200
    assert metrics.psnr(_as_u8(truth), _as_u8(stopped)) > metrics.psnr(
        _as_u8(truth), _as_u8(unstopped)
    )


def test_clamp_keeps_each_pixel_in_its_render_pixels_range() -> None:
    """Temporal's output clamp: the 3x3 range widened by its slack (3 levels), reached
    where the image lies beyond it."""
    slack = TemporalParams().output_clamp_slack
    color = _texture(3, (9, 12))
    image = np.random.default_rng(0).uniform(-50, 300, (18, 24, 3)).astype(np.float32)
    out = clamp_to_samples(image, color)
    padded = np.pad(color.astype(np.float32), ((1, 1), (1, 1), (0, 0)), mode="edge")
    for y in range(18):
        for x in range(24):
            box = padded[y // 2 : y // 2 + 3, x // 2 : x // 2 + 3].reshape(-1, 3)
            lo, hi = box.min(axis=0) - slack, box.max(axis=0) + slack
            assert np.all(out[y, x] >= lo) and np.all(out[y, x] <= hi)
            assert np.all((out[y, x] == lo) | (out[y, x] == hi) | (out[y, x] == image[y, x]))
    flat = np.full((9, 12, 3), 77, np.uint8)
    assert np.all(np.abs(clamp_to_samples(image, flat) - 77) <= slack)


def test_measured_frames_spread_over_the_span() -> None:
    assert measured_frames(32, 8) == [8, 16, 23, 31]
    assert measured_frames(5, 8) == [4]


@pytest.mark.parametrize("kind", ["still", "pan"])
def test_the_reference_beats_one_frame_on_a_sequence(kind: str) -> None:
    """On a textured picture the samples of a dozen frames allow more than a spatial
    upscale of the last one (OpenCV's cubic of the unjittered render), for the still
    camera and the pan alike, and within the clamp no pixel leaves its range."""
    src = _texture(4, (200, 300))
    display = Size(96, 64)
    refs = sequence_reference(kind, src, display, 2.0, 12, 4)
    seq = build_sequence(kind, "t", src, src, display, 2.0, 12)
    assert [r.frame for r in refs] == [4, 6, 9, 11]
    for b in refs:
        spatial = cv2.resize(seq.unjittered[b.frame].color, (96, 64), interpolation=cv2.INTER_CUBIC)
        one_frame = metrics.psnr(seq.truth[b.frame], spatial)
        assert b.psnr > one_frame + 1.0, (b, one_frame)
        assert np.isfinite(b.psnr_clamped)
    with pytest.raises(ValueError, match="covers still, pan"):
        sequence_reference("zoom", src, display, 2.0, 12, 4)


def test_eval_reports_the_reference_per_photograph(tmp_path: Path) -> None:
    (tmp_path / "c" / "pics").mkdir(parents=True)
    Image.fromarray(_texture(5, (220, 300))).save(tmp_path / "c" / "pics" / "a.png")
    out = tmp_path / "r.json"
    code = main(
        ["eval", "upscalers", "--json", str(out), "--table", str(tmp_path / "r.md"),
         "--scenes", "none", "--scales", "2", "--methods", "bicubic,temporal",
         "--real-content", str(tmp_path / "c"), "--real-frames", "8",
         "--real-measure-from", "3", "--real-display-size", "96x64", "--multiframe-ls"]
    )  # fmt: skip
    assert code == 0
    ref = json.loads(out.read_text())["real_content"]["multiframe_ls"]["scales"]["2"]
    assert set(ref) == {"still", "pan"}
    for kind in ref.values():
        assert list(kind["psnr_by_image"]) == ["pics/a.png"]
        assert 15 < kind["psnr_db"] < 70 and 15 < kind["psnr_clamped_db"] < 70
    table = (tmp_path / "r.md").read_text()
    assert "Multi-frame least squares" in table and "| pics/a.png |" in table


def test_multiframe_ls_needs_real_content(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="--multiframe-ls needs --real-content"):
        main(["eval", "upscalers", "--json", str(tmp_path / "x.json"), "--multiframe-ls"])
