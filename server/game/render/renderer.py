"""The reference game renderer: scene + camera + input -> G-buffers of the frame contract.

Previous-frame state: the camera and object poses of the previous frame are
those at ``prev_t``, which defaults to the ``t`` of the last ``render`` call
(with the player input as it was then). The first call, frame index 0 and any
frame whose (prev_t, t] spans a scene cut carry RESET, with prev matrices equal
to the current ones and zero motion.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from server.frames.frame import Camera, F32Array, FrameFlags, FrameMeta, RenderFrame, Size, U8Array
from server.game.render.camera import CameraInput, CameraPose, GameCamera, InputState
from server.game.render.intersect import ClassHits, depth_pass, fmask
from server.game.render.mip_bias import game_lod_bias
from server.game.render.motion import depth_from_s, object_motion, static_motion
from server.game.render.rays import FrameSetup, ObjectInstance, RayGrid, make_grid
from server.game.render.scene import Scene
from server.game.render.scenes import make_scene
from server.game.render.shading import encode_srgb_into, shade, shade_ground, sky_into
from server.game.render.surfaces import (
    MaterialEntry,
    S,
    ground_surface,
    material_entry,
    object_surface,
    sun_direction,
)
from server.game.render.textures import TextureAtlas, texture_atlas
from server.game.render.transforms import jitter_offset, jitter_phase_count, perspective

# Rows per band when supersampling, bounding temporaries to a few hundred MB.
MAX_BAND_PIXELS = 1 << 20


@dataclass
class RenderTargets:
    """Where a frame's planes go; may be views into a shared-memory ring slot."""

    color: U8Array  # (H, W, 3)
    depth: F32Array  # (H, W)
    motion: F32Array  # (H, W, 2)
    dynamic_mask: U8Array  # (H, W)

    @classmethod
    def allocate(cls, size: Size) -> RenderTargets:
        w, h = size
        return cls(
            np.empty((h, w, 3), np.uint8),
            np.empty((h, w), np.float32),
            np.empty((h, w, 2), np.float32),
            np.empty((h, w), np.uint8),
        )

    def check(self, size: Size) -> None:
        w, h = size
        expected = {
            "color": ((h, w, 3), np.uint8),
            "depth": ((h, w), np.float32),
            "motion": ((h, w, 2), np.float32),
            "dynamic_mask": ((h, w), np.uint8),
        }
        for name, (shape, dtype) in expected.items():
            arr = getattr(self, name)
            if arr.shape != shape or arr.dtype != dtype:
                raise ValueError(
                    f"target {name} must be {dtype.__name__}{shape}, got {arr.dtype}{arr.shape}"
                )


@dataclass
class _Band:
    color: torch.Tensor  # (3, rows, W) linear planes
    s: torch.Tensor | None = None  # (rows, W) inverse view depth, 0 = sky
    motion: tuple[torch.Tensor, torch.Tensor] | None = None  # x, y planes
    mask: torch.Tensor | None = None


@dataclass
class _ShadedObjects:
    """The pixels bounded objects won in a band, with their s and linear colour."""

    pix: torch.Tensor  # (n,) flat index into the band
    s: torch.Tensor  # (n,) inverse view depth
    planes: list[torch.Tensor]  # 3 x (n,) linear colour
    # (class hits, object column, instance, local hit points) of each moving object
    moving: list[tuple[ClassHits, int, ObjectInstance, torch.Tensor]]


def _camera_of(setup: FrameSetup) -> Camera:
    f32 = np.float32
    return Camera(
        setup.view.astype(f32),
        setup.proj.astype(f32),
        setup.prev_view.astype(f32),
        setup.prev_proj.astype(f32),
        setup.near,
        setup.far,
        setup.fov_y_deg,
    )


def _row_span(rows: torch.Tensor) -> tuple[int, int]:
    """[first, last + 1) of the True entries of a (rows,) bool tensor, (0, 0) if none."""
    idx = rows.nonzero()
    if idx.numel() == 0:
        return 0, 0
    return int(idx[0, 0]), int(idx[-1, 0]) + 1


