"""Compiled CPU kernels of FSR 1 (numba): EASU and RCAS as loops over output rows.

The same math as the torch code (``fsr1_easu`` / ``fsr1_rcas``, and the
whole-tensor form ``fsr1_fused`` that these follow line by line), written as
one pass per stage over the pixels: eager torch runs EASU as ~200 elementwise
passes over display-size temporaries, which on a 2-core CPU costs about five
times the arithmetic itself. Here every output pixel is computed from its 12
taps in registers, and the inner loops over a row are simple enough for LLVM
to vectorize.

Stages (``fsr1_cpu.py`` is the typed boundary that calls them):

1. ``pad_and_fields``: the (H, W, 3) uint8 input as a planar, edge-padded float
   image in [0, 1] and the per-texel direction / length fields (computed once at
   input resolution; EASU blends them bilinearly per output pixel).
2. ``easu_integer`` / ``easu_gathered``: EASU of every output pixel, into a planar
   float image.
3. ``rcas_to_rgb8`` / ``interior_to_rgb8``: RCAS (or nothing) and the quantization
   to the (H, W, 3) uint8 layout of ring U, in one pass.

Outputs go into caller-owned arrays; nothing allocates per frame.
"""

# numba has no type stubs and its decorators are untyped: mypy skips this module;
# ``fsr1_cpu.py`` is the typed boundary.
# mypy: ignore-errors

from __future__ import annotations

import llvmlite.binding as llvm
import numpy as np
from numba import literally, njit, prange

# LLVM vectorizes a loop that writes one array while reading others only after
# run-time checks that they do not overlap, and gives up above 8 such checks; the
# EASU loop reads 36 taps and 12 field values, so it would stay scalar (measured:
# 29 ms against 5 ms at 1280x720). The options only raise LLVM's limits; they are
# process-wide and must be set before numba compiles the kernels below (cached
# machine code keeps what it was compiled with).
llvm.set_option("", "-runtime-memory-check-threshold=2000")
llvm.set_option("", "-vectorize-memory-check-threshold=2000")

F32 = np.float32
U = np.uint64  # array indices: numba adds a negative-index wrap to signed ones, which
# makes every access an indirect one that LLVM cannot vectorize
# fastmath lets LLVM vectorize min/max and reorder the tap sums; the tests bound the
# difference to the torch path.
_JIT = {"cache": True, "nogil": True, "fastmath": True, "error_model": "numpy"}

ROW_BLOCK = 8  # output rows per parallel work item
PAD = 2  # fsr1_easu.PAD
DIR_ZERO = F32(1.0 / 32768.0)  # fsr1_easu.DIR_ZERO
TINY = F32(1.0 / 65536.0)  # fsr1_easu.TINY
RCAS_LIMIT = F32(0.25 - 1.0 / 16.0)  # fsr1_rcas.RCAS_LIMIT


@njit(parallel=True, **_JIT)
def pad_and_fields(src, padded, luma, fields):
    """``src`` (H, W, 3) uint8 -> ``padded`` (3, H + 4, W + 4) float32 in [0, 1], edges
    repeated; ``luma`` (H + 4, W + 4) scratch; ``fields`` (3, H + 2, W + 2): per texel
    -1 .. n the horizontal and vertical luma difference and the summed edge length."""
    h, w = src.shape[0], src.shape[1]
    hp, wp = h + 2 * PAD, w + 2 * PAD
    inv = F32(1.0 / 255.0)
    for y in prange(hp):
        sy = min(max(y - PAD, 0), h - 1)
        for x in range(wp):
            sx = min(max(x - PAD, 0), w - 1)
            r = F32(src[sy, sx, 0]) * inv
            g = F32(src[sy, sx, 1]) * inv
            b = F32(src[sy, sx, 2]) * inv
            padded[0, y, x] = r
            padded[1, y, x] = g
            padded[2, y, x] = b
            luma[y, x] = (r + b) * F32(0.5) + g
    for fy in prange(h + 2):
        y = fy + 1  # padded row of this texel
        for fx in range(w + 2):
            x = fx + 1
            centre = luma[y, x]
            left, right = luma[y, x - 1], luma[y, x + 1]
            up, down = luma[y - 1, x], luma[y + 1, x]
            dx = right - left
            side = max(abs(right - centre), abs(centre - left))
            rx = min(abs(dx) / max(side, TINY), F32(1.0))
            dy = down - up
            side = max(abs(down - centre), abs(centre - up))
            ry = min(abs(dy) / max(side, TINY), F32(1.0))
            fields[0, fy, fx] = dx
            fields[1, fy, fx] = dy
            fields[2, fy, fx] = rx * rx + ry * ry


