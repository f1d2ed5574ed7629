"""``upcast bench framegen``: frame prediction quality and cost against the rendered truth.

For each scene, frames 0 .. 2N-1 at 60 fps scene time (``jitter=False``):
even frames are rendered and observed (their motion spans the previous even
frame, as in a pipeline that renders every other frame); odd frames are
predicted from the previous even frame with the odd frame's real camera, and
rendered for ground truth. The game would draw its moving objects into the
predicted frame itself, so the true dynamic pixels of the odd frame are
composited over every prediction before scoring. A prediction refused across
a scene cut (the odd frame carries RESET) counts as ``refused`` and the frame
is shown as a repeat.

Costs are ``observe`` + ``predict`` per predicted frame (the cache is only
needed for prediction), interleaved across methods, next to the median cost
of rendering one frame at the same size in the same run.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from server.ops.progress import progress

if TYPE_CHECKING:
    from upscalers.framegen import FramePredictor

TORCH_SUFFIX = "_torch"
PSNR_CAP_DB = 100.0  # identical images (static scene) score this instead of inf
DEFAULT_SCENES = "slow_pan,fast_yaw,dolly,thin_detail,default,moving_objects,scene_cut,static"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, required=True, help="where to write the report")
    parser.add_argument("--plot", type=Path, default=None, help="optional PNG: PSNR against cost")
    parser.add_argument(
        "--scenes", default=DEFAULT_SCENES, help="comma-separated scene names, or all"
    )
    parser.add_argument("--size", default="640x360", help="render size WxH")
    parser.add_argument("--frames", type=int, default=12, help="predicted frames per scene")
    parser.add_argument("--tiles", default="8,16", help="comma-separated MPE tile sizes")
    parser.add_argument(
        "--flip-frames", type=int, default=2, help="frames per case scored with FLIP"
    )
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: leave as is)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--start", type=float, default=0.25, help="scene time of frame 0 (s)")


@dataclass
class _Case:
    scene: str
    method: str
    psnr: list[float] = field(default_factory=list)
    ssim: list[float] = field(default_factory=list)
    flip: list[float] = field(default_factory=list)
    holes: list[float] = field(default_factory=list)
    cost_ms: list[float] = field(default_factory=list)
    predict_ms: list[float] = field(default_factory=list)
    refused: int = 0


def _methods(tiles: list[int], device: str) -> dict[str, Callable[[], FramePredictor]]:
    from functools import partial

    from upscalers.framegen import (
        BackwardWarpPredictor,
        MeshProjectionPredictor,
        MpeOptions,
        RepeatPredictor,
        SplatPredictor,
    )

    def mpe(
        tile: int,
        tensile: bool = True,
        shear: bool = True,
        backend: Literal["auto", "torch", "numba"] = "auto",
    ) -> FramePredictor:
        options = MpeOptions(tile=tile, tensile=tensile, shear=shear, backend=backend)
        return MeshProjectionPredictor(options, device)

    out: dict[str, Callable[[], FramePredictor]] = {
        "repeat": partial(RepeatPredictor, device=device),
        "splat": partial(SplatPredictor, device=device),
        "backward_warp": partial(BackwardWarpPredictor, device=device),
    }
    for tile in tiles:
        out[f"mpe{tile}"] = partial(mpe, tile)
    # The ablation at the paper's upper tile size (16) or the first one given.
    t = 16 if 16 in tiles else tiles[0]
    if device == "cpu":  # the torch reference next to the default (numba) backend
        out[f"mpe{t}{TORCH_SUFFIX}"] = partial(mpe, t, backend="torch")
    out[f"mpe{t}_no_tensile"] = partial(mpe, t, tensile=False)
    out[f"mpe{t}_no_shear"] = partial(mpe, t, shear=False)
    out[f"mpe{t}_none"] = partial(mpe, t, tensile=False, shear=False)
    return out


def run(args: argparse.Namespace) -> int:
    import numpy as np
    import torch

    from server.frames.frame import RenderFrame, Size
    from server.game.render.renderer import Renderer, RenderTargets
    from server.game.render.scenes import SCENES, make_scene, parse_scene_list
    from server.ops.report import BenchReport, summarize_ms
    from upscalers import metrics

    size = Size.parse(args.size)
    scenes = parse_scene_list(args.scenes)
    tiles = [int(x) for x in args.tiles.split(",") if x]
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    warm_up_s = None
    if args.device == "cpu":
        # The numba kernels compile (or load from __pycache__) once per process, here,
        # so no predicted frame below pays for it.
        from upscalers.framegen import MpeOptions
        from upscalers.framegen.mpe_cpu import warm_up

        warm_up_s = warm_up(MpeOptions())
    methods = _methods(tiles, args.device)
    report = BenchReport(
        "framegen",
        {
            "size": str(size),
            "frames": args.frames,
            "scenes": scenes,
            "tiles": tiles,
            "methods": list(methods),
            "flip_frames": args.flip_frames,
            "threads": torch.get_num_threads(),
            "device": args.device,
            "fps": 60,
            "start_s": args.start,
            "mpe_numba_warm_up_s": warm_up_s,
        },
    )
    report.notes += [
        "reference: the rendered odd frame (jitter off); quality after compositing its true "
        "dynamic pixels over the prediction (the game draws moving objects itself)",
        "cost_ms: observe + predict per predicted frame; render_ms: Renderer.render at the "
        "same size, same run; cost_over_render = median cost / that scene's median render, "
        "cost_over_size_render = median cost / the median render over all scenes",
        "sky_share: share of rendered pixels at depth >= 1 (sky), which this renderer fills "
        "almost for free and MPE reprojects like any other pixel",
        "holes: share of pixels the predictor marks as having no reliable source",
        "mpeN runs MPE's default backend (numba kernels on the CPU, torch on CUDA); "
        f"mpeN{TORCH_SUFFIX} the torch reference on the same frames, interleaved",
        f"PSNR of identical images is capped at {PSNR_CAP_DB:.0f} dB",
    ]
    cases: dict[tuple[str, str], _Case] = {}
    render_ms: dict[str, list[float]] = {}
    sky_share: dict[str, float] = {}
    for scene in scenes:
        renderer = Renderer(scene, size, jitter=False, device=args.device)
        predictors = {name: make() for name, make in methods.items()}
        start = args.start
        cuts = make_scene(scene).cut_times
        if cuts:  # put the cut in the middle of the run, between an even and an odd frame
            start = cuts[0] - (2 * (args.frames // 2) + 1) / 60.0 + 1e-4
        samples: list[float] = []
        sky: list[float] = []
        prev_t: float | None = None
        for j in range(args.frames):
            t_even, t_odd = start + 2 * j / 60.0, start + (2 * j + 1) / 60.0
            targets = RenderTargets.allocate(size)
            t0 = time.perf_counter()
            rendered: RenderFrame = renderer.render(2 * j, t_even, targets, prev_t=prev_t)
            samples.append((time.perf_counter() - t0) * 1e3)
            # Sky costs this renderer almost nothing and MPE as much as any pixel.
            sky.append(float(np.mean(~(np.asarray(rendered.depth) < 1.0))))
            t0 = time.perf_counter()
            truth = renderer.render(2 * j + 1, t_odd, prev_t=t_even)
            samples.append((time.perf_counter() - t0) * 1e3)
            prev_t = t_even
            cam = truth.meta.camera
            dyn = truth.dynamic_mask[..., None] != 0
            for name, predictor in predictors.items():
                case = cases.setdefault((scene, name), _Case(scene, name))
                t0 = time.perf_counter()
                predictor.observe(rendered)
                t1 = time.perf_counter()
                pred = predictor.predict(cam.view, cam.proj, truth.meta.flags)
                t2 = time.perf_counter()
                if pred is None:
                    case.refused += 1
                    continue
                case.cost_ms.append((t2 - t0) * 1e3)
                case.predict_ms.append((t2 - t1) * 1e3)
                shown = np.where(dyn, truth.color, pred.color)
                case.psnr.append(min(PSNR_CAP_DB, metrics.psnr(truth.color, shown)))
                case.ssim.append(metrics.ssim(truth.color, shown))
                case.holes.append(pred.hole_share)
                if len(case.flip) < args.flip_frames and j >= 1:
                    case.flip.append(metrics.flip(truth.color, shown))
            progress(f"{scene}: frame pair {j + 1}/{args.frames}")
        render_ms[scene] = samples
        sky_share[scene] = float(np.mean(sky)) if sky else 0.0

    all_render = [x for s in render_ms.values() for x in s]
    render_med = float(np.median(all_render)) if all_render else float("nan")
    report.add_case("render", kind="render", **summarize_ms(all_render))

    def mean(xs: list[float]) -> float | None:
        finite = [x for x in xs if np.isfinite(x)]
        return float(np.mean(finite)) if finite else None

    rows = []
    for (scene, name), case in cases.items():
        stats = summarize_ms(case.cost_ms)
        entry = report.add_case(
            f"{scene}/{name}",
            kind="predict",
            scene=scene,
            method=name,
            camera_motion=SCENES[scene].camera_motion,
            predicted=len(case.psnr),
            refused=case.refused,
            psnr_db=mean(case.psnr),
            ssim=mean(case.ssim),
            flip=mean(case.flip),
            flip_frames=len(case.flip),
            hole_share=mean(case.holes),
            predict_only=summarize_ms(case.predict_ms),
            scene_render_median_ms=float(np.median(render_ms[scene])),
            sky_share=sky_share[scene],
            **stats,
        )
        if case.cost_ms:
            # Two yardsticks: this scene's own render, and the median render at this size
            # over all scenes (a frame of the game at this size).
            ratio = stats["median_ms"] / float(np.median(render_ms[scene]))
            entry["cost_over_render"] = ratio
            report.add_ratio(f"{scene}/{name} cost / render", name, "render", ratio)
            size_ratio = stats["median_ms"] / render_med
            entry["cost_over_size_render"] = size_ratio
            report.add_ratio(
                f"{scene}/{name} cost / median render at this size", name, "render", size_ratio
            )
        rows.append(entry)

    for r in rows:  # the compiled backend against the torch reference, same scene
        name = r["method"]
        ref = next(
            (o for o in rows if o["scene"] == r["scene"] and o["method"] == name + TORCH_SUFFIX),
            None,
        )
        if ref is not None and "median_ms" in r and "median_ms" in ref:
            ratio = r["median_ms"] / ref["median_ms"]
            r["cost_over_torch"] = ratio
            report.add_ratio(f"{r['scene']}/{name} cost / torch", name, name + TORCH_SUFFIX, ratio)
    _summaries(report, rows, list(methods))
    _print_table(rows, render_med)
    report.write(args.json)
    print(f"wrote {args.json}")
    if args.plot is not None:
        _plot(rows, render_med, args.plot)
        print(f"wrote {args.plot}")
    return 0


def _summaries(report: Any, rows: list[dict[str, Any]], methods: list[str]) -> None:
    """Means over the scenes with camera motion, and MPE's margins over the baselines."""
    moving = [r for r in rows if r["camera_motion"] and r["psnr_db"] is not None]
    means: dict[str, float] = {}
    for m in methods:
        vals = [r["psnr_db"] for r in moving if r["method"] == m]
        if vals:
            means[m] = sum(vals) / len(vals)
    report.config["camera_motion_mean_psnr_db"] = means
    for m in methods:  # the ablation: what each correction earns, per camera-motion scene
        full, _, variant = m.partition("_")
        if not m.startswith("mpe") or variant not in ("no_tensile", "no_shear", "none"):
            continue
        gains = []
        for r in moving:
            if r["method"] == full:
                other = next(
                    (o for o in moving if o["scene"] == r["scene"] and o["method"] == m), None
                )
                if other is not None:
                    gains.append(f"{r['scene']} {r['psnr_db'] - other['psnr_db']:+.2f}")
        if gains:
            report.notes.append(f"{full} over {m} (dB): " + ", ".join(gains))
    for m in methods:
        if not m.startswith("mpe") or "_" in m:
            continue
        for base in ("repeat", "splat"):
            margins = []
            for r in moving:
                if r["method"] != m:
                    continue
                other = next(
                    (o for o in moving if o["scene"] == r["scene"] and o["method"] == base), None
                )
                if other is not None:
                    margins.append(r["psnr_db"] - other["psnr_db"])
            if margins:
                report.notes.append(
                    f"{m} over {base} on camera-motion scenes: min {min(margins):+.2f} dB, "
                    f"mean {sum(margins) / len(margins):+.2f} dB"
                )


