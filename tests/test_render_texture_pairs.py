"""The pair-gather texture sampler matches the plain four-tap bilinear formula."""

from __future__ import annotations

import torch

from server.game.render.shading import mip_level, sample_texture
from server.game.render.textures import LEVEL_OFFSETS, PYRAMID_TEXELS, SIZE, texture_atlas


def _plain(atlas, u, v, tex, foot):  # type: ignore[no-untyped-def]
    level = mip_level(foot).long()
    size = (SIZE >> level).float()
    base = torch.tensor(LEVEL_OFFSETS)[level] + tex.long() * PYRAMID_TEXELS
    x, y = u * size - 0.5, v * size - 0.5  # float32, like the renderer
    x0, y0 = x.floor(), y.floor()
    fx, fy = x - x0, y - y0
    size, x0, y0 = size.long(), x0.long(), y0.long()
    taps = [[base + torch.remainder(yy, size) * size + torch.remainder(xx, size)
             for xx in (x0, x0 + 1)] for yy in (y0, y0 + 1)]  # fmt: skip
    out = []
    for plane in atlas.planes:
        t = [[plane[i.long()] for i in row] for row in taps]
        out.append(
            torch.lerp(torch.lerp(t[0][0], t[0][1], fx), torch.lerp(t[1][0], t[1][1], fx), fy)
        )
    return out


def test_pair_sampler_matches_plain_bilinear() -> None:
    atlas = texture_atlas("cpu")
    gen = torch.Generator().manual_seed(0)
    n = 200_000
    u = (torch.rand(n, generator=gen) - 0.5) * 40.0
    v = (torch.rand(n, generator=gen) - 0.5) * 40.0
    tex = torch.randint(0, len(atlas.names), (n,), generator=gen).float()
    foot = torch.exp2(torch.rand(n, generator=gen) * 12.0 - 2.0)
    got = sample_texture(atlas, u, v, tex, foot)
    ref = _plain(atlas, u, v, tex, foot)
    for g, r in zip(got, ref, strict=True):
        assert torch.equal(g, r)
