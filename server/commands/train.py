"""``upcast train``: train a neural upscaler on the game's own frames and ground truth.

Renders (or loads from --data-dir) the training sequences, trains with a fixed
number of steps from --seed (same seed and arguments on the same machine: the
same weights), and writes a float16 checkpoint that ``upscalers.neural.load``
reads. Progress: the stage, step/total, loss and the time left, on stderr.
"""

from __future__ import annotations

import argparse
import json
import platform
import shlex
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from upscalers.names import DEFAULT_NETWORK_BASE, NETWORK_BASES

if TYPE_CHECKING:
    from torch import nn

    from server.frames.frame import Size

DEFAULT_DATA_DIR = Path.home() / ".cache" / "upcast"


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0.0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {value}")
    return value


def _share(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {value}")
    return value


def _mip_bias(text: str, render: Size, scale: int) -> float:
    """``--mip-bias`` as the number the dataset key records."""
    from server.game.render.mip_bias import game_lod_bias, parse_mip_bias

    try:
        bias = parse_mip_bias(text, render, render.scaled(scale))
    except ValueError as e:
        raise SystemExit(str(e)) from None
    # Training renders are all jittered: the game's choice for those.
    return game_lod_bias(True, scale) if bias is None else bias


def _initial_model(
    name: str, scale: int, init: Path | None, base: str | None
) -> tuple[nn.Module, dict[str, Any]]:
    """The network training starts from: untrained (residual zero) on ``base``, or the
    weights of ``init`` with their meta, refused where they are another network or
    scale; ``base`` (None: the checkpoint's own) moves them onto another upsampling."""
    from upscalers.neural.network import build_model, load_checkpoint, set_base

    if init is None:
        return build_model(name, scale, base=base or DEFAULT_NETWORK_BASE), {}
    try:
        found, model, found_scale, meta = load_checkpoint(init)
    except (FileNotFoundError, ValueError) as e:
        raise SystemExit(f"--init: {e}") from None
    if found != name or found_scale != scale:
        raise SystemExit(f"--init: {init} holds {found} at {found_scale}x, not {name} at {scale}x")
    if base is not None:
        set_base(model, base)
    return model, meta


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--model", required=True, choices=("unet", "unetpp"), help="network to train"
    )
    parser.add_argument(
        "--mip-bias",
        default="game",
        help="texture LOD bias of the training renders: 'game' (the default) or 'auto' for "
        "the display size's mips (-1 at 2x), what the game renders for a temporal upscaler; "
        "a number fixes it (0: the render size's mips, what the weights before 2026-11-23 "
        "were trained on). The truth always picks the display size's mips",
    )
    parser.add_argument("--seed", type=int, default=0, help="seeds data, crops and weights")
    parser.add_argument("--steps", type=_positive_int, default=1500, help="optimizer steps")
    parser.add_argument(
        "--minutes",
        type=_positive_float,
        default=None,
        help="wall-time cap for the training stage: stop early (and say so) past it",
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="checkpoint (default: the shipped weights path)"
    )
    parser.add_argument(
        "--data-dir", type=Path, default=DEFAULT_DATA_DIR, help="where the dataset is cached"
    )
    parser.add_argument("--sequences", type=_positive_int, default=96, help="rendered sequences")
    parser.add_argument(
        "--frames",
        type=_positive_int,
        default=10,
        help="frames per sequence; the last 3 have ground truth, the others warm up history",
    )
    parser.add_argument("--render-size", default="640x360", help="render size WxH (2x truth)")
    parser.add_argument("--batch", type=_positive_int, default=8, help="crops per step")
    parser.add_argument("--crop", type=_positive_int, default=96, help="crop side, render px")
    parser.add_argument("--lr", type=_positive_float, default=1e-3, help="peak learning rate")
    parser.add_argument(
        "--cache-aware",
        type=_share,
        default=0.0,
        help="share of unrolled frames (after the first) that reuse the previous frame's "
        "deep-branch output at the default cache point, so the network learns to serve "
        "layer-cached frames (0: off)",
    )
    parser.add_argument("--threads", type=_positive_int, default=2, help="torch CPU threads")
    parser.add_argument(
        "--device",
        default="cpu",
        help="where the network trains: cpu (the default) or cuda; the weights are saved "
        "for the CPU either way",
    )
    parser.add_argument(
        "--data-workers",
        type=_positive_int,
        default=1,
        help="processes rendering the game's training sequences when they are not cached "
        "(the data are the same for any number)",
    )
    parser.add_argument(
        "--fresh-start",
        type=_share,
        default=0.0,
        help="share of steps whose unroll starts at the first frame with ground truth, "
        "so the frame without history (first frame, cut, reset) is trained more often "
        "(0: a uniform start, 1 step in frames - 2)",
    )
    parser.add_argument(
        "--real-content",
        type=Path,
        default=None,
        metavar="DIR",
        help="also train on the training pictures of DIR (`upcast eval content --fetch --dir "
        "DIR`): photographs and game screenshots as pans, zooms and rotations with exact "
        "motion; their held-out pictures are never used",
    )
    parser.add_argument(
        "--real-share",
        type=_share,
        default=0.5,
        help="with --real-content: share of the steps whose batch comes from the pictures "
        "(three quarters photographs, one quarter screenshots); the rest from the game",
    )
    parser.add_argument(
        "--scenes", default="all", help="comma-separated scenes to render (default all)"
    )
    parser.add_argument(
        "--init",
        type=Path,
        default=None,
        metavar="CHECKPOINT",
        help="start from these weights instead of the untrained network (fine-tuning: "
        "pair with a lower --lr); the checkpoint must be the same --model at 2x",
    )
    parser.add_argument(
        "--base",
        choices=NETWORK_BASES,
        default=None,
        help="the upsampling the network's residual is added to: bilinear or cubic "
        f"(Catmull-Rom); default: --init's own, else {DEFAULT_NETWORK_BASE}",
    )


