"""``upcast render``: render a scene to PNG and .npz files for a person to look at."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # Scene names come from the numpy-only registry: no torch import at parse time.
    from server.game.render.scenes import SCENE_NAMES

    parser.add_argument("--scene", required=True, choices=SCENE_NAMES, help="scene preset")
    parser.add_argument("--frames", type=int, default=8, help="number of frames")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--size", default="640x360", help="render size WxH")
    parser.add_argument("--scale", type=float, default=2.0, help="display / render size")
    parser.add_argument("--fps", type=float, default=60.0, help="frame rate of the scene clock")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--ground-truth", action="store_true", help="also write display-size GT")
    parser.add_argument("--no-jitter", action="store_true", help="render without sub-pixel jitter")


def run(args: argparse.Namespace) -> int:
    import numpy as np
    from PIL import Image

    from server.frames.frame import Size
    from server.game.render.renderer import Renderer
    from server.game.render.visualize import depth_image, motion_image

    size = Size.parse(args.size)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    renderer = Renderer(
        args.scene, size, seed=args.seed, jitter=not args.no_jitter, scale=args.scale
    )
    display = size.scaled(args.scale)
    for i in range(args.frames):
        t = i / args.fps
        frame = renderer.render(i, t)
        stem = out / f"{args.scene}_{i:04d}"
        Image.fromarray(frame.color).save(f"{stem}_color.png")
        Image.fromarray(depth_image(frame.depth)).save(f"{stem}_depth.png")
        Image.fromarray(motion_image(frame.motion)).save(f"{stem}_motion.png")
        Image.fromarray(frame.dynamic_mask * 255).save(f"{stem}_mask.png")
        extra: dict[str, Any] = {}
        if args.ground_truth:
            gt = renderer.render_ground_truth(t, display)
            Image.fromarray(gt).save(f"{stem}_gt.png")
            extra["ground_truth"] = gt
        cam = frame.meta.camera
        np.savez_compressed(
            f"{stem}.npz",
            color=frame.color,
            depth=frame.depth,
            motion=frame.motion,
            dynamic_mask=frame.dynamic_mask,
            view=cam.view,
            proj=cam.proj,
            prev_view=cam.prev_view,
            prev_proj=cam.prev_proj,
            near=cam.near,
            far=cam.far,
            fov_y_deg=cam.fov_y_deg,
            jitter=np.asarray(frame.meta.jitter, np.float32),
            flags=int(frame.meta.flags),
            frame_id=frame.meta.frame_id,
            t=t,
            **extra,
        )
        print(
            f"frame {i + 1}/{args.frames} t={t:.3f}s flags={int(frame.meta.flags)} -> {stem}_*.png",
            file=sys.stderr,
        )
    return 0