class Renderer:
    """Renders one named scene at ``render_size``; see the module doc for prev-frame state.

    Texture mips: a jittered render feeds a temporal upscaler, which gathers the
    display size's detail over several frames, so by default it picks the mips
    of the display size (LOD bias log2(render / display) = -log2(scale), as the
    FSR and DLSS integration guides ask); an unjittered render feeds a spatial
    upscaler, which cannot resolve more than one frame's detail, and keeps the
    render size's mips (finer ones would only alias). ``texture_lod_bias``
    fixes the bias for every frame instead (> 0 picks blurrier mips: tests that
    check geometry by warping use it so texture detail does not dominate the
    resampling error). The ground truth always picks the display size's mips.
    """

    def __init__(
        self,
        scene_name: str,
        render_size: Size,
        *,
        seed: int = 0,
        jitter: bool = True,
        jitter_phases: int | None = None,
        scale: float = 2.0,
        device: str = "cpu",
        texture_lod_bias: float | None = None,
    ) -> None:
        self.scene: Scene = make_scene(scene_name, seed)
        self.render_size = Size(*render_size)
        self.jitter = jitter
        self.scale = scale
        self.jitter_phases = (
            jitter_phases if jitter_phases is not None else jitter_phase_count(scale)
        )
        self.device = torch.device(device)
        self.atlas: TextureAtlas = texture_atlas(str(self.device))
        self.fixed_lod_bias = texture_lod_bias
        self._entries_by_bias: dict[float, dict[str, MaterialEntry]] = {}
        self.game_camera = GameCamera()
        self._last_t: float | None = None
        self._last_input: InputState = self.game_camera.state

    @property
    def texture_lod_bias(self) -> float:
        """The mip bias of the next frame (see the class doc)."""
        if self.fixed_lod_bias is not None:
            return self.fixed_lod_bias
        return game_lod_bias(self.jitter, self.scale)

    @property
    def entries(self) -> dict[str, MaterialEntry]:
        """Material table of the next frame, for its mip bias (built once per bias)."""
        return self._entries_for(self.texture_lod_bias)

    def _entries_for(self, bias: float) -> dict[str, MaterialEntry]:
        entries = self._entries_by_bias.get(bias)
        if entries is None:
            entries = {
                name: material_entry(m, self.atlas, bias)
                for name, m in self.scene.materials.items()
            }
            self._entries_by_bias[bias] = entries
        return entries

    def scene_cut_between(self, t0: float, t1: float) -> bool:
        return self.scene.cut_between(t0, t1)

    def apply_input(self, event: CameraInput) -> None:
        """Player input, applied from the next rendered frame on."""
        self.game_camera.apply_input(event)

    def set_jitter(self, on: bool) -> None:
        """Jitter the camera (temporal upscalers) or not (spatial ones), from the next frame."""
        self.jitter = on
        self.jitter_phases = jitter_phase_count(self.scale)

    def set_render_size(self, render_size: Size, scale: float) -> None:
        """Render at another size from the next frame on (the player changed the scale).

        The next frame is a RESET frame: its motion vectors and every upscaler's
        history refer to the old size, so temporal methods must restart."""
        self.jitter_phases = jitter_phase_count(scale)
        self.render_size = Size(*render_size)
        self.scale = scale
        self._last_t = None

    def jitter_for(self, frame_index: int) -> tuple[float, float]:
        return jitter_offset(frame_index, self.jitter_phases) if self.jitter else (0.0, 0.0)

    def camera_pose(self, t: float, state: InputState | None = None) -> CameraPose:
        return self.game_camera.pose(self.scene.camera(t), state)

    def _setup(
        self, t: float, prev_t: float, size: Size, reset: bool, prev_input: InputState
    ) -> FrameSetup:
        sc = self.scene
        pose = self.camera_pose(t)
        prev_pose = pose if reset else self.camera_pose(prev_t, prev_input)
        proj = perspective(sc.fov_y_deg, size.width / size.height, sc.near, sc.far)
        instances = []
        for i, obj in enumerate(sc.objects):
            world = obj.pose_at(t).matrix()
            prev_world = world if reset or not obj.moving else obj.pose_at(prev_t).matrix()
            instances.append(ObjectInstance(i, obj, world, prev_world))
        return FrameSetup(
            pose.rotation(),
            np.asarray(pose.position, dtype=np.float64),
            pose.view_matrix(),
            proj,
            prev_pose.view_matrix(),
            proj,
            sc.fov_y_deg,
            sc.near,
            sc.far,
            tuple(instances),
        )

    def _shade_objects(
        self,
        classes: list[ClassHits],
        setup: FrameSetup,
        grid: RayGrid,
        sun: np.ndarray,
        entries: dict[str, MaterialEntry],
    ) -> _ShadedObjects | None:
        """Linear colour of every pixel won by a bounded object; None if there is none."""
        surfs: list[torch.Tensor] = []
        pix: list[torch.Tensor] = []
        moving = []
        for hits in classes:
            rows, q = object_surface(hits, entries, grid, sun)
            surfs.append(rows)
            pix.append(hits.pix)
            moving += [(hits, k, inst, q) for k, inst in enumerate(hits.insts) if inst.obj.moving]
        if not surfs:
            return None
        surf_all = surfs[0] if len(surfs) == 1 else torch.cat(surfs, dim=1)
        pix_all = pix[0] if len(pix) == 1 else torch.cat(pix)
        planes = shade(self.atlas, surf_all, self.scene.lighting, setup.far, surf_all[S])
        return _ShadedObjects(pix_all, surf_all[S], planes, moving)

    def _trace(
        self,
        setup: FrameSetup,
        grid: RayGrid,
        gbuffers: bool,
        motion: bool,
        entries: dict[str, MaterialEntry],
    ) -> _Band:
        """Colour (and optionally s, motion, mask) of one band of rays, textured by ``entries``."""
        lighting = self.scene.lighting
        sun = sun_direction(lighting)
        dp = depth_pass(setup, grid)
        s = dp.s
        color = torch.empty(3, grid.rows, grid.width, device=grid.xs.device)
        multi = len(dp.grounds) > 1
        if multi:
            color.zero_()
        a0, a1 = _row_span(s.amin(dim=1) <= 0.0)
        if a1 > a0:
            sky_into(color[:, a0:a1], grid, lighting, a0, a1)
        for g in dp.grounds:
            b0, b1 = _row_span(g.s.amax(dim=1) > 0.0)
            if b1 <= b0:
                continue
            surf = ground_surface(g, entries, setup, grid, (b0, b1), sun)
            planes = shade_ground(self.atlas, surf, lighting, setup.far)
            # Rows that may hold other pixels (sky, another ground) blend by coverage.
            c0, c1 = (b0, b1) if multi else (max(a0, b0), min(a1, b1))
            mask = fmask(torch.gt, g.s[c0:c1], 0.0) if c1 > c0 else None
            for ch, plane in enumerate(planes):
                dst = color[ch, b0:b1]
                if mask is None:
                    dst.copy_(plane)
                    continue
                if not multi:
                    dst[: c0 - b0].copy_(plane[: c0 - b0])
                    dst[c1 - b0 :].copy_(plane[c1 - b0 :])
                part = dst[c0 - b0 : c1 - b0]
                part.lerp_(plane[c0 - b0 : c1 - b0], mask)
        shaded = self._shade_objects(dp.classes, setup, grid, sun, entries)
        if shaded is not None:
            for ch, plane in enumerate(shaded.planes):
                color[ch].view(-1).index_copy_(0, shaded.pix, plane)
        moving = [] if shaded is None else shaded.moving
        band = _Band(color)
        if not gbuffers:
            return band
        band.s = s
        band.mask = torch.zeros(grid.rows, grid.width, dtype=torch.uint8, device=grid.xs.device)
        if motion:
            band.motion = static_motion(setup, grid, s)
        for hits, k, inst, q in moving:
            sel = (hits.oid == k).nonzero().view(-1)
            if sel.numel() == 0:
                continue
            p = hits.pix.index_select(0, sel)
            band.mask.view(-1).index_fill_(0, p, 1)
            if band.motion is not None:
                mv = object_motion(setup, grid, inst.world, inst.prev_world, q.index_select(1, sel))
                for plane, vals in zip(band.motion, mv, strict=True):
                    plane.view(-1).index_copy_(0, p, vals)
        return band

    def _linear_color(
        self,
        setup: FrameSetup,
        size: Size,
        jitter: tuple[float, float],
        ss: int,
        entries: dict[str, MaterialEntry],
    ) -> torch.Tensor:
        """(3, H, W) linear colour averaged over an ss x ss grid of subsamples per pixel."""
        w, h = size.width * ss, size.height * ss
        out = torch.empty(3, size.height, size.width, device=self.device)
        band_rows = max(ss, (MAX_BAND_PIXELS // w) // ss * ss)
        for y0 in range(0, h, band_rows):
            y1 = min(h, y0 + band_rows)
            grid = make_grid(setup, w, h, (jitter[0] * ss, jitter[1] * ss), y0, y1, self.device)
            col = self._trace(setup, grid, gbuffers=False, motion=False, entries=entries).color
            rows = (y1 - y0) // ss
            pooled = col.view(3, rows, ss, size.width, ss).mean(dim=(2, 4))
            out[:, y0 // ss : y0 // ss + rows] = pooled
        return out

    def render(
        self,
        frame_index: int,
        t: float,
        targets: RenderTargets | None = None,
        *,
        prev_t: float | None = None,
        supersample: int = 1,
    ) -> RenderFrame:
        """Render frame ``frame_index`` at time ``t`` into ``targets`` (allocated if None).

        ``supersample`` > 1 averages the colour over a regular grid of subsamples
        per pixel (depth, motion and mask stay single-sample): for tests that
        want geometry without texture aliasing.
        """
        size = self.render_size
        if targets is None:
            targets = RenderTargets.allocate(size)
        targets.check(size)
        if prev_t is None:
            prev_t = self._last_t
        reset = frame_index == 0 or prev_t is None or self.scene.cut_between(prev_t, t)
        prev = t if prev_t is None or reset else prev_t
        setup = self._setup(t, prev, size, reset, self._last_input)
        jit = self.jitter_for(frame_index)
        grid = make_grid(setup, size.width, size.height, jit, 0, size.height, self.device)
        band = self._trace(setup, grid, gbuffers=True, motion=not reset, entries=self.entries)
        assert band.s is not None and band.mask is not None
        color = (
            band.color
            if supersample <= 1
            else self._linear_color(setup, size, jit, supersample, self.entries)
        )
        encode_srgb_into(color, torch.from_numpy(targets.color))
        depth = torch.from_numpy(targets.depth)
        depth_from_s(band.s, setup, out=depth).nan_to_num_(nan=1.0)
        motion = torch.from_numpy(targets.motion)
        if band.motion is None:  # RESET: no previous frame to move from
            motion.zero_()
        else:
            lim = 4.0 * max(size)
            for ch, plane in enumerate(band.motion):
                plane.nan_to_num_(nan=0.0, posinf=lim, neginf=-lim).clamp_(-lim, lim)
                motion[..., ch].copy_(plane)
        torch.from_numpy(targets.dynamic_mask).copy_(band.mask)
        self._last_t = t
        self._last_input = self.game_camera.state
        meta = FrameMeta(
            frame_index, _camera_of(setup), jit, FrameFlags.RESET if reset else FrameFlags.NONE
        )
        return RenderFrame(targets.color, targets.depth, targets.motion, targets.dynamic_mask, meta)

    def render_dynamic(
        self, frame_index: int, t: float, targets: RenderTargets | None = None
    ) -> RenderFrame:
        """Only the scene's moving objects at ``t``, for frame generation (flag PREDICTED).

        The worker predicts the static world from the last full render and
        composites this layer over it by depth test, so here the moving objects
        are drawn against nothing: static geometry does not occlude them (the
        worker's depth test does that), and no ground or sky is traced. Where a
        moving object is seen: its shaded sRGB colour, NDC depth and mask 1;
        elsewhere colour 0, depth 1.0, mask 0; motion is 0 everywhere. The
        shading is the full render's for the same surface (the renderer casts no
        shadows, so static objects do not change how a moving one is lit).

        Unjittered, with the camera of ``t`` and, as prev, the camera of the
        last full ``render`` (the frame the worker predicts from; RESET too if
        there was none). The previous-frame state is left alone: the next full
        render's motion still spans from the last full render.
        """
        size = self.render_size
        if targets is None:
            targets = RenderTargets.allocate(size)
        targets.check(size)
        last_t = self._last_t
        no_full_render = last_t is None
        full = self._setup(
            t, t if last_t is None else last_t, size, no_full_render, self._last_input
        )
        moving = tuple(inst for inst in full.instances if inst.obj.moving)
        setup = dataclasses.replace(full, instances=moving)
        grid = make_grid(setup, size.width, size.height, (0.0, 0.0), 0, size.height, self.device)
        targets.color.fill(0)
        targets.depth.fill(1.0)
        targets.motion.fill(0.0)
        targets.dynamic_mask.fill(0)
        shaded = (
            self._shade_objects(
                depth_pass(setup, grid).classes,
                setup,
                grid,
                sun_direction(self.scene.lighting),
                self.entries,
            )
            if moving
            else None
        )
        if shaded is not None:
            n = shaded.pix.numel()
            rgb = torch.empty(1, n, 3, dtype=torch.uint8, device=self.device)
            encode_srgb_into(torch.stack(shaded.planes).view(3, 1, n), rgb)
            torch.from_numpy(targets.color).view(-1, 3).index_copy_(0, shaded.pix, rgb.view(n, 3))
            depth = depth_from_s(shaded.s, setup).nan_to_num_(nan=1.0)
            torch.from_numpy(targets.depth).view(-1).index_copy_(0, shaded.pix, depth)
            torch.from_numpy(targets.dynamic_mask).view(-1).index_fill_(0, shaded.pix, 1)
        flags = FrameFlags.PREDICTED | (FrameFlags.RESET if no_full_render else FrameFlags.NONE)
        meta = FrameMeta(frame_index, _camera_of(setup), (0.0, 0.0), flags)
        return RenderFrame(targets.color, targets.depth, targets.motion, targets.dynamic_mask, meta)

    def render_ground_truth(self, t: float, display_size: Size, supersample: int = 3) -> U8Array:
        """Display-size sRGB at ``t``: unjittered, ss x ss subsamples averaged in linear light.

        It picks the display size's mips (bias 0) whatever the renders use: the
        reference is what a native display-size render would show."""
        size = Size(*display_size)
        setup = self._setup(t, t, size, True, self.game_camera.state)
        color = self._linear_color(
            setup, size, (0.0, 0.0), max(1, supersample), self._entries_for(0.0)
        )
        out = np.empty((size.height, size.width, 3), np.uint8)
        encode_srgb_into(color, torch.from_numpy(out))
        return out