@njit(inline="always", **_JIT)
def _lerp(a, b, t):
    return a + (b - a) * t


@njit(inline="always", **_JIT)
def _weight(d2s, clip):
    """Unnormalized EASU weight of a tap at stretched squared distance ``d2s - 2.5``;
    EASU's constant factors cancel in the normalization (see fsr1_easu)."""
    e = min(d2s - clip, F32(0.0))
    return (d2s * d2s - F32(2.25)) * e * e


@njit(**_JIT)
def _easu_row(padded, fields, r, py, col0, step, px0, phases, n, row, one_phase):
    """EASU of ``n`` pixels of one output row into (3, n) ``row``; 'f' is on padded row
    ``r`` with phase ``py``. Pixel j has 'f' on padded column ``col0 + j`` and its
    horizontal neighbours ``step`` columns apart, so every tap is a fixed offset from
    j and the loop vectorizes. Its horizontal phase is ``px0`` with ``one_phase`` (a
    literal: one phase of an integer scale) or else ``phases[j]``.

    Two layouts feed it: the padded image itself (``step`` 1, one phase of an
    integer scale, where pixel j k + m has 'f' at ``col0[m] + j``), and, for any
    other scale, copies of the rows whose columns were gathered per output pixel
    (``step`` = the output width; see ``easu_gathered``).

    What keeps the loop vectorizable (each measured 47-51 ms against 8 ms at
    1280x720 when broken): the body is written out flat, since a helper that takes
    arrays, inlined or not, and a tuple of running sums both kept it scalar; and
    ``one_phase`` is a compile-time literal, since LLVM did not split the loop on a
    run-time flag. Taps at run-time column indices (gathers) kept it scalar too
    (26 ms), hence the gathered copies."""
    literally(one_phase)  # compiled once per value, the other branch pruned away
    ra, rb, rc, rd = r - U(1), r, r + U(1), r + U(2)  # padded rows of the taps
    vya, vyb, vyc, vyd = F32(-1.0) - py, -py, F32(1.0) - py, F32(2.0) - py
    for j in range(n):
        i0 = col0 + U(j)
        px = px0 if one_phase else phases[U(j)]
        im, i1, i2 = i0 - step, i0 + step, i0 + step + step
        # Bilinear blend of the texels' fields at 'f g j k' (field row/col = padded - 1).
        gdx = _lerp(
            _lerp(fields[0, ra, im], fields[0, ra, i0], px),
            _lerp(fields[0, rb, im], fields[0, rb, i0], px),
            py,
        )
        gdy = _lerp(
            _lerp(fields[1, ra, im], fields[1, ra, i0], px),
            _lerp(fields[1, rb, im], fields[1, rb, i0], px),
            py,
        )
        length = _lerp(
            _lerp(fields[2, ra, im], fields[2, ra, i0], px),
            _lerp(fields[2, rb, im], fields[2, rb, i0], px),
            py,
        )
        # Direction normalized; FSR's "no direction" sets x to 1 and keeps y (tiny).
        r2 = gdx * gdx + gdy * gdy
        keep = r2 >= DIR_ZERO
        inv = F32(1.0) / np.sqrt(max(r2, DIR_ZERO)) if keep else F32(1.0)
        dx = gdx * inv if keep else F32(1.0)
        dy = gdy * inv
        ln = length * F32(0.5)
        ln = ln * ln
        dx2, dy2 = dx * dx, dy * dy
        stretch = (dx2 + dy2) / max(abs(dx), abs(dy))
        lx2 = (stretch - F32(1.0)) * ln + F32(1.0)
        lx2 = lx2 * lx2
        ly2 = ln * F32(-0.5) + F32(1.0)
        ly2 = ly2 * ly2
        clip = F32(1.0) / (ln * F32(0.25 - 0.04 - 0.5) + F32(0.5)) - F32(2.5)
        # Each tap's rotated, stretched squared distance a vx^2 + b vx vy + c vy^2.
        a = dx2 * lx2 + dy2 * ly2
        c = dy2 * lx2 + dx2 * ly2
        b = dx * dy * (lx2 - ly2) * F32(2.0)
        vxm, vx0, vx1, vx2 = F32(-1.0) - px, -px, F32(1.0) - px, F32(2.0) - px
        axm, ax0, ax1, ax2 = a * vxm * vxm, a * vx0 * vx0, a * vx1 * vx1, a * vx2 * vx2
        s0 = s1 = s2 = sw = F32(0.0)
        cr, br = c * vya * vya - F32(2.5), b * vya  # row 'b c'
        w = _weight(cr + ax0 + br * vx0, clip)
        s0 += padded[0, ra, i0] * w
        s1 += padded[1, ra, i0] * w
        s2 += padded[2, ra, i0] * w
        sw += w
        w = _weight(cr + ax1 + br * vx1, clip)
        s0 += padded[0, ra, i1] * w
        s1 += padded[1, ra, i1] * w
        s2 += padded[2, ra, i1] * w
        sw += w
        cr, br = c * vyb * vyb - F32(2.5), b * vyb  # row 'e f g h'
        w = _weight(cr + axm + br * vxm, clip)
        s0 += padded[0, rb, im] * w
        s1 += padded[1, rb, im] * w
        s2 += padded[2, rb, im] * w
        sw += w
        w = _weight(cr + ax0 + br * vx0, clip)
        s0 += padded[0, rb, i0] * w
        s1 += padded[1, rb, i0] * w
        s2 += padded[2, rb, i0] * w
        sw += w
        w = _weight(cr + ax1 + br * vx1, clip)
        s0 += padded[0, rb, i1] * w
        s1 += padded[1, rb, i1] * w
        s2 += padded[2, rb, i1] * w
        sw += w
        w = _weight(cr + ax2 + br * vx2, clip)
        s0 += padded[0, rb, i2] * w
        s1 += padded[1, rb, i2] * w
        s2 += padded[2, rb, i2] * w
        sw += w
        cr, br = c * vyc * vyc - F32(2.5), b * vyc  # row 'i j k l'
        w = _weight(cr + axm + br * vxm, clip)
        s0 += padded[0, rc, im] * w
        s1 += padded[1, rc, im] * w
        s2 += padded[2, rc, im] * w
        sw += w
        w = _weight(cr + ax0 + br * vx0, clip)
        s0 += padded[0, rc, i0] * w
        s1 += padded[1, rc, i0] * w
        s2 += padded[2, rc, i0] * w
        sw += w
        w = _weight(cr + ax1 + br * vx1, clip)
        s0 += padded[0, rc, i1] * w
        s1 += padded[1, rc, i1] * w
        s2 += padded[2, rc, i1] * w
        sw += w
        w = _weight(cr + ax2 + br * vx2, clip)
        s0 += padded[0, rc, i2] * w
        s1 += padded[1, rc, i2] * w
        s2 += padded[2, rc, i2] * w
        sw += w
        cr, br = c * vyd * vyd - F32(2.5), b * vyd  # row 'n o'
        w = _weight(cr + ax0 + br * vx0, clip)
        s0 += padded[0, rd, i0] * w
        s1 += padded[1, rd, i0] * w
        s2 += padded[2, rd, i0] * w
        sw += w
        w = _weight(cr + ax1 + br * vx1, clip)
        s0 += padded[0, rd, i1] * w
        s1 += padded[1, rd, i1] * w
        s2 += padded[2, rd, i1] * w
        sw += w
        norm = F32(1.0) / max(sw, TINY)
        # De-ringing: clamped to each channel's min / max over the quad 'f g j k'.
        q00, q01 = padded[0, rb, i0], padded[0, rb, i1]
        q10, q11 = padded[0, rc, i0], padded[0, rc, i1]
        lo = min(min(q00, q01), min(q10, q11))
        hi = max(max(q00, q01), max(q10, q11))
        row[0, U(j)] = min(max(s0 * norm, lo), hi)
        q00, q01 = padded[1, rb, i0], padded[1, rb, i1]
        q10, q11 = padded[1, rc, i0], padded[1, rc, i1]
        lo = min(min(q00, q01), min(q10, q11))
        hi = max(max(q00, q01), max(q10, q11))
        row[1, U(j)] = min(max(s1 * norm, lo), hi)
        q00, q01 = padded[2, rb, i0], padded[2, rb, i1]
        q10, q11 = padded[2, rc, i0], padded[2, rc, i1]
        lo = min(min(q00, q01), min(q10, q11))
        hi = max(max(q00, q01), max(q10, q11))
        row[2, U(j)] = min(max(s2 * norm, lo), hi)


