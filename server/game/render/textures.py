"""Texture atlas: real photographs from the scikit-image wheel plus procedural ones.

Every texture is resampled to SIZE x SIZE and stored with its full mip pyramid
in flat linear-light channel planes, so that the shader can sample any
texture at any level with a single gather per bilinear tap. Square power-of-two
textures keep the level offsets the same for every texture.
"""

from __future__ import annotations

import importlib.util
import math
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, ImageDraw, ImageFont

SIZE = 512
LEVELS = int(math.log2(SIZE)) + 1
LEVEL_SIZES = [SIZE >> i for i in range(LEVELS)]
LEVEL_OFFSETS = [sum(s * s for s in LEVEL_SIZES[:i]) for i in range(LEVELS)]
PYRAMID_TEXELS = sum(s * s for s in LEVEL_SIZES)

# Files shipped inside the scikit-image wheel (skimage/data/), never downloaded.
SKIMAGE_FILES: dict[str, str] = {
    "brick": "brick.png",
    "grass": "grass.png",
    "gravel": "gravel.png",
    "coffee": "coffee.png",
    "chelsea": "chelsea.png",
    "astronaut": "astronaut.png",
    "rocket": "rocket.jpg",
    "text": "text.png",
    "page": "page.png",
}
PROCEDURAL = ("checker", "stripes", "noise", "white", "sign")
TEXTURE_NAMES: tuple[str, ...] = (*SKIMAGE_FILES, *PROCEDURAL)
SIGN_LINES = ("UPCAST", "cloud gaming", "60 fps @ 640x360", "upscale me if you can: 0123456789")


def skimage_data_dir() -> Path:
    """The ``data`` folder inside the installed scikit-image package."""
    spec = importlib.util.find_spec("skimage")
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError("scikit-image is not installed; it ships the texture images")
    return Path(next(iter(spec.submodule_search_locations))) / "data"


def srgb_to_linear(x: torch.Tensor) -> torch.Tensor:
    return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def _load_file(name: str) -> torch.Tensor:
    path = skimage_data_dir() / SKIMAGE_FILES[name]
    with Image.open(path) as im:
        rgb = im.convert("RGB").resize((SIZE, SIZE), Image.Resampling.LANCZOS)
        arr = np.asarray(rgb, dtype=np.float32) / 255.0
    return srgb_to_linear(torch.from_numpy(arr.copy()))


def _sign() -> torch.Tensor:
    """White board with lines of shrinking text: big enough to read, small enough to alias."""
    im = Image.new("RGB", (SIZE, SIZE), (235, 232, 220))
    draw = ImageDraw.Draw(im)
    y = 16
    for line, size in zip(SIGN_LINES, (110, 64, 44, 26), strict=True):
        font = ImageFont.load_default(size=size)
        draw.text((18, y), line, fill=(20, 20, 30), font=font)
        y += int(size * 1.35)
    for i in range(6):  # small print: thin strokes for the thin_detail scene
        font = ImageFont.load_default(size=16)
        draw.text(
            (18, y + i * 22),
            f"fine print line {i}: the quick brown fox jumps",
            (40, 40, 40),
            font,
        )
    arr = np.asarray(im, dtype=np.float32) / 255.0
    return srgb_to_linear(torch.from_numpy(arr.copy()))


