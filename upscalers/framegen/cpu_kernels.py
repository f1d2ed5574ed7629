"""Compiled CPU kernels of Mesh Projection Estimation (numba): the torch path's steps as loops.

Eager torch pays for every intermediate tensor of 230k pixels; these loops
touch each pixel once per stage, so a predicted frame costs about a tenth of a
render on the CPU. They follow the torch implementation (``mesh.py``,
``raster.py``, ``mpe.py``, ``fill.py``, ``sample.py``) step by step and keep
its precision: vertex reprojection in float64, triangle set-up, raster and
pixel stage in float32 (constants go through ``F32`` so that numba does not
promote a stage to float64). Ties break as torch's ``argmax``/``argmin`` and
the packed-key ``scatter_reduce(amin)`` do: the first pixel of a tile, the
lowest triangle id at equal depth.

Outputs are written into caller-owned arrays; nothing here allocates per
pixel. ``parallel`` kernels split rows over numba's threads (``prange``) in
blocks of rows or triangles; for the raster and the pixel stage ``mpe_cpu``
has the threads take them one at a time (``set_parallel_chunksize``; it cannot
be called in here without disabling the on-disk cache), so on shared cores a
thread the OS parks delays only its block, not half the frame.
"""

# numba has no type stubs and its decorators are untyped: mypy skips this module;
# ``mpe_cpu.py`` is the typed boundary.
# mypy: ignore-errors

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

F32 = np.float32
_JIT = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}

MIN_CLIP_W = 1e-6  # geometry.MIN_CLIP_W
ROW_BLOCK = 8  # rows per parallel work item of the per-pixel kernels
EDGE_EPS = 1e-5  # raster.rasterize's eps: pixel centres this far outside an edge still count