@njit(**_JIT)
def _interleave_phase(row, out, y, k, m, n):
    """Row (3, n) into ``out[:, y, 1 + j k + m]`` (the interior of a 1-pixel border)."""
    for ch in range(3):
        for j in range(n):
            out[U(ch), y, U(1 + j * k + m)] = row[U(ch), U(j)]


@njit(parallel=True, **_JIT)
def easu_integer(padded, fields, row_f, phase_y, col0, phase_x0, out):
    """EASU at an integer horizontal scale k = ``col0.size`` into the interior of
    ``out`` (3, H_out + 2, W_out + 2). ``row_f`` / ``phase_y``: padded row of texel 'f'
    and phase per output row; ``col0`` / ``phase_x0``: padded column of 'f' and phase of
    output columns 0 .. k - 1 (column j k + m has 'f' at ``col0[m] + j``)."""
    ho = row_f.shape[0]
    k = col0.shape[0]
    n = (out.shape[2] - 2) // k
    no_phases = np.empty(0, np.float32)
    n_blocks = (ho + ROW_BLOCK - 1) // ROW_BLOCK
    for blk in prange(n_blocks):
        row = np.empty((3, n), np.float32)
        for y in range(blk * ROW_BLOCK, min(ho, (blk + 1) * ROW_BLOCK)):
            for m in range(k):
                r, py = U(row_f[y]), phase_y[y]
                _easu_row(
                    padded, fields, r, py, U(col0[m]), U(1), phase_x0[m], no_phases, n, row, True
                )
                _interleave_phase(row, out, U(y + 1), k, m, n)


