"""FSR 1 RCAS (robust contrast adaptive sharpening), vectorized.

Written from the math of AMD's ``ffx_fsr1.h`` (FsrRcasF). Each pixel ``c`` and
its cross neighbours ``n w e s`` give

    out = (lobe (n + w + e + s) + c) / (4 lobe + 1)

with a negative ``lobe`` as strong as possible without the result leaving
[0, 1], solved per channel from the ring's min and max (``mn``, ``mx``)::

    hitMin = mn / (4 mx)            hitMax = (1 - mx) / (4 mn - 4)
    lobe   = max(-hitMin, hitMax)   (the largest over the channels)

then limited to ``[-(1/4 - 1/16), 0]`` (FSR_RCAS_LIMIT) and scaled by
``2^-sharpness`` (sharpness in stops: 0 is the strongest). Since
``-hitMin = -mn / (4 mx)`` and ``hitMax = -(1 - mx) / (4 (1 - mn))``, the lobe is
``-min(mn / mx, (1 - mx) / (1 - mn)) / 4`` over the channels. The optional noise
removal scales the lobe down where the luma's cross high-pass is large relative
to the local luma range.

The result is written as ``c + lobe (n + w + e + s - 4 c) / (4 lobe + 1)``, the
same value, which keeps a flat neighbourhood exactly flat, and clamped to [0, 1].
Pixels outside the image repeat the edge.
"""

from __future__ import annotations

import torch

from upscalers.fsr1.easu import TINY, Buffers, band_rows

RCAS_LIMIT = 0.25 - 1.0 / 16.0
# 1.5 stops below the strongest sharpening (FSR's sample uses 0.2). Chosen by the sweep
# in docs/reports/eval_rcas_sharpness.{json,md} (8 scenes, 2x, unjittered input as the
# pipeline sends spatial methods, PSNR and FLIP against the supersampled ground truth):
# 0.2 / 0.5 / 1 / 1.5 / 2 stops beat bicubic in PSNR on 1 / 6 / 6 / 7 / 6 of 8 scenes
# and in FLIP on all 8; only 1.5 wins 7 (mean 26.06 dB; 1 stop has the best mean,
# 26.07, but loses thin_detail). Stronger sharpening gains FLIP and SSIM but costs
# PSNR, most on thin_detail's fine texture. No setting wins 'default' in PSNR.
DEFAULT_SHARPNESS = 1.5


def fill_edges(padded: torch.Tensor) -> None:
    """Repeat the interior's edge into the 1-pixel border of a (C, H + 2, W + 2) tensor."""
    padded[:, 1:-1, 0].copy_(padded[:, 1:-1, 1])
    padded[:, 1:-1, -1].copy_(padded[:, 1:-1, -2])
    padded[:, 0].copy_(padded[:, 1])
    padded[:, -1].copy_(padded[:, -2])