def _procedural(name: str) -> torch.Tensor:
    coords = (torch.arange(SIZE, dtype=torch.float32) + 0.5) / SIZE
    v, u = torch.meshgrid(coords, coords, indexing="ij")
    if name == "sign":
        return _sign()
    if name == "white":
        return torch.full((SIZE, SIZE, 3), 0.8)
    if name == "checker":
        g = ((u * 8).floor() + (v * 8).floor()) % 2
        val = 0.12 + 0.7 * g
    elif name == "stripes":
        val = 0.15 + 0.7 * (torch.sin(u * 2 * math.pi * 6) > 0).float()
    else:  # noise: octaves of smooth value noise, seeded so every process agrees
        gen = torch.Generator().manual_seed(1234)
        val = torch.zeros(SIZE, SIZE)
        for octave in range(1, 6):
            n = 4 * 2**octave
            grid = torch.rand(1, 1, n, n, generator=gen)
            # Wrap-pad so the noise tiles seamlessly when the texture repeats.
            grid = torch.cat([grid, grid[..., :1, :]], dim=2)
            grid = torch.cat([grid, grid[..., :, :1]], dim=3)
            up = F.interpolate(grid, size=(SIZE + SIZE // n, SIZE + SIZE // n), mode="bicubic")
            val += up[0, 0, :SIZE, :SIZE] * 0.5**octave
        val = 0.25 + 0.6 * (val - val.min()) / (val.max() - val.min())
    return val[..., None].expand(SIZE, SIZE, 3).contiguous()


def _pyramid(img: torch.Tensor) -> torch.Tensor:
    """All mip levels of an (S, S, 3) image, box-filtered in linear light, flattened."""
    levels = [img.reshape(-1, 3)]
    cur = img.permute(2, 0, 1)[None]
    while cur.shape[-1] > 1:
        cur = F.avg_pool2d(cur, 2)
        levels.append(cur[0].permute(1, 2, 0).reshape(-1, 3))
    return torch.cat(levels)


@dataclass(frozen=True)
class TextureAtlas:
    # (3, len(names) * PYRAMID_TEXELS) int64, one plane per channel: texel (x, y) of a
    # level holds the float32 bits of texel x and of texel (x + 1) mod size of the same
    # row, so one gather fetches both horizontal taps of a bilinear filter, wrap included.
    pairs: torch.Tensor
    names: tuple[str, ...]
    level_offsets: torch.Tensor  # (LEVELS,) float: texel offset of each level in a pyramid
    level_sizes: torch.Tensor  # (LEVELS,) float

    @property
    def planes(self) -> torch.Tensor:
        """(3, texels) float32 linear RGB (a strided view of ``pairs``)."""
        return self.pairs.view(torch.float32).view(3, -1, 2)[..., 0]

    def index(self, name: str) -> int:
        if name not in self.names:
            raise KeyError(f"unknown texture {name!r}; known: {', '.join(self.names)}")
        return self.names.index(name)


def _pairs(planes: torch.Tensor) -> torch.Tensor:
    """Pair planes (see ``TextureAtlas.pairs``) of (3, n * PYRAMID_TEXELS) channel planes."""
    pairs = torch.empty(3, planes.shape[1], 2)
    for t in range(planes.shape[1] // PYRAMID_TEXELS):
        for size, offset in zip(LEVEL_SIZES, LEVEL_OFFSETS, strict=True):
            o = t * PYRAMID_TEXELS + offset
            img = planes[:, o : o + size * size].view(3, size, size)
            pairs[:, o : o + size * size, 0] = img.reshape(3, -1)
            pairs[:, o : o + size * size, 1] = img.roll(-1, 2).reshape(3, -1)
    return pairs.view(torch.int64).view(3, -1)


@cache
def _atlas_cpu() -> TextureAtlas:
    parts = []
    for name in TEXTURE_NAMES:
        img = _load_file(name) if name in SKIMAGE_FILES else _procedural(name)
        parts.append(_pyramid(img))
    planes = torch.cat(parts).T.contiguous()
    return TextureAtlas(
        _pairs(planes),
        TEXTURE_NAMES,
        torch.tensor(LEVEL_OFFSETS, dtype=torch.float32),
        torch.tensor(LEVEL_SIZES, dtype=torch.float32),
    )


@cache
def texture_atlas(device: str = "cpu") -> TextureAtlas:
    """The atlas on ``device``, built once per process and cached per device."""
    cpu = _atlas_cpu()
    if torch.device(device).type == "cpu":
        return cpu
    return TextureAtlas(
        cpu.pairs.to(device),
        cpu.names,
        cpu.level_offsets.to(device),
        cpu.level_sizes.to(device),
    )
