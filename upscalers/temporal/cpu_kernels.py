"""Compiled CPU kernels of the temporal upscaler (numba): the torch path's steps as loops.

Eager torch makes a pass over memory per operation (about 240 copies and a
dozen grid samples per frame at 1280x720); these loops make three passes at
render size and one at display size. They follow ``temporal.py`` and
``temporal_ops.py`` step by step and keep the arithmetic of torch's CPU
kernels: float32 throughout (constants through ``F32`` so that numba does not
promote a stage to float64), and a fused multiply-add (``fma32``) exactly where
torch's vectorized kernels fuse one: ``lerp``, ``addcmul``, ``add`` with
``alpha``, the 3x3 colour matrix products (sgemm's chain) and grid_sample's
unnormalization and bilinear sum. Selections (3x3 min/max, closest depth,
trust, clamps) are exact, so both paths make the same decisions; on the test
sequences the two give the same bits.

Speed comes from inner loops that LLVM vectorizes, which takes four rules:
rows are indexed by the loop variable plus a constant (they are sliced first:
numba wraps negative indices, and an index it cannot prove non-negative turns
the access into a gather); bodies are branch-free (selects, not an if with two
returns; branches on the frame's mode go outside the loops); no call inside
takes an array (an inlined numba function still counts references to its
array arguments); and a loop touches few arrays (LLVM gives up when the
run-time overlap checks get too many). Render-size planes carry one replicated
column on each side ("padded"), so a neighbour is a constant offset. At display
size the common scale 2 works in display order, both sub-pixels of a render
column per iteration (interleaves LLVM vectorizes); other integer scales work a
display row as S planar rows of the render width and interleave the result.
The history fetch at p + motion is indexed by data and does not vectorize (LLVM
emits no gathers for this CPU): its corners and weights are computed vectorized,
and where consecutive pixels read consecutive corners (a pan, a still
background: over 99% of the pixels of the reference scenes) the loads are
vector loads too; the rest is a tight scalar loop.

Outputs go into caller-owned arrays; ``parallel`` kernels split rows over
numba's threads (``prange``) in blocks of rows, each with a few row buffers.
"""

# numba has no type stubs and its decorators are untyped: mypy skips this module;
# ``temporal_cpu.py`` is the typed boundary.
# mypy: ignore-errors

from __future__ import annotations

import numpy as np
from numba import njit, prange, types
from numba.extending import intrinsic

F32 = np.float32
U64 = np.uint64
_JIT = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}

ROW_BLOCK = 8  # render rows per parallel work item
MAX_PIXELS = 1 << 24  # gather offsets (flat indices) are exact float32 integers below this
DISPLAY_BLOCK = 36  # display rows per parallel work item (each fetches 2 halo rows more)

# How the display stage gets the history pixel ``prev`` (temporal.TemporalUpscaler.upscale).
PREV_CURRENT = 0  # no history: the current frame's reconstruction
PREV_IN_PLACE = 1  # nothing moved: the history pixel itself (NaN -> 0, Inf -> float32 max)
PREV_FETCH = 2  # bilinear fetch at p + motion (non-finite -> 0), Catmull-Rom optional

_F32_MAX = 3.4028234663852886e38


@intrinsic
def fma32(typingctx, a, b, c):
    """a * b + c with one rounding (llvm.fma), float32 only: what torch's AVX kernels compute
    for lerp, addcmul, add with alpha and the contracted grid_sample arithmetic."""
    if not (a == types.float32 and b == types.float32 and c == types.float32):
        return None

    def codegen(context, builder, signature, args):
        return builder.fma(*args)

    return types.float32(types.float32, types.float32, types.float32), codegen


# -- scalar helpers (inlined; scalars only, so they keep loops vectorizable) -------------


@njit(inline="always", **_JIT)
def _lerp(a, b, t):
    """torch.lerp(a, b, t) as its vectorized CPU kernel computes it."""
    small = abs(t) < F32(0.5)
    return fma32(t if small else t - F32(1.0), b - a, a if small else b)


@njit(inline="always", **_JIT)
def _finite_or_zero(v):
    """torch.nan_to_num(v, nan=0, posinf=0, neginf=0)."""
    return v if v - v == F32(0.0) else F32(0.0)


@njit(inline="always", **_JIT)
def _nan_to_zero(v):
    """torch.nan_to_num(v, nan=0.0): infinities become the largest float32 values."""
    return F32(0.0) if v != v else min(max(v, F32(-_F32_MAX)), F32(_F32_MAX))


@njit(inline="always", **_JIT)
def _clampi(i, n):
    return min(max(i, 0), n - 1)


@njit(inline="always", **_JIT)
def _closer(bd, bx, by, cd, cx, cy):
    """The candidate (depth, motion) if strictly nearer, else the best so far (as selects:
    an if with two returns keeps LLVM from vectorizing the loop around it)."""
    closer = cd < bd
    return (cd if closer else bd), (cx if closer else bx), (cy if closer else by)


@njit(inline="always", **_JIT)
def _closest_of_three(dl, xl, yl, dc, xc, yc, dr, xr, yr):
    """``ops.closest_3x3``'s pass along a row: the centre, replaced by the left one if
    strictly nearer, then by the right one if strictly nearer than that."""
    d, mx, my = _closer(dc, xc, yc, dl, xl, yl)
    return _closer(d, mx, my, dr, xr, yr)


@njit(inline="always", **_JIT)
def _min3(a, b, c):
    return min(min(a, b), c)


@njit(inline="always", **_JIT)
def _max3(a, b, c):
    return max(max(a, b), c)


@njit(inline="always", **_JIT)
def _axis_position(g, half, last):
    """grid_sample's source position (align_corners=False, border padding) of normalized
    coordinate ``g`` on an axis of ``2 half`` pixels: its floor and the fraction."""
    u = fma32(g + F32(1.0), half, F32(-0.5))
    u = min(max(u, F32(0.0)), last)
    u0 = np.floor(u)
    return u0, u - u0


@njit(inline="always", **_JIT)
def _fetch_corners(gx, gy, big_w, big_h):
    """Corners and weights of grid_sample's bilinear fetch of the (3, H, W) history at
    normalized (gx, gy): flat offsets of the upper-left and lower-left corner, 1 or 0
    for the column to the right, the weights (nw, ne, sw, se). A corner past the edge
    (torch reads 0 there) has weight 0, as the position was clipped to the last pixel:
    the edge pixel is read instead, with the same result. Offsets are float32, exact
    below 2^24 pixels (``MAX_PIXELS``): integer vectors would halve the width."""
    one, zero = F32(1.0), F32(0.0)
    fw, last_x, last_y = F32(big_w), F32(big_w - 1), F32(big_h - 1)
    u0, fx = _axis_position(gx, fw * F32(0.5), last_x)
    v0, fy = _axis_position(gy, F32(big_h) * F32(0.5), last_y)
    top = v0 * fw + u0
    bottom = top + (fw if v0 < last_y else zero)
    right = one if u0 < last_x else zero
    s, e = one - fy, one - fx
    return top, bottom, right, s * e, s * fx, fy * e, fy * fx