# Output rows per work item of ``easu_gathered``: more rows share each gathered input
# row (4 + rows / scale input rows per item), fewer keep the copies in L2 (about
# 100 KB per input row at 1280 output columns).
GATHER_ROW_BLOCK = 16


@njit(parallel=True, **_JIT)
def easu_gathered(padded, fields, row_f, col_f, phase_y, phase_x, out):
    """EASU at any scale into the interior of ``out`` (3, H_out + 2, W_out + 2): 'f' and
    the phase per output row and column (``easu_integer`` is the faster path for an
    integer horizontal scale).

    Per block of output rows, the input rows it reads are first copied with their
    columns gathered per output pixel: segment d of copied row i holds, at j, the
    texel d - 1 columns right of pixel j's 'f'. EASU then reads every tap at a fixed
    offset from j (segments ``W_out`` apart), as in the integer path, and
    vectorizes; the copy is a plain gather loop, once per input row and block."""
    ho, wo = row_f.shape[0], col_f.shape[0]
    n_blocks = (ho + GATHER_ROW_BLOCK - 1) // GATHER_ROW_BLOCK
    step = U(wo)
    for blk in prange(n_blocks):
        y0 = blk * GATHER_ROW_BLOCK
        y1 = min(ho, y0 + GATHER_ROW_BLOCK)
        first = row_f[y0] - 1  # padded row of copy row 0 (row_f does not decrease)
        n_rows = row_f[y1 - 1] - first + 3  # taps reach rows 'f' - 1 .. 'f' + 2
        colours = np.empty((3, n_rows, 4 * wo), np.float32)
        # Field rows 'f' - 1 and 'f' hold texel rows 'f g' and 'j k' (a texel's field row is
        # its padded row - 1, see pad_and_fields).
        field_rows = np.empty((3, n_rows - 2, 2 * wo), np.float32)
        for i in range(n_rows):
            src = U(first + i)
            for ch in range(3):
                for d in range(4):
                    base = U(d * wo)
                    for j in range(wo):
                        colours[U(ch), U(i), base + U(j)] = padded[U(ch), src, U(col_f[j] + d - 1)]
            if i < n_rows - 2:
                for f in range(3):
                    for d in range(2):
                        base = U(d * wo)
                        for j in range(wo):
                            field_rows[U(f), U(i), base + U(j)] = fields[
                                U(f), src, U(col_f[j] + d - 1)
                            ]
        row = np.empty((3, wo), np.float32)
        for y in range(y0, y1):
            r = U(row_f[y] - first)
            _easu_row(
                colours, field_rows, r, phase_y[y], step, step, F32(0.0), phase_x, wo, row, False
            )
            for ch in range(3):
                out[ch, y + 1, 1 : wo + 1] = row[ch]


