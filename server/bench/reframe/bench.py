"""``upcast bench reframe``: ReFrame layer caching on the neural upscaler, per scene and policy.

For each scene the game renders a run of jittered frames (the neural upscaler
is temporal) at display / 2 and the ground truth at display size. Every frame
goes, interleaved in one process (the order rotates per frame), through:

- the uncached network (``unet``; ``unetpp`` too for the ablation), the
  reference of the quality figures and the denominator of the speedup;
- one ``CachedUpscaler`` per case: each policy at cache level 1, each fixed
  SMAPE threshold of the sweep (for the budget comparison), and Delta_L at
  levels 2, 3 and U-Net++ configs A, B (the ablation, on fewer scenes).

Each case has its own network instance and history, as in a real session:
cached outputs feed the cached run's own next frame. Speedup is the uncached
wall time over the cached wall time on the same frames (``upscale`` calls:
features, policy, network, history), after the first frame. Eliminated FLOPs
count what ran: full frames, cached frames and the budget policy's audits, from
torch's FLOP counter on the real forward paths.

Quality against the uncached output: PSNR on every frame (mean and the worst
frame); FLIP and SSIM, which cost seconds per 720p frame on a CPU, on
``--flip-frames`` evenly spaced frames plus each case's worst-PSNR frame.
Against the ground truth: PSNR on every ``--gt-every``-th frame, FLIP and SSIM on
one of them.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from server.ops.progress import elapsed_and_left, progress

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

    from server.frames.frame import RenderFrame, Size
    from upscalers.cache.cached_upscaler import NeuralUpscalerLike

    U8 = npt.NDArray[np.uint8]

MAIN_POLICIES = "delta_h,delta_l,every_2,every_5,deepcache,motion,budget,budget@41"
SWEEP = "delta@0.04,delta@0.06,delta@0.07,delta@0.1,delta@0.15,delta@2"
ABLATION = "unet:2,unet:3,unetpp:A,unetpp:B"
ABLATION_SCENES = "slow_pan,fast_yaw,default"
ABLATION_POLICY = "delta_l"
WARMUP_FRAMES = 1  # the first frame allocates and is always full: left out of timings
PSNR_CAP_DB = 100.0  # identical images score this instead of inf


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, required=True, help="JSON report path")
    parser.add_argument("--plot", type=Path, default=None, help="PNG: speedup against FLIP")
    parser.add_argument(
        "--tables", type=Path, default=None, help="Markdown tables (default: JSON path, .md)"
    )
    parser.add_argument("--scenes", default="all", help="comma-separated scene names, or all")
    parser.add_argument("--frames", type=int, default=24, help="frames per scene")
    parser.add_argument("--display-size", default="1280x720", help="render size is half")
    parser.add_argument("--policies", default=MAIN_POLICIES, help="cache level 1 policies")
    parser.add_argument(
        "--sweep", default=SWEEP, help="fixed thresholds compared with the budget policy"
    )
    parser.add_argument(
        "--levels", default=ABLATION, help="NET:CONFIG ablation cases (Delta_L), or none"
    )
    parser.add_argument("--ablation-scenes", default=ABLATION_SCENES, help="or all")
    parser.add_argument("--flip-frames", type=int, default=3, help="FLIP/SSIM frames per case")
    parser.add_argument("--gt-every", type=int, default=3, help="ground-truth PSNR stride")
    parser.add_argument("--supersample", type=int, default=2, help="ground truth ss x ss")
    parser.add_argument(
        "--seed",
        type=int,
        default=0,
        help="scene seed (crate placement); another seed is held-out content for the "
        "budget policy, whose margin was measured on seed 0",
    )
    parser.add_argument("--fps", type=float, default=60.0)
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--device", default="cpu")


@dataclass(frozen=True)
class CaseSpec:
    """One cached configuration: which network, cache config, policy, and table."""

    label: str
    network: str
    config: str
    policy: str
    group: str  # "policy", "sweep" or "ablation"


@dataclass
class CaseRun:
    spec: CaseSpec
    upscaler: Any  # CachedUpscaler (imported lazily)
    times_ms: list[float] = field(default_factory=list)
    ref_times_ms: list[float] = field(default_factory=list)
    psnr: list[float] = field(default_factory=list)
    flip: list[float] = field(default_factory=list)
    ssim: list[float] = field(default_factory=list)
    gt_psnr: list[float] = field(default_factory=list)
    gt_flip: list[float] = field(default_factory=list)
    gt_ssim: list[float] = field(default_factory=list)
    actions: list[str] = field(default_factory=list)
    worst: tuple[float, int, U8, U8] | None = None  # (psnr, frame, reference, test)


def _csv(text: str) -> list[str]:
    return [p.strip() for p in text.split(",") if p.strip() and p.strip() != "none"]


def parse_cases(args: argparse.Namespace) -> list[CaseSpec]:
    from upscalers.cache.policies import make_policy

    cases: list[CaseSpec] = []
    for group, text in (("policy", args.policies), ("sweep", args.sweep)):
        for p in _csv(text):
            make_policy(p)  # a bad name fails here, before any rendering
            cases.append(CaseSpec(p, "unet", "1", p, group))
    for item in _csv(args.levels):
        network, sep, config = item.partition(":")
        if not sep or network not in ("unet", "unetpp"):
            raise ValueError(f"ablation case {item!r}: expected unet:LEVEL or unetpp:CONFIG")
        cases.append(CaseSpec(f"{network}:{config}", network, config, ABLATION_POLICY, "ablation"))
    labels = [c.label for c in cases]
    if len(set(labels)) != len(labels):
        raise ValueError(f"a case is listed twice: {labels}")
    return cases


def _psnr(reference: U8, test: U8) -> float:
    from upscalers import metrics

    return min(metrics.psnr(reference, test), PSNR_CAP_DB)


def _start_time(scene: str, frames: int, fps: float) -> float:
    """A scene with a cut starts so that the cut falls mid-run: the cached frames
    before it and the recovery after it are both measured."""
    from server.game.render.scenes import make_scene

    cuts = make_scene(scene).cut_times
    return max(0.0, cuts[0] - (frames // 2 - 0.5) / fps) if cuts else 0.25


def _sample(frames: int, count: int) -> list[int]:
    """``count`` evenly spaced frames after the first (which is always full)."""
    if count <= 0 or frames <= 1:
        return []
    step = (frames - 1) / count
    return sorted({1 + int(step * (i + 0.5)) for i in range(count)})


LoadNetwork = Callable[[str], "NeuralUpscalerLike"]


def default_loader(device: str) -> LoadNetwork:
    def load(name: str) -> NeuralUpscalerLike:
        from upscalers import neural

        return neural.load(name, device=device)

    return load


@dataclass
class ReferenceRun:
    """An uncached network on the scene: the reference and the speedup's numerator."""

    network: str
    upscaler: Any  # NeuralUpscaler
    times_ms: list[float] = field(default_factory=list)
    gt_psnr: list[float] = field(default_factory=list)
    gt_flip: list[float] = field(default_factory=list)
    gt_ssim: list[float] = field(default_factory=list)