class Rcas:
    """RCAS of an image held in the interior of a (3, H + 2, W + 2) buffer.

    ``sharpness`` is in stops (0 = strongest, each stop halves the lobe);
    ``denoise`` enables FSR's optional noise removal. Scratch buffers are kept
    between calls: use one instance per thread.
    """

    def __init__(
        self,
        sharpness: float = DEFAULT_SHARPNESS,
        denoise: bool = False,
        band_pixels: int | None = None,
    ) -> None:
        if not sharpness >= 0.0:
            raise ValueError(f"sharpness must be >= 0 stops, got {sharpness}")
        self.sharpness = sharpness
        self.scale = 2.0 ** (-sharpness)
        self.denoise = denoise
        self.band_pixels = band_pixels
        self._buf: Buffers | None = None

    def __call__(self, padded: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
        """Sharpen the interior of ``padded`` (its border is overwritten with the edge)."""
        _, hp, wp = padded.shape
        h, w = hp - 2, wp - 2
        if (
            self._buf is None
            or self._buf.device != padded.device
            or self._buf.dtype != padded.dtype
        ):
            self._buf = Buffers(padded.device, padded.dtype)
        inner = padded[:, 1:-1, 1:-1]
        torch.nan_to_num(inner, nan=0.0, posinf=1.0, neginf=0.0, out=inner).clamp_(0.0, 1.0)
        fill_edges(padded)
        if out is None:
            out = torch.empty((3, h, w), dtype=padded.dtype, device=padded.device)
        rows = band_rows(self.band_pixels, w) if padded.device.type == "cpu" else h
        for y0 in range(0, h, rows):
            y1 = min(h, y0 + rows)
            self._band(padded, out[:, y0:y1], y0, y1)
        return out

    def _band(self, p: torch.Tensor, out: torch.Tensor, y0: int, y1: int) -> None:
        buf = self._buf
        assert buf is not None
        shape = out.shape
        north = p[:, y0:y1, 1:-1]
        south = p[:, y0 + 2 : y1 + 2, 1:-1]
        west = p[:, y0 + 1 : y1 + 1, :-2]
        east = p[:, y0 + 1 : y1 + 1, 2:]
        centre = p[:, y0 + 1 : y1 + 1, 1:-1]
        mn = torch.minimum(north, south, out=buf("mn", *shape))
        torch.minimum(mn, west, out=mn)
        torch.minimum(mn, east, out=mn)
        mx = torch.maximum(north, south, out=buf("mx", *shape))
        torch.maximum(mx, west, out=mx)
        torch.maximum(mx, east, out=mx)
        # mn / mx and (1 - mx) / (1 - mn), with a tiny bias that keeps 0/0 finite
        # (a black ring gives 1: no limit from that side, as FSR's max() of a NaN).
        ratio = torch.div(mn.add_(TINY), mx.add_(TINY), out=buf("ratio", *shape))
        # 1 - mx + TINY and 1 - mn + TINY, each written by one op.
        one = torch.full((), 1.0 + 2.0 * TINY, dtype=p.dtype, device=p.device)
        room_up = torch.sub(one, mx, out=buf("room_up", *shape))
        room_down = torch.sub(one, mn, out=mx)
        torch.minimum(ratio, room_up.div_(room_down), out=ratio)
        lobe = torch.amin(ratio, dim=0, out=buf("lobe", *shape[1:]))
        lobe.mul_(-0.25).clamp_min_(-RCAS_LIMIT).mul_(self.scale)
        if self.denoise:
            lobe.mul_(self._noise_factor(north, south, west, east, centre))
        # out = c + lobe (n + w + e + s - 4 c) / (4 lobe + 1)
        gain = torch.mul(lobe, 4.0, out=buf("gain", *shape[1:])).add_(1.0)
        gain.reciprocal_().mul_(lobe)
        ring = torch.add(north, west, out=buf("ring", *shape))
        ring.add_(torch.add(east, south, out=buf("ring2", *shape))).sub_(centre, alpha=4.0)
        torch.addcmul(centre, ring, gain, out=out)
        out.clamp_(0.0, 1.0)

    def _noise_factor(
        self,
        north: torch.Tensor,
        south: torch.Tensor,
        west: torch.Tensor,
        east: torch.Tensor,
        centre: torch.Tensor,
    ) -> torch.Tensor:
        """1 - |cross high-pass of luma| / (2 luma range), in [1/2, 1]."""
        buf = self._buf
        assert buf is not None
        shape = centre.shape[1:]
        lumas = buf("lumas", 5, *shape)
        for i, t in enumerate((north, south, west, east, centre)):
            torch.add(t[0], t[2], out=lumas[i]).mul_(0.5).add_(t[1])
        hp = torch.sum(lumas[:4], dim=0, out=buf("hp", *shape)).mul_(0.25).sub_(lumas[4]).abs_()
        rng = torch.amax(lumas, dim=0, out=buf("lrange", *shape))
        rng.sub_(torch.amin(lumas, dim=0, out=buf("lmin", *shape))).clamp_min_(TINY)
        return hp.div_(rng).clamp_(0.0, 1.0).mul_(-0.5).add_(1.0)