@njit(**_JIT)
def _fill_border(image):
    """Repeat the edge of the interior of a (3, H + 2, W + 2) image into its border."""
    h2, w2 = image.shape[1], image.shape[2]
    for ch in range(3):
        for y in range(1, h2 - 1):
            image[ch, y, 0] = image[ch, y, 1]
            image[ch, y, w2 - 1] = image[ch, y, w2 - 2]
        for x in range(w2):
            image[ch, 0, x] = image[ch, 1, x]
            image[ch, h2 - 1, x] = image[ch, h2 - 2, x]


@njit(inline="always", **_JIT)
def _to_u8(v):
    """[0, 1] float -> uint8, rounded half up (the float path's quantize_into rounds half
    to even: a different byte only where v * 255 is exactly k + 0.5)."""
    return np.uint8(min(max(v, F32(0.0)), F32(1.0)) * F32(255.0) + F32(0.5))


@njit(**_JIT)
def _rcas_row(image, y, scale, gain, row):
    """RCAS of row ``y`` of a bordered (3, H + 2, W + 2) image into (3, W) ``row``;
    ``gain`` is (W,) scratch."""
    w = row.shape[1]
    one = F32(1.0) + F32(2.0) * TINY
    for x in range(w):
        gain[U(x)] = F32(1.0)
    for ch in range(3):  # the lobe is limited by the tightest channel
        c = U(ch)
        for x in range(w):
            i = U(x + 1)
            n, s = image[c, y - U(1), i], image[c, y + U(1), i]
            wv, e = image[c, y, i - U(1)], image[c, y, i + U(1)]
            mn = min(min(n, s), min(wv, e)) + TINY
            mx = max(max(n, s), max(wv, e)) + TINY
            gain[U(x)] = min(gain[U(x)], min(mn / mx, (one - mx) / (one - mn)))
    for x in range(w):
        lobe = max(gain[U(x)] * F32(-0.25), -RCAS_LIMIT) * scale
        gain[U(x)] = lobe / (lobe * F32(4.0) + F32(1.0))
    for ch in range(3):
        c = U(ch)
        for x in range(w):
            i = U(x + 1)
            centre = image[c, y, i]
            ring = (image[c, y - U(1), i] + image[c, y, i - U(1)]) + (
                image[c, y, i + U(1)] + image[c, y + U(1), i]
            )
            row[c, U(x)] = centre + (ring - centre * F32(4.0)) * gain[U(x)]


@njit(**_JIT)
def _row_to_rgb8(row, out, y):
    """(3, W) float row in [0, 1] (clamped here) into row ``y`` of ``out``, (H, W, 3)
    uint8 seen as (H, 3 W): with a pixel's stride a constant 3 (a third axis's stride
    is a run-time value LLVM must assume may be 1) the three stores of a pixel
    vectorize as one interleaved store."""
    for x in range(row.shape[1]):
        i = U(x)
        o = U(3) * i
        out[y, o] = _to_u8(row[U(0), i])
        out[y, o + U(1)] = _to_u8(row[U(1), i])
        out[y, o + U(2)] = _to_u8(row[U(2), i])


@njit(parallel=True, **_JIT)
def rcas_to_rgb8(image, scale, out):
    """RCAS (lobe scaled by ``scale``) of the interior of a (3, H + 2, W + 2) image whose
    border this fills with the edge, quantized into ``out`` (H, W, 3) uint8 given as
    (H, 3 W)."""
    _fill_border(image)
    h, w = out.shape[0], out.shape[1] // 3
    n_blocks = (h + ROW_BLOCK - 1) // ROW_BLOCK
    for blk in prange(n_blocks):
        row = np.empty((3, w), np.float32)
        gain = np.empty(w, np.float32)
        for y in range(blk * ROW_BLOCK, min(h, (blk + 1) * ROW_BLOCK)):
            _rcas_row(image, U(y + 1), scale, gain, row)
            _row_to_rgb8(row, out, U(y))


@njit(parallel=True, **_JIT)
def interior_to_rgb8(image, out):
    """The interior of a (3, H + 2, W + 2) image in [0, 1] into ``out`` (H, W, 3) uint8
    given as (H, 3 W)."""
    h = out.shape[0]
    for y in prange(h):
        _row_to_rgb8(image[:, y + 1, 1:-1], out, U(y))
