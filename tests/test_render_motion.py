"""Motion vectors reproduce frame t from frame t-1 on surfaces that stay visible."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from server.frames.frame import RenderFrame, Size
from server.game.render.renderer import Renderer
from server.game.render.scenes import SCENES

SIZE = Size(320, 180)
FPS = 60.0
SS = 4
LOD_BIAS = 2.0
MOVING = [n for n, info in SCENES.items() if info.camera_motion or info.moving_objects]
# The schedule's first 12 s are a still camera: warp it inside each moving segment
# (slow pan, fast yaw at its second place, crossing objects, thin detail) instead.
SCHEDULE_TIMES = (18.5, 29.5, 40.5, 52.5)
CASES = [pytest.param(n, 0.5, id=n) for n in MOVING if n != "schedule"] + [
    pytest.param("schedule", t, id=f"schedule@{t:g}") for t in SCHEDULE_TIMES
]


def _linear_depth(ndc: np.ndarray, near: float, far: float) -> np.ndarray:
    return near * far / (far - ndc * (far - near))


def _reprojected_view_depth(frame: RenderFrame) -> np.ndarray:
    """View depth in the previous camera of the current surface (static-world reprojection)."""
    cam = frame.meta.camera
    h, w = frame.depth.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    ndc = np.stack(
        [2 * xs / w - 1, 1 - 2 * ys / h, frame.depth.astype(np.float64), np.ones_like(xs)], -1
    )
    inv = np.linalg.inv(cam.proj.astype(np.float64) @ cam.view.astype(np.float64))
    world = ndc @ inv.T
    world /= world[..., 3:4]
    prev_view = world @ cam.prev_view.astype(np.float64).T
    return -prev_view[..., 2]


def _sample(img: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Bilinear sample of an (H, W, C) image at pixel positions (H, W, 2) (centres at +0.5)."""
    h, w = img.shape[:2]
    gx = pos[..., 0] / w * 2 - 1
    gy = pos[..., 1] / h * 2 - 1
    grid = torch.from_numpy(np.stack([gx, gy], -1)[None].astype(np.float32))
    src = torch.from_numpy(img.astype(np.float32)).permute(2, 0, 1)[None]
    out = F.grid_sample(src, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[0].permute(1, 2, 0).numpy()


def _stable_mask(prev: RenderFrame, cur: RenderFrame, pos: np.ndarray) -> np.ndarray:
    cam = cur.meta.camera
    near, far = cam.near, cam.far
    h, w = cur.depth.shape
    lin_cur = _linear_depth(cur.depth, near, far)
    expected = _reprojected_view_depth(cur)
    lin_prev = _linear_depth(_sample(prev.depth[..., None], pos)[..., 0], near, far)
    agree = np.abs(lin_prev - expected) < 0.02 * expected
    # Away from depth edges (2 px) and the dynamic-mask boundary, and on screen.
    # 1 / depth is affine in screen space across a plane: its second difference
    # flags creases and silhouettes, then dilate by 2 px.
    inv = 1.0 / lin_cur
    pad = np.pad(inv, 1, mode="edge")
    d2 = np.maximum(
        np.abs(pad[1:-1, 2:] + pad[1:-1, :-2] - 2 * inv),
        np.abs(pad[2:, 1:-1] + pad[:-2, 1:-1] - 2 * inv),
    )
    edge = torch.from_numpy((d2 > 0.01 * inv).astype(np.float32))[None, None]
    flat = F.max_pool2d(edge, 5, 1, 2)[0, 0].numpy() == 0
    m = torch.from_numpy(cur.dynamic_mask.astype(np.float32))[None, None]
    mask_edge = (F.max_pool2d(m, 5, 1, 2) - -F.max_pool2d(-m, 5, 1, 2))[0, 0].numpy() > 0
    on_screen = (
        (pos[..., 0] > 1) & (pos[..., 0] < w - 1) & (pos[..., 1] > 1) & (pos[..., 1] < h - 1)
    )
    sky = cur.depth >= 1.0
    return (agree | sky) & flat & ~mask_edge & on_screen


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * np.log10(255.0**2 / max(mse, 1e-12))


@pytest.mark.parametrize(("scene", "t0"), CASES)
def test_warp_with_motion_reproduces_frame(scene: str, t0: float) -> None:
    # Supersampled colour and blurrier mips: the test checks geometry, not how
    # well bilinear resampling reproduces texture detail at the Nyquist limit.
    r = Renderer(scene, SIZE, jitter=False, texture_lod_bias=LOD_BIAS)
    prev = r.render(0, t0 - 1 / FPS, supersample=SS)
    cur = r.render(1, t0, supersample=SS)
    assert not cur.meta.flags
    h, w = cur.depth.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32) + 0.5
    pos = np.stack([xs, ys], -1) + cur.motion
    warped = _sample(prev.color, pos)
    mask = _stable_mask(prev, cur, pos)
    assert mask.mean() > 0.5, f"too few stable pixels: {mask.mean():.2f}"
    psnr = _psnr(warped[mask], cur.color[mask])
    moved = np.abs(cur.motion[mask]).max()
    assert moved > 0.2, "test frames should actually move"
    assert psnr >= 40.0, f"{scene}: warp PSNR {psnr:.1f} dB"


def test_static_scene_motion_is_exactly_zero_with_jitter() -> None:
    r = Renderer("static", Size(160, 90), jitter=True)
    for i in range(4):
        f = r.render(i, i / FPS)
        assert f.meta.jitter != (0.0, 0.0)
        assert np.all(f.motion == 0.0)
        assert not f.dynamic_mask.any()


def test_sky_depth_is_one_and_sky_motion_follows_yaw() -> None:
    r = Renderer("fast_yaw", Size(160, 90), jitter=False)
    r.render(0, 0.5 - 1 / FPS)
    f = r.render(1, 0.5)
    sky = f.depth == 1.0
    assert sky.sum() > 1000
    cam = f.meta.camera
    # Expected: direction through each sky pixel, rotated by the previous view only.
    h, w = f.depth.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    ndc = np.stack([2 * xs / w - 1, 1 - 2 * ys / h], -1)
    p, v, pv = (m.astype(np.float64) for m in (cam.proj, cam.view, cam.prev_view))
    dirs_view = np.stack([ndc[..., 0] / p[0, 0], ndc[..., 1] / p[1, 1], -np.ones_like(xs)], -1)
    dirs_world = dirs_view @ v[:3, :3]  # view -> world is the transpose
    prev_dir = dirs_world @ pv[:3, :3].T
    clip = prev_dir @ p[:, :3].T
    px = (clip[..., 0] / clip[..., 3] + 1) * w / 2
    py = (1 - clip[..., 1] / clip[..., 3]) * h / 2
    expected = np.stack([px - xs, py - ys], -1)
    err = np.abs(f.motion - expected)[sky]
    assert err.max() < 1e-2
    # 200 deg/s at 60 fps is 3.3 deg of yaw: several pixels of horizontal sky motion.
    assert np.abs(f.motion[sky][:, 0]).mean() > 2.0
