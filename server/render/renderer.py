"""The reference game renderer: scene + camera + input -> G-buffers of the frame contract.

Previous-frame state: the camera and object poses of the previous frame are
those at ``prev_t``, which defaults to the ``t`` of the last ``render`` call
(with the player input as it was then). The first call, frame index 0 and any
frame whose (prev_t, t] spans a scene cut carry RESET, with prev matrices equal
to the current ones and zero motion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from server.frame import Camera, F32Array, FrameFlags, FrameMeta, RenderFrame, Size, U8Array
from server.render.camera import CameraInput, CameraPose, GameCamera, InputState
from server.render.intersect import depth_pass
from server.render.motion import depth_from_s, object_motion, static_motion
from server.render.rays import FrameSetup, ObjectInstance, RayGrid, make_grid
from server.render.scene import Scene
from server.render.scenes import make_scene
from server.render.shading import linear_to_srgb, quantize_into, shade, sky
from server.render.surfaces import MaterialEntry, Surface, material_entry, surface_of
from server.render.textures import TextureAtlas, texture_atlas
from server.render.transforms import jitter_offset, jitter_phase_count, perspective

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
    color: torch.Tensor  # (rows, W, 3) linear
    depth: torch.Tensor | None = None
    motion: torch.Tensor | None = None
    mask: torch.Tensor | None = None


class Renderer:
    """Renders one named scene at ``render_size``; see the module doc for prev-frame state.

    ``texture_lod_bias`` > 0 picks blurrier mip levels (tests that check geometry
    by warping use it so texture detail does not dominate the resampling error).
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
        texture_lod_bias: float = 0.0,
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
        self.entries: dict[str, MaterialEntry] = {
            name: material_entry(m, self.atlas, texture_lod_bias)
            for name, m in self.scene.materials.items()
        }
        self.game_camera = GameCamera()
        self._last_t: float | None = None
        self._last_input: InputState = self.game_camera.state

    def apply_input(self, event: CameraInput) -> None:
        """Player input, applied from the next rendered frame on."""
        self.game_camera.apply_input(event)

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

    def _trace(self, setup: FrameSetup, grid: RayGrid, gbuffers: bool) -> _Band:
        """Colour (and optionally depth, motion, mask) of one band of rays."""
        dp = depth_pass(setup, grid)
        color = sky(grid, self.scene.lighting)
        parts: list[Surface] = []
        moving: list[tuple[ObjectInstance, Surface]] = []
        for inst in setup.instances:
            surf = surface_of(inst, self.entries, setup, grid, dp)
            if surf is None:
                continue
            parts.append(surf)
            if inst.obj.moving:
                moving.append((inst, surf))
        if parts:
            hits = Surface.cat(parts)
            shaded = shade(self.atlas, hits, self.scene.lighting, setup.far)
            color.view(-1, 3).index_copy_(0, hits.flat, shaded)
        band = _Band(color)
        if not gbuffers:
            return band
        s = dp.t.reciprocal()
        s.masked_fill_(dp.ids < 0, 0.0)  # sky: a point at infinity
        band.depth = depth_from_s(s, setup)
        band.motion = static_motion(setup, grid, s)
        band.mask = torch.zeros(grid.rows, grid.width, dtype=torch.uint8, device=grid.xs.device)
        for inst, surf in moving:
            band.mask.view(-1).index_fill_(0, surf.flat, 1)
            mv = object_motion(setup, grid, inst, surf.flat, surf.t)
            band.motion.view(-1, 2).index_copy_(0, surf.flat, mv)
        return band

    def _linear_color(
        self, setup: FrameSetup, size: Size, jitter: tuple[float, float], ss: int
    ) -> torch.Tensor:
        """(H, W, 3) linear colour averaged over an ss x ss grid of subsamples per pixel."""
        w, h = size.width * ss, size.height * ss
        out = torch.empty(size.height, size.width, 3, device=self.device)
        band_rows = max(ss, (MAX_BAND_PIXELS // w) // ss * ss)
        for y0 in range(0, h, band_rows):
            y1 = min(h, y0 + band_rows)
            grid = make_grid(setup, w, h, (jitter[0] * ss, jitter[1] * ss), y0, y1, self.device)
            col = self._trace(setup, grid, gbuffers=False).color
            rows = (y1 - y0) // ss
            pooled = col.view(rows, ss, size.width, ss, 3).mean(dim=(1, 3))
            out[y0 // ss : y0 // ss + rows] = pooled
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
        band = self._trace(setup, grid, gbuffers=True)
        assert band.depth is not None and band.motion is not None and band.mask is not None
        color = (
            band.color if supersample <= 1 else self._linear_color(setup, size, jit, supersample)
        )
        if reset:
            band.motion.zero_()
        lim = 4.0 * max(size)
        motion = torch.nan_to_num(band.motion, nan=0.0, posinf=lim, neginf=-lim).clamp_(-lim, lim)
        depth = torch.nan_to_num(band.depth, nan=1.0)
        quantize_into(linear_to_srgb(color), torch.from_numpy(targets.color))
        torch.from_numpy(targets.depth).copy_(depth)
        torch.from_numpy(targets.motion).copy_(motion)
        torch.from_numpy(targets.dynamic_mask).copy_(band.mask)
        self._last_t = t
        self._last_input = self.game_camera.state
        f32 = np.float32
        camera = Camera(
            setup.view.astype(f32),
            setup.proj.astype(f32),
            setup.prev_view.astype(f32),
            setup.prev_proj.astype(f32),
            setup.near,
            setup.far,
            self.scene.fov_y_deg,
        )
        meta = FrameMeta(frame_index, camera, jit, FrameFlags.RESET if reset else FrameFlags.NONE)
        return RenderFrame(targets.color, targets.depth, targets.motion, targets.dynamic_mask, meta)

    def render_ground_truth(self, t: float, display_size: Size, supersample: int = 3) -> U8Array:
        """Display-size sRGB at ``t``: unjittered, ss x ss subsamples averaged in linear light."""
        size = Size(*display_size)
        setup = self._setup(t, t, size, True, self.game_camera.state)
        color = self._linear_color(setup, size, (0.0, 0.0), max(1, supersample))
        out = np.empty((size.height, size.width, 3), np.uint8)
        quantize_into(linear_to_srgb(color), torch.from_numpy(out))
        return out
