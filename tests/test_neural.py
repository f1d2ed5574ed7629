"""Neural upscalers: features, networks, shipped weights, history handling, training."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from server.frames.frame import RenderFrame, Size
from server.game.render.renderer import Renderer
from server.train.dataset import DatasetSpec, generate
from upscalers import metrics, registry
from upscalers.neural import conv_flops, load
from upscalers.neural.features import (
    base_phases,
    bilinear_phases,
    feature_channels,
    warp_history,
)
from upscalers.neural.network import base_of, build_model, load_checkpoint, predict
from upscalers.neural.upscaler import NeuralUpscaler, UNetUpscaler
from upscalers.output import to_uint8

NETWORKS = ("unet", "unetpp")


@pytest.fixture(scope="module")
def shipped() -> dict[str, NeuralUpscaler]:
    torch.set_num_threads(2)
    return {name: load(name, device="cpu") for name in NETWORKS}


@pytest.fixture(scope="module")
def sequence() -> tuple[list[RenderFrame], np.ndarray]:
    """Six jittered frames of a moving scene at 320x180 and the 640x360 truth of the last."""
    renderer = Renderer("slow_pan", Size(320, 180), seed=0, jitter=True, scale=2.0)
    times = [i / 60.0 for i in range(6)]
    frames = [renderer.render(i, t) for i, t in enumerate(times)]
    frames = [dataclasses.replace(f, color=f.color.copy()) for f in frames]
    truth = renderer.render_ground_truth(times[-1], Size(640, 360), 3)
    return frames, truth


def fresh(name: str) -> NeuralUpscaler:
    return load(name, device="cpu")


# -- features -------------------------------------------------------------------------


def test_untrained_network_is_exactly_bilinear() -> None:
    """The residual starts at zero, so the bilinear phases must equal F.interpolate."""
    torch.manual_seed(0)
    color = torch.rand(1, 3, 13, 17)
    feats = torch.zeros(1, feature_channels(), 13, 17)
    feats[:, :3] = color
    for name in NETWORKS:
        out = predict(build_model(name), feats, 2)
        ref = F.interpolate(color, scale_factor=2.0, mode="bilinear", align_corners=False)
        torch.testing.assert_close(out, ref.clamp(0, 1), atol=1e-6, rtol=0)
    assert bilinear_phases(color, 2).shape == (1, 12, 13, 17)


def test_jittered_base_samples_where_the_frame_sampled() -> None:
    """With jitter j, render pixel i holds the scene at i + 0.5 + j: the base must equal
    bilinear sampling at display centres shifted by -j (interior; edges are clamped)."""
    torch.manual_seed(2)
    color = torch.rand(2, 3, 9, 11)
    jitter = torch.tensor([[0.3, -0.45], [-0.2, 0.1]])
    out = F.pixel_shuffle(bilinear_phases(color, 2, jitter), 2)
    for n in range(2):
        x = (torch.arange(22) + 0.5) / 2 - jitter[n, 0]
        y = (torch.arange(18) + 0.5) / 2 - jitter[n, 1]
        grid = torch.stack(
            ((x * 2 / 11 - 1).expand(18, 22), (y * 2 / 9 - 1)[:, None].expand(18, 22)), -1
        )
        ref = F.grid_sample(
            color[n : n + 1], grid[None], padding_mode="border", align_corners=False
        )
        torch.testing.assert_close(out[n : n + 1, :, 1:-1, 1:-1], ref[..., 1:-1, 1:-1])
    # Jitter really moves it: the unjittered base differs.
    assert not torch.allclose(bilinear_phases(color, 2), bilinear_phases(color, 2, jitter))


def test_cubic_base_reproduces_quadratics_where_the_frame_sampled() -> None:
    """Catmull-Rom reproduces polynomials up to degree 2: samples of a quadratic taken
    at i + 0.5 + j must come back as the quadratic at the display centres (interior;
    edges are clamped), for any jitter. Bilinear cannot (its error is the curvature)."""
    jitter = torch.tensor([[0.3, -0.45], [-0.2, 0.1]])
    h, w = 12, 14

    def quadratic(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return 0.2 + 0.01 * x + 0.02 * y + 0.003 * x * x - 0.002 * x * y + 0.004 * y * y

    for n in range(2):
        jx, jy = float(jitter[n, 0]), float(jitter[n, 1])
        ys, xs = torch.meshgrid(torch.arange(h) + 0.5 + jy, torch.arange(w) + 0.5 + jx,
                                indexing="ij")  # fmt: skip
        color = quadratic(xs, ys).expand(1, 3, h, w).contiguous()
        dy, dx = torch.meshgrid((torch.arange(2 * h) + 0.5) / 2, (torch.arange(2 * w) + 0.5) / 2,
                                indexing="ij")  # fmt: skip
        truth = quadratic(dx, dy).expand(1, 3, 2 * h, 2 * w)
        inner = (..., slice(6, -6), slice(6, -6))
        for base, exact in (("cubic", True), ("bilinear", False)):
            out = F.pixel_shuffle(base_phases(color, 2, jitter[n : n + 1], base), 2)
            err = (out - truth)[inner].abs().max().item()
            assert (err < 1e-5) == exact, (base, err)
    with pytest.raises(ValueError, match="base"):
        base_phases(color, 2, None, "lanczos")


def test_checkpoints_keep_their_base(tmp_path: Path) -> None:
    """A network trained on one base must upscale on it: the checkpoint records it, and
    a checkpoint from before the field was written loads as bilinear."""
    from upscalers.neural.network import save_checkpoint

    model = build_model("unet", 2, base="cubic")
    save_checkpoint(tmp_path / "c.pt", "unet", model, 2, {})
    assert base_of(load_checkpoint(tmp_path / "c.pt")[1]) == "cubic"
    ckpt = torch.load(tmp_path / "c.pt", weights_only=True)
    del ckpt["base"]
    torch.save(ckpt, tmp_path / "old.pt")
    assert base_of(load_checkpoint(tmp_path / "old.pt")[1]) == "bilinear"
    # Untrained, the network is its base: cubic here, not bilinear.
    color = torch.rand(1, 3, 8, 8)
    feats = torch.zeros(1, feature_channels(2), 8, 8)
    feats[:, :3] = color
    out = predict(model, feats, 2)
    bilinear = F.interpolate(color, scale_factor=2.0, mode="bilinear", align_corners=False)
    assert not torch.allclose(out, bilinear.clamp(0, 1), atol=1e-3)
    with pytest.raises(ValueError, match="base"):
        build_model("unet", 2, base="nearest")


def test_warp_history_order_and_shift() -> None:
    torch.manual_seed(1)
    out = torch.rand(2, 3, 16, 20)
    still = torch.zeros(2, 2, 8, 10)
    torch.testing.assert_close(warp_history(out, still, 2), F.pixel_unshuffle(out, 2))
    # Motion of +1 render pixel in x fetches the display image 2 pixels to the right.
    moved = torch.zeros(2, 2, 8, 10)
    moved[:, 0] = 1.0
    got = F.pixel_shuffle(warp_history(out, moved, 2), 2)
    torch.testing.assert_close(got[..., :-2], out[..., 2:])


# -- networks and cache points --------------------------------------------------------


@pytest.mark.parametrize("name", NETWORKS)
def test_cache_points_are_called_once_per_forward(name: str) -> None:
    model = build_model(name)
    cls = type(model)
    assert cls.default_cache_config in cls.cache_configs
    calls: dict[str, int] = {}
    points = {p for cfg in cls.cache_configs.values() for p in cfg}
    for p in points:
        model.get_submodule(p).register_forward_hook(
            lambda _m, _i, _o, p=p: calls.__setitem__(p, calls.get(p, 0) + 1)
        )
    with torch.no_grad():
        model(torch.rand(1, feature_channels(), 16, 24))
    assert calls == dict.fromkeys(points, 1)


@pytest.mark.parametrize("name", NETWORKS)
def test_conv_flops_add_up(name: str) -> None:
    model = build_model(name)
    flops = conv_flops(model, (1, feature_channels(), 64, 96))
    children = [n for n, _ in model.named_children()]
    assert flops[""] == sum(flops[c] for c in children) > 0
    for cfg in type(model).cache_configs.values():
        assert 0 < sum(flops[p] for p in cfg) < flops[""]
    # One convolution by hand: the first one sees every input channel at full size.
    first = next(m for m in model.modules() if isinstance(m, torch.nn.Conv2d))
    first_name = next(n for n, m in model.named_modules() if m is first)
    expected = 64 * 96 * first.out_channels * (2 * feature_channels() * 9 + 1)
    assert flops[first_name] == expected


def test_unet_levels_remove_less_as_they_go_deeper() -> None:
    model = build_model("unet")
    f = conv_flops(model, (1, feature_channels(), 360, 640))
    level = [f[model.cache_configs[k][0]] for k in ("1", "2", "3")]
    assert level[0] > level[1] > level[2] > 0
    pp = build_model("unetpp")
    g = conv_flops(pp, (1, feature_channels(), 360, 640))
    removed = {k: sum(g[p] for p in v) for k, v in pp.cache_configs.items()}
    assert removed["B"] > removed["A"] > 0


# -- shipped weights ------------------------------------------------------------------


@pytest.mark.parametrize("name", NETWORKS)
def test_shipped_weights_load_and_are_small(name: str, shipped: dict[str, NeuralUpscaler]) -> None:
    up = shipped[name]
    path = Path(__file__).resolve().parents[1] / "upscalers" / "neural" / "weights" / f"{name}.pt"
    assert path.stat().st_size < 2_000_000
    assert up.scale == 2 and up.temporal
    assert all(torch.isfinite(p).all() for p in up.model.parameters())
    # Trained: the output convolution is no longer the zero it starts from.
    last = [m for m in up.model.modules() if isinstance(m, torch.nn.Conv2d)][-1]
    assert last.weight.abs().sum() > 0
    assert registry.is_temporal(name)
    assert isinstance(registry.create(name, device="cpu"), NeuralUpscaler)


@pytest.mark.parametrize("name", NETWORKS)
def test_beats_bilinear_on_a_rendered_frame(
    name: str, sequence: tuple[list[RenderFrame], np.ndarray]
) -> None:
    frames, truth = sequence
    up = fresh(name)
    for f in frames:
        out = up.upscale(f, Size(640, 360))
    assert out.shape == (3, 360, 640) and out.dtype == torch.float32
    assert torch.isfinite(out).all()
    ours = metrics.psnr(truth, to_uint8(out))
    bilinear = metrics.psnr(
        truth, to_uint8(registry.create("bilinear").upscale(frames[-1], Size(640, 360)))
    )
    assert ours > bilinear + 0.5, (ours, bilinear)


def test_upscale_is_features_run_remember(sequence: tuple[list[RenderFrame], np.ndarray]) -> None:
    frames, _ = sequence
    a, b = fresh("unet"), fresh("unet")
    display = Size(640, 360)
    for f in frames[:3]:
        x = b.features(f, display)
        y = b.run(x)
        b.remember(y)
        assert torch.equal(a.upscale(f, display), y[0])


def test_remember_without_features_is_refused() -> None:
    with pytest.raises(RuntimeError, match="features"):
        fresh("unet").remember(torch.zeros(1, 3, 4, 4))


# -- hard cases -----------------------------------------------------------------------


def _poisoned(frame: RenderFrame) -> RenderFrame:
    depth = frame.depth.copy()
    motion = frame.motion.copy()
    depth[::7, ::5] = np.nan
    depth[3, :] = np.inf
    motion[::3, ::4, 0] = np.nan
    motion[5, :, 1] = -np.inf
    meta = dataclasses.replace(frame.meta, jitter=(float("nan"), float("inf")))
    return dataclasses.replace(frame, depth=depth, motion=motion, meta=meta)


@pytest.mark.parametrize("name", NETWORKS)
def test_nan_and_inf_input_never_reach_output_or_history(
    name: str, sequence: tuple[list[RenderFrame], np.ndarray]
) -> None:
    frames, _ = sequence
    up = fresh(name)
    display = Size(640, 360)
    up.upscale(frames[0], display)
    out = up.upscale(_poisoned(frames[1]), display)
    assert torch.isfinite(out).all()
    assert up._history is not None and torch.isfinite(up._history.output).all()
    assert torch.isfinite(up.upscale(frames[2], display)).all()


@pytest.mark.parametrize("name", NETWORKS)
def test_odd_sizes(name: str) -> None:
    renderer = Renderer("dolly", Size(161, 91), seed=0, jitter=True)
    up = fresh(name)
    for i in range(2):
        out = up.upscale(renderer.render(i, i / 60.0), Size(322, 182))
        assert out.shape == (3, 182, 322) and torch.isfinite(out).all()


@pytest.mark.parametrize("display", [Size(480, 270), Size(960, 540), Size(300, 170)])
def test_other_scales_resample_the_2x_output(
    display: Size, sequence: tuple[list[RenderFrame], np.ndarray]
) -> None:
    frames, _ = sequence
    up = fresh("unet")
    for f in frames[:2]:
        out = up.upscale(f, display)
        assert out.shape == (3, display.height, display.width) and torch.isfinite(out).all()


def test_first_frame_and_reset_equal_a_fresh_start(
    sequence: tuple[list[RenderFrame], np.ndarray],
) -> None:
    frames, _ = sequence
    display = Size(640, 360)
    first = fresh("unet").upscale(frames[3], display)
    up = fresh("unet")
    for f in frames[:3]:
        up.upscale(f, display)
    with_history = up.upscale(frames[3], display)
    assert not torch.equal(with_history, first)  # history is really used
    up.reset()
    assert torch.equal(up.upscale(frames[3], display), first)


def test_resolution_change_drops_history(sequence: tuple[list[RenderFrame], np.ndarray]) -> None:
    frames, _ = sequence
    small = Renderer("slow_pan", Size(160, 90), seed=0, jitter=True).render(1, 1 / 60.0)
    up = fresh("unet")
    for f in frames[:3]:
        up.upscale(f, Size(640, 360))
    changed = up.upscale(small, Size(320, 180))
    assert torch.equal(changed, fresh("unet").upscale(small, Size(320, 180)))
    # Same render size, another display size: also a new start.
    up.upscale(frames[0], Size(640, 360))
    other = up.upscale(frames[1], Size(480, 270))
    assert torch.equal(other, fresh("unet").upscale(frames[1], Size(480, 270)))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("name", NETWORKS)
def test_float16_cuda_matches_cpu(
    name: str, sequence: tuple[list[RenderFrame], np.ndarray]
) -> None:
    """float16 on CUDA against float32 on the CPU over a run of frames (history included):
    mean absolute difference below 1/255 and 99.9 % of pixels within 4/255."""
    frames, _ = sequence
    cpu = load(name, device="cpu")
    gpu = load(name, device="cuda", dtype=torch.float16)
    for f in frames:
        a = cpu.upscale(f, Size(640, 360))
        b = gpu.upscale(f, Size(640, 360)).float().cpu()
    diff = (a - b).abs()
    assert float(diff.mean()) < 1.0 / 255.0
    assert float((diff > 4.0 / 255.0).float().mean()) < 1e-3


# -- training -------------------------------------------------------------------------


def _train(tmp: Path, out: str, seed: int = 0) -> dict[str, torch.Tensor]:
    from server.cli import main

    args = ["train", "--model", "unet", "--steps", "2", "--sequences", "1",
            "--render-size", "32x24", "--crop", "16", "--batch", "2", "--seed", str(seed),
            "--data-dir", str(tmp / "data"), "--out", str(tmp / out)]  # fmt: skip
    assert main(args) == 0
    ckpt = torch.load(tmp / out, weights_only=True)
    return dict(ckpt["state_dict"])


def test_train_end_to_end_is_reproducible(tmp_path: Path) -> None:
    a = _train(tmp_path, "a.pt")
    b = _train(tmp_path, "b.pt")  # the second run loads the cached dataset
    assert len(list((tmp_path / "data").glob("*.npz"))) == 1
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    c = _train(tmp_path, "c.pt", seed=1)
    assert any(not torch.equal(a[k], c[k]) for k in a)
    up = UNetUpscaler(device="cpu", weights=tmp_path / "a.pt")
    frame = Renderer("static", Size(32, 24), seed=0).render(0, 0.0)
    assert torch.isfinite(up.upscale(frame, Size(64, 48))).all()


def test_train_from_init_fine_tunes_those_weights(tmp_path: Path) -> None:
    """--init starts from a checkpoint (another network or scale is refused), keeps its
    base unless --base moves it, and says where it started in the meta."""
    from server.cli import main

    _train(tmp_path, "a.pt")
    common = ["--steps", "1", "--sequences", "1", "--render-size", "32x24", "--crop", "16",
              "--batch", "2", "--lr", "1e-9", "--data-dir", str(tmp_path / "data")]  # fmt: skip
    assert main(["train", "--model", "unet", *common, "--init", str(tmp_path / "a.pt"),
                 "--base", "cubic", "--out", str(tmp_path / "b.pt")]) == 0  # fmt: skip
    a = torch.load(tmp_path / "a.pt", weights_only=True)
    b = torch.load(tmp_path / "b.pt", weights_only=True)
    # One step at lr 1e-9 from a's weights: still a's weights (to float16), on cubic.
    assert all(torch.allclose(a["state_dict"][k].float(), v.float(), atol=1e-3)
               for k, v in b["state_dict"].items())  # fmt: skip
    assert b["base"] == "cubic" and b["meta"]["init"] == str(tmp_path / "a.pt")
    assert b["meta"]["init_command"] == a["meta"]["command"]
    for bad in (["--model", "unetpp", "--init", str(tmp_path / "a.pt")],
                ["--model", "unet", "--init", str(tmp_path / "missing.pt")]):  # fmt: skip
        with pytest.raises(SystemExit) as exc:
            main(["train", *bad, *common, "--out", str(tmp_path / "x.pt")])
        assert "--init" in str(exc.value.code)
    assert not (tmp_path / "x.pt").exists()


def test_dataset_mip_bias_is_part_of_its_key_and_of_its_renders() -> None:
    plain = DatasetSpec(sequences=1, frames=3, render_size="48x32", scenes=("static",))
    biased = dataclasses.replace(plain, texture_lod_bias=-1.0)
    # Bias 0 keeps the key datasets had before the field existed (their caches stay valid).
    assert "texture_lod_bias" not in plain.key() and plain.key() != biased.key()
    a, b = generate(plain, progress=False), generate(biased, progress=False)
    assert np.array_equal(a.depth, b.depth) and np.array_equal(a.truth, b.truth)
    assert not np.array_equal(a.color, b.color)  # finer mips in the renders only


def test_dataset_rendered_by_workers_is_the_same_data() -> None:
    spec = DatasetSpec(sequences=3, frames=3, render_size="48x32", scenes=("static", "dolly"))
    one, two = generate(spec, progress=False), generate(spec, progress=False, workers=2)
    for name in one.__dataclass_fields__:
        assert np.array_equal(getattr(one, name), getattr(two, name)), name
    with pytest.raises(ValueError, match="workers"):
        generate(spec, progress=False, workers=0)


NO_CUDA = [] if torch.cuda.is_available() else [["--model", "unet", "--device", "cuda"]]


@pytest.mark.parametrize(
    "bad",
    [["--model", "vgg"], ["--model", "unet", "--steps", "0"], ["--model", "unet", "--lr", "x"],
     ["--model", "unet", "--render-size", "64"], ["--model", "unet", "--crop", "999"],
     ["--model", "unet", "--device", "tpu9"], *NO_CUDA],
)  # fmt: skip
def test_train_refuses_bad_arguments(bad: list[str], tmp_path: Path) -> None:
    from server.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["train", *bad, "--data-dir", str(tmp_path), "--out", str(tmp_path / "x.pt")])
    assert exc.value.code != 0
    assert not (tmp_path / "x.pt").exists()


def test_cache_aware_training_reuses_the_deep_branch_and_keeps_the_weight_names(
    tmp_path: Path,
) -> None:
    from server.train import loop
    from server.train.dataset import DatasetSpec
    from server.train.loop import TrainConfig, train
    from upscalers.cache.layer_cache import BranchAction, CachedBranch
    from upscalers.neural.network import build_model

    data = generate(
        DatasetSpec(sequences=1, frames=4, render_size="32x24", scenes=("static",)),
        progress=False,
    )
    model = build_model("unet", 2)
    names = set(model.state_dict())
    actions: list[BranchAction] = []
    forward = CachedBranch.forward

    def spy(self: CachedBranch, *args: object, **kwargs: object) -> object:
        out = forward(self, *args, **kwargs)
        actions.append(self.last_action)
        return out

    cfg = TrainConfig(steps=2, batch=2, crop=16, cached_share=1.0)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(CachedBranch, "forward", spy)
        result = train(model, data, cfg, 2, progress=False)
    assert math.isfinite(result.final_loss)
    # Every frame after an unroll's first reused what the frame before it kept.
    assert BranchAction.REUSED in actions and BranchAction.COMPUTED in actions
    assert set(model.state_dict()) == names  # the wrappers are gone again
    assert not any(isinstance(m, CachedBranch) for m in model.modules())
    with pytest.raises(ValueError, match="cached_share"):
        train(model, data, TrainConfig(steps=1, cached_share=1.5), 2, progress=False)
    assert loop.TrainConfig().cached_share == 0.0  # off unless asked


# -- output range (issue 19) ------------------------------------------------------------


def _range_frame(color: np.ndarray, index: int) -> RenderFrame:
    from server.frames.frame import Camera, FrameFlags, FrameMeta
    from server.game.render.transforms import jitter_offset, jitter_phase_count

    h, w = color.shape[:2]
    return RenderFrame(
        color=color,
        depth=np.full((h, w), 0.5, np.float32),
        motion=np.full((h, w, 2), 0.3, np.float32),
        dynamic_mask=np.zeros((h, w), np.uint8),
        meta=FrameMeta(
            index, Camera.identity(), jitter_offset(index, jitter_phase_count(2.0)),
            FrameFlags.NONE,
        ),
    )  # fmt: skip


def _step_and_checkerboard() -> list[np.ndarray]:
    step = np.full((32, 48, 3), 64, np.uint8)
    step[:, 24:] = 191
    yy, xx = np.mgrid[:32, :48]
    checker = np.where(((yy + xx) % 2 == 0)[..., None], 64, 191).astype(np.uint8).repeat(3, 2)
    return [step, checker]


@pytest.mark.parametrize("name", ["unet", "unetpp"])
def test_output_stays_inside_the_inputs_local_range(
    name: str, shipped: dict[str, NeuralUpscaler]
) -> None:
    """A 64|191 step and a one-pixel 64/191 checkerboard never come out darker or brighter
    than their input (no halo, no ringing), and a constant frame stays constant, frame
    after frame with the network's own history."""
    up = shipped[name]
    for image in _step_and_checkerboard():
        up.reset()
        for i in range(6):
            out = to_uint8(up.upscale(_range_frame(image, i), Size(96, 64))).astype(int)
            assert out.min() >= 64 and out.max() <= 191, (i, out.min(), out.max())
    for level in (0, 137, 255):
        up.reset()
        flat = np.full((32, 48, 3), level, np.uint8)
        for i in range(4):
            out = to_uint8(up.upscale(_range_frame(flat, i), Size(96, 64))).astype(int)
            assert np.abs(out - level).max() <= 1, (level, i)


