"""The numba backend of MPE against the torch reference: same algorithm, same outputs.

Both backends run the same arithmetic in the same precision (vertices in
float64, raster and pixel stage in float32), so they agree almost bit for
bit. What may differ: the order of float32 operations inside one expression
(torch's vectorized kernels may fuse multiply-adds), which can move a pixel
centre that lies within an ulp of a triangle edge, or a depth comparison at
the shear tolerance, to the other side; and the colour, which numba rounds to
8 bits before the pull-push fill of holes (torch after). Hence the tolerances:
colours >= 40 dB PSNR apart, hole and fill masks equal on >= 99% of pixels,
depths within 1e-3 on >= 99% of pixels.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from server.frames.frame import RenderFrame, Size
from server.game.render.renderer import Renderer
from upscalers import metrics
from upscalers.framegen import MeshProjectionPredictor, MpeOptions, Prediction
from upscalers.framegen.mpe_cpu import warm_up

MIN_PSNR_DB = 40.0
MIN_MASK_AGREEMENT = 0.99


def _copy(f: RenderFrame) -> RenderFrame:
    return RenderFrame(
        f.color.copy(), f.depth.copy(), f.motion.copy(), f.dynamic_mask.copy(), f.meta
    )


def _pair(scene: str, size: Size, t: float, dt: float) -> tuple[RenderFrame, RenderFrame]:
    r = Renderer(scene, size, jitter=False)
    first = _copy(r.render(0, t))
    return first, r.render(1, t + dt)


def _both(options: MpeOptions, first: RenderFrame, second: RenderFrame) -> list[Prediction]:
    out = []
    for backend in ("torch", "numba"):
        p = MeshProjectionPredictor(MpeOptions(**{**options.__dict__, "backend": backend}), "cpu")
        assert p.backend == backend
        p.observe(first)
        pred = p.predict(second.meta.camera.view, second.meta.camera.proj)
        assert pred is not None
        out.append(pred)
    return out


def _assert_agree(ref: Prediction, fast: Prediction) -> None:
    assert fast.color.shape == ref.color.shape and fast.color.dtype == np.uint8
    assert fast.holes.shape == ref.holes.shape and fast.filled.shape == ref.filled.shape
    assert fast.depth.dtype == np.float32 and np.isfinite(fast.depth).all()
    assert fast.source_frame_id == ref.source_frame_id
    psnr = metrics.psnr(ref.color, fast.color)
    assert psnr >= MIN_PSNR_DB, psnr
    assert (ref.holes == fast.holes).mean() >= MIN_MASK_AGREEMENT
    assert (ref.filled == fast.filled).mean() >= MIN_MASK_AGREEMENT
    assert (np.abs(ref.depth - fast.depth) <= 1e-3).mean() >= MIN_MASK_AGREEMENT


@pytest.mark.parametrize("size", [Size(160, 90), Size(161, 91)])
@pytest.mark.parametrize("tile", [8, 16])
@pytest.mark.parametrize("scene", ["slow_pan", "fast_yaw", "dolly", "moving_objects"])
def test_backends_agree_on_real_scenes(scene: str, tile: int, size: Size) -> None:
    first, second = _pair(scene, size, 0.4, 2 / 60)
    if scene == "moving_objects":
        assert first.dynamic_mask.any()  # the dynamic-pixel paths are exercised
    ref, fast = _both(MpeOptions(tile=tile), first, second)
    _assert_agree(ref, fast)
    assert ref.holes.any()  # a non-trivial case: something to disagree on


@pytest.mark.parametrize(
    "options",
    [
        MpeOptions(tensile=False),
        MpeOptions(shear=False),
        MpeOptions(tensile=False, shear=False),
        MpeOptions(shear_iterations=3),
        MpeOptions(shear_min_shift_px=0.25),
        MpeOptions(tensile_threshold_px=0.25, shear_tolerance=0.002),
        MpeOptions(tile=5, max_bbox_share=0.001),
    ],
)
def test_backends_agree_for_every_option(options: MpeOptions) -> None:
    first, second = _pair("dolly", Size(160, 90), 0.5, 3 / 60)
    ref, fast = _both(options, first, second)
    _assert_agree(ref, fast)


def test_backend_choice() -> None:
    assert MeshProjectionPredictor(device="cpu").backend == "numba"
    assert MeshProjectionPredictor(MpeOptions(backend="torch"), "cpu").backend == "torch"
    # A CUDA device takes the torch path; numba there is a configuration error.
    assert MeshProjectionPredictor(device=torch.device("cuda")).backend == "torch"
    with pytest.raises(ValueError, match="CPU"):
        MeshProjectionPredictor(MpeOptions(backend="numba"), torch.device("cuda"))
    with pytest.raises(ValueError, match="backend"):
        MeshProjectionPredictor(MpeOptions(backend="fast"), "cpu")  # type: ignore[arg-type]


def test_returned_frames_are_not_reused_buffers() -> None:
    first, second = _pair("slow_pan", Size(96, 54), 0.3, 1 / 60)
    p = MeshProjectionPredictor(device="cpu")
    p.observe(first)
    cam = second.meta.camera
    a = p.predict(cam.view, cam.proj)
    assert a is not None
    kept = (a.color.copy(), a.holes.copy(), a.depth.copy(), a.filled.copy())
    p.observe(_copy(second))  # same size: the cache buffers are reused
    b = p.predict(first.meta.camera.view, first.meta.camera.proj)
    assert b is not None and b.source_frame_id == second.meta.frame_id
    for before, now in zip(kept, (a.color, a.holes, a.depth, a.filled), strict=True):
        assert np.array_equal(before, now)


def test_frame_size_changes_between_observes() -> None:
    p = MeshProjectionPredictor(device="cpu")
    for size in (Size(64, 36), Size(33, 17), Size(64, 36)):
        first, second = _pair("slow_pan", size, 0.3, 1 / 60)
        p.observe(first)
        pred = p.predict(second.meta.camera.view, second.meta.camera.proj)
        assert pred is not None and pred.color.shape == (size.height, size.width, 3)


def test_mismatched_frame_buffers_are_refused() -> None:
    first, _ = _pair("slow_pan", Size(32, 18), 0.3, 1 / 60)
    bad = RenderFrame(
        first.color[:, :-1], first.depth, first.motion, first.dynamic_mask, first.meta
    )
    with pytest.raises(ValueError, match="disagree"):
        MeshProjectionPredictor(device="cpu").observe(bad)


def test_tiny_frames() -> None:
    # One pixel, one row: every pyramid and tile loop at its smallest.
    for w, h in ((1, 1), (7, 1), (1, 5), (3, 2)):
        r = np.zeros((h, w, 3), np.uint8)
        first, second = _pair("slow_pan", Size(32, 18), 0.3, 1 / 60)
        frame = RenderFrame(
            r,
            np.full((h, w), 0.5, np.float32),
            np.zeros((h, w, 2), np.float32),
            np.zeros((h, w), np.uint8),
            first.meta,
        )
        ref, fast = _both(MpeOptions(tile=8), frame, second)
        assert fast.color.shape == (h, w, 3)
        assert np.array_equal(ref.holes, fast.holes)


def test_warm_up_runs_once() -> None:
    MeshProjectionPredictor(device="cpu")  # compiles or loads the kernels
    assert warm_up(MpeOptions()) == 0.0


def _hole_masks(h: int, w: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Hole layouts that exercise every path of the block-wise fill."""
    masks = {"scattered": rng.random((h, w)) < 0.1}
    blob = np.zeros((h, w), bool)
    blob[h // 3 : h // 3 + max(1, h // 5), w // 4 : w // 4 + max(1, w // 6)] = True
    masks["blob"] = blob  # holes with valid pixels in their own 32 x 32 blocks
    big = np.zeros((h, w), bool)
    big[:, : max(1, 3 * w // 4)] = True
    big[: h // 2] = True
    masks["most_of_the_frame"] = big  # whole blocks without a valid pixel
    one_left = np.ones((h, w), bool)
    one_left[h - 1, w - 1] = False
    masks["one_valid_pixel"] = one_left
    masks["none"] = np.zeros((h, w), bool)
    masks["all"] = np.ones((h, w), bool)
    return masks


@pytest.mark.parametrize("size", [(360, 640), (91, 161), (14, 24), (16, 16), (33, 65), (1, 1)])
@pytest.mark.parametrize("channels", [1, 3])
def test_block_fill_matches_the_whole_frame_pyramid(size: tuple[int, int], channels: int) -> None:
    """The numba fill works per 32 x 32 block; it must give what torch's whole-frame
    pull-push gives, for holes inside blocks, whole empty blocks, and the edge cases."""
    from upscalers.framegen import cpu_kernels
    from upscalers.framegen.fill import pull_push_fill

    h, w = size
    rng = np.random.default_rng(h * 1000 + w)
    for name, holes in _hole_masks(h, w, rng).items():
        values = (rng.random((h, w, channels)) * 255).astype(np.float32)
        want = pull_push_fill(torch.from_numpy(values.copy()), torch.from_numpy(holes)).numpy()
        got = values.copy()
        n = cpu_kernels.pull_push_fill(got, holes, False)
        assert n == int(holes.sum()), name
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-3, err_msg=name)
        colour = values.astype(np.uint8)
        rounded = colour.copy()
        cpu_kernels.pull_push_fill(rounded, holes, True)
        want8 = pull_push_fill(
            torch.from_numpy(colour.astype(np.float32)), torch.from_numpy(holes)
        ).numpy()
        want8 = np.clip(want8 + 0.5, 0, 255).astype(np.uint8)
        assert (np.abs(rounded.astype(int) - want8) <= 1).all(), name
        assert np.array_equal(rounded[~holes], colour[~holes]), name
