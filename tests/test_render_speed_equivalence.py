"""The fast paths of the renderer agree with the plain formulas they replace."""

from __future__ import annotations

import math

import numpy as np
import torch

from server.frames.frame import Size
from server.game.render.rays import ObjectInstance, make_grid, screen_rects
from server.game.render.renderer import Renderer
from server.game.render.shading import encode_srgb_into, linear_to_srgb, mip_level, quantize_into
from server.game.render.shapes import Box, SceneObject
from server.game.render.textures import LEVELS


def test_srgb_table_matches_pow_within_one_code() -> None:
    lin = torch.linspace(-0.1, 1.1, 300_001).view(1, 1, -1).expand(3, 1, -1).contiguous()
    lin[0, 0, :5] = math.nan
    lin[1, 0, :5] = math.inf
    lin[2, 0, :5] = -math.inf
    out = torch.empty(1, lin.shape[2], 3, dtype=torch.uint8)
    encode_srgb_into(lin, out)
    ref = torch.empty_like(out)
    quantize_into(linear_to_srgb(lin.permute(1, 2, 0)), ref)
    diff = (out.int() - ref.int()).abs()
    assert int(diff.max()) <= 1
    assert float((diff > 0).float().mean()) < 0.01
    assert (out[0, :5, 0] == 0).all() and (out[0, :5, 1] == 255).all()
    assert (out[0, :5, 2] == 0).all()


def test_mip_level_is_rounded_log2() -> None:
    foot = torch.exp2(torch.linspace(-3.0, 12.0, 10_001)) * math.sqrt(2.0)
    expected = (torch.log2(foot / math.sqrt(2.0)) + 1e-4).round().clamp(0, LEVELS - 1)
    got = mip_level(foot)
    assert (got.float() - expected).abs().max() <= 1
    assert float((got.float() != expected).float().mean()) < 1e-3
    special = torch.tensor([0.0, -1.0, math.nan, math.inf, 1e-30])
    assert mip_level(special).tolist() == [0, 0, LEVELS - 1, LEVELS - 1, 0]


def test_rects_clip_at_the_near_plane() -> None:
    r = Renderer("static", Size(160, 90), jitter=False)
    pose = r.scene.camera(0.0)
    px, py, pz = pose.position
    behind = SceneObject.still(Box((0.5, 0.5, 0.5)), "brick", (px, py, pz + 3.0))
    # Straddles the camera plane, its front part off to the right of the view.
    side = SceneObject.still(Box((0.3, 0.3, 2.0)), "brick", (px + 1.0, py, pz))
    setup = r._setup(0.0, 0.0, r.render_size, True, r.game_camera.state)
    grid = make_grid(setup, 160, 90, (0.0, 0.0), 0, 90, r.device)

    insts = [ObjectInstance(i, o, o.pose_at(0.0).matrix(), o.pose_at(0.0).matrix())
             for i, o in enumerate((behind, side))]  # fmt: skip
    rects = screen_rects(setup, insts, grid)
    assert rects[0] is None
    assert rects[1] is not None
    _, _, c0, c1 = rects[1]
    assert c0 > 80 and c1 == 160  # right half only, not the whole band


def test_supersampled_colour_close_to_single_sample() -> None:
    r = Renderer("default", Size(160, 90), jitter=False, texture_lod_bias=2.0)
    one = r.render(0, 0.5).color.astype(np.float64)
    ss = r.render(0, 0.5, supersample=2).color.astype(np.float64)
    assert np.abs(one - ss).mean() < 12.0