@njit(inline="always", **_JIT)
def _bilerp(top_l, top_r, bottom_l, bottom_r, fx, fy):
    """``ops.reconstruct_blocked`` at one display pixel: lerp along the two rows, then
    between them."""
    return _lerp(_lerp(top_l, top_r, fx), _lerp(bottom_l, bottom_r, fx), fy)


@njit(inline="always", **_JIT)
def _blend(prev, cur, lo, hi, alpha):
    """Clamp both to the box, then torch.lerp towards the current frame."""
    return _lerp(min(max(prev, lo), hi), min(max(cur, lo), hi), alpha)


@njit(inline="always", **_JIT)
def _catmull_rom(value, left, right, up, down, mx, my, scale, k_cr):
    """``_sharpen_fetch`` at one pixel: per axis c = -gain t (1 - t) / 2 of the motion's
    sub-pixel fraction t, then value (1 - 2 cx - 2 cy) + cx (left + right) + cy (up +
    down), in the torch path's order."""
    return _catmull_rom_xy(value, left, right, up, down, mx * scale, my * scale, k_cr)


@njit(inline="always", **_JIT)
def _catmull_rom_xy(value, left, right, up, down, tx, ty, k_cr):
    """``_catmull_rom`` of a motion already in display pixels per axis (tx, ty)."""
    one = F32(1.0)
    tx = tx - np.floor(tx)
    ty = ty - np.floor(ty)
    cx = tx * (one - tx) * k_cr
    cy = ty * (one - ty) * k_cr
    centre = (cx + cy) * F32(-2.0) + one
    return fma32(up + down, cy, fma32(left + right, cx, value * centre))


@njit(inline="always", **_JIT)
def _to_u8(v):
    """Clamp to [0, 255] and truncate; NaN -> 0 (max keeps its first argument then), as
    torch's cast gives."""
    return np.uint8(np.int32(min(max(F32(0.0), v), F32(255.0))))


# -- render size ---------------------------------------------------------------------


@njit(inline="always", **_JIT)
def _pad(row):
    """Replicate the edge values of a padded row into its pad columns."""
    n = row.shape[0]
    row[0] = row[1]
    row[n - 1] = row[n - 2]