@pytest.mark.parametrize("name", ["unet", "unetpp"])
def test_an_angled_filtered_edge_gets_no_halo(
    name: str, shipped: dict[str, NeuralUpscaler]
) -> None:
    """A hard 64|191 edge at a sub-pixel position and 0-60 degrees, rendered box-filtered
    with the jitter and panned: samples between the levels along it, which the
    pixel-aligned step lacks, never come out past the input's range."""
    from server.frames.frame import FrameFlags
    from tests.test_temporal_reset import EDGE_ANGLES, PHOTO_DISPLAY, _photo_pan, angled_edge

    up = shipped[name]
    for angle in EDGE_ANGLES:
        up.reset()
        src = angled_edge(angle)
        for i in range(6):
            flags = FrameFlags.RESET if i == 0 else FrameFlags.NONE
            frame, _ = _photo_pan(src, i, 0.37, flags)
            out = to_uint8(up.upscale(frame, PHOTO_DISPLAY)).astype(int)
            assert out.min() >= 64 and out.max() <= 191, (angle, i, out.min(), out.max())


def test_fresh_start_trains_the_frame_without_history(tmp_path: Path) -> None:
    from server.train import loop
    from server.train.loop import TrainConfig, train
    from upscalers.neural.network import build_model

    data = generate(
        DatasetSpec(sequences=1, frames=5, truth_frames=3, render_size="32x24",
                    scenes=("static",)),
        progress=False,
    )  # fmt: skip
    unrolls: list[tuple[int, bool]] = []
    batch = loop._batch

    def spy(*args: object, **kwargs: object) -> object:
        frames, truths = batch(*args, **kwargs)  # type: ignore[arg-type]
        unrolls.append((len(frames), truths[0] is not None))
        return frames, truths

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(loop, "_batch", spy)
        train(build_model("unet", 2), data, TrainConfig(steps=6, batch=1, crop=16,
              fresh_share=1.0), 2, progress=False)  # fmt: skip
        # Every unroll starts at the first frame with truth: no warm-up, trained at once.
        assert unrolls == [(3, True)] * 6
        unrolls.clear()
        train(build_model("unet", 2), data, TrainConfig(steps=12, batch=1, crop=16), 2,
              progress=False)  # fmt: skip
        assert any(n > 3 for n, _ in unrolls)  # a uniform start warms up most unrolls
    with pytest.raises(ValueError, match="fresh_share"):
        train(build_model("unet", 2), data, TrainConfig(steps=1, fresh_share=2.0), 2)
