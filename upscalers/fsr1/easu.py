"""FSR 1 EASU (edge adaptive spatial upsampling), vectorized over all output pixels.

Written from the math of AMD's ``ffx_fsr1.h`` (FsrEasuF). For every output pixel:

- its position in the input is ``p = (o + 0.5) * in / out - 0.5``; ``f = floor(p)``
  is the top-left texel of the 2x2 quad 'f g j k' and ``pp = p - f`` the phase;
- the 12 taps around the quad (texel offsets (x, y) from 'f')::

        b c         (0,-1) (1,-1)
      e f g h  (-1,0) (0,0) (1,0) (2,0)
      i j k l  (-1,1) (0,1) (1,1) (2,1)
        n o         (0,2)  (1,2)

- luma ``0.5 R + G + 0.5 B`` of the sRGB values; a '+' shaped gradient around each
  quad texel gives a direction ``(lD - lB, lE - lA)`` and a length (1 on a clean
  edge, 0 on a gradient reversal); both are blended with the bilinear weights of
  ``pp``, the direction normalized, the length shaped into an anisotropic stretch
  and a negative-lobe strength ``lob``;
- each tap is weighted by ``(25/16 (2/5 d^2 - 1)^2 - 9/16) (lob d^2 - 1)^2`` with
  ``d^2`` the rotated, stretched squared distance clipped at ``1/lob``; the
  weighted mean is clamped to the min/max of the quad ('de-ringing').

Texels outside the image repeat the edge (a clamp-to-edge sampler).

What makes it fast on a CPU:

- the '+' gradients are properties of input texels: computed once at input
  resolution, then blended for the output pixels (the bilinear blend of the four
  per-texel terms is a bilinear resize of those per-texel fields);
- at integer scales (2x, 3x, ...) every tap of every output pixel is a plain view
  of one nearest-upsampled copy of the input, so the 12 taps cost no gathers;
  other scales gather whole rows (contiguous copies) after gathering the columns
  once at input height;
- at integer scales the de-ringing min/max of each quad is found once at input
  size and upsampled like the taps, instead of per output pixel;
- the rotated, stretched distance is a quadratic form ``a ox^2 + b ox oy + c oy^2``
  whose per-pixel coefficients are computed once and shared by the 12 taps;
- the kernel's constant factors (``1/4`` of the base, ``lob^2`` of the window)
  are the same for all taps of a pixel and cancel in the normalization, leaving
  ``w = (d^2 - 1)(d^2 - 4) min(d^2 - 1/lob, 0)^2``;
- scratch buffers are kept for the next frame of the same sizes.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod

import torch

# (ty, (tx, ...)): tap offsets from 'f', by row so that a row's terms are built once.
TAP_ROWS: tuple[tuple[int, tuple[int, ...]], ...] = (
    (-1, (0, 1)),
    (0, (-1, 0, 1, 2)),
    (1, (-1, 0, 1, 2)),
    (2, (0, 1)),
)
# Direction vectors shorter than this (squared) are "no direction" (FSR's constant).
DIR_ZERO = 1.0 / 32768.0
# Guard against 0/0; exact for 8-bit input (luma steps are >= 0.5/255) and
# representable in float16.
TINY = 1.0 / 65536.0
PAD = 2  # texels of edge replication around the input (taps reach f - 1 .. f + 2)


BAND_PIXELS_PER_THREAD = 1 << 15


def band_rows(band_pixels: int | None, width: int) -> int:
    """Rows per band: ``band_pixels`` (default: 32 Ki pixels per torch thread) / ``width``.

    On the 2-core Xeon (2 MiB L2 per core) 32 Ki pixels per thread beat 128 Ki by
    about 12 % for EASU and RCAS: a band's ~20 scratch planes stay in L2."""
    if band_pixels is None:
        band_pixels = BAND_PIXELS_PER_THREAD * torch.get_num_threads()
    return max(1, band_pixels // width)


def axis_map(n_in: int, n_out: int, shift: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Input index of 'f' (may be -1) and the phase in [0, 1) of each output pixel; input
    sample i lies at i + 0.5 + ``shift`` (|shift| <= 0.5: a jittered render)."""
    src = (torch.arange(n_out, dtype=torch.float64) + 0.5) * (n_in / n_out) - 0.5 - shift
    base = torch.floor(src)
    return base.to(torch.long), src - base


class Buffers:
    """Named scratch tensors, allocated once per geometry and reused every frame."""

    def __init__(self, device: torch.device, dtype: torch.dtype) -> None:
        self.device = device
        self.dtype = dtype
        self._store: dict[str, torch.Tensor] = {}

    def __call__(self, name: str, *shape: int, dtype: torch.dtype | None = None) -> torch.Tensor:
        """A contiguous tensor of ``shape``; smaller requests reuse the same storage."""
        dtype = dtype or self.dtype
        n = math.prod(shape)
        t = self._store.get(name)
        if t is None or t.numel() < n or t.dtype != dtype:
            t = torch.empty(n, dtype=dtype, device=self.device)
            self._store[name] = t
        return t[:n].view(shape)


def replicate_pad_into(image: torch.Tensor, out: torch.Tensor, pad: int) -> None:
    """Write ``image`` (any dtype; uint8 becomes [0, 1]) into ``out`` with ``pad`` edge copies."""
    _, h, w = image.shape
    inner = out[:, pad : pad + h, pad : pad + w]
    inner.copy_(image)
    if image.dtype == torch.uint8:
        inner.div_(255.0)
    else:  # a float caller's NaN/Inf must not spread over the kernel's footprint
        torch.nan_to_num(inner, nan=0.0, posinf=1.0, neginf=0.0, out=inner).clamp_(0.0, 1.0)
    out[:, pad : pad + h, :pad].copy_(inner[:, :, :1].expand(-1, -1, pad))
    out[:, pad : pad + h, pad + w :].copy_(inner[:, :, -1:].expand(-1, -1, pad))
    out[:, :pad].copy_(out[:, pad : pad + 1].expand(-1, pad, -1))
    out[:, pad + h :].copy_(out[:, pad + h - 1 : pad + h].expand(-1, pad, -1))


class _Sampler(ABC):
    """Where the taps of each output pixel come from, for one geometry."""

    phase_x: torch.Tensor  # (W_out,) phase of each output column
    phase_y: torch.Tensor  # (H_out, 1) phase of each output row

    def __init__(self, buf: Buffers, out_hw: tuple[int, int]) -> None:
        self.buf = buf
        self.out_hw = out_hw

    def offsets(self) -> None:
        """Tap offsets from the sample position, and their squares, per row and column."""
        self.oy = {ty: ty - self.phase_y for ty, _ in TAP_ROWS}  # (H_out, 1)
        self.ox = {tx: tx - self.phase_x for tx in (-1, 0, 1, 2)}  # (W_out,)
        self.oy2 = {k: v * v for k, v in self.oy.items()}
        self.ox2 = {k: v * v for k, v in self.ox.items()}

    @abstractmethod
    def load(self, padded: torch.Tensor) -> None:
        """Prepare the taps of a padded (3, H + 4, W + 4) image."""

    @abstractmethod
    def tap(self, tx: int, ty: int, y0: int, y1: int) -> torch.Tensor:
        """(3, y1 - y0, W_out) colour of tap (tx, ty) of the output rows y0 .. y1 - 1."""

    @abstractmethod
    def blend_fields(self, fields: torch.Tensor) -> torch.Tensor:
        """Bilinear blend of per-texel (C, H + 2, W + 2) fields (texels -1 .. n) at 'f g j k'."""

    def quad_bounds(self, y0: int, y1: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Min and max of the quad 'f g j k' of the output rows y0 .. y1 - 1, if precomputed."""
        return None


class _NearestSampler(_Sampler):
    """Integer scales: taps are views of a nearest-upsampled (repeated texels) copy.

    With ``k`` output pixels per texel, ``f(x) = (x - k // 2) // k`` exactly, so the
    texel ``f(x) + t`` of the padded image is column ``x + k (t + PAD) - k // 2`` of
    its k-times nearest upsample, for all x at once.
    """

    def __init__(self, buf: Buffers, out_hw: tuple[int, int], kx: int, ky: int) -> None:
        super().__init__(buf, out_hw)
        self.kx, self.ky = kx, ky
        _, fx = axis_map(1, kx)  # phases repeat every k pixels
        _, fy = axis_map(1, ky)
        ho, wo = out_hw
        self.phase_x = fx.to(buf.dtype).repeat(wo // kx).to(buf.device)
        self.phase_y = fy.to(buf.dtype).repeat(ho // ky).to(buf.device).unsqueeze(1)
        self.upsampled = torch.empty(0)
        self.quad: list[torch.Tensor] = []
        self.offsets()

    def _start(self, k: int, t: int) -> int:
        return k * (t + PAD) - k // 2

    def load(self, padded: torch.Tensor) -> None:
        _, hp, wp = padded.shape
        out = self.buf("upsampled", 3, self.ky * hp, self.kx * wp)
        self.upsampled = nearest(padded, self.ky * hp, self.kx * wp, out)
        # The de-ringing bounds are properties of the quad at texel 'f': found once at
        # input size and upsampled like the taps (index = padded index of 'f').
        self.quad = []
        for name, op in (("quad_lo", torch.minimum), ("quad_hi", torch.maximum)):
            q = op(padded[:, :-1, :-1], padded[:, :-1, 1:], out=self.buf(name, 3, hp - 1, wp - 1))
            op(q, padded[:, 1:, :-1], out=q)
            op(q, padded[:, 1:, 1:], out=q)
            up = self.buf(name + "_up", 3, self.ky * (hp - 1), self.kx * (wp - 1))
            self.quad.append(nearest(q, self.ky * (hp - 1), self.kx * (wp - 1), up))

    def quad_bounds(self, y0: int, y1: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        wo = self.out_hw[1]
        r0, x0 = self._start(self.ky, 0) + y0, self._start(self.kx, 0)
        lo, hi = (q[:, r0 : r0 + y1 - y0, x0 : x0 + wo] for q in self.quad)
        return lo, hi

    def tap(self, tx: int, ty: int, y0: int, y1: int) -> torch.Tensor:
        wo = self.out_hw[1]
        r0, x0 = self._start(self.ky, ty) + y0, self._start(self.kx, tx)
        return self.upsampled[:, r0 : r0 + y1 - y0, x0 : x0 + wo]

    def blend_fields(self, fields: torch.Tensor) -> torch.Tensor:
        ho, wo = self.out_hw
        c, hf, wf = fields.shape
        # Field index of a texel is texel + 1, i.e. one texel less padding than PAD.
        cols = nearest(fields, hf, self.kx * wf)
        x0 = self._start(self.kx, 0) - self.kx
        across = self.buf("across", c, hf, wo)
        torch.lerp(
            cols[:, :, x0 : x0 + wo], cols[:, :, x0 + self.kx : x0 + self.kx + wo], self.phase_x,
            out=across,
        )  # fmt: skip
        rows = nearest(across, self.ky * hf, wo, self.buf("across_rows", c, self.ky * hf, wo))
        y0 = self._start(self.ky, 0) - self.ky
        blended = self.buf("blended", c, ho, wo)
        return torch.lerp(
            rows[:, y0 : y0 + ho], rows[:, y0 + self.ky : y0 + self.ky + ho], self.phase_y,
            out=blended,
        )  # fmt: skip


class _GatherSampler(_Sampler):
    """Any scale: tap columns gathered once at input height, rows gathered per tap."""

    def __init__(
        self,
        buf: Buffers,
        in_hw: tuple[int, int],
        out_hw: tuple[int, int],
        shift: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        super().__init__(buf, out_hw)
        (h, w), (ho, wo) = in_hw, out_hw
        bx, fx = axis_map(w, wo, shift[0])
        by, fy = axis_map(h, ho, shift[1])
        dev = buf.device
        self.phase_x = fx.to(buf.dtype).to(dev)
        self.phase_y = fy.to(buf.dtype).to(dev).unsqueeze(1)
        self.col_f = (bx + PAD).to(dev)  # padded column of 'f'
        self.row_f = (by + PAD).to(dev)
        self.col_taps = torch.cat([self.col_f + t for t in (-1, 0, 1, 2)])
        self.cols = torch.empty(0)
        self.offsets()

    def load(self, padded: torch.Tensor) -> None:
        _, hp, wp = padded.shape
        wo = self.out_hw[1]
        transposed = self.buf("padded_t", 3, wp, hp)
        transposed.copy_(padded.transpose(1, 2))
        gathered = self.buf("cols_t", 3, 4 * wo, hp)
        torch.index_select(transposed, 1, self.col_taps, out=gathered)
        self.cols = self.buf("cols", 4, 3, hp, wo)
        self.cols.copy_(gathered.view(3, 4, wo, hp).permute(1, 0, 3, 2))

    def tap(self, tx: int, ty: int, y0: int, y1: int) -> torch.Tensor:
        out = self.buf("tap", 3, y1 - y0, self.out_hw[1])
        return torch.index_select(self.cols[tx + 1], 1, self.row_f[y0:y1] + ty, out=out)

    def blend_fields(self, fields: torch.Tensor) -> torch.Tensor:
        ho, wo = self.out_hw
        c, hf, wf = fields.shape
        fields_t = self.buf("fields_t", c, wf, hf)
        fields_t.copy_(fields.transpose(1, 2))
        k = self.col_f - 1  # field index of a texel is texel + 1
        left = torch.index_select(fields_t, 1, k, out=self.buf("left", c, wo, hf))
        right = torch.index_select(fields_t, 1, k + 1, out=self.buf("right", c, wo, hf))
        left.lerp_(right, self.phase_x.unsqueeze(1))
        across = self.buf("across", c, hf, wo)
        across.copy_(left.transpose(1, 2))
        r = self.row_f - 1
        top = torch.index_select(across, 1, r, out=self.buf("blended", c, ho, wo))
        bottom = torch.index_select(across, 1, r + 1, out=self.buf("bottom", c, ho, wo))
        return top.lerp_(bottom, self.phase_y)


def nearest(x: torch.Tensor, h: int, w: int, out: torch.Tensor | None = None) -> torch.Tensor:
    """(C, h, w) nearest upsample of (C, H, W) by the integers h / H and w / W."""
    c, hi, wi = x.shape
    ky, kx = h // hi, w // wi
    if out is None:
        out = torch.empty((c, h, w), dtype=x.dtype, device=x.device)
    # Strided copies into the first row of each block, then that row broadcast down:
    # about 25 % faster than interpolate's general kernel, and exactly a repeat.
    blocks = out.view(c, hi, ky, wi, kx)
    for s in range(kx):
        blocks[:, :, 0, :, s].copy_(x)
    if ky > 1:
        rows = out.view(c, hi, ky, w)
        rows[:, :, 1:].copy_(rows[:, :, :1].expand(c, hi, ky - 1, w))
    return out


class Easu:
    """EASU from any input size to any output size (FSR is made for 1x to 4x).

    Call it with a (3, H, W) image, uint8 or float in [0, 1], on any device; it
    returns a (3, H_out, W_out) float image (``dtype``, or the input's float dtype)
    on the input's device, written into ``out`` when given (for example the
    interior of a padded buffer for RCAS). Keeps scratch buffers between calls:
    use one instance per thread.
    """

    def __init__(self, dtype: torch.dtype | None = None, band_pixels: int | None = None) -> None:
        self.dtype = dtype
        # Per-pixel work runs over bands of rows of about this many pixels (None:
        # see band_rows): small enough for the band's temporaries to stay in cache,
        # large enough to keep the per-op overhead of eager torch small.
        self.band_pixels = band_pixels
        self._key: tuple[object, ...] | None = None
        self._buf = Buffers(torch.device("cpu"), torch.float32)
        self._sampler: _Sampler | None = None

    def _setup(
        self, image: torch.Tensor, out_hw: tuple[int, int], shift: tuple[float, float]
    ) -> _Sampler:
        _, h, w = image.shape
        ho, wo = out_hw
        dtype = self.dtype or (image.dtype if image.is_floating_point() else torch.float32)
        key = (h, w, ho, wo, image.device, dtype, shift)
        if self._sampler is not None and self._key == key:
            return self._sampler
        self._key = key
        self._buf = buf = Buffers(image.device, dtype)
        kx, ky = wo // w, ho // h
        integer = kx * w == wo and ky * h == ho
        if integer and shift == (0.0, 0.0):
            self._sampler = _NearestSampler(buf, out_hw, kx, ky)
        else:
            self._sampler = _GatherSampler(buf, (h, w), out_hw, shift)
        self._minus_9_4 = torch.tensor(-2.25, dtype=dtype, device=image.device)
        return self._sampler

    def __call__(
        self,
        image: torch.Tensor,
        out_hw: tuple[int, int],
        out: torch.Tensor | None = None,
        *,
        sample_offset: tuple[float, float] = (0.0, 0.0),
    ) -> torch.Tensor:
        """``sample_offset``: (x, y) where the input's samples lie from their pixel centres,
        in input pixels, each within [-0.5, 0.5] (a jittered render passes its jitter;
        the taps then sit where the samples were taken)."""
        if not all(-0.5 <= o <= 0.5 for o in sample_offset):
            raise ValueError(f"sample_offset must be within [-0.5, 0.5], got {sample_offset}")
        sampler = self._setup(image, out_hw, (float(sample_offset[0]), float(sample_offset[1])))
        buf = self._buf
        _, h, w = image.shape
        ho, wo = out_hw
        padded = buf("padded", 3, h + 2 * PAD, w + 2 * PAD)
        replicate_pad_into(image, padded, PAD)
        sampler.load(padded)

        fields = sampler.blend_fields(_texel_fields(padded, buf))
        if out is None:
            out = torch.empty((3, ho, wo), dtype=buf.dtype, device=buf.device)
        rows = band_rows(self.band_pixels, wo) if image.device.type == "cpu" else ho
        for y0 in range(0, ho, rows):
            y1 = min(ho, y0 + rows)
            band = fields[:, y0:y1]
            coef = _kernel_coefficients(band[0], band[1], band[2], buf)
            acc = out[:, y0:y1]
            lo, hi = _accumulate(acc, sampler, y0, y1, *coef, self._minus_9_4, buf)
            acc.clamp_(lo, hi)
        return out


def _texel_fields(padded: torch.Tensor, buf: Buffers) -> torch.Tensor:
    """(3, H + 2, W + 2) direction x, direction y, length of texels -1 .. n of the input."""
    _, hp, wp = padded.shape
    lum = buf("lum", hp, wp)
    torch.add(padded[0], padded[2], out=lum).mul_(0.5).add_(padded[1])
    hf, wf = hp - 2, wp - 2
    fields = buf("fields", 3, hf, wf)
    length = fields[2].zero_()
    centre = lum[1:-1, 1:-1]
    one_sided = buf("one_sided", hf, wf)
    other_side = buf("other_side", hf, wf)
    ratio = buf("ratio", hf, wf)
    for axis, (before, after) in enumerate(
        ((lum[1:-1, :-2], lum[1:-1, 2:]), (lum[:-2, 1:-1], lum[2:, 1:-1]))
    ):
        diff = torch.sub(after, before, out=fields[axis])
        # |full difference| / larger one-sided difference is 2 on a clean edge and 0
        # on a reversal; saturated to 1, squared, summed over both axes.
        torch.sub(after, centre, out=one_sided).abs_()
        torch.sub(centre, before, out=other_side).abs_()
        torch.maximum(one_sided, other_side, out=one_sided).clamp_min_(TINY)
        torch.abs(diff, out=ratio).div_(one_sided).clamp_max_(1.0)
        length.addcmul_(ratio, ratio)
    return fields


def _kernel_coefficients(
    dx: torch.Tensor, dy: torch.Tensor, length: torch.Tensor, buf: Buffers
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Quadratic form a, b, c of the rotated, stretched distance, and the clip point.

    Works in place on the blended fields.
    """
    shape = dx.shape
    # Normalize the direction; a (near) zero one becomes (1, dy) as in FSR, blended
    # arithmetically (torch.where is slow on CPU).
    r2 = torch.mul(dx, dx, out=buf("r2", *shape)).addcmul_(dy, dy)
    keep = buf("keep", *shape)
    keep.copy_(torch.ge(r2, DIR_ZERO, out=buf("keep_mask", *shape, dtype=torch.bool)))
    zero = torch.neg(keep, out=buf("zero", *shape)).add_(1.0)
    inv = r2.clamp_min_(DIR_ZERO).rsqrt_().mul_(keep).add_(zero)
    dx.mul_(keep).add_(zero).mul_(inv)
    dy.mul_(inv)
    # Length {0..2} -> {0..1}, squared.
    ln = length.mul_(0.5).square_()
    dx2 = torch.mul(dx, dx, out=buf("dx2", *shape))
    dy2 = torch.mul(dy, dy, out=buf("dy2", *shape))
    # Stretch: 1 along the axes, up to sqrt(2) on the diagonal.
    ax = torch.abs(dx, out=buf("ax", *shape))
    torch.maximum(ax, torch.abs(dy, out=keep), out=ax)
    stretch = torch.add(dx2, dy2, out=buf("stretch", *shape)).div_(ax)
    # Anisotropic lengths, squared: along the edge 1 -> stretch, across 1 -> 1/2.
    lx2 = stretch.sub_(1.0).mul_(ln).add_(1.0).square_()
    ly2 = torch.mul(ln, -0.5, out=buf("ly2", *shape)).add_(1.0).square_()
    # Negative lobe from 1/2 (flat) to 0.21 (edges); the window ends at d^2 = 1/lob.
    clip = torch.mul(ln, (0.25 - 0.04) - 0.5, out=buf("clip", *shape)).add_(0.5).reciprocal_()
    a = torch.mul(dx2, lx2, out=buf("a", *shape)).addcmul_(dy2, ly2)
    c = torch.mul(dy2, lx2, out=buf("c", *shape)).addcmul_(dx2, ly2)
    b = torch.mul(dx, dy, out=buf("b", *shape)).mul_(lx2.sub_(ly2)).mul_(2.0)
    return a, b, c, clip


def _accumulate(
    acc: torch.Tensor,
    sampler: _Sampler,
    y0: int,
    y1: int,
    a: torch.Tensor,
    b: torch.Tensor,
    c: torch.Tensor,
    clip: torch.Tensor,
    minus_9_4: torch.Tensor,
    buf: Buffers,
) -> tuple[torch.Tensor, torch.Tensor]:
    """acc = sum_t w_t colour_t / sum_t w_t over the 12 taps; returns the quad min, max."""
    shape = a.shape
    acc.zero_()
    weight_sum = buf("weight_sum", *shape).zero_()
    bounds = sampler.quad_bounds(y0, y1)
    lo = buf("band_lo", *acc.shape) if bounds is None else bounds[0]
    hi = buf("band_hi", *acc.shape) if bounds is None else bounds[1]
    # With d2s = d^2 - 5/2: (d^2 - 1)(d^2 - 4) = d2s^2 - 9/4 and d^2 - clip = d2s - clip_s.
    clip_s = clip.sub_(2.5)
    c_row = buf("c_row", *shape)
    b_row = buf("b_row", *shape)
    d2s = buf("d2s", *shape)
    e = buf("e", *shape)
    w = buf("w", *shape)
    for ty, txs in TAP_ROWS:
        torch.mul(c, sampler.oy2[ty][y0:y1], out=c_row).sub_(2.5)
        torch.mul(b, sampler.oy[ty][y0:y1], out=b_row)
        for tx in txs:
            torch.addcmul(c_row, a, sampler.ox2[tx], out=d2s).addcmul_(b_row, sampler.ox[tx])
            torch.sub(d2s, clip_s, out=e).clamp_max_(0.0)
            torch.addcmul(minus_9_4, d2s, d2s, out=w).mul_(e).mul_(e)
            weight_sum.add_(w)
            colour = sampler.tap(tx, ty, y0, y1)
            acc.addcmul_(colour, w)
            if bounds is not None:
                continue
            if (tx, ty) == (0, 0):
                lo.copy_(colour)
                hi.copy_(colour)
            elif tx in (0, 1) and ty in (0, 1):
                torch.minimum(lo, colour, out=lo)
                torch.maximum(hi, colour, out=hi)
    acc.mul_(weight_sum.clamp_min_(TINY).reciprocal_())
    return lo, hi