def _fmt(x: float | None, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def _print_table(rows: list[dict[str, Any]], render_med: float) -> None:
    head = (
        f"{'scene':15s} {'method':22s} {'PSNR':>6s} {'SSIM':>6s} {'FLIP':>6s} {'holes':>6s} "
        f"{'med ms':>7s} {'p95 ms':>7s} {'/render':>7s} {'/size':>6s} {'/torch':>7s} "
        f"{'refused':>7s}"
    )
    print(head)
    for r in rows:
        print(
            f"{r['scene']:15s} {r['method']:22s} {_fmt(r['psnr_db'], '6.2f')} "
            f"{_fmt(r['ssim'], '6.3f')} {_fmt(r['flip'], '6.3f')} {_fmt(r['hole_share'], '6.3f')} "
            f"{_fmt(r.get('median_ms'), '7.2f')} {_fmt(r.get('p95_ms'), '7.2f')} "
            f"{_fmt(r.get('cost_over_render'), '7.2f')} "
            f"{_fmt(r.get('cost_over_size_render'), '6.2f')} "
            f"{_fmt(r.get('cost_over_torch'), '7.2f')} "
            f"{r['refused']:7d}"
        )
    print(
        f"render median {render_med:.2f} ms per frame (/render: over that scene's render; "
        "/size: over this median)"
    )


def _plot(rows: list[dict[str, Any]], render_med: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5))
    methods = sorted({r["method"] for r in rows})
    for m in methods:
        pts = [
            (r["median_ms"], r["psnr_db"])
            for r in rows
            if r["method"] == m and r["psnr_db"] is not None and "median_ms" in r
        ]
        if pts:
            xs, ys = zip(*pts, strict=True)
            ax.scatter(xs, ys, label=m, s=18)
    ax.axvline(render_med, color="k", ls="--", lw=1, label="render (median)")
    ax.axvline(0.25 * render_med, color="gray", ls=":", lw=1, label="25% of render")
    ax.set_xlabel("cost per predicted frame (ms, median)")
    ax.set_ylabel("PSNR vs rendered frame (dB)")
    ax.set_title("frame prediction: quality against cost, one point per scene")
    ax.legend(fontsize=7)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
