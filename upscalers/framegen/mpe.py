"""Mesh Projection Estimation (Arena Breakout, GDC): per-vertex reprojection of a screen mesh.

``observe`` caches the frame; ``predict`` builds the SSAM (``mesh.py``: tile
vertices at the largest depth gradient, tensile correction, pinned edges),
rasterizes it at the cached size with a depth test (``raster.py``) and runs
the pixel stage below, then samples the cached colour bilinearly.

Pixel stage (the paper's pixel shader), per covered pixel with interpolated
source UV ``uv``:

1. ``d0`` = cached depth at ``uv``; reprojecting (uv, d0) gives the output
   depth ``z`` ("reproject depth for higher precision").
2. Shear correction: inverse-reproject this pixel with ``z`` into the cached
   frame -> ``prev``; when the cached depth at ``prev`` agrees with ``d0``
   (same surface, relative view-depth difference under ``shear_tolerance``),
   ``prev`` is the exact per-pixel source and replaces the mesh's
   interpolated ``uv``; otherwise ``uv`` stays. ``shear_iterations`` > 1
   repeats the step from the new UV (the paper does one).

Holes (``Prediction.holes``): no triangle covers the pixel, the source lies
under a dynamic object (filled by pull-push, the game draws its moving
objects there), the true source is off the cached screen (pinned-edge
stretch), or the depth check disagrees (disocclusion: the surface was hidden
in the cached frame; the tensile correction gives it background colour).

Backends (``MpeOptions.backend``): this file is the torch implementation, the
reference and the CUDA path; on the CPU the same steps run as compiled numba
loops (``mpe_cpu.py``, ``cpu_kernels.py``), with the same options and outputs,
because eager torch pays for every 230k-pixel intermediate tensor.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

import numpy.typing as npt
import torch

from server.frames.frame import FrameFlags, RenderFrame
from upscalers.framegen.base import (
    CachedFrame,
    FramePredictor,
    Prediction,
    reprojection_from,
    to_prediction,
)
from upscalers.framegen.fill import pull_push_fill
from upscalers.framegen.geometry import Reprojection, pixel_space_matrices, sky_as_direction
from upscalers.framegen.mesh import MeshOptions, build_mesh
from upscalers.framegen.mpe_options import MpeOptions
from upscalers.framegen.raster import rasterize
from upscalers.framegen.sample import bilinear, inside, nearest_index, to_texture
from upscalers.kernels.readiness import kernels_ready

if TYPE_CHECKING:
    from upscalers.framegen.mpe_cpu import HostMeshProjection


def _resolve_backend(backend: str, device: torch.device) -> Literal["torch", "numba"]:
    if backend == "torch" or (backend == "auto" and device.type != "cpu"):
        return "torch"
    if backend == "auto" and not kernels_ready("MPE frame prediction"):
        return "torch"
    if backend in ("auto", "numba"):
        if device.type != "cpu":
            raise ValueError(f"MpeOptions.backend 'numba' runs on the CPU, not on {device}")
        return "numba"
    raise ValueError(f"MpeOptions.backend must be auto, torch or numba, got {backend!r}")


class MeshProjectionPredictor(FramePredictor):
    name = "mpe"

    def __init__(
        self, options: MpeOptions | None = None, device: str | torch.device | None = None
    ) -> None:
        super().__init__(device)
        self.options = options or MpeOptions()
        if not 2 <= self.options.tile <= 64:
            raise ValueError(f"tile must be in [2, 64] pixels, got {self.options.tile}")
        self.backend = _resolve_backend(self.options.backend, self.device)
        self._host: HostMeshProjection | None = None
        if self.backend == "numba":
            # Imported here: numba (and compiling its kernels) is paid only by CPU users.
            from upscalers.framegen.mpe_cpu import HostMeshProjection, warm_up

            warm_up(self.options)
            self._host = HostMeshProjection(self.options)

    def reset(self) -> None:
        super().reset()
        if self._host is not None:
            self._host.reset()

    def observe(self, frame: RenderFrame) -> None:
        if self._host is None:
            super().observe(frame)
        else:
            self._host.observe(frame)

    def predict(
        self, view: npt.ArrayLike, proj: npt.ArrayLike, flags: FrameFlags = FrameFlags.NONE
    ) -> Prediction | None:
        host = self._host
        if host is None:
            return super().predict(view, proj, flags)
        cached = host.frame
        camera = None if cached is None else (cached.view, cached.proj)
        reproj = reprojection_from(camera, view, proj, flags)
        return None if reproj is None else host.predict(reproj)

    def _predict(self, cache: CachedFrame, reproj: Reprojection) -> Prediction:
        o = self.options
        w, h = cache.size
        dev = self.device
        depth_raw = cache.depth
        if bool(cache.dynamic.any()):
            # Dynamic pixels carry the moving object's depth: guess the static
            # background behind them from the surroundings for the mesh.
            depth_raw = pull_push_fill(depth_raw[..., None], cache.dynamic)[..., 0]
        depth_eff = sky_as_direction(depth_raw, reproj.cached_z_inf)
        fwd64 = torch.as_tensor(reproj.forward, dtype=torch.float64, device=dev)
        tris = build_mesh(
            depth_eff,
            depth_raw,
            cache.dynamic,
            fwd64,
            MeshOptions(o.tile, o.tensile, o.tensile_threshold_px),
        )
        ras = rasterize(tris, w, h, max(16, int(o.max_bbox_share * w * h)))
        u, v = ras.attrs

        f_pix, g_pix = pixel_space_matrices(reproj, w, h)
        fm, gm = f_pix.tolist(), g_pix.tolist()
        zi0, zi1 = reproj.cached_z_inf, reproj.new_z_inf
        flat_depth = depth_eff.view(-1)
        xs = torch.arange(w, device=dev, dtype=torch.float32) + 0.5
        ys = torch.arange(h, device=dev, dtype=torch.float32) + 0.5
        # The z-free part of G is affine over the screen: one broadcast add per row.
        base = [((ys * gm[i][1] + gm[i][3])[:, None] + xs * gm[i][0]).view(-1) for i in (0, 1, 3)]

        def step(
            u: torch.Tensor, v: torch.Tensor
        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
            """Source depth, reprojected depth, where this pixel came from, and validity."""
            d0 = flat_depth.index_select(0, nearest_index(u, v, w, h))
            cz = (d0 * fm[2][2]).add_(u, alpha=fm[2][0]).add_(v, alpha=fm[2][1]).add_(fm[2][3])
            cw = (d0 * fm[3][2]).add_(u, alpha=fm[3][0]).add_(v, alpha=fm[3][1]).add_(fm[3][3])
            ok = cw > 1e-6
            z = torch.where(d0 > 1.0, zi1, cz.div_(cw.clamp_min_(1e-6)))  # sky stays at infinity
            px = torch.add(base[0], z, alpha=gm[0][2])
            py = torch.add(base[1], z, alpha=gm[1][2])
            pw = torch.add(base[2], z, alpha=gm[3][2])
            ok &= pw > 1e-6
            inv = pw.clamp_min_(1e-6).reciprocal_()
            return d0, z, px.mul_(inv), py.mul_(inv), ok

        def consistent(
            d0: torch.Tensor, qx: torch.Tensor, qy: torch.Tensor, ok: torch.Tensor
        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            """Whether the cached depth where the pixel came from matches ``d0``."""
            idx = nearest_index(qx, qy, w, h)
            d1 = flat_depth.index_select(0, idx)
            seen = ok & inside(qx, qy, w, h)
            tol = (zi0 - torch.maximum(d0, d1)).clamp_min_(0.0).mul_(o.shear_tolerance).add_(1e-7)
            return seen, seen & ((d1 - d0).abs_() <= tol), idx

        d0, z, qx, qy, ok = step(u, v)
        _, agree, prev_idx = consistent(d0, qx, qy, ok)
        src = nearest_index(u, v, w, h)
        if o.shear:
            for it in range(o.shear_iterations):
                take = agree
                if o.shear_min_shift_px > 0.0:
                    take = take & (torch.hypot(qx - u, qy - v) > o.shear_min_shift_px)
                u = torch.where(take, qx, u)
                v = torch.where(take, qy, v)
                src = torch.where(take, prev_idx, src)
                if it + 1 < o.shear_iterations:
                    d0, _, qx, qy, ok = step(u, v)
                    _, agree, prev_idx = consistent(d0, qx, qy, ok)

        no_colour = ~ras.covered | cache.dynamic.view(-1).index_select(0, src)
        holes = no_colour | ~agree
        color = bilinear(to_texture(cache.color), u, v).view(h, w, 3)
        color = pull_push_fill(color, no_colour.view(h, w))
        depth = torch.where(ras.covered, z.clamp_(0.0, 1.0), 1.0)
        return to_prediction(
            color, holes.view(h, w), depth.view(h, w), cache.frame_id, no_colour.view(h, w)
        )