@njit(parallel=True, **_JIT)
def sanitize_frame(
    color_src, color_words, depth_src, dyn_src, packed, depth, dynamic, z_inf, depth_eff
):
    """Copy a rendered frame into the cache buffers: colour packed as 0x00BBGGRR (flat),
    NaN/+inf depth -> 1 (sky), -inf -> 0, dynamic mask as bool, and ``depth_eff`` as
    ``sky_as_direction`` makes it (unless ``z_inf`` is NaN). Returns the dynamic pixel count.

    ``color_words``: ``color_src``'s memory as uint32 words when rows are whole words
    (W divisible by 4, contiguous), else empty; see ``_pack_rgb_row``.
    """
    h, w = depth.shape
    zf = F32(z_inf)
    make_eff = z_inf == z_inf
    n_dyn = 0
    for blk in prange((h + ROW_BLOCK - 1) // ROW_BLOCK):
        for y in range(blk * ROW_BLOCK, min(h, (blk + 1) * ROW_BLOCK)):
            _pack_rgb_row(color_src, color_words, y, packed)
            for x in range(w):
                d = depth_src[y, x]
                d = F32(1.0) if (d != d) | (d > F32(1.0)) else max(d, F32(0.0))
                depth[y, x] = d
                if make_eff:
                    depth_eff[y, x] = zf if d >= F32(1.0) else d
                m = dyn_src[y, x] != 0
                dynamic[y, x] = m
                n_dyn += np.int64(m)
    return n_dyn


@njit(inline="always", **_JIT)
def _pack_rgb_row(color_src, color_words, y, packed):
    """Row ``y`` of (H, W, 3) uint8 colour into ``packed`` as 0x00BBGGRR; from three
    32-bit words per four pixels when ``color_words`` is given (vectorizes)."""
    w = color_src.shape[1]
    row = y * w
    if color_words.size == 0 or w % 4 != 0:
        for x in range(w):
            packed[row + x] = (
                np.uint32(color_src[y, x, 0])
                | (np.uint32(color_src[y, x, 1]) << np.uint32(8))
                | (np.uint32(color_src[y, x, 2]) << np.uint32(16))
            )
        return
    base = y * (w * 3 // 4)
    low24 = np.uint32(0x00FFFFFF)
    for g in range(w // 4):
        # Little-endian bytes R0 G0 B0 R1 | G1 B1 R2 G2 | B2 R3 G3 B3
        a, b, c = (
            color_words[base + 3 * g],
            color_words[base + 3 * g + 1],
            color_words[base + 3 * g + 2],
        )
        packed[row + 4 * g] = a & low24
        packed[row + 4 * g + 1] = ((a >> np.uint32(24)) | (b << np.uint32(8))) & low24
        packed[row + 4 * g + 2] = ((b >> np.uint32(16)) | (c << np.uint32(16))) & low24
        packed[row + 4 * g + 3] = c >> np.uint32(8)


@njit(inline="always", **_JIT)
def _pull_level(img, wt, so, ss, sh, sw, do, ds):
    """One pull step on flat (cells, C) ``img`` / (cells,) ``wt``: the (sh, sw) level at
    offset ``so`` with row stride ``ss`` -> its 2 x 2 sums at ``do`` with stride ``ds``
    (zero weight outside odd edges; colour premultiplied by a weight clamped to 1)."""
    nc = img.shape[1]
    one = F32(1.0)
    for y in range((sh + 1) // 2):
        for x in range((sw + 1) // 2):
            q = do + y * ds + x
            s_w = F32(0.0)
            for c in range(nc):
                img[q, c] = 0.0
            for yy in range(2 * y, min(2 * y + 2, sh)):
                for xx in range(2 * x, min(2 * x + 2, sw)):
                    p = so + yy * ss + xx
                    s_w += wt[p]
                    for c in range(nc):
                        img[q, c] += img[p, c]
            div = max(s_w, one)
            for c in range(nc):
                img[q, c] = img[q, c] / div
            wt[q] = min(s_w, one)


@njit(**_JIT)
def _pull_push_dense(values, holes):
    """``fill.pull_push_fill`` in place on (H, W, C) float32 ``values`` over the whole pyramid.

    Used on the coarse grid of fill blocks (``pull_push_fill``); returns the hole count.
    """
    h, w, nc = values.shape
    n_holes = 0
    for y in range(h):
        for x in range(w):
            n_holes += holes[y, x]
    if n_holes == 0:
        return 0
    if n_holes == h * w:
        values[:] = 0.0
        return n_holes
    # Pyramid level sizes and their offsets in one flat buffer.
    n_levels = 1
    lh, lw = h, w
    while max(lh, lw) > 1:
        lh, lw = (lh + 1) // 2, (lw + 1) // 2
        n_levels += 1
    hs = np.empty(n_levels, np.int64)
    ws = np.empty(n_levels, np.int64)
    off = np.empty(n_levels + 1, np.int64)
    hs[0], ws[0], off[0] = h, w, 0
    for lv in range(1, n_levels):
        hs[lv], ws[lv] = (hs[lv - 1] + 1) // 2, (ws[lv - 1] + 1) // 2
    for lv in range(n_levels):
        off[lv + 1] = off[lv] + hs[lv] * ws[lv]
    img = np.empty((off[n_levels], nc), np.float32)
    wt = np.empty(off[n_levels], np.float32)
    one = F32(1.0)
    for y in range(h):
        for x in range(w):
            p = y * w + x
            if holes[y, x]:
                wt[p] = 0.0
                for c in range(nc):
                    img[p, c] = 0.0
            else:
                wt[p] = one
                for c in range(nc):
                    img[p, c] = values[y, x, c]
    # Pull: 2 x 2 sums (zero weight outside odd edges), colour premultiplied by a weight <= 1.
    for lv in range(n_levels - 1):
        _pull_level(img, wt, off[lv], ws[lv], hs[lv], ws[lv], off[lv + 1], ws[lv + 1])
    top = off[n_levels - 1]
    for c in range(nc):
        img[top, c] = img[top, c] / max(wt[top], F32(1e-6))
    # Push: each level is its premultiplied colour plus the coarser result where weight is missing.
    for lv in range(n_levels - 2, -1, -1):
        lh, lw, lo = hs[lv], ws[lv], off[lv]
        uw, uo = ws[lv + 1], off[lv + 1]
        for y in range(lh):
            for x in range(lw):
                p = lo + y * lw + x
                if lv == 0 and not holes[y, x]:
                    continue
                q = uo + (y // 2) * uw + x // 2
                miss = one - wt[p]
                for c in range(nc):
                    img[p, c] = img[p, c] + img[q, c] * miss
    for y in range(h):
        for x in range(w):
            if holes[y, x]:
                for c in range(nc):
                    values[y, x, c] = img[y * w + x, c]
    return n_holes


FILL_LEVELS = 5  # pyramid levels kept inside one fill block
FILL_BLOCK = 1 << FILL_LEVELS  # a fill block is one cell of pyramid level FILL_LEVELS


@njit(inline="always", **_JIT)
def _load(values, y, x, c):
    return F32(values[y, x, c])


# Cells of levels 1 .. FILL_LEVELS of one block, each level at a fixed row stride
# (16, 8, 4, 2, 1): offsets into one small flat buffer.
_FILL_STRIDE = np.array([FILL_BLOCK >> lv for lv in range(FILL_LEVELS + 1)], np.int64)
_FILL_OFFSET = np.array(
    [0] + [sum((FILL_BLOCK >> k) ** 2 for k in range(1, lv)) for lv in range(1, FILL_LEVELS + 1)],
    np.int64,
)
FILL_CELLS = sum((FILL_BLOCK >> k) ** 2 for k in range(1, FILL_LEVELS + 1))


@njit(**_JIT)
def _fill_block(
    values, holes, quantize, y0, x0, lvl_img, lvl_wt, fill_holes, grid, grid_wt, by, bx
):
    """Pull one fill block's pyramid (levels 1 .. FILL_LEVELS) and fill its holes from it.

    Every pull-push weight is 0 or 1 (a hole counts 0, a pixel 1, a coarser cell
    1 if any of its pixels is valid), and a hole's pushed value is the pulled
    value of its first ancestor that has weight 1, which depends only on the
    pixels under that ancestor. So a block with a valid pixel fills its holes
    exactly as the whole-frame pyramid would, from its own pixels; the block's
    top value and weight go to ``grid`` for blocks with no valid pixel.
    Cells, sizes and summation order follow ``_pull_push_dense``, so the values
    are the same bit for bit. Level 0 is read in place; ``lvl_img`` (FILL_CELLS,
    C) and ``lvl_wt`` (FILL_CELLS,) hold the rest (a few KB).
    """
    h, w, nc = values.shape
    bh, bw = min(FILL_BLOCK, h - y0), min(FILL_BLOCK, w - x0)
    one, zero = F32(1.0), F32(0.0)
    # Level 1 from the pixels.
    dh, dw = (bh + 1) // 2, (bw + 1) // 2
    stride = _FILL_STRIDE[1]
    for y in range(dh):
        for x in range(dw):
            q = y * stride + x
            s_w = zero
            for c in range(nc):
                lvl_img[q, c] = 0.0
            for yy in range(2 * y, min(2 * y + 2, bh)):
                for xx in range(2 * x, min(2 * x + 2, bw)):
                    valid = not holes[y0 + yy, x0 + xx]
                    s_w += one if valid else zero
                    for c in range(nc):
                        lvl_img[q, c] += _load(values, y0 + yy, x0 + xx, c) if valid else zero
            div = max(s_w, one)
            for c in range(nc):
                lvl_img[q, c] = lvl_img[q, c] / div
            lvl_wt[q] = min(s_w, one)
    sh, sw = dh, dw
    for lv in range(2, FILL_LEVELS + 1):
        dh, dw = (sh + 1) // 2, (sw + 1) // 2
        so, ss = _FILL_OFFSET[lv - 1], _FILL_STRIDE[lv - 1]
        _pull_level(lvl_img, lvl_wt, so, ss, sh, sw, _FILL_OFFSET[lv], _FILL_STRIDE[lv])
        sh, sw = dh, dw
    top = _FILL_OFFSET[FILL_LEVELS]
    grid_wt[by, bx] = lvl_wt[top]
    for c in range(nc):
        grid[by, bx, c] = lvl_img[top, c]
    if not fill_holes or lvl_wt[top] == 0.0:
        return
    for y in range(bh):
        for x in range(bw):
            if not holes[y0 + y, x0 + x]:
                continue
            lv = 1
            q = _FILL_OFFSET[1] + (y >> 1) * _FILL_STRIDE[1] + (x >> 1)
            while lvl_wt[q] == 0.0:
                lv += 1
                q = _FILL_OFFSET[lv] + (y >> lv) * _FILL_STRIDE[lv] + (x >> lv)
            for c in range(nc):
                _store(values, y0 + y, x0 + x, c, lvl_img[q, c], quantize)


@njit(inline="always", **_JIT)
def _store(values, y, x, c, v, quantize):
    if quantize:  # 8-bit colour: round to nearest, clamped
        values[y, x, c] = min(max(v + F32(0.5), F32(0.0)), F32(255.0))
    else:
        values[y, x, c] = v


@njit(parallel=True, **_JIT)
def pull_push_fill(values, holes, quantize):
    """``fill.pull_push_fill`` in place on (H, W, C) ``values``; returns the hole count.

    ``quantize``: ``values`` is 8-bit colour, filled in float32 and rounded.

    Work is per 32 x 32 block that has holes (see ``_fill_block``), so the cost
    follows the holes, not the frame. Only blocks without a single valid pixel
    need the coarser levels: the blocks under their first weighted ancestor are
    pulled too, and that coarse grid is pull-pushed whole (it is small).
    """
    h, w, nc = values.shape
    nby, nbx = (h + FILL_BLOCK - 1) // FILL_BLOCK, (w + FILL_BLOCK - 1) // FILL_BLOCK
    n_holes_b = np.zeros((nby, nbx), np.int64)
    for by in prange(nby):
        for bx in range(nbx):
            count = 0
            for y in range(by * FILL_BLOCK, min(h, (by + 1) * FILL_BLOCK)):
                for x in range(bx * FILL_BLOCK, min(w, (bx + 1) * FILL_BLOCK)):
                    count += holes[y, x]
            n_holes_b[by, bx] = count
    n_holes = 0
    n_empty = 0
    for by in range(nby):
        for bx in range(nbx):
            n_holes += n_holes_b[by, bx]
            bh = min(FILL_BLOCK, h - by * FILL_BLOCK)
            bw = min(FILL_BLOCK, w - bx * FILL_BLOCK)
            n_empty += n_holes_b[by, bx] == bh * bw
    if n_holes == 0:
        return 0
    if n_holes == h * w:
        values[:] = 0
        return n_holes
    # Which blocks to pull: those with holes, and for blocks with no valid pixel
    # every block under their first ancestor (in block units) that has one.
    pull = np.zeros((nby, nbx), np.bool_)
    for by in range(nby):
        for bx in range(nbx):
            pull[by, bx] = n_holes_b[by, bx] > 0
    if n_empty:
        for by in range(nby):
            for bx in range(nbx):
                bh = min(FILL_BLOCK, h - by * FILL_BLOCK)
                bw = min(FILL_BLOCK, w - bx * FILL_BLOCK)
                if n_holes_b[by, bx] != bh * bw:
                    continue
                k = 1
                while True:
                    ay0, ax0 = (by >> k) << k, (bx >> k) << k
                    ay1, ax1 = min(ay0 + (1 << k), nby), min(ax0 + (1 << k), nbx)
                    found = False
                    for yy in range(ay0, ay1):
                        for xx in range(ax0, ax1):
                            bh2 = min(FILL_BLOCK, h - yy * FILL_BLOCK)
                            bw2 = min(FILL_BLOCK, w - xx * FILL_BLOCK)
                            found |= n_holes_b[yy, xx] < bh2 * bw2
                    if found:
                        for yy in range(ay0, ay1):
                            for xx in range(ax0, ax1):
                                pull[yy, xx] = True
                        break
                    k += 1
    grid = np.zeros((nby, nbx, nc), np.float32)
    grid_wt = np.zeros((nby, nbx), np.float32)
    for by in prange(nby):
        lvl_img = np.empty((FILL_CELLS, nc), np.float32)
        lvl_wt = np.empty(FILL_CELLS, np.float32)
        for bx in range(nbx):
            if pull[by, bx]:
                _fill_block(
                    values,
                    holes,
                    quantize,
                    by * FILL_BLOCK,
                    bx * FILL_BLOCK,
                    lvl_img,
                    lvl_wt,
                    n_holes_b[by, bx] > 0,
                    grid,
                    grid_wt,
                    by,
                    bx,
                )
    if n_empty:
        grid_holes = np.zeros((nby, nbx), np.bool_)
        for by in range(nby):
            for bx in range(nbx):
                grid_holes[by, bx] = grid_wt[by, bx] == 0.0
        _pull_push_dense(grid, grid_holes)
        for by in prange(nby):
            for bx in range(nbx):
                bh = min(FILL_BLOCK, h - by * FILL_BLOCK)
                bw = min(FILL_BLOCK, w - bx * FILL_BLOCK)
                if n_holes_b[by, bx] != bh * bw:
                    continue  # filled by its own block (or has no holes)
                for y in range(by * FILL_BLOCK, min(h, (by + 1) * FILL_BLOCK)):
                    for x in range(bx * FILL_BLOCK, min(w, (bx + 1) * FILL_BLOCK)):
                        for c in range(nc):
                            _store(values, y, x, c, grid[by, bx, c], quantize)
    return n_holes


@njit(**_JIT)
def sky_as_direction(depth, z_inf, out):
    """``geometry.sky_as_direction`` into ``out`` (float32)."""
    h, w = depth.shape
    zf = F32(z_inf)
    for y in range(h):
        for x in range(w):
            d = depth[y, x]
            out[y, x] = zf if d >= 1.0 else d


@njit(**_JIT)
def _project(depth_eff, m, x, y, w, h):
    """``geometry.reproject_points`` of pixel (x, y) in float64: (px, py, depth, valid)."""
    d = np.float64(depth_eff[y, x])
    nx = (x + 0.5) * (2.0 / w) - 1.0
    ny = 1.0 - (y + 0.5) * (2.0 / h)
    cx = nx * m[0, 0] + ny * m[0, 1] + d * m[0, 2] + m[0, 3]
    cy = nx * m[1, 0] + ny * m[1, 1] + d * m[1, 2] + m[1, 3]
    cz = nx * m[2, 0] + ny * m[2, 1] + d * m[2, 2] + m[2, 3]
    cw = nx * m[3, 0] + ny * m[3, 1] + d * m[3, 2] + m[3, 3]
    valid = cw > MIN_CLIP_W and cz >= 0.0 and np.isfinite(cx) and np.isfinite(cy)
    if not valid:
        return 0.0, 0.0, 1.0, False
    inv_w = 1.0 / cw
    lim = 64.0 * max(w, h)
    qx = min(max((cx * inv_w + 1.0) * (0.5 * w), -lim), lim)
    qy = min(max((1.0 - cy * inv_w) * (0.5 * h), -lim), lim)
    return qx, qy, cz * inv_w, True


@njit(parallel=True, **_JIT)
def mesh_vertices(depth_raw, depth_eff, dynamic, fwd, tile, tensile, tensile_threshold, out):
    """The SSAM vertices (``mesh.build_mesh`` up to the triangles) on a (Th + 2, Tw + 2) grid.

    ``out`` is (6, Th + 2, Tw + 2) float64: x, y, depth (new camera), u, v (source
    pixel), valid (1.0 / 0.0). The outer ring is pinned to the screen border.
    """
    h, w = depth_raw.shape
    th, tw = -(-h // tile), -(-w // tile)
    bias = F32(1e-9)
    for ty in prange(th):
        # Each tile's pixel of largest squared depth gradient (the first one on ties):
        # gradients a pixel row at a time (vectorizes), then a running maximum per tile.
        grad = np.empty(w, np.float32)
        best = np.full(tw, F32(-3.0))
        best_x = np.empty(tw, np.int64)
        best_y = np.empty(tw, np.int64)
        for yy in range(ty * tile, min(h, (ty + 1) * tile)):
            below = min(yy + 1, h - 1)  # the last row has no dy term: d - d = 0
            for xx in range(w - 1):
                d = depth_raw[yy, xx]
                dx = depth_raw[yy, xx + 1] - d
                dy = depth_raw[below, xx] - d
                g = dx * dx + dy * dy
                grad[xx] = F32(-1.0) if dynamic[yy, xx] else g
            d = depth_raw[yy, w - 1]  # the last column has no dx term
            dy = depth_raw[below, w - 1] - d
            grad[w - 1] = F32(-1.0) if dynamic[yy, w - 1] else dy * dy
            for tx in range(tw):
                if yy == ty * tile:
                    best_x[tx], best_y[tx] = tx * tile, yy
                x0, x1 = tx * tile, min(w, (tx + 1) * tile)
                # The row's maximum first (a reduction that vectorizes); only a strictly
                # larger one moves the vertex, to its first pixel in the row.
                m = grad[x0]
                for xx in range(x0 + 1, x1):
                    m = max(m, grad[xx])
                if m > best[tx]:
                    xx = x0
                    while grad[xx] != m:
                        xx += 1
                    best[tx], best_x[tx], best_y[tx] = m, xx, yy
        for tx in range(tw):
            vx, vy = best_x[tx], best_y[tx]
            if tensile:
                # Nearest and farthest of the 3 x 3 neighbours (ties to the first, the
                # centre biased by a hair as in mesh._neighbour_extremes).
                fk_best, bk_best = F32(np.inf), F32(-np.inf)
                fgx, fgy, bgx, bgy = vx, vy, vx, vy
                for k in range(9):
                    nx = min(max(vx + k % 3 - 1, 0), w - 1)
                    ny = min(max(vy + k // 3 - 1, 0), h - 1)
                    d = depth_raw[ny, nx]
                    b = bias if k == 4 else F32(0.0)
                    fk, bk = d - b, d + b
                    if fk < fk_best or k == 0:
                        fk_best, fgx, fgy = fk, nx, ny
                    if bk > bk_best or k == 0:
                        bk_best, bgx, bgy = bk, nx, ny
                fx, fy, fz, fv = _project(depth_eff, fwd, fgx, fgy, w, h)
                bx, by, _, bv = _project(depth_eff, fwd, bgx, bgy, w, h)
                bex, bey = float(fgx - bgx), float(fgy - bgy)
                afx, afy = fx - bx, fy - by
                same_dir = bex * afx + bey * afy > 0.0
                grow = math.hypot(afx, afy) - math.hypot(bex, bey)
                tear = fv and bv and same_dir and grow > tensile_threshold
                ux, uy = (bgx, bgy) if tear else (fgx, fgy)
                px, py, pz, pv = fx, fy, fz, fv
            else:
                ux, uy = vx, vy
                px, py, pz, pv = _project(depth_eff, fwd, vx, vy, w, h)
            gy, gx = ty + 1, tx + 1
            out[0, gy, gx] = px
            out[1, gy, gx] = py
            out[2, gy, gx] = pz
            out[3, gy, gx] = ux + 0.5
            out[4, gy, gx] = uy + 0.5
            out[5, gy, gx] = 1.0 if pv else 0.0
    # Replicate the outer ring from its neighbours, then pin it to the border.
    for k in range(6):
        for gy in range(1, th + 1):
            out[k, gy, 0] = out[k, gy, 1]
            out[k, gy, tw + 1] = out[k, gy, tw]
        for gx in range(tw + 2):
            out[k, 0, gx] = out[k, 1, gx]
            out[k, th + 1, gx] = out[k, th, gx]
    for gy in range(th + 2):
        out[0, gy, 0], out[0, gy, tw + 1] = 0.0, float(w)
        out[3, gy, 0], out[3, gy, tw + 1] = 0.0, float(w)
    for gx in range(tw + 2):
        out[1, 0, gx], out[1, th + 1, gx] = 0.0, float(h)
        out[4, 0, gx], out[4, th + 1, gx] = 0.0, float(h)


@njit(**_JIT)
def _corner(t, n_half, nx):
    """Grid (row, col) offsets of triangle ``t``'s corners: (00, 01, 11) then (00, 11, 10)."""
    cell = t % n_half
    i, j = cell // nx, cell % nx
    if t < n_half:
        return i, j, i, j + 1, i + 1, j + 1
    return i, j, i + 1, j + 1, i + 1, j


@njit(inline="always", **_JIT)
def _floor(x):
    """floor of a float32 in int range (math.floor compiles to a slower library call)."""
    i = np.int64(x)
    return i - 1 if F32(i) > x else i


@njit(inline="always", **_JIT)
def _ceil(x):
    i = np.int64(x)
    return i + 1 if F32(i) < x else i


RASTER_BANDS = 8  # row bands rasterized in parallel (each walks every triangle)
SETUP_BLOCK = 256  # triangles per parallel work item of the set-up


@njit(**_JIT)
def _setup_triangle(verts, t, n_half, nx, w, h, max_bbox_pixels, planes, bary):
    """Planes of triangle ``t`` (``raster._planes``) and its rows (iy0, iy1); (0, -1) if unused."""
    one, half = F32(1.0), F32(0.5)
    r0, c0, r1, c1, r2, c2 = _corner(t, n_half, nx)
    if verts[5, r0, c0] < 0.5 or verts[5, r1, c1] < 0.5 or verts[5, r2, c2] < 0.5:
        return 0, -1
    x0, x1, x2 = F32(verts[0, r0, c0]), F32(verts[0, r1, c1]), F32(verts[0, r2, c2])
    y0, y1, y2 = F32(verts[1, r0, c0]), F32(verts[1, r1, c1]), F32(verts[1, r2, c2])
    den = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    if not abs(den) > 1e-6:
        return 0, -1
    inv = one / den
    a1, b1 = (y2 - y0) * inv, (x0 - x2) * inv
    a2, b2 = (y0 - y1) * inv, (x1 - x0) * inv
    cc1 = -(a1 * x0 + b1 * y0)
    cc2 = -(a2 * x0 + b2 * y0)
    bary[t, 0, 0], bary[t, 0, 1], bary[t, 0, 2] = -a1 - a2, -b1 - b2, one - cc1 - cc2
    bary[t, 1, 0], bary[t, 1, 1], bary[t, 1, 2] = a1, b1, cc1
    bary[t, 2, 0], bary[t, 2, 1], bary[t, 2, 2] = a2, b2, cc2
    for k in range(3):  # depth (clamped at 0 as build_mesh does), u, v
        v0, v1, v2 = F32(verts[2 + k, r0, c0]), F32(verts[2 + k, r1, c1]), F32(verts[2 + k, r2, c2])
        if k == 0:
            v0, v1, v2 = max(v0, F32(0.0)), max(v1, F32(0.0)), max(v2, F32(0.0))
        d1, d2 = v1 - v0, v2 - v0
        planes[t, k, 0] = a1 * d1 + a2 * d2
        planes[t, k, 1] = b1 * d1 + b2 * d2
        planes[t, k, 2] = v0 + cc1 * d1 + cc2 * d2
    bx1 = min(max(math.floor(max(x0, x1, x2) - half), -1), w - 1)
    bx0 = min(max(math.ceil(min(x0, x1, x2) - half), 0), w - 1)
    iy0 = min(max(math.ceil(min(y0, y1, y2) - half), 0), h - 1)
    iy1 = min(max(math.floor(max(y0, y1, y2) - half), -1), h - 1)
    bw, bh = max(bx1 - bx0 + 1, 0), max(iy1 - iy0 + 1, 0)
    if bw * bh > max_bbox_pixels:
        return 0, -1
    return iy0, iy1


@njit(parallel=True, **_JIT)
def rasterize(verts, w, h, max_bbox_pixels, zbuf, u_map, v_map, planes):
    """Scanline raster of the vertex grid with a depth test (``raster.rasterize``).

    Writes per pixel the winning triangle's depth (``zbuf``, inf where none)
    and the source position its u and v planes give at the pixel centre
    (``u_map``, ``v_map``: what ``raster.rasterize``'s triangle id leads to),
    and per triangle the screen planes (a, b, c) of depth, u and v
    (``planes``, (T, 3, 3)). Triangles are set up in parallel, then row bands
    are rasterized in parallel, each band walking the triangles in id order, so
    ties keep the lowest id.
    """
    half = F32(0.5)
    eps = F32(EDGE_EPS)
    ny, nx = verts.shape[1] - 1, verts.shape[2] - 1
    n_half = ny * nx
    n_tri = 2 * n_half
    bary = np.empty((n_tri, 3, 3), np.float32)
    rows = np.empty((n_tri, 2), np.int64)
    for blk in prange((n_tri + SETUP_BLOCK - 1) // SETUP_BLOCK):
        for t in range(blk * SETUP_BLOCK, min(n_tri, (blk + 1) * SETUP_BLOCK)):
            rows[t, 0], rows[t, 1] = _setup_triangle(
                verts, t, n_half, nx, w, h, max_bbox_pixels, planes, bary
            )
    band_h = (h + RASTER_BANDS - 1) // RASTER_BANDS
    for band in prange(RASTER_BANDS):
        top, bottom = band * band_h, min(h, (band + 1) * band_h)
        for p in range(top * w, bottom * w):
            zbuf[p] = np.inf
            u_map[p] = F32(0.5)
            v_map[p] = F32(0.5)
        # Spans of all rows of a triangle first (independent rows: vectorizes), then fills.
        span_lo = np.empty(band_h, np.int64)
        span_hi = np.empty(band_h, np.int64)
        span_z = np.empty(band_h, np.float32)
        for t in range(n_tri):
            first, last = max(rows[t, 0], top), min(rows[t, 1], bottom - 1)
            if first > last:
                continue
            za, zb, zc = planes[t, 0, 0], planes[t, 0, 1], planes[t, 0, 2]
            ua, ub, uc = planes[t, 1, 0], planes[t, 1, 1], planes[t, 1, 2]
            va, vb, vc = planes[t, 2, 0], planes[t, 2, 1], planes[t, 2, 2]
            for j in range(last - first + 1):
                cy = F32(first + j) + half
                # The pixel centres inside all three edges (b_k(x) + eps >= 0): an edge bounds
                # from the left (a > 0), the right (a < 0), or is parallel to the row and
                # keeps it whole or empties it.
                lo, hi = F32(-np.inf), F32(np.inf)
                empty = False
                for k in range(3):
                    a = bary[t, k, 0]
                    c = bary[t, k, 1] * cy + bary[t, k, 2] + eps
                    flat = abs(a) <= 1e-12
                    root = -c / (F32(1.0) if flat else a)
                    lo = max(lo, root if a > 1e-12 else F32(-np.inf))
                    hi = min(hi, root if a < -1e-12 else F32(np.inf))
                    empty |= flat & (c < 0.0)
                i0 = max(_ceil(min(max(lo, F32(-1.0)), F32(w)) - half), 0)
                i1 = min(_floor(min(max(hi, F32(-1.0)), F32(w + 1)) - half), w - 1)
                span_lo[j] = i0
                span_hi[j] = i0 - 1 if empty | (lo > hi) else i1
                span_z[j] = za * (F32(i0) + half) + zb * cy + zc
            for j in range(last - first + 1):
                base = (first + j) * w
                i0, z0 = span_lo[j], span_z[j]
                cy = F32(first + j) + half
                for i in range(i0, span_hi[j] + 1):
                    z = max(z0 + za * F32(i - i0), F32(0.0))
                    cx = F32(i) + half
                    # The same expressions as the torch pixel stage evaluates for the winner.
                    uu = uc + ua * cx + ub * cy
                    vv = vc + va * cx + vb * cy
                    # Triangles come in id order: a strict test keeps the lowest id on ties.
                    # Selects over loaded values, not a branch: the span vectorizes.
                    z_old, u_old, v_old = zbuf[base + i], u_map[base + i], v_map[base + i]
                    nearer = z < z_old
                    zbuf[base + i] = z if nearer else z_old
                    u_map[base + i] = uu if nearer else u_old
                    v_map[base + i] = vv if nearer else v_old


@njit(inline="always", **_JIT)
def _nearest(px, py, w, h):
    """``sample.nearest_index``: flat index of the pixel containing (px, py), clamped."""
    iy = np.int32(min(max(py, F32(0.0)), F32(h - 0.5)))
    return iy * np.int32(w) + np.int32(min(max(px, F32(0.0)), F32(w - 0.5)))


@njit(inline="always", **_JIT)
def _reproject_row(x0, n, cy, u, v, d0, fm, gm, zi1, w, z, qx, qy, ok, prev, h):
    """``mpe.step`` over a row: reprojected depth z, where each pixel came from (qx, qy), ok."""
    eps = F32(MIN_CLIP_W)
    rx = cy * gm[0, 1] + gm[0, 3]
    ry = cy * gm[1, 1] + gm[1, 3]
    rw = cy * gm[3, 1] + gm[3, 3]
    f20, f21, f22, f23 = fm[2, 0], fm[2, 1], fm[2, 2], fm[2, 3]
    f30, f31, f32, f33 = fm[3, 0], fm[3, 1], fm[3, 2], fm[3, 3]
    g00, g10, g30, g02, g12, g32 = gm[0, 0], gm[1, 0], gm[3, 0], gm[0, 2], gm[1, 2], gm[3, 2]
    for i in range(n):
        cx = F32(x0 + i) + F32(0.5)
        d = d0[i]
        cz = d * f22 + u[i] * f20 + v[i] * f21 + f23
        cw = d * f32 + u[i] * f30 + v[i] * f31 + f33
        zz = zi1 if d > F32(1.0) else cz / max(cw, eps)
        pw = (rw + cx * g30) + zz * g32
        inv = F32(1.0) / max(pw, eps)
        px = ((rx + cx * g00) + zz * g02) * inv
        py = ((ry + cx * g10) + zz * g12) * inv
        z[i], qx[i], qy[i] = zz, px, py
        ok[i] = (cw > eps) & (pw > eps)
        prev[i] = _nearest(px, py, w, h)


@njit(inline="always", **_JIT)
def _agree_row(n, d0, d1, qx, qy, ok, zi0, tolerance, w, h, agree):
    """``mpe.consistent`` over a row: the cached depth where the pixel came from matches d0."""
    fw, fh = F32(w), F32(h)
    for i in range(n):
        seen = ok[i] & (qx[i] >= F32(0.0)) & (qx[i] <= fw) & (qy[i] >= F32(0.0)) & (qy[i] <= fh)
        tol = max(zi0 - max(d0[i], d1[i]), F32(0.0)) * tolerance + F32(1e-7)
        agree[i] = seen & (abs(d1[i] - d0[i]) <= tol)


@njit(inline="always", **_JIT)
def _gather(n, table, index, out):
    for i in range(n):
        out[i] = table[index[i]]


@njit(inline="always", **_JIT)
def _bilinear_row(n, packed, u, v, w, h, i00, i01, i10, i11, fx, fy, t00, t01, t10, t11, out):
    """``sample.bilinear`` (border, align_corners=False) of packed RGB, rounded to 8 bits.

    Split in three loops (indices, gathers, blend) so that the two arithmetic
    ones vectorize; ``out`` gets packed 0x00BBGGRR.
    """
    fw1, fh1 = F32(w - 1), F32(h - 1)
    wi = np.int32(w)
    for i in range(n):
        ix = min(max(u[i] - F32(0.5), F32(0.0)), fw1)
        iy = min(max(v[i] - F32(0.5), F32(0.0)), fh1)
        x0, y0 = np.int32(ix), np.int32(iy)
        x1, y1 = min(x0 + np.int32(1), wi - np.int32(1)), min(y0 + np.int32(1), np.int32(h - 1))
        fx[i], fy[i] = ix - F32(x0), iy - F32(y0)
        i00[i], i01[i] = y0 * wi + x0, y0 * wi + x1
        i10[i], i11[i] = y1 * wi + x0, y1 * wi + x1
    for i in range(n):
        t00[i], t01[i], t10[i], t11[i] = (
            packed[i00[i]],
            packed[i01[i]],
            packed[i10[i]],
            packed[i11[i]],
        )
    m = np.int32(255)
    for i in range(n):
        ax, ay = fx[i], fy[i]
        bx, by = F32(1.0) - ax, F32(1.0) - ay
        a, b, c, d = np.int32(t00[i]), np.int32(t01[i]), np.int32(t10[i]), np.int32(t11[i])
        res = np.int32(0)
        for k in range(3):
            s = np.int32(8 * k)
            top = F32((a >> s) & m) * bx + F32((b >> s) & m) * ax
            bot = F32((c >> s) & m) * bx + F32((d >> s) & m) * ax
            val = min(max(top * by + bot * ay + F32(0.5), F32(0.0)), F32(255.0))
            res |= np.int32(val) << s
        out[i] = np.uint32(res)


@njit(inline="always", **_JIT)
def _store_rgb_row(row_packed, out_rgb, out_words, y):
    """Row ``y`` of 0x00BBGGRR pixels into (H, W, 3) uint8 ``out_rgb``.

    When a row is a whole number of 32-bit words (W divisible by 4) and
    ``out_words`` views ``out_rgb``'s memory, four pixels go out as three words
    (vectorizes); otherwise byte by byte.
    """
    w = out_rgb.shape[1]
    if out_words.size == 0 or w % 4 != 0:
        m8 = np.uint32(255)
        for x in range(w):
            c = row_packed[x]
            out_rgb[y, x, 0] = np.uint8(c & m8)
            out_rgb[y, x, 1] = np.uint8((c >> np.uint32(8)) & m8)
            out_rgb[y, x, 2] = np.uint8((c >> np.uint32(16)) & m8)
        return
    base = y * (w * 3 // 4)
    for g in range(w // 4):
        c0, c1 = row_packed[4 * g], row_packed[4 * g + 1]
        c2, c3 = row_packed[4 * g + 2], row_packed[4 * g + 3]
        # Little-endian bytes R0 G0 B0 R1 | G1 B1 R2 G2 | B2 R3 G3 B3
        out_words[base + 3 * g] = c0 | (c1 << np.uint32(24))
        out_words[base + 3 * g + 1] = (c1 >> np.uint32(8)) | (c2 << np.uint32(16))
        out_words[base + 3 * g + 2] = (c2 >> np.uint32(16)) | (c3 << np.uint32(8))


@njit(parallel=True, **_JIT)
def pixel_stage(
    zbuf,
    u_map,
    v_map,
    depth_eff,
    dynamic,
    packed,
    fm,
    gm,
    zi0,
    zi1,
    shear,
    tolerance,
    min_shift,
    iterations,
    out_rgb,
    out_words,
    out_depth,
    holes,
    no_colour,
):
    """``mpe._predict`` after the raster: shear correction, colour, depth, hole masks.

    Flat (H * W,) arrays except ``out_depth`` (H, W) and ``out_rgb`` (H, W, 3) uint8
    (``out_words``: the same memory as uint32 words, see ``_store_rgb_row``);
    ``packed`` holds the cached RGB as 0x00BBGGRR; ``fm``/``gm`` are float32 (4, 4).
    Work goes row by row in passes over row buffers: the arithmetic passes vectorize, the
    gathers (depth and colour at data-dependent positions) stay scalar.
    """
    h, w = out_depth.shape
    zi0, zi1 = F32(zi0), F32(zi1)
    tolerance = F32(tolerance)
    shift2 = F32(min_shift) * F32(min_shift)
    n_blocks = (h + ROW_BLOCK - 1) // ROW_BLOCK
    for blk in prange(n_blocks):
        f4 = np.empty((9, w), np.float32)
        u, v, d0, d1, z, qx, qy, fx, fy = (
            f4[0],
            f4[1],
            f4[2],
            f4[3],
            f4[4],
            f4[5],
            f4[6],
            f4[7],
            f4[8],
        )
        i4 = np.empty((6, w), np.int32)
        src, prev, i00, i01, i10, i11 = i4[0], i4[1], i4[2], i4[3], i4[4], i4[5]
        u4 = np.empty((5, w), np.uint32)
        b1 = np.empty((3, w), np.bool_)
        ok, agree, cov = b1[0], b1[1], b1[2]
        for y in range(blk * ROW_BLOCK, min(h, (blk + 1) * ROW_BLOCK)):
            row = y * w
            cy = F32(y) + F32(0.5)
            for x in range(w):
                u[x] = u_map[row + x]
                v[x] = v_map[row + x]
                cov[x] = zbuf[row + x] < np.inf
            for x in range(w):
                src[x] = _nearest(u[x], v[x], w, h)
            _gather(w, depth_eff, src, d0)
            _reproject_row(0, w, cy, u, v, d0, fm, gm, zi1, w, z, qx, qy, ok, prev, h)
            for x in range(w):
                out_depth[y, x] = min(max(z[x], F32(0.0)), F32(1.0)) if cov[x] else F32(1.0)
            _gather(w, depth_eff, prev, d1)
            _agree_row(w, d0, d1, qx, qy, ok, zi0, tolerance, w, h, agree)
            if shear:
                for it in range(iterations):
                    for x in range(w):
                        # Every operand loaded before the selects: a load inside a
                        # conditional keeps LLVM from vectorizing the loop.
                        take = agree[x]
                        ax, ay, bx, by = qx[x], qy[x], u[x], v[x]
                        new_src, old_src = prev[x], src[x]
                        if shift2 > 0.0:
                            dx, dy = ax - bx, ay - by
                            take = take & (dx * dx + dy * dy > shift2)
                        u[x] = ax if take else bx
                        v[x] = ay if take else by
                        src[x] = new_src if take else old_src
                    if it + 1 < iterations:
                        _gather(w, depth_eff, src, d0)
                        # z of later steps is unused: the output depth is the first step's.
                        _reproject_row(0, w, cy, u, v, d0, fm, gm, zi1, w, d1, qx, qy, ok, prev, h)
                        _gather(w, depth_eff, prev, d1)
                        _agree_row(w, d0, d1, qx, qy, ok, zi0, tolerance, w, h, agree)
            for x in range(w):
                nc = (not cov[x]) | dynamic[src[x]]
                no_colour[row + x] = nc
                holes[row + x] = nc | (not agree[x])
            _bilinear_row(
                w,
                packed,
                u,
                v,
                w,
                h,
                i00,
                i01,
                i10,
                i11,
                fx,
                fy,
                u4[0],
                u4[1],
                u4[2],
                u4[3],
                u4[4],
            )
            _store_rgb_row(u4[4], out_rgb, out_words, y)