def run_scene(
    scene: str,
    cases: list[CaseSpec],
    load: LoadNetwork,
    args: argparse.Namespace,
    display: Size,
) -> tuple[list[CaseRun], list[ReferenceRun]]:
    """All cases and their uncached references on one scene, interleaved per frame."""
    from server.frames.frame import FrameFlags, Size
    from server.game.render.renderer import Renderer, RenderTargets
    from upscalers import metrics
    from upscalers.cache.cached_upscaler import CachedUpscaler
    from upscalers.output import to_uint8

    render = Size(display.width // 2, display.height // 2)
    start = _start_time(scene, args.frames, args.fps)
    times = [start + i / args.fps for i in range(args.frames)]
    # Jittered, so with the display size's texture mips: what the game sends a temporal method.
    renderer = Renderer(scene, render, seed=args.seed, scale=2.0, jitter=True)
    frames: list[RenderFrame] = [
        renderer.render(i, t, RenderTargets.allocate(render)) for i, t in enumerate(times)
    ]
    gt_renderer = Renderer(scene, display, seed=args.seed, jitter=False)
    gt_frames = (
        set(range(args.gt_every, args.frames, args.gt_every)) if args.gt_every > 0 else set()
    )
    gt_flip_frame = max(gt_frames) if gt_frames else None
    flip_frames = set(_sample(args.frames, args.flip_frames))

    refs = {n: ReferenceRun(n, load(n)) for n in dict.fromkeys(c.network for c in cases)}
    runs = [CaseRun(c, CachedUpscaler(load(c.network), c.policy, c.config)) for c in cases]
    jobs: list[ReferenceRun | CaseRun] = [*refs.values(), *runs]
    for i, frame in enumerate(frames):
        k = i % len(jobs)  # rotate: no run always goes first (cold caches) or last
        images: dict[int, U8] = {}
        cut = bool(frame.meta.flags & FrameFlags.RESET)
        for job in jobs[k:] + jobs[:k]:
            up = job.upscaler
            if cut:  # what UpscalerHost does in the worker: history means nothing now
                up.reset()
            t0 = time.perf_counter_ns()
            image = up.upscale(frame, display)
            ms = (time.perf_counter_ns() - t0) / 1e6
            job.times_ms.append(ms)
            if isinstance(job, CaseRun):
                job.actions.append(up.last_action)
            images[id(job)] = to_uint8(image)
        truth = None
        if i in gt_frames:
            truth = gt_renderer.render_ground_truth(times[i], display, args.supersample)
            for ref in refs.values():
                _score_truth(ref, truth, images[id(ref)], i == gt_flip_frame)
        for r in runs:
            test, reference = images[id(r)], images[id(refs[r.spec.network])]
            r.ref_times_ms.append(refs[r.spec.network].times_ms[-1])
            p = _psnr(reference, test)
            r.psnr.append(p)
            if i >= WARMUP_FRAMES and (r.worst is None or p < r.worst[0]):
                r.worst = (p, i, reference, test)
            if i in flip_frames:
                r.flip.append(metrics.flip(reference, test))
                r.ssim.append(metrics.ssim(reference, test))
            if truth is not None:
                _score_truth(r, truth, test, i == gt_flip_frame)
    for r in runs:
        r.upscaler.close()
    return runs, list(refs.values())


def _score_truth(run: ReferenceRun | CaseRun, truth: U8, image: U8, full: bool) -> None:
    from upscalers import metrics

    run.gt_psnr.append(_psnr(truth, image))
    if full:
        run.gt_flip.append(metrics.flip(truth, image))
        run.gt_ssim.append(metrics.ssim(truth, image))


def _mean(values: list[float]) -> float | None:
    return float(sum(values) / len(values)) if values else None


def summarize(
    scene: str, run: CaseRun, flops: dict[tuple[str, str], tuple[int, int]]
) -> dict[str, Any]:
    """The report case of one (scene, case)."""
    from upscalers import metrics

    stats = run.upscaler.stats
    full, cached = flops[(run.spec.network, run.spec.config)]
    executed = stats.refreshes * full + (stats.cached + stats.audits) * cached
    eliminated = 1.0 - executed / (stats.frames * full) if stats.frames and full else 0.0
    t_cached = sum(run.times_ms[WARMUP_FRAMES:])
    t_ref = sum(run.ref_times_ms[WARMUP_FRAMES:])
    worst_psnr = worst_flip = None
    worst_frame = None
    if run.worst is not None:
        worst_psnr, worst_frame, ref, test = run.worst
        worst_flip = metrics.flip(ref, test)
    return {
        "name": f"{scene}/{run.spec.label}",
        "scene": scene,
        "case": run.spec.label,
        "group": run.spec.group,
        "network": run.spec.network,
        "cache_config": run.spec.config,
        "policy": run.upscaler.policy.describe(),
        "frames": stats.frames,
        "refreshes": stats.refreshes,
        "forced_refreshes": stats.forced,
        "cached_frames": stats.cached,
        "skipped_share": stats.cached_share,
        "audits": stats.audits,
        "flops_full": full,
        "flops_cached_frame": cached,
        "eliminated_flops_share": eliminated,
        "median_ms": _median(run.times_ms[WARMUP_FRAMES:]),
        "p95_ms": _p95(run.times_ms[WARMUP_FRAMES:]),
        "uncached_median_ms": _median(run.ref_times_ms[WARMUP_FRAMES:]),
        "speedup": t_ref / t_cached if t_cached > 0 else None,
        "psnr_db": _mean(run.psnr[WARMUP_FRAMES:]),
        "flip": _mean(run.flip),
        "ssim": _mean(run.ssim),
        "worst_psnr_db": worst_psnr,
        "worst_flip": worst_flip,
        "worst_frame": worst_frame,
        "max_flip": max([*run.flip, worst_flip or 0.0]),
        "gt_psnr_db": _mean(run.gt_psnr),
        "gt_flip": _mean(run.gt_flip),
        "gt_ssim": _mean(run.gt_ssim),
        "cache_bytes": stats.peak_cache_bytes,
        "reference_bytes": stats.reference_bytes,
        "budget_db": getattr(run.upscaler.policy, "budget_db", None),
        "tau_end": getattr(run.upscaler.policy, "tau", None),
        "run_limit_end": getattr(run.upscaler.policy, "run_limit", None),
        "actions": "".join(a[0] for a in run.actions),  # f=forced r=refresh c=cached n=nonfinite
    }


def _median(values: list[float]) -> float | None:
    if not values:
        return None
    s = sorted(values)
    return float(s[len(s) // 2]) if len(s) % 2 else float((s[len(s) // 2 - 1] + s[len(s) // 2]) / 2)


def _p95(values: list[float]) -> float | None:
    if not values:
        return None
    s = sorted(values)
    return float(s[min(len(s) - 1, round(0.95 * (len(s) - 1)))])


def measure_flops(
    cases: list[CaseSpec], load: LoadNetwork, frame: RenderFrame, display: Size
) -> dict[tuple[str, str], tuple[int, int]]:
    """(full, cached-frame) FLOPs per (network, cache config), on a throwaway instance."""
    from upscalers.cache.flops import path_flops
    from upscalers.cache.layer_cache import LayerCache

    out: dict[tuple[str, str], tuple[int, int]] = {}
    for key in dict.fromkeys((c.network, c.config) for c in cases):
        up = load(key[0])
        x = up.features(frame, display)
        with LayerCache(up.model, key[1]) as cache:
            f = path_flops(cache, up.run, x)
        out[key] = (f.full, f.cached)
    return out


def run(args: argparse.Namespace, load: LoadNetwork | None = None) -> int:
    import torch

    from server.bench.reframe.tables import must_show_checks, speedup_flip_plot, tables
    from server.frames.frame import Size
    from server.game.render.renderer import Renderer, RenderTargets
    from server.game.render.scenes import parse_scene_list
    from server.ops.report import BenchReport

    try:
        display = Size.parse(args.display_size)
        cases = parse_cases(args)
    except ValueError as e:
        raise SystemExit(str(e)) from None
    if display.width % 16 or display.height % 16:
        raise SystemExit("--display-size must be multiples of 16 (render size is half)")
    if args.frames < 3:
        raise SystemExit("--frames must be at least 3")
    scenes = parse_scene_list(args.scenes)
    ablation_scenes = set(parse_scene_list(args.ablation_scenes))
    torch.set_num_threads(args.threads)
    load = load or default_loader(args.device)
    report = BenchReport(
        "reframe",
        {
            "scenes": scenes,
            "frames": args.frames,
            "display_size": str(display),
            "render_size": f"{display.width // 2}x{display.height // 2}",
            "cases": [c.__dict__ for c in cases],
            "ablation_scenes": sorted(ablation_scenes),
            "flip_frames": args.flip_frames,
            "gt_every": args.gt_every,
            "supersample": args.supersample,
            "fps": args.fps,
            "seed": args.seed,
            "texture_mips": "jittered renders with the display size's mips (LOD bias -1), "
            "as the game renders for temporal upscalers; ground truth the same mips",
            "threads": torch.get_num_threads(),
            "device": args.device,
            "load_average_start": _loadavg(),
        },
    )
    render = Size(display.width // 2, display.height // 2)
    probe = Renderer(scenes[0], render, scale=2.0, jitter=True).render(
        0, 0.25, RenderTargets.allocate(render)
    )
    flops = measure_flops(cases, load, probe, display)
    started = time.monotonic()
    for n, scene in enumerate(scenes, 1):
        scene_cases = [c for c in cases if c.group != "ablation" or scene in ablation_scenes]
        runs, refs = run_scene(scene, scene_cases, load, args, display)
        for r in runs:
            case = report.add_case(**summarize(scene, r, flops))
            progress(
                f"  {case['case']:14} skipped {case['cached_frames']:3d}/{case['frames']}  "
                f"speedup {case['speedup']:.2f}  PSNR {case['psnr_db']:.2f} "
                f"(worst {case['worst_psnr_db']:.2f})  FLIP {_fmt_opt(case['flip'])}"
            )
        for ref in refs:
            report.add_case(
                f"{scene}/{ref.network}_uncached",
                scene=scene,
                case=f"{ref.network}_uncached",
                group="uncached",
                network=ref.network,
                median_ms=_median(ref.times_ms[WARMUP_FRAMES:]),
                p95_ms=_p95(ref.times_ms[WARMUP_FRAMES:]),
                gt_psnr_db=_mean(ref.gt_psnr),
                gt_flip=_mean(ref.gt_flip),
                gt_ssim=_mean(ref.gt_ssim),
                flops_full=next(f for (net, _), (f, _c) in flops.items() if net == ref.network),
            )
        elapsed, left = elapsed_and_left(n, len(scenes), started)
        progress(
            f"[{n}/{len(scenes)}] {scene}: {len(runs)} cases "
            f"({elapsed:.0f} s elapsed, ~{left:.0f} s left)"
        )
    report.config["load_average_end"] = _loadavg()
    checks = must_show_checks(report.cases)
    report.notes.extend(f"{'PASS' if ok else 'FAIL'}: {text}" for text, ok in checks)
    report.notes += [
        "reference of FLIP/SSIM/PSNR: the uncached network's output on the same frames "
        "(its own history); gt_*: the game's ground truth, unjittered, supersampled",
        "speedup: sum of uncached upscale times / sum of cached upscale times on the "
        "same frames, interleaved in one process, first frame left out",
        "eliminated_flops_share: 1 - FLOPs run (full frames + cached frames + audits) / "
        "FLOPs of running every frame uncached; convolution FLOPs (FlopCounterMode)",
        f"flip/ssim: mean over {args.flip_frames} evenly spaced frames per case; "
        "worst_*: the frame with the lowest PSNR against the uncached output",
    ]
    report.write(args.json)
    text = tables(report.cases, checks)
    print(text)
    tables_path = args.tables or args.json.with_suffix(".md")
    tables_path.parent.mkdir(parents=True, exist_ok=True)
    tables_path.write_text(text + "\n")
    if args.plot:
        speedup_flip_plot(report.cases, args.plot)
        print(f"plot written to {args.plot}")
    print(f"report written to {args.json}, tables to {tables_path}")
    return 0


def _fmt_opt(value: float | None) -> str:
    return "-" if value is None else f"{value:.4f}"


def _loadavg() -> list[float] | None:
    try:
        with open("/proc/loadavg", encoding="ascii") as f:
            return [float(v) for v in f.read().split()[:3]]
    except OSError:
        return None
