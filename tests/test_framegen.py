"""Frame generation: the predictor contract, MPE geometry edge cases, quality over baselines."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from server.frames.frame import Camera, FrameFlags, FrameMeta, RenderFrame, Size
from server.game.render.camera import CameraInput
from server.game.render.renderer import Renderer
from server.game.render.transforms import perspective, rigid, rotation_y
from upscalers import metrics
from upscalers.framegen import (
    PREDICTORS,
    FramePredictor,
    MeshProjectionPredictor,
    MpeOptions,
    create,
)
from upscalers.framegen.mesh import vertex_pixels

SMALL = Size(160, 90)
REGISTERED = ("repeat", "splat", "backward_warp", "mpe")
# "mpe" is the default backend (numba on the CPU); "mpe_torch" the torch reference path.
ALL = (*REGISTERED, "mpe_torch")
BACKENDS = ("numba", "torch")


def _create(name: str) -> FramePredictor:
    if name == "mpe_torch":
        return MeshProjectionPredictor(MpeOptions(backend="torch"), "cpu")
    return create(name, "cpu")


def _copy(f: RenderFrame) -> RenderFrame:
    return RenderFrame(
        f.color.copy(), f.depth.copy(), f.motion.copy(), f.dynamic_mask.copy(), f.meta
    )


def _frame(
    color: np.ndarray, depth: np.ndarray, view: np.ndarray, proj: np.ndarray, frame_id: int = 0
) -> RenderFrame:
    h, w = depth.shape
    f32 = np.float32
    cam = Camera(
        view.astype(f32), proj.astype(f32), view.astype(f32), proj.astype(f32), 0.1, 200.0, 60.0
    )
    return RenderFrame(
        color.astype(np.uint8),
        depth.astype(f32),
        np.zeros((h, w, 2), f32),
        np.zeros((h, w), np.uint8),
        FrameMeta(frame_id, cam),
    )


def _proj(size: Size) -> np.ndarray:
    return perspective(60.0, size.width / size.height, 0.1, 200.0)


def _yawed_view(
    yaw_deg: float, position: tuple[float, float, float] = (0.0, 0.0, 0.0)
) -> np.ndarray:
    """World -> view of a camera at ``position`` turned by ``yaw_deg`` about +y."""
    cam_to_world = rigid(rotation_y(math.radians(yaw_deg)), np.asarray(position, dtype=np.float64))
    return np.linalg.inv(cam_to_world)


def _pair(scene: str, size: Size, t: float, dt: float = 1 / 60) -> tuple[RenderFrame, RenderFrame]:
    r = Renderer(scene, size, jitter=False)
    first = _copy(r.render(0, t))
    return first, r.render(1, t + dt)


def test_registry_names_and_unknown() -> None:
    assert set(REGISTERED) <= set(PREDICTORS)
    for name in REGISTERED:
        assert create(name, "cpu").name == name
    with pytest.raises(ValueError, match="allowed"):
        create("nope")


@pytest.mark.parametrize("name", ALL)
def test_nothing_to_predict_before_observe_and_after_reset(name: str) -> None:
    first, second = _pair("slow_pan", SMALL, 0.3)
    p = _create(name)
    cam = second.meta.camera
    assert p.predict(cam.view, cam.proj) is None  # first frame: nothing cached
    p.observe(first)
    assert p.predict(cam.view, cam.proj) is not None
    p.reset()
    assert p.predict(cam.view, cam.proj) is None


@pytest.mark.parametrize("name", ALL)
def test_no_prediction_across_a_scene_cut(name: str) -> None:
    # scene_cut jumps at t = 1.0: the frame after the cut carries RESET.
    r = Renderer("scene_cut", SMALL, jitter=False)
    before = _copy(r.render(0, 1.0 - 1 / 60))
    after = _copy(r.render(1, 1.0 + 1 / 120))
    assert after.meta.flags & FrameFlags.RESET
    p = _create(name)
    p.observe(before)
    cam = after.meta.camera
    assert p.predict(cam.view, cam.proj, after.meta.flags) is None
    # Observing the RESET frame starts afresh: predicting forward from it is fine.
    p.observe(after)
    later = r.render(2, 1.0 + 1 / 60, prev_t=1.0 + 1 / 120)
    assert not later.meta.flags & FrameFlags.RESET
    pred = p.predict(later.meta.camera.view, later.meta.camera.proj, later.meta.flags)
    assert pred is not None and pred.source_frame_id == 1


def test_fast_yaw_180_deg_per_s_beats_repeat() -> None:
    r = Renderer("static", SMALL, jitter=False)
    cached = _copy(r.render(0, 0.0))
    r.apply_input(CameraInput(dyaw_deg=180.0 / 60.0))
    truth = r.render(1, 1 / 60)
    scores = {}
    for name in ("repeat", "splat", "mpe", "mpe_torch"):
        p = _create(name)
        p.observe(cached)
        pred = p.predict(truth.meta.camera.view, truth.meta.camera.proj)
        assert pred is not None
        scores[name] = metrics.psnr(truth.color, pred.color)
    for mpe in ("mpe", "mpe_torch"):
        assert scores[mpe] > scores["repeat"] + 5.0, scores
        assert scores[mpe] > scores["splat"], scores


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("tile", [8, 16])
def test_tiles_on_sizes_they_do_not_divide(tile: int, backend: str) -> None:
    size = Size(161, 91)
    first, second = _pair("fast_yaw", size, 0.4)
    vxy = vertex_pixels(torch.from_numpy(first.depth), torch.zeros(91, 161, dtype=torch.bool), tile)
    assert vxy.shape[:2] == (-(-91 // tile), -(-161 // tile))
    assert int(vxy[..., 0].max()) < 161 and int(vxy[..., 1].max()) < 91
    p = MeshProjectionPredictor(MpeOptions(tile=tile, backend=backend), "cpu")
    p.observe(first)
    pred = p.predict(second.meta.camera.view, second.meta.camera.proj)
    assert pred is not None
    assert pred.color.shape == (91, 161, 3) and pred.holes.shape == (91, 161)
    assert np.isfinite(pred.depth).all()
    repeat = metrics.psnr(second.color, first.color)
    assert metrics.psnr(second.color, pred.color) > repeat + 4.0


@pytest.mark.parametrize("name", ALL)
def test_geometry_at_the_near_plane_and_behind_the_camera(name: str) -> None:
    size = SMALL
    rng = np.random.default_rng(1)
    color = rng.integers(0, 255, (size.height, size.width, 3))
    depth = np.zeros((size.height, size.width), np.float32)  # everything on the near plane
    depth[:, size.width // 2 :] = 0.5  # and a wall 0.2 m away
    depth[::7, ::5] = 1.0  # and some sky
    p = _create(name)
    p.observe(_frame(color, depth, np.eye(4), _proj(size)))
    # Step 1 m forward (all but the sky is now behind the eye), then turn around.
    for view in (_yawed_view(0.0, (0.0, 0.0, -1.0)), _yawed_view(180.0, (0.0, 0.0, -1.0))):
        pred = p.predict(view, _proj(size))
        assert pred is not None
        assert pred.color.dtype == np.uint8
        assert np.isfinite(pred.depth).all()
        assert ((pred.depth >= 0) & (pred.depth <= 1)).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_sky_reprojects_by_rotation_only(backend: str) -> None:
    size = Size(160, 90)
    h, w = size.height, size.width
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    proj = _proj(size)

    # Colour = a smooth function of the view direction, so any sampling position is checkable.
    def paint(dx: np.ndarray, dy: np.ndarray, dz: np.ndarray) -> np.ndarray:
        az = np.degrees(np.arctan2(dx, -dz))
        el = np.degrees(np.arctan2(dy, np.hypot(dx, dz)))
        return np.stack((128 + 3 * az, 128 + 3 * el, 128 + az + el), axis=-1)

    def directions(view: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        vx = (2 * xs / w - 1) / proj[0, 0]
        vy = (1 - 2 * ys / h) / proj[1, 1]
        rot = np.linalg.inv(view)[:3, :3]  # view -> world rotation
        d = np.stack((vx, vy, -np.ones_like(vx)), -1) @ rot.T
        return d[..., 0], d[..., 1], d[..., 2]

    cached_view = _yawed_view(10.0)
    color = paint(*directions(cached_view)).clip(0, 255).round()
    p = MeshProjectionPredictor(MpeOptions(backend=backend), "cpu")
    p.observe(_frame(color, np.ones((h, w)), cached_view, proj))
    # Turn 4 degrees and walk 20 m: sky must follow the rotation and ignore the walk.
    new_view = _yawed_view(14.0, (3.0, 1.0, -20.0))
    pred = p.predict(new_view, proj)
    assert pred is not None
    expected = paint(*directions(new_view)).clip(0, 255)
    ok = ~pred.holes
    assert ok.mean() > 0.9  # only the strip turned into view has no source
    err = np.abs(pred.color.astype(np.float64) - expected)[ok]
    assert err.mean() < 1.0 and err.max() <= 3.0
    assert (pred.depth[ok] == 1.0).all()


@pytest.mark.parametrize("name", ALL)
def test_nan_depth_is_sanitized(name: str) -> None:
    first, second = _pair("dolly", SMALL, 0.5)
    first.depth[10:30, 20:60] = np.nan
    first.depth[0, :] = np.inf
    first.depth[-1, :5] = -np.inf
    p = _create(name)
    p.observe(first)
    pred = p.predict(second.meta.camera.view, second.meta.camera.proj)
    assert pred is not None
    assert np.isfinite(pred.depth).all()
    assert pred.color.dtype == np.uint8


@pytest.mark.parametrize(
    "options",
    [
        MpeOptions(backend=backend, **kw)
        for backend in BACKENDS
        for kw in ({}, {"tile": 8}, {"tensile": False, "shear": False})
    ],
)
def test_identity_camera_reproduces_the_cached_frame(options: MpeOptions) -> None:
    r = Renderer("moving_objects", SMALL, jitter=False)
    r.render(0, 0.5)
    frame = _copy(r.render(1, 0.5 + 1 / 30))
    assert frame.dynamic_mask.any()
    p = MeshProjectionPredictor(options, "cpu")
    p.observe(frame)
    pred = p.predict(frame.meta.camera.view, frame.meta.camera.proj)
    assert pred is not None
    static = frame.dynamic_mask == 0
    assert np.array_equal(pred.color[static], frame.color[static])
    assert not pred.holes[static].any()


@pytest.mark.parametrize("name", ["splat", "backward_warp"])
def test_identity_camera_baselines(name: str) -> None:
    first, _ = _pair("static", SMALL, 0.0)
    p: FramePredictor = create(name, "cpu")
    p.observe(first)
    pred = p.predict(first.meta.camera.view, first.meta.camera.proj)
    assert pred is not None
    assert np.array_equal(pred.color, first.color)


@pytest.mark.parametrize("backend", BACKENDS)
def test_pinned_edges_keep_the_border_covered(backend: str) -> None:
    # Cache the frame a step further along the dolly, predict the camera a step back:
    # the image shrinks, so without pinned edges the border would be uncovered.
    r = Renderer("dolly", SMALL, jitter=False)
    truth = _copy(r.render(0, 0.5))
    cached = _copy(r.render(1, 0.5 + 4 / 60))
    p = MeshProjectionPredictor(MpeOptions(backend=backend), "cpu")
    p.observe(cached)
    pred = p.predict(truth.meta.camera.view, truth.meta.camera.proj)
    assert pred is not None
    border = np.zeros(pred.filled.shape, bool)
    border[[0, -1], :] = True
    border[:, [0, -1]] = True
    assert not pred.filled[border].any()  # every border pixel came from the mesh
    assert pred.holes[border].mean() > 0.5  # and is known to be a stretched guess
    splat = create("splat", "cpu")
    splat.observe(cached)
    sp = splat.predict(truth.meta.camera.view, truth.meta.camera.proj)
    assert sp is not None and sp.filled[border].mean() > 0.5