@njit(parallel=True, **_JIT)
def render_inputs(
    color, depth, motion, mask, to_ycocg, use_lin, lin_a, lin_b, limit, raw, lin, mvs, mask_f
):
    """Sanitized inputs of one frame into padded planes (column x at x + 1): ``raw`` (3,
    h, w + 2) YCoCg of the uint8 colour (``rgb8_to_ycocg``; the matrix ``to_ycocg``
    includes the 1/255), ``lin`` the depth (NaN/+Inf -> 1, -Inf -> 0, clamped to [0, 1])
    made linear as 1 / (d lin_a + lin_b) when ``use_lin``, ``mvs`` (2, ...) the motion
    (non-finite -> 0, clamped to +-limit) and ``mask_f`` the dynamic mask as float."""
    h, w = depth.shape
    la, lb, lim, one = F32(lin_a), F32(lin_b), F32(limit), F32(1.0)
    # sgemm's order: a fused multiply-add chain over the inner dimension.
    a0, a1, a2 = to_ycocg[0, 0], to_ycocg[0, 1], to_ycocg[0, 2]
    b0, b1, b2 = to_ycocg[1, 0], to_ycocg[1, 1], to_ycocg[1, 2]
    c0, c1, c2 = to_ycocg[2, 0], to_ycocg[2, 1], to_ycocg[2, 2]
    for blk in prange((h + ROW_BLOCK - 1) // ROW_BLOCK):
        for y in range(blk * ROW_BLOCK, min(h, (blk + 1) * ROW_BLOCK)):
            # Interleaved rows as flat ones: LLVM vectorizes the strided loads then.
            rgb = color[y].reshape(-1)
            luma, co, cg = raw[0, y, 1:], raw[1, y, 1:], raw[2, y, 1:]
            for x in range(w):
                r, g, b = F32(rgb[3 * x]), F32(rgb[3 * x + 1]), F32(rgb[3 * x + 2])
                luma[x] = fma32(a2, b, fma32(a1, g, a0 * r))
                co[x] = fma32(b2, b, fma32(b1, g, b0 * r))
                cg[x] = fma32(c2, b, fma32(c1, g, c0 * r))
            d_row, lin_row = depth[y], lin[y, 1:]
            if use_lin:
                for x in range(w):
                    d = d_row[x]
                    d = one if d != d else min(max(d, F32(0.0)), one)
                    lin_row[x] = one / (d * la + lb)
            else:
                for x in range(w):
                    d = d_row[x]
                    lin_row[x] = one if d != d else min(max(d, F32(0.0)), one)
            mv_row, mvx, mvy = motion[y].reshape(-1), mvs[0, y, 1:], mvs[1, y, 1:]
            for x in range(w):
                mvx[x] = min(max(_finite_or_zero(mv_row[2 * x]), -lim), lim)
                mvy[x] = min(max(_finite_or_zero(mv_row[2 * x + 1]), -lim), lim)
            m_row, mf_row = mask[y], mask_f[y, 1:]
            for x in range(w):
                mf_row[x] = F32(m_row[x])
            for c in range(3):
                _pad(raw[c, y])
            for c in range(2):
                _pad(mvs[c, y])
            _pad(lin[y])
            _pad(mask_f[y])


@njit(parallel=True, **_JIT)
def render_reproject(
    raw, amount, lin, mvs, mask_f, prev_far, weight, has_history, reset_weight, x_off, y_off,
    px_off, py_off, far_scale, keep_minus_one, max_weight, moving_max_weight, ycc, mvd,
    prev_weight,
):  # fmt: skip
    """Presharpened colour, dilated motion and the trusted accumulated weight (render size).

    ``ycc`` (padded) = ``ops.sharpen(raw, amount)`` (``raw`` itself when ``amount`` <= 0);
    ``mvd`` (2, h, w) the motion of the closest depth of the 3x3 neighbourhood
    (``ops.closest_3x3``: rows first, then the column; on ties the centre, then the
    left / upper one); ``prev_weight`` the last frame's accumulated ``weight`` at the
    reprojected position times the trust (``TemporalUpscaler._reproject_weight``;
    ``reset_weight`` everywhere without history). ``x_off`` = 0.5 + jitter x, ``px_off``
    the same of the previous frame. Returns how many pixels have non-zero dilated motion.
    """
    h, w = prev_weight.shape
    sharpen = amount > 0.0
    k_nb, k_x = F32(-0.25 * amount), F32(1.0 + amount)
    fw, fh, last_x, last_y = F32(w), F32(h), F32(w - 1), F32(h - 1)
    zero, one = F32(0.0), F32(1.0)
    far_flat, weight_flat = prev_far.reshape(-1), weight.reshape(-1)
    moving = 0
    for blk in prange((h + ROW_BLOCK - 1) // ROW_BLOCK):
        # Per row: the reprojected pixel (flat index, an exact float32 integer) and what its
        # trust needs (the loads there do not vectorize, so they are a loop of their own).
        k_row = np.empty(w, F32)
        depth_d = np.empty(w, F32)
        inside_f = np.empty(w, F32)
        mask_factor = np.empty(w, F32)
        for y in range(blk * ROW_BLOCK, min(h, (blk + 1) * ROW_BLOCK)):
            yu, yd = max(y - 1, 0), min(y + 1, h - 1)
            for c in range(3):
                up, mid, down, out = raw[c, yu, 1:], raw[c, y], raw[c, yd, 1:], ycc[c, y, 1:]
                if sharpen:
                    for x in range(w):
                        nb = up[x] + down[x] + mid[x] + mid[x + 2]
                        out[x] = fma32(mid[x + 1], k_x, nb * k_nb)
                else:
                    for x in range(w):
                        out[x] = mid[x + 1]
                _pad(ycc[c, y])
            # Padded rows: column x is at x + 1, its neighbours at x and x + 2.
            lu, lc, ld = lin[yu], lin[y], lin[yd]
            xu, xc, xd = mvs[0, yu], mvs[0, y], mvs[0, yd]
            vu, vc, vd = mvs[1, yu], mvs[1, y], mvs[1, yd]
            mu, mc, md = mask_f[yu], mask_f[y], mask_f[yd]
            mvd_x, mvd_y = mvd[0, y], mvd[1, y]
            fy = F32(y) + y_off
            moving_row = 0
            for x in range(w):
                bd, bx, by = _closest_of_three(
                    lc[x], xc[x], vc[x], lc[x + 1], xc[x + 1], vc[x + 1], lc[x + 2], xc[x + 2],
                    vc[x + 2],
                )  # fmt: skip
                d, mx, my = _closest_of_three(
                    lu[x], xu[x], vu[x], lu[x + 1], xu[x + 1], vu[x + 1], lu[x + 2], xu[x + 2],
                    vu[x + 2],
                )  # fmt: skip
                bd, bx, by = _closer(bd, bx, by, d, mx, my)
                d, mx, my = _closest_of_three(
                    ld[x], xd[x], vd[x], ld[x + 1], xd[x + 1], vd[x + 1], ld[x + 2], xd[x + 2],
                    vd[x + 2],
                )  # fmt: skip
                bd, bx, by = _closer(bd, bx, by, d, mx, my)
                mvd_x[x] = bx
                mvd_y[x] = by
                depth_d[x] = bd
                moving_row += np.int64((bx != zero) | (by != zero))
            # A loop of its own: LLVM gives up on one with this many arrays.
            for x in range(w):
                bx, by = mvd_x[x], mvd_y[x]
                m = max(_max3(mu[x], mu[x + 1], mu[x + 2]), _max3(mc[x], mc[x + 1], mc[x + 2]))
                m = max(m, _max3(md[x], md[x + 1], md[x + 2]))
                qx = bx + (F32(x) + x_off)
                qy = by + fy
                inside = (qx >= zero) & (qx <= fw) & (qy >= zero) & (qy <= fh)
                kx = min(max(np.floor(qx - px_off), zero), last_x)
                k_row[x] = min(max(np.floor(qy - py_off), zero), last_y) * fw + kx
                inside_f[x] = one if inside else zero
                mask_factor[x] = m * keep_minus_one + one
            moving += moving_row
            pw_row = prev_weight[y]
            if not has_history:
                for x in range(w):
                    pw_row[x] = reset_weight
                continue
            for x in range(w):
                k = U64(k_row[x])  # unsigned: numba skips its negative-index wrap
                visible = far_flat[k] * far_scale >= depth_d[x]
                wv = weight_flat[k]
                wv = zero if wv != wv or wv == np.inf else wv
                trust = (one if inside_f[x] != zero and visible else zero) * mask_factor[x]
                still = (mvd_x[x] == zero) & (mvd_y[x] == zero)
                cap = max_weight if still else moving_max_weight
                pw_row[x] = min(max(wv, zero), cap) * trust
    return moving


@njit(parallel=True, **_JIT)
def render_finish(
    ycc, lin, prev_weight, mean_weight, max_weight, slack, lo, hi, prev_far, weight,
):  # fmt: skip
    """The 3x3 YCoCg box (``ops.box_3x3``) of the padded ``ycc``, widened by ``slack``
    times its extent on each side (``ops.widen_box``), and the state for the
    next frame: the 2x2 max of linear depth (``ops.max_2x2``) and the accumulated weight
    (``TemporalUpscaler._store_weight``), written over the last frame's."""
    h, w = prev_weight.shape
    for blk in prange((h + ROW_BLOCK - 1) // ROW_BLOCK):
        for y in range(blk * ROW_BLOCK, min(h, (blk + 1) * ROW_BLOCK)):
            yu, yd = max(y - 1, 0), min(y + 1, h - 1)
            for c in range(3):
                up, mid, down = ycc[c, yu], ycc[c, y], ycc[c, yd]
                lo_row, hi_row = lo[c, y], hi[c, y]
                for x in range(w):
                    u0, u1, u2 = up[x], up[x + 1], up[x + 2]
                    m0, m1, m2 = mid[x], mid[x + 1], mid[x + 2]
                    d0, d1, d2 = down[x], down[x + 1], down[x + 2]
                    mn = min(min(_min3(u0, u1, u2), _min3(m0, m1, m2)), _min3(d0, d1, d2))
                    mx = max(max(_max3(u0, u1, u2), _max3(m0, m1, m2)), _max3(d0, d1, d2))
                    d = (mx - mn) * slack
                    lo_row[x] = mn - d
                    hi_row[x] = mx + d
            lin_y, lin_d = lin[y, 1:], lin[yd, 1:]
            far_row, pw_row, weight_row = prev_far[y], prev_weight[y], weight[y]
            for x in range(w):
                far_row[x] = max(max(lin_y[x], lin_y[x + 1]), max(lin_d[x], lin_d[x + 1]))
                weight_row[x] = min(pw_row[x] + mean_weight, max_weight)


# -- display size --------------------------------------------------------------------


@njit(inline="always", **_JIT)
def _upsample_motion(mvd, i, scale, mv_up):
    """Render row ``i`` of the dilated motion at display width: mv_up[:, X] = motion of
    render column X // S."""
    w = mvd.shape[2]
    for c in range(2):
        src, dst = mvd[c, i], mv_up[c]
        if scale == 2:  # an interleave LLVM vectorizes
            for j in range(w):
                dst[2 * j] = src[j]
                dst[2 * j + 1] = src[j]
        else:
            for b in range(scale):
                for j in range(w):
                    dst[j * scale + b] = src[j]


@njit(inline="always", **_JIT)
def _fetch_scalar(hist_flat, plane, t, bo, r, nw, ne, sw, se, dst, col):
    """One pixel of the bilinear fetch: grid_sample's corner order, fused; non-finite -> 0
    (the torch path's nan_to_num after the fetch). Unsigned offsets: numba then skips
    its negative-index wrap."""
    o = U64(0)
    for c in range(3):
        acc = fma32(hist_flat[o + t + r], ne, hist_flat[o + t] * nw)
        acc = fma32(hist_flat[o + bo], sw, acc)
        acc = fma32(hist_flat[o + bo + r], se, acc)
        dst[c, col] = _finite_or_zero(acc)
        o += plane


MIN_SPAN = 8  # contiguous fetch pixels worth a vector loop


@njit(inline="always", **_JIT)
def run_words(big_w):
    """Words of ``_fetch_row``'s span markers for a row of ``big_w`` pixels (one spare)."""
    return big_w // 8 + 1


@njit(inline="always", **_JIT)
def _fetch_span(hist_flat, plane, corners, x_start, x_end, dst):
    """Pixels x_start .. x_end - 1 of a fetch whose corners are consecutive (each reads the
    pixels after the previous one's, none at the right edge): the loads are unit-stride
    slices, so this vectorizes."""
    n = x_end - x_start
    upper_at, lower_at = np.int64(corners[0, x_start]), np.int64(corners[1, x_start])
    nw_, ne_ = corners[3, x_start:], corners[4, x_start:]
    sw_, se_ = corners[5, x_start:], corners[6, x_start:]
    o = 0
    for c in range(3):
        upper, lower = hist_flat[o + upper_at :], hist_flat[o + lower_at :]
        out = dst[c, x_start + 1 :]
        for k in range(n):
            acc = fma32(upper[k + 1], ne_[k], upper[k] * nw_[k])
            acc = fma32(lower[k], sw_[k], acc)
            acc = fma32(lower[k + 1], se_[k], acc)
            out[k] = _finite_or_zero(acc)
        o += plane


@njit(inline="always", **_JIT)
def _fetch_row(
    hist_flat, big_w, big_h, mv_up, gx_base, gx_off, gy_base, gy_off, step_x, step_y, corners,
    runs, dst,
):  # fmt: skip
    """A display row of the history fetched at p + motion into dst (3, W + 2) (column X at
    X + 1, edges replicated into the pad columns).

    Grid x of pixel X: mv_up[0, X] step_x + gx_base[X], plus gx_off[X] (``_fetch_history``
    of an integer scale adds the motion to the grid of sub-pixel (0, 0) of the block,
    then the sub-pixel offset; 0 elsewhere, which changes no value); y likewise with
    scalars. Corners and weights are computed vectorized into ``corners`` (7, W). The
    loads are indexed by data, which LLVM does not vectorize here; but where motion is
    smooth, spans of pixels read consecutive corners (a pan, a still background), and
    those are loaded as vectors. ``runs`` (``run_words(W)`` * 8,) uint8 is scratch: 0
    where a pixel continues the span of the one before, 1 where it starts one, 2 at the
    right edge; it is scanned eight pixels to a word.
    """
    top, bottom, right = corners[0], corners[1], corners[2]
    nw_, ne_, sw_, se_ = corners[3], corners[4], corners[5], corners[6]
    mvx, mvy = mv_up[0], mv_up[1]
    for x in range(big_w):
        gx = fma32(mvx[x], step_x, gx_base[x]) + gx_off[x]
        gy = fma32(mvy[x], step_y, gy_base) + gy_off
        t, bo, r, nw, ne, sw, se = _fetch_corners(gx, gy, big_w, big_h)
        top[x] = t
        bottom[x] = bo
        right[x] = r
        nw_[x] = nw
        ne_[x] = ne
        sw_[x] = sw
        se_[x] = se
    one = F32(1.0)
    runs[0] = 1 if right[0] == one else 2
    top_next, bottom_next, right_next, runs_next = top[1:], bottom[1:], right[1:], runs[1:]
    for x in range(big_w - 1):
        follows = (top_next[x] == top[x] + one) & (bottom_next[x] == bottom[x] + one)
        runs_next[x] = 2 if right_next[x] != one else (0 if follows else 1)
    for x in range(big_w, runs.shape[0]):
        runs[x] = 1  # the words' tail ends the last span
    words = runs.view(U64)
    plane = big_w * big_h
    x = 0
    while x < big_w:
        start = x
        x += 1
        if runs[start] != 2:
            while x & 7 and runs[x] == 0:
                x += 1
            while x < big_w and words[x >> 3] == 0:
                x += 8
            while x < big_w and runs[x] == 0:
                x += 1
        if x - start >= MIN_SPAN:
            _fetch_span(hist_flat, plane, corners, start, x, dst)
            continue
        for p in range(start, x):
            _fetch_scalar(
                hist_flat, U64(plane), U64(top[p]), U64(bottom[p]), U64(right[p]), nw_[p],
                ne_[p], sw_[p], se_[p], dst, p + 1,
            )  # fmt: skip
    # Pads: the Catmull-Rom neighbours of the edge pixels are themselves.
    for c in range(3):
        dst[c, 0] = dst[c, 1]
        dst[c, big_w + 1] = dst[c, big_w]


@njit(**_JIT)
def _history_row(hist, y, dst):
    """Display row ``y`` of the history as it is (NaN -> 0, Inf -> float32 max), laid out
    like ``_fetch_row``'s."""
    big_w = hist.shape[2]
    for c in range(3):
        row, out = hist[c, y], dst[c, 1:]
        for x in range(big_w):
            out[x] = _nan_to_zero(row[x])


@njit(**_JIT)
def _to_planar(disp, scale, dst):
    """A display-order row (3, W + 2) (``_fetch_row``) as planar sub-pixel rows dst (3, S,
    w + 2): sub-pixel b of render column j at [:, b, j + 1]. The pads are the
    display neighbours of the edge pixels: left of sub-pixel 0 is sub-pixel S - 1 of the
    column before, right of S - 1 is 0 of the column after; at the image edges, the
    edge pixel itself (edges replicated)."""
    w = dst.shape[2] - 2
    for c in range(3):
        src = disp[c, 1:]
        for b in range(scale):
            out = dst[c, b, 1:]
            for j in range(w):
                out[j] = src[j * scale + b]
    for c in range(3):
        dst[c, scale - 1, 0] = dst[c, 0, 1]
        dst[c, 0, w + 1] = dst[c, scale - 1, w]


@njit(**_JIT)
def _blend_row_blocked(
    ycc, lo, hi, prev_weight, mvd, i, r0, r1, fy, tap_x, frac_x, sub_weight_a, source,
    mid, up, down, k_cr, alpha, new,
):  # fmt: skip
    """The new history of one display row (sub-pixel row a of render row i) into ``new``
    (3, S, w), planar (sub-pixel b of render column j at [:, b, j]); ``alpha`` (w,) is
    scratch. ``source``: 0 = no history, 1 = ``mid`` as it is, 2 = ``mid`` with
    ``_sharpen_fetch``'s Catmull-Rom correction (``up``, ``down``: the fetched
    rows above and below), all three laid out by ``_to_planar``. The current frame is
    ``ops.reconstruct_blocked`` from the padded rows r0 and r1 of ``ycc``."""
    n_sub, w = new.shape[1], new.shape[2]
    fs = F32(n_sub)
    pw_i, mvx_i, mvy_i = prev_weight[i], mvd[0, i], mvd[1, i]
    for b in range(n_sub):
        x0 = tap_x[b] + 1  # padded column of the left tap of render column 0
        fx, wt = frac_x[b], sub_weight_a[b]
        # Display neighbours: sub-pixels b -/+ 1, or the previous/next column's last/first.
        lb, ls = (b - 1, 1) if b > 0 else (n_sub - 1, 0)
        rb, rs = (b + 1, 1) if b < n_sub - 1 else (0, 2)
        for j in range(w):
            alpha[j] = wt / (pw_i[j] + wt)
        # Branches outside the loops over j: LLVM vectorizes only branch-free bodies.
        for c in range(3):
            lo_c, hi_c, mid_c, new_c = lo[c, i], hi[c, i], mid[c, b, 1:], new[c, b]
            top, bottom = ycc[c, r0, x0:], ycc[c, r1, x0:]
            if source == 0:
                for j in range(w):
                    cur = _bilerp(top[j], top[j + 1], bottom[j], bottom[j + 1], fx, fy)
                    new_c[j] = _blend(cur, cur, lo_c[j], hi_c[j], alpha[j])
            elif source == 1:
                for j in range(w):
                    cur = _bilerp(top[j], top[j + 1], bottom[j], bottom[j + 1], fx, fy)
                    new_c[j] = _blend(mid_c[j], cur, lo_c[j], hi_c[j], alpha[j])
            else:
                left, right = mid[c, lb, ls:], mid[c, rb, rs:]
                up_b, down_b = up[c, b, 1:], down[c, b, 1:]
                for j in range(w):
                    cur = _bilerp(top[j], top[j + 1], bottom[j], bottom[j + 1], fx, fy)
                    prev = _catmull_rom(
                        mid_c[j], left[j], right[j], up_b[j], down_b[j], mvx_i[j], mvy_i[j], fs,
                        k_cr,
                    )  # fmt: skip
                    new_c[j] = _blend(prev, cur, lo_c[j], hi_c[j], alpha[j])


@njit(inline="always", **_JIT)
def _blend_row_2x(
    ycc, lo, hi, prev_weight, mvd, i, r0, r1, fy, tap_x, frac_x, sub_weight_a, source,
    mid, up, down, k_cr, alpha, hist_new, y,
):  # fmt: skip
    """``_blend_row_blocked`` for S = 2, straight into display row ``y`` of ``hist_new``:
    both sub-pixels of render column j in one iteration, the fetched rows read in display
    order (``_fetch_row``) and the result written so, as interleaves LLVM vectorizes (the
    common scale skips two passes of reordering). ``alpha`` (2, w) is scratch."""
    w = prev_weight.shape[1]
    fs = F32(2.0)
    pw_i, mvx_i, mvy_i = prev_weight[i], mvd[0, i], mvd[1, i]
    x0, x1 = tap_x[0] + 1, tap_x[1] + 1  # padded column of each sub-pixel's left tap
    fx0, fx1 = frac_x[0], frac_x[1]
    wt0, wt1 = sub_weight_a[0], sub_weight_a[1]
    alpha0, alpha1 = alpha[0], alpha[1]
    for j in range(w):
        alpha0[j] = wt0 / (pw_i[j] + wt0)
        alpha1[j] = wt1 / (pw_i[j] + wt1)
    for c in range(3):
        lo_c, hi_c, out = lo[c, i], hi[c, i], hist_new[c, y]
        top0, bottom0 = ycc[c, r0, x0:], ycc[c, r1, x0:]
        top1, bottom1 = ycc[c, r0, x1:], ycc[c, r1, x1:]
        m = mid[c, 1:]  # display column X at m[X]
        if source == 0:
            for j in range(w):
                cur0 = _bilerp(top0[j], top0[j + 1], bottom0[j], bottom0[j + 1], fx0, fy)
                cur1 = _bilerp(top1[j], top1[j + 1], bottom1[j], bottom1[j + 1], fx1, fy)
                out[2 * j] = _blend(cur0, cur0, lo_c[j], hi_c[j], alpha0[j])
                out[2 * j + 1] = _blend(cur1, cur1, lo_c[j], hi_c[j], alpha1[j])
        elif source == 1:
            for j in range(w):
                cur0 = _bilerp(top0[j], top0[j + 1], bottom0[j], bottom0[j + 1], fx0, fy)
                cur1 = _bilerp(top1[j], top1[j + 1], bottom1[j], bottom1[j + 1], fx1, fy)
                out[2 * j] = _blend(m[2 * j], cur0, lo_c[j], hi_c[j], alpha0[j])
                out[2 * j + 1] = _blend(m[2 * j + 1], cur1, lo_c[j], hi_c[j], alpha1[j])
        else:
            pad, u, d = mid[c], up[c, 1:], down[c, 1:]  # pad[X + 1] is display column X
            for j in range(w):
                cur0 = _bilerp(top0[j], top0[j + 1], bottom0[j], bottom0[j + 1], fx0, fy)
                cur1 = _bilerp(top1[j], top1[j + 1], bottom1[j], bottom1[j + 1], fx1, fy)
                mx, my = mvx_i[j], mvy_i[j]
                prev0 = _catmull_rom(
                    pad[2 * j + 1], pad[2 * j], pad[2 * j + 2], u[2 * j], d[2 * j], mx, my, fs,
                    k_cr,
                )  # fmt: skip
                prev1 = _catmull_rom(
                    pad[2 * j + 2], pad[2 * j + 1], pad[2 * j + 3], u[2 * j + 1], d[2 * j + 1], mx,
                    my, fs, k_cr,
                )  # fmt: skip
                out[2 * j] = _blend(prev0, cur0, lo_c[j], hi_c[j], alpha0[j])
                out[2 * j + 1] = _blend(prev1, cur1, lo_c[j], hi_c[j], alpha1[j])


@njit(**_JIT)
def _store_row(new, hist_new, y):
    """Planar (3, S, w) row into display row ``y`` of the history."""
    n_sub, w = new.shape[1], new.shape[2]
    for c in range(3):
        out = hist_new[c, y]
        for b in range(n_sub):
            src = new[c, b]
            for j in range(w):
                out[j * n_sub + b] = src[j]


@njit(inline="always", **_JIT)
def _rgb_row(hist, y, out):
    """Display row ``y`` of the history as uint8 sRGB into ``out`` (H, W, 3), C-contiguous
    (``ops.ycocg_to_rgb8``: 255 M x + 0.5 summed as sgemm does, clamped, truncated)."""
    big_w = hist.shape[2]
    k = F32(255.0)
    half = F32(0.5)
    luma, co, cg = hist[0, y], hist[1, y], hist[2, y]
    row = out[y].reshape(-1)
    for x in range(big_w):
        base = k * luma[x]
        row[3 * x] = _to_u8(fma32(-k, cg[x], fma32(k, co[x], base)) + half)
        row[3 * x + 1] = _to_u8(fma32(k, cg[x], base) + half)
        row[3 * x + 2] = _to_u8(fma32(-k, cg[x], fma32(-k, co[x], base)) + half)


@njit(parallel=True, **_JIT)
def display_blocked(
    ycc, lo, hi, prev_weight, mvd, tap_y, frac_y, tap_x, frac_x, sub_weight, gx_base, gx_off,
    gy, gy_off, step_x, step_y, prev_mode, catmull_rom, sharpen_gain, hist, hist_new, out,
):  # fmt: skip
    """The display stage of an integer scale S >= 2 (``TemporalUpscaler.upscale``).

    Display pixel (i S + a, j S + b) is sub-pixel (a, b) of render pixel (i, j): it is
    reconstructed from the padded ``ycc`` with the taps (``ops.phase_taps``: rows i +
    tap_y[a] and the next at fraction frac_y[a], columns likewise), takes the box,
    weight and motion of render pixel (i, j) and the sample weight sub_weight[a, b];
    its history comes as ``prev_mode`` says (fetch grid: ``gx_base[X]`` the x of
    sub-pixel 0 of X's block, ``gx_off[X]`` X's offset from it, ``gy`` the y of every
    display row, ``gy_off[a]`` likewise). With ``catmull_rom`` the fetched planes get
    ``_sharpen_fetch``'s correction, which needs the fetched rows above and below:
    each block of rows fetches into a ring of three rows. Writes ``hist_new`` (``hist``
    is read around each pixel, so it cannot be written in place) and ``out`` (H, W, 3).
    """
    _, big_h, big_w = hist.shape
    h, w = prev_weight.shape
    scale = tap_y.shape[0]
    hist_flat = hist.reshape(-1)
    fetch = prev_mode == PREV_FETCH
    cr = fetch and catmull_rom
    source = 0 if prev_mode == PREV_CURRENT else (2 if cr else 1)
    k_cr = F32(-0.5 * sharpen_gain)
    # With Catmull-Rom, row y is blended once row y + 1 is fetched.
    lag = 1 if cr else 0
    two = scale == 2  # the common scale works in display order throughout
    for blk in prange((big_h + DISPLAY_BLOCK - 1) // DISPLAY_BLOCK):
        y_start = blk * DISPLAY_BLOCK
        y_end = min(big_h, y_start + DISPLAY_BLOCK)
        ring = np.empty((3, 3, big_w + 2), F32)  # history rows, row r in slot r % 3
        planar = np.empty((3, 3, scale, w + 2), F32)  # the same as sub-pixel rows (S != 2)
        corners = np.empty((7, big_w), F32)
        runs = np.empty(run_words(big_w) * 8, np.uint8)
        mv_up = np.empty((2, big_w), F32)
        mv_row = -1  # the render row mv_up holds
        new = np.empty((3, scale, w), F32)
        alpha = np.empty((2, w), F32)
        for r in range(y_start - lag, y_end + lag):
            if fetch:
                rr = _clampi(r, big_h)
                i_r = rr // scale
                if i_r != mv_row:
                    _upsample_motion(mvd, i_r, scale, mv_up)
                    mv_row = i_r
                _fetch_row(
                    hist_flat, big_w, big_h, mv_up, gx_base, gx_off, gy[i_r * scale],
                    gy_off[rr - i_r * scale], step_x, step_y, corners, runs, ring[r % 3],
                )  # fmt: skip
                if not two:
                    _to_planar(ring[r % 3], scale, planar[r % 3])
            y = r - lag
            if y < y_start:
                continue
            if prev_mode == PREV_IN_PLACE:
                _history_row(hist, y, ring[y % 3])
                if not two:
                    _to_planar(ring[y % 3], scale, planar[y % 3])
            i = y // scale
            a = y - i * scale
            r0, r1 = _clampi(i + tap_y[a], h), _clampi(i + tap_y[a] + 1, h)
            if two:
                _blend_row_2x(
                    ycc, lo, hi, prev_weight, mvd, i, r0, r1, frac_y[a], tap_x, frac_x,
                    sub_weight[a], source, ring[y % 3], ring[(y - 1) % 3], ring[(y + 1) % 3],
                    k_cr, alpha, hist_new, y,
                )  # fmt: skip
            else:
                _blend_row_blocked(
                    ycc, lo, hi, prev_weight, mvd, i, r0, r1, frac_y[a], tap_x, frac_x,
                    sub_weight[a], source, planar[y % 3], planar[(y - 1) % 3],
                    planar[(y + 1) % 3], k_cr, alpha[0], new,
                )  # fmt: skip
                _store_row(new, hist_new, y)
            _rgb_row(hist_new, y, out)


@njit(parallel=True, **_JIT)
def display_generic(
    ycc, lo, hi, prev_weight, mvd, near_x, near_y, grid_x, grid_y, weight_x, weight_y, gxb, gyb,
    step_x, step_y, prev_mode, catmull_rom, sharpen_gain, scale_x, scale_y, hist, hist_new, out,
):  # fmt: skip
    """The display stage of any other scale (``TemporalUpscaler._generic_inputs``).

    Display pixel (Y, X) reconstructs the padded ``ycc`` at normalized (grid_x[X],
    grid_y[Y]) (``ops.jittered_grid``, bilinear, border padding), takes box, weight
    and motion of render pixel (near_y[Y], near_x[X]) (``ops.nearest_index``) and the
    sample weight weight_y[Y] weight_x[X]; its history as in ``display_blocked``, the
    Catmull-Rom correction's fraction from the motion in display pixels (render motion
    times ``scale_x`` / ``scale_y``, display over render size per axis), its rows above
    and below from a ring of three fetched rows. Render values are picked per display
    pixel, so less of this vectorizes.
    """
    _, big_h, big_w = hist.shape
    h, w = prev_weight.shape
    hist_flat = hist.reshape(-1)
    half_rw, half_rh = F32(w) * F32(0.5), F32(h) * F32(0.5)
    one = F32(1.0)
    no_offset = np.zeros(big_w, F32)
    fetch = prev_mode == PREV_FETCH
    cr = fetch and catmull_rom
    k_cr = F32(-0.5 * sharpen_gain)
    # With Catmull-Rom, row y is blended once row y + 1 is fetched.
    lag = 1 if cr else 0
    for blk in prange((big_h + DISPLAY_BLOCK - 1) // DISPLAY_BLOCK):
        y_start = blk * DISPLAY_BLOCK
        y_end = min(big_h, y_start + DISPLAY_BLOCK)
        ring = np.empty((3, 3, big_w + 2), F32)  # history rows, row r in slot r % 3
        corners = np.empty((7, big_w), F32)
        runs = np.empty(run_words(big_w) * 8, np.uint8)
        mv_up = np.empty((2, big_w), F32)
        new = np.empty((3, 1, big_w), F32)
        for r in range(y_start - lag, y_end + lag):
            if fetch:
                rr = _clampi(r, big_h)
                i_r = near_y[rr]
                for c in range(2):
                    src, dst = mvd[c, i_r], mv_up[c]
                    for x in range(big_w):
                        dst[x] = src[near_x[x]]
                _fetch_row(
                    hist_flat, big_w, big_h, mv_up, gxb, no_offset, gyb[rr], F32(0.0), step_x,
                    step_y, corners, runs, ring[r % 3],
                )  # fmt: skip
            y = r - lag
            if y < y_start:
                continue
            fetched, up, down = ring[y % 3], ring[(y - 1) % 3], ring[(y + 1) % 3]
            if prev_mode == PREV_IN_PLACE:
                _history_row(hist, y, fetched)
            i = near_y[y]
            v0, fy = _axis_position(grid_y[y], half_rh, F32(h - 1))
            y0 = np.int64(v0)
            y1 = min(y0 + 1, h - 1)
            s = one - fy
            pw_i, mvx_i, mvy_i = prev_weight[i], mvd[0, i], mvd[1, i]
            for x in range(big_w):
                j = near_x[x]
                u0, fx = _axis_position(grid_x[x], half_rw, F32(w - 1))
                x0 = np.int64(u0) + 1  # padded: the column after is x0 + 1 or the pad
                e = one - fx
                nw, ne, sw, se = s * e, s * fx, fy * e, fy * fx
                wt = weight_y[y] * weight_x[x]
                alpha = wt / (pw_i[j] + wt)
                tx, ty = mvx_i[j] * scale_x, mvy_i[j] * scale_y
                for c in range(3):
                    cur = fma32(ycc[c, y0, x0 + 1], ne, ycc[c, y0, x0] * nw)
                    cur = fma32(ycc[c, y1, x0], sw, cur)
                    cur = fma32(ycc[c, y1, x0 + 1], se, cur)
                    if prev_mode == PREV_CURRENT:
                        prev = cur
                    elif cr:
                        prev = _catmull_rom_xy(
                            fetched[c, x + 1], fetched[c, x], fetched[c, x + 2], up[c, x + 1],
                            down[c, x + 1], tx, ty, k_cr,
                        )  # fmt: skip
                    else:
                        prev = fetched[c, x + 1]
                    new[c, 0, x] = _blend(prev, cur, lo[c, i, j], hi[c, i, j], alpha)
            _store_row(new, hist_new, y)
            _rgb_row(hist_new, y, out)


@njit(parallel=True, **_JIT)
def rgb8_to_padded(rgb, padded):
    """(H, W, 3) uint8 into the interior of a (3, H + 2, W + 2) float image in [0, 1]
    (``TemporalUpscaler._finish_output``'s input; the RCAS kernel fills the border)."""
    h, w = rgb.shape[0], rgb.shape[1]
    k = F32(1.0 / 255.0)
    for y in prange(h):
        for c in range(3):
            dst = padded[c, y + 1]
            for x in range(w):
                dst[x + 1] = F32(rgb[y, x, c]) * k


@njit(parallel=True, **_JIT)
def rgb8_box_3x3(color, lo, hi):
    """Per render pixel and channel, the min and max of the (h, w, 3) uint8 colour over
    its 3x3 neighbourhood, edges replicated (``ops.box_3x3``), into ``lo`` and ``hi``
    (C-contiguous). Separable: the min and max of three rows, then of three
    neighbouring pixels (3 values apart in a flat row), so both loops vectorize."""
    h, w = color.shape[0], color.shape[1]
    n = 3 * w
    for y in prange(h):
        up, mid, down = (
            color[max(y - 1, 0)].reshape(-1),
            color[y].reshape(-1),
            color[min(y + 1, h - 1)].reshape(-1),
        )
        col_lo = np.empty(n + 6, np.uint8)  # one replicated pixel on each side
        col_hi = np.empty(n + 6, np.uint8)
        for k in range(n):
            col_lo[k + 3] = min(min(up[k], mid[k]), down[k])
            col_hi[k + 3] = max(max(up[k], mid[k]), down[k])
        for c in range(3):
            col_lo[c] = col_lo[c + 3]
            col_hi[c] = col_hi[c + 3]
            col_lo[n + 3 + c] = col_lo[n + c]
            col_hi[n + 3 + c] = col_hi[n + c]
        row_lo, row_hi = lo[y].reshape(-1), hi[y].reshape(-1)
        left_lo, right_lo, centre_lo = col_lo[0:n], col_lo[6 : n + 6], col_lo[3 : n + 3]
        left_hi, right_hi, centre_hi = col_hi[0:n], col_hi[6 : n + 6], col_hi[3 : n + 3]
        for k in range(n):
            row_lo[k] = min(min(left_lo[k], centre_lo[k]), right_lo[k])
            row_hi[k] = max(max(left_hi[k], centre_hi[k]), right_hi[k])


@njit(parallel=True, **_JIT)
def clamp_rgb8(out, lo, hi, near_x, near_y, slack):
    """Clamp display pixel (Y, X) of ``out`` (H, W, 3) uint8 to the box of render pixel
    (near_y[Y], near_x[X]) (``ops.nearest_index``) widened by ``slack`` levels each way
    (an int; the box and ``out`` are uint8, so the sums are taken as ints)."""
    big_h, big_w = out.shape[0], out.shape[1]
    for y in prange(big_h):
        i = near_y[y]
        for x in range(big_w):
            j = near_x[x]
            for c in range(3):
                low = np.int32(lo[i, j, c]) - slack
                high = np.int32(hi[i, j, c]) + slack
                out[y, x, c] = min(max(np.int32(out[y, x, c]), low), high)


# Back-projection (``back_projection.back_project``), four passes over the frame: the
# prediction along the columns, then along the rows with the error; the error back along
# the rows, then along the columns, added to the history with the output's conversion.
# Every sum runs over the taps in order from 0, one tap for a whole row at a time, so
# the row loops vectorize; the x tables come transposed, (taps, n). At 2x the interior of
# a row follows one pattern (``back_projection.Regular2x``): there the column passes read
# and write contiguous runs instead of gathering through the tables, which they keep for
# the few edge pixels. The terms and their order are those of the tables, so the result
# is the same (a table's padding adds 0).


@njit(parallel=True, **_JIT)
def bp_predict_x(hist, fx_i, fx_w, base, reg_w, r_lo, r_hi, across):
    """(3, H, w) prediction along the columns; the pattern covers [r_lo, r_hi) (none if
    empty): render column r reads display columns 2 r + base + t."""
    big_h, w = hist.shape[1], across.shape[2]
    n_fx, n_reg = fx_i.shape[0], reg_w.shape[0]
    for y in prange(big_h):
        for c in range(3):
            src, dst = hist[c, y], across[c, y]
            dst[:] = F32(0.0)
            for t in range(n_fx):
                idx, wt = fx_i[t], fx_w[t]
                for r in range(r_lo):
                    dst[r] += src[idx[r]] * wt[r]
                for r in range(r_hi, w):
                    dst[r] += src[idx[r]] * wt[r]
            if r_hi > r_lo:
                inner = dst[r_lo:r_hi]
                for t in range(n_reg):
                    seg = src[2 * r_lo + base + t : 2 * r_hi + base + t]
                    wt = reg_w[t]
                    for r in range(r_hi - r_lo):
                        inner[r] += seg[2 * r] * wt


@njit(parallel=True, **_JIT)
def bp_error(raw, fy_i, fy_w, across, error):
    """(3, h, w) error: the padded samples ``raw`` minus the prediction along the rows."""
    h, w = error.shape[1], error.shape[2]
    n_fy = fy_i.shape[1]
    for i in prange(h):
        for c in range(3):
            dst, seen = error[c, i], raw[c, i]
            dst[:] = F32(0.0)
            for t in range(n_fy):
                row, wt = across[c, fy_i[i, t]], fy_w[i, t]
                for r in range(w):
                    dst[r] += row[r] * wt
            for r in range(w):
                dst[r] = seen[r + 1] - dst[r]


@njit(parallel=True, **_JIT)
def bp_back_y(error, by_i, by_w, across):
    """The error back along the rows, into ``across`` (3, H, w)."""
    big_h, w = across.shape[1], across.shape[2]
    n_by = by_i.shape[1]
    for y in prange(big_h):
        for c in range(3):
            down = across[c, y]
            down[:] = F32(0.0)
            for u in range(n_by):
                src, wt = error[c, by_i[y, u]], by_w[y, u]
                for r in range(w):
                    down[r] += src[r] * wt


@njit(parallel=True, **_JIT)
def bp_back_x(hist, bx_i, bx_w, steps, near_x, near_y, across, out):
    """Any scale: the error back along the columns, added to the history times the step
    of the display pixel's nearest render pixel (``steps`` (h, w), ``near_x`` /
    ``near_y`` the nearest render column / row of each display one), and the history as
    uint8 sRGB into ``out``."""
    big_h, big_w = hist.shape[1], hist.shape[2]
    n_bx = bx_i.shape[0]
    for y in prange(big_h):
        acc = np.empty(big_w, np.float32)
        step_row = steps[near_y[y]]
        for c in range(3):
            down, row = across[c, y], hist[c, y]
            acc[:] = F32(0.0)
            for u in range(n_bx):
                idx, wt = bx_i[u], bx_w[u]
                for x in range(big_w):
                    acc[x] += down[idx[x]] * wt[x]
            for x in range(big_w):
                row[x] = fma32(step_row[near_x[x]], acc[x], row[x])
        _rgb_row(hist, y, out)


@njit(parallel=True, **_JIT)
def bp_back_x_2x(hist, bx_i, bx_w, offsets, reg_w, q_lo, q_hi, steps, near_y, across, out):
    """``bp_back_x`` at 2x: display column 2 q + a of the pattern's [q_lo, q_hi) reads the
    error at q + offsets[a, u]; the two sub-columns are summed planar and interleaved
    in the update, with the step of render column q (``steps`` (h, w); exact 2x: display
    columns 2 q and 2 q + 1 are in render column q)."""
    big_h, big_w = hist.shape[1], hist.shape[2]
    w = big_w // 2
    n_bx, n_reg = bx_i.shape[0], offsets.shape[1]
    for y in prange(big_h):
        even = np.empty(w, np.float32)
        odd = np.empty(w, np.float32)
        step_row = steps[near_y[y]]
        for c in range(3):
            down, row = across[c, y], hist[c, y]
            even[:] = F32(0.0)
            odd[:] = F32(0.0)
            if q_hi > q_lo:
                inner_even, inner_odd = even[q_lo:q_hi], odd[q_lo:q_hi]
                for u in range(n_reg):
                    seg = down[q_lo + offsets[0, u] : q_hi + offsets[0, u]]
                    wt = reg_w[0, u]
                    for q in range(q_hi - q_lo):
                        inner_even[q] += seg[q] * wt
                    seg = down[q_lo + offsets[1, u] : q_hi + offsets[1, u]]
                    wt = reg_w[1, u]
                    for q in range(q_hi - q_lo):
                        inner_odd[q] += seg[q] * wt
            for x in range(big_w):
                if 2 * q_lo <= x < 2 * q_hi:
                    continue  # the pattern's
                v = F32(0.0)
                for u in range(n_bx):
                    v += down[bx_i[u, x]] * bx_w[u, x]
                if x % 2 == 0:
                    even[x // 2] = v
                else:
                    odd[x // 2] = v
            for q in range(w):
                step = step_row[q]
                row[2 * q] = fma32(step, even[q], row[2 * q])
                row[2 * q + 1] = fma32(step, odd[q], row[2 * q + 1])
        _rgb_row(hist, y, out)


# Preconditioned back-projection (frames flagged AREA_SAMPLES only, never the stream's
# renders): the correction is summed whole into a buffer (``bp_predict_x`` without a
# pattern does bp_back_x's sums over the back tables), filtered per axis by
# [-c, 1 + 2c, -c] (``back_projection.precondition_filter``, the same sums in the same
# order) and added with the step. Generic tables at every scale: this path is for
# photographs and video, where a millisecond matters less than on the game's frames.


@njit(inline="always", **_JIT)
def _filter_at(row, x, centre, side):
    """``row`` at ``x`` filtered by [side, centre, side], its ends replicated."""
    n = row.shape[0]
    return row[x] * centre + (row[max(x - 1, 0)] + row[min(x + 1, n - 1)]) * side


@njit(parallel=True, **_JIT)
def precondition_add(hist, corr, cs, steps, near_x, near_y, out):
    """``corr`` (3, H, W) filtered per axis by [-c, 1 + 2c, -c] (along the rows first,
    edges replicated), c that of the display pixel's nearest render pixel in ``cs``
    (h, w), added to the history times its step (``steps``), and the history as uint8
    sRGB into ``out`` (``bp_back_x``)."""
    big_h, big_w = hist.shape[1], hist.shape[2]
    for y in prange(big_h):
        step_row, c_row = steps[near_y[y]], cs[near_y[y]]
        yu, yd = max(y - 1, 0), min(y + 1, big_h - 1)
        for ch in range(3):
            above, here, below = corr[ch, yu], corr[ch, y], corr[ch, yd]
            row = hist[ch, y]
            for x in range(big_w):
                c = c_row[near_x[x]]
                centre, side = F32(1.0) + F32(2.0) * c, -c
                v = (
                    _filter_at(here, x, centre, side) * centre
                    + (_filter_at(above, x, centre, side) + _filter_at(below, x, centre, side))
                    * side
                )
                row[x] = fma32(step_row[near_x[x]], v, row[x])
        _rgb_row(hist, y, out)
