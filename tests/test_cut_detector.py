"""Scene cuts without the RESET flag: found, and only where the picture changed."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from server.eval.real_content_sequences import build_sequence
from server.frames.frame import Camera, FrameFlags, FrameMeta, RenderFrame, Size
from server.game.render.transforms import jitter_offset
from tests.test_real_content import _photo
from upscalers import metrics
from upscalers.api import upscale_sequence
from upscalers.host import UpscalerHost
from upscalers.output import to_uint8
from upscalers.temporal.cut_detector import CutDetector


def _picture(seed: int, h: int = 270, w: int = 480) -> np.ndarray:
    return _photo(seed, (h, w))


def _frame(color: np.ndarray, motion: np.ndarray | None = None, index: int = 0) -> RenderFrame:
    h, w = color.shape[:2]
    return RenderFrame(
        color=color,
        depth=np.full((h, w), 0.5, np.float32),
        motion=np.zeros((h, w, 2), np.float32) if motion is None else motion,
        dynamic_mask=np.zeros((h, w), np.uint8),
        meta=FrameMeta(index, Camera.identity(), jitter_offset(index, 8), FrameFlags.NONE),
    )


def _shares(frames: list[RenderFrame]) -> list[float | None]:
    detector = CutDetector()
    out = []
    for f in frames:
        detector.observe(f)
        out.append(detector.last_changed)
    return out


@pytest.mark.parametrize("kind", ["still", "pan", "zoom"])
def test_a_camera_over_one_picture_is_never_a_cut(kind: str) -> None:
    src = _picture(1, 540, 960)
    seq = build_sequence(kind, "synthetic", src, src, Size(480, 270), 2.0, 12)
    shares = _shares(seq.jittered)
    assert shares[0] is None  # nothing to compare the first frame with
    # The largest share seen on the game's scenes and 158 photographs was 0.04.
    assert max(s for s in shares[1:] if s is not None) < 0.05


def test_a_cut_to_another_picture_is_found() -> None:
    before, after = _picture(2), _picture(3)
    detector = CutDetector()
    assert not detector.observe(_frame(before))
    assert detector.observe(_frame(after))
    assert detector.last_changed is not None and detector.last_changed > 0.5


def test_texture_giving_way_to_a_flat_picture_is_found() -> None:
    # Every flat value lies inside the textured picture's wide 3x3 ranges: only the
    # other way round (the old values against the flat picture's ranges) shows it.
    rng = np.random.default_rng(4)
    texture = rng.integers(0, 256, (90, 160, 3), dtype=np.uint8)
    flat = np.full((90, 160, 3), 128, np.uint8)
    detector = CutDetector()
    detector.observe(_frame(texture))
    assert detector.observe(_frame(flat))


def test_motion_decides_where_a_sample_is_compared() -> None:
    """A fast pan (30 render pixels a frame) is no cut with its motion, and is one when
    the same frames come without it."""
    src = _picture(5, 200, 400)
    a, b = src[:, :300], src[:, 30:330]
    motion = np.zeros((200, 300, 2), np.float32)
    motion[..., 0] = 30.0  # the content at x was at x + 30 in the frame before
    with_motion = CutDetector()
    with_motion.observe(_frame(a))
    assert not with_motion.observe(_frame(b, motion, 1))
    assert with_motion.last_changed == 0.0
    without = CutDetector()
    without.observe(_frame(a))
    assert without.observe(_frame(b, None, 1))


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (5, 1), (3, 5), (37, 61)])
def test_tiny_and_odd_sizes(shape: tuple[int, int]) -> None:
    rng = np.random.default_rng(6)
    detector = CutDetector()
    for i in range(3):
        color = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)
        detector.observe(_frame(color, None, i))
    assert detector.last_changed is not None and 0.0 <= detector.last_changed <= 1.0


def test_bad_motion_is_taken_as_none_and_far_motion_is_not_judged() -> None:
    color = _picture(7, 90, 160)
    detector = CutDetector()
    detector.observe(_frame(color))
    nan = np.full((90, 160, 2), np.nan, np.float32)
    assert not detector.observe(_frame(color, nan, 1))
    assert detector.last_changed == 0.0
    far = np.full((90, 160, 2), 1e6, np.float32)
    assert not detector.observe(_frame(_picture(8, 90, 160), far, 2))
    assert detector.last_changed is None  # nothing of the frame before is on screen


def test_a_size_change_starts_afresh() -> None:
    detector = CutDetector()
    detector.observe(_frame(_picture(9, 90, 160)))
    assert not detector.observe(_frame(_picture(10, 45, 80)))
    assert detector.last_changed is None


def test_the_remembered_frame_is_a_copy() -> None:
    """The worker hands frames that are views of ring slots, rewritten by the next
    frame: what the detector remembers must not change with them."""
    slot = _picture(11, 90, 160)
    detector = CutDetector()
    detector.observe(_frame(slot))
    slot[:] = _picture(12, 90, 160)
    assert detector.observe(_frame(slot))


def _unflag(frame: RenderFrame) -> RenderFrame:
    flags = frame.meta.flags & ~FrameFlags.RESET
    return dataclasses.replace(frame, meta=dataclasses.replace(frame.meta, flags=flags))


def _cut_psnr(detect: bool, flagged: bool) -> list[float]:
    src, other = _picture(13, 540, 960), _picture(14, 540, 960)
    display = Size(320, 180)
    seq = build_sequence("cut", "synthetic", src, other, display, 2.0, 12)
    assert seq.cut is not None
    host = UpscalerHost("temporal", display, detect_cuts=detect)
    psnr = []
    for t, frame in enumerate(seq.jittered):
        frame = frame if flagged or t != seq.cut else _unflag(frame)
        psnr.append(metrics.psnr(seq.truth[t], to_uint8(host.upscale(frame))))
    if detect and not flagged:
        assert host.cuts_found == 1
    return psnr[seq.cut : seq.cut + 3]


def test_an_unflagged_cut_upscales_as_a_flagged_one() -> None:
    flagged = _cut_psnr(detect=True, flagged=True)
    found = _cut_psnr(detect=True, flagged=False)
    missed = _cut_psnr(detect=False, flagged=False)
    # The frames after the cut come out as if it had been flagged ...
    assert found == pytest.approx(flagged, abs=0.01)
    # ... where blending across it ghosts the picture before.
    assert missed[0] < flagged[0] - 3.0


def test_spatial_methods_and_flagged_frames_do_not_count() -> None:
    a, b = _picture(15, 90, 160), _picture(16, 90, 160)
    spatial = UpscalerHost("bicubic", Size(320, 180))
    spatial.upscale(_frame(a))
    spatial.upscale(_frame(b))
    assert spatial.cuts_found == 0
    temporal = UpscalerHost("temporal", Size(320, 180))
    temporal.upscale(_frame(a))
    cut = _frame(b, None, 1)
    temporal.upscale(
        dataclasses.replace(cut, meta=dataclasses.replace(cut.meta, flags=FrameFlags.RESET))
    )
    assert temporal.cuts_found == 0  # flagged: the flag reset it already


def test_the_sequence_api_finds_cuts_unless_told_not_to() -> None:
    frames = [_picture(17, 90, 160)] * 4 + [_picture(18, 90, 160)] * 4
    on = list(upscale_sequence(frames, 2, method="temporal"))
    off = list(upscale_sequence(frames, 2, method="temporal", detect_cuts=False))
    first_after = upscale_sequence([frames[4]], 2, method="temporal")
    alone = next(iter(first_after))
    # With detection the frame after the cut is the new picture's own first frame.
    assert np.array_equal(on[4], alone)
    assert not np.array_equal(off[4], alone)