def run(args: argparse.Namespace) -> int:
    import numpy as np
    import torch

    from server.frames.frame import Size
    from server.game.render.scenes import parse_scene_list
    from server.train.dataset import DatasetSpec, load_or_generate
    from server.train.loop import TrainConfig, train
    from server.train.mix import build_mix
    from server.train.photo_dataset import PhotoSpec
    from upscalers.neural.features import feature_channels
    from upscalers.neural.flops import conv_flops
    from upscalers.neural.network import (
        WEIGHTS_DIR,
        base_of,
        save_checkpoint,
        with_memory_format,
    )

    try:
        render = Size.parse(args.render_size)
    except ValueError as e:
        raise SystemExit(f"--render-size: {e}") from None
    try:
        device = torch.device(args.device)
    except RuntimeError as e:
        raise SystemExit(f"--device: {e}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: torch sees no CUDA device here (train on cpu)")
    if args.crop > min(render):
        raise SystemExit(f"--crop {args.crop} is larger than the render size {render}")
    scale = 2
    if args.frames < 3:
        raise SystemExit(f"--frames must be >= 3 (3 frames have ground truth), got {args.frames}")
    spec = DatasetSpec(
        sequences=args.sequences,
        frames=args.frames,
        render_size=str(render),
        scale=scale,
        seed=args.seed,
        scenes=tuple(parse_scene_list(args.scenes)),
        texture_lod_bias=_mip_bias(args.mip_bias, render, scale),
    )
    out: Path = args.out or WEIGHTS_DIR / f"{args.model}.pt"
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    np.random.seed(args.seed)

    started = time.monotonic()
    print(f"[data] {spec.sequences} sequences at {render} -> 2x, cache {args.data_dir}",
          file=sys.stderr)  # fmt: skip
    game_data = load_or_generate(spec, args.data_dir, workers=args.data_workers)
    try:
        data = build_mix(
            game_data,
            args.real_content,
            args.real_share,
            PhotoSpec(
                frames=spec.frames, truth_frames=spec.truth_frames, scale=scale, seed=args.seed
            ),
            args.data_dir,
        )
    except (FileNotFoundError, ValueError) as e:
        raise SystemExit(f"--real-content: {e}") from None
    data_s = time.monotonic() - started

    model, init_meta = _initial_model(args.model, scale, args.init, args.base)
    model = with_memory_format(model, torch.channels_last)
    cfg = TrainConfig(
        steps=args.steps,
        batch=args.batch,
        crop=args.crop,
        lr=args.lr,
        seed=args.seed,
        minutes=args.minutes,
        cached_share=args.cache_aware,
        fresh_share=args.fresh_start,
        device=args.device,
    )
    result = train(model, data, cfg, scale)
    if result.stopped_early:
        print(
            f"[train] stopped at step {result.steps_done}/{cfg.steps}: --minutes {args.minutes} "
            "reached (the weights are not the reproducible full run)",
            file=sys.stderr,
        )
    model = with_memory_format(model, torch.contiguous_format)
    flops = conv_flops(model, (1, feature_channels(scale), 360, 640))
    meta = {
        "command": "upcast train " + shlex.join(sys.argv[2:] if len(sys.argv) > 2 else []),
        "seed": args.seed,
        "steps": result.steps_done,
        "steps_planned": cfg.steps,
        "stopped_early": result.stopped_early,
        "batch": cfg.batch,
        "crop": cfg.crop,
        "lr": cfg.lr,
        "cache_aware": cfg.cached_share,
        "fresh_start": cfg.fresh_share,
        "init": None if args.init is None else str(args.init),
        "init_command": init_meta.get("command"),
        "base": base_of(model),
        "final_l1": result.final_loss,
        "final_l1_by_part": json.dumps(result.final_loss_by_part),
        "real_content": None if args.real_content is None else args.real_share,
        "train_seconds": round(result.seconds, 1),
        "data_seconds": round(data_s, 1),
        "dataset": json.dumps(
            {
                "sequences": spec.sequences,
                "frames": spec.frames,
                "truth": spec.truth_frames,
                "render": spec.render_size,
                "supersample": spec.supersample,
                "texture_lod_bias": spec.texture_lod_bias,
                "key": spec.key(),
            }
        ),
        "params": sum(p.numel() for p in model.parameters()),
        "gflops_640x360": round(flops[""] / 1e9, 3),
        "threads": args.threads,
        "device": args.device,
        "machine": platform.processor() or platform.machine(),
        "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        "torch": str(torch.__version__),
    }
    save_checkpoint(out, args.model, model, scale, meta)
    total = time.monotonic() - started
    print(
        f"[done] {out} ({out.stat().st_size / 1e6:.2f} MB), {result.steps_done} steps, "
        f"L1 {result.final_loss:.4f}, data {data_s:.0f} s + train {result.seconds:.0f} s "
        f"= {total / 60:.1f} min",
        file=sys.stderr,
    )
    return 0
