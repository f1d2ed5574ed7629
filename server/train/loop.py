"""The training loop: recurrent unrolls over random crops, L1 in sRGB, Adam.

A step takes a batch of crops (the same window in every frame of a sequence,
randomly mirrored) and a start frame: frames before the first one with ground
truth run without gradients and only build history; from the start frame on,
the network sees its own previous output warped by the motion vectors, as it
will when upscaling. The start frame has no history, so the first frame after
a cut or a reset is trained too. History is detached between frames.

Cache-aware training (``cached_share`` > 0): the network's deep branch at its
default cache point (``upscalers/cache``) is wrapped in a ``LayerCache``, and
each frame after the first of an unroll reuses the branch output kept from the
previous frame with that probability, as a cached frame does when upscaling.
Frames then differ by their jitter as well as by motion, and a network trained
only on fresh deep features draws fine texture detail from them that a stale
copy gets wrong; trained on both, its shallow levels learn to carry that detail.

Deterministic from the seed on one machine: every random choice comes from
generators seeded here, and torch's CPU kernels are deterministic for these ops.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
import torch.nn.functional as F
from torch import nn

from server.ops.progress import elapsed_and_left
from server.ops.progress import progress as report_progress
from server.train.dataset import Dataset
from upscalers.cache.layer_cache import CacheMode, LayerCache
from upscalers.neural.features import FrameTensors, History, build_features
from upscalers.neural.network import predict

GRAD_CLIP = 1.0


@dataclass(frozen=True)
class TrainConfig:
    steps: int = 1500
    batch: int = 8
    crop: int = 96  # render pixels
    lr: float = 1e-3
    final_lr: float = 5e-5
    seed: int = 0
    minutes: float | None = None  # stop early (and say so) past this wall time
    log_every: int = 10
    # Share of unrolled frames after the first that reuse the previous frame's deep
    # branch output (cache-aware training; 0: never).
    cached_share: float = 0.0
    # Where the network trains ("cpu", "cuda"): batches are made on the CPU and moved.
    device: str = "cpu"
    # Share of steps whose unroll starts at the first frame with truth, so the frame
    # without history (a first frame, a cut, a reset) is trained. With a uniform start
    # only 1 in (warm-up frames + 1) steps train it, and a network trained so fell below
    # bicubic on photographs' first frames while beating it once history built up.
    fresh_share: float = 0.0


@dataclass
class TrainResult:
    steps_done: int
    seconds: float
    final_loss: float
    stopped_early: bool
    # Mean L1 of the last steps drawn from each dataset of the mix, by label.
    final_loss_by_part: dict[str, float] = field(default_factory=dict)


def _stacked(parts: Sequence[npt.NDArray[Any]], device: str) -> torch.Tensor:
    """The crops of one frame as one tensor on the training device."""
    return torch.from_numpy(np.stack(parts)).to(device)


def _batch(
    data: Dataset, rng: np.random.Generator, cfg: TrainConfig, scale: int, fresh: bool = False
) -> tuple[list[FrameTensors], list[torch.Tensor | None]]:
    """Frame tensors per frame of the unroll and the matching truth (None: warm-up);
    ``fresh``: the unroll starts at the first frame with truth (no warm-up)."""
    h, w = data.color.shape[2:4]
    crop = min(cfg.crop, h, w)
    seqs = rng.integers(0, data.sequences, cfg.batch)
    ys = rng.integers(0, h - crop + 1, cfg.batch)
    xs = rng.integers(0, w - crop + 1, cfg.batch)
    flips = rng.random(cfg.batch) < 0.5
    # Drawn even when fresh, so the crops that follow stay the same draws.
    start = int(rng.integers(0, data.first_truth + 1))
    if fresh:
        start = data.first_truth
    frames: list[FrameTensors] = []
    truths: list[torch.Tensor | None] = []
    for f in range(start, data.frames):
        col, dep, mot, jit, gts = [], [], [], [], []
        for b in range(cfg.batch):
            i, y, x = int(seqs[b]), int(ys[b]), int(xs[b])
            c = data.color[i, f, y : y + crop, x : x + crop]
            d = data.depth[i, f, y : y + crop, x : x + crop]
            m = data.motion[i, f, y : y + crop, x : x + crop].astype(np.float32)
            j = data.jitter[i, f].copy()
            g = None
            k = f - data.first_truth
            if k >= 0:
                g = data.truth[i, k, scale * y : scale * (y + crop), scale * x : scale * (x + crop)]
            if flips[b]:
                # Mirror x: sample offsets and motion change sign along x.
                c, d, m = c[:, ::-1], d[:, ::-1], m[:, ::-1].copy()
                m[..., 0] *= -1.0
                j[0] = -j[0]
                g = None if g is None else g[:, ::-1]
            col.append(np.ascontiguousarray(c))
            dep.append(np.ascontiguousarray(d, dtype=np.float32))
            mot.append(np.ascontiguousarray(m))
            jit.append(j)
            if g is not None:
                gts.append(np.ascontiguousarray(g))
        frames.append(
            FrameTensors(
                color=_stacked(col, cfg.device).permute(0, 3, 1, 2).float().div_(255.0),
                depth=_stacked(dep, cfg.device).unsqueeze(1),
                motion=_stacked(mot, cfg.device).permute(0, 3, 1, 2).contiguous(),
                jitter=_stacked(jit, cfg.device),
                near_far=torch.from_numpy(data.near_far[seqs]).to(cfg.device),
            )
        )
        truths.append(
            _stacked(gts, cfg.device).permute(0, 3, 1, 2).float().div_(255.0) if gts else None
        )
    return frames, truths


def _lr_at(step: int, cfg: TrainConfig) -> float:
    """Linear warm-up over the first 3 % of steps, then cosine decay to final_lr."""
    warm = max(1, cfg.steps // 33)
    if step < warm:
        return cfg.lr * (step + 1) / warm
    p = (step - warm) / max(1, cfg.steps - warm)
    return cfg.final_lr + 0.5 * (cfg.lr - cfg.final_lr) * (1.0 + math.cos(math.pi * p))


@contextmanager
def _cache_mode(cache: LayerCache | None, reuse: bool) -> Iterator[None]:
    if cache is None:
        yield
        return
    with cache.using(CacheMode.REUSE if reuse else CacheMode.REFRESH):
        yield


@dataclass(frozen=True)
class DataMix:
    """Datasets trained on together: each step's batch comes from one of them, drawn
    with the given weights (their own generator, so one dataset alone draws the
    same batches as before mixes existed)."""

    parts: tuple[tuple[str, Dataset, float], ...]  # (label, data, weight)

    def __post_init__(self) -> None:
        if not self.parts:
            raise ValueError("a data mix needs at least one dataset")
        if any(weight <= 0.0 for _, _, weight in self.parts):
            raise ValueError(f"mix weights must be > 0, got {[w for _, _, w in self.parts]}")

    def probabilities(self) -> npt.NDArray[np.float64]:
        weights = np.array([weight for _, _, weight in self.parts], np.float64)
        return np.asarray(weights / weights.sum(), dtype=np.float64)


def train(
    model: nn.Module,
    data: Dataset | DataMix,
    cfg: TrainConfig,
    scale: int,
    progress: bool = True,
) -> TrainResult:
    if not 0.0 <= cfg.cached_share <= 1.0:
        raise ValueError(f"cached_share must be in [0, 1], got {cfg.cached_share}")
    if not 0.0 <= cfg.fresh_share <= 1.0:
        raise ValueError(f"fresh_share must be in [0, 1], got {cfg.fresh_share}")
    # The cache installs wrappers in place of the deep branch: restored before returning,
    # so the model's parameters and state-dict names stay what they were.
    model.to(cfg.device)
    cache = LayerCache(model) if cfg.cached_share > 0 else None
    try:
        return _train(model, data, cfg, scale, progress, cache)
    finally:
        if cache is not None:
            cache.restore()
        model.to("cpu")  # saved and used on the CPU


def _train(
    model: nn.Module,
    data: Dataset | DataMix,
    cfg: TrainConfig,
    scale: int,
    progress: bool,
    cache: LayerCache | None,
) -> TrainResult:
    rng = np.random.default_rng(cfg.seed)
    # Its own generator: runs without the cache draw the same batches as before it.
    cache_rng = np.random.default_rng([cfg.seed, 1])
    mix = data if isinstance(data, DataMix) else DataMix((("data", data, 1.0),))
    mix_rng = np.random.default_rng([cfg.seed, 2])
    mix_p = mix.probabilities()
    fresh_rng = np.random.default_rng([cfg.seed, 3])
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    model.train()
    started = time.monotonic()
    recent: list[float] = []
    by_part: dict[str, list[float]] = {}
    step = 0
    stopped_early = False
    for step in range(cfg.steps):
        if cfg.minutes is not None and time.monotonic() - started > 60.0 * cfg.minutes:
            stopped_early = True
            break
        for group in opt.param_groups:
            group["lr"] = _lr_at(step, cfg)
        part = 0 if len(mix.parts) == 1 else int(mix_rng.choice(len(mix.parts), p=mix_p))
        fresh = cfg.fresh_share > 0 and fresh_rng.random() < cfg.fresh_share
        frames, truths = _batch(mix.parts[part][1], rng, cfg, scale, fresh)
        history: History | None = None
        opt.zero_grad(set_to_none=True)
        losses = []
        if cache is not None:
            cache.invalidate()  # new crops: nothing kept belongs to them
        for i, (ft, gt) in enumerate(zip(frames, truths, strict=True)):
            reuse = cache is not None and i > 0 and cache_rng.random() < cfg.cached_share
            with torch.set_grad_enabled(gt is not None), _cache_mode(cache, reuse):
                x, dfeat = build_features(ft, history, scale)
                y = predict(model, x, scale)
            if gt is not None:
                losses.append(F.l1_loss(y, gt))
            history = History(y.detach(), dfeat)
        loss = torch.stack(losses).mean()
        loss.backward()  # type: ignore[no-untyped-call]
        # A recurrent unroll occasionally spikes (a bad history feeds the next frame):
        # clipping keeps one such batch from undoing what was learnt.
        torch.nn.utils.clip_grad_norm_(model.parameters(), GRAD_CLIP)
        opt.step()
        recent.append(float(loss.detach()))
        recent = recent[-50:]
        label = mix.parts[part][0]
        by_part[label] = [*by_part.get(label, []), recent[-1]][-50:]
        if progress and (step % cfg.log_every == 0 or step == cfg.steps - 1):
            elapsed, eta = elapsed_and_left(step + 1, cfg.steps, started)
            parts = (
                ""
                if len(mix.parts) == 1
                else " (" + ", ".join(f"{k} {np.mean(v):.4f}" for k, v in by_part.items()) + ")"
            )
            report_progress(
                f"[train] step {step + 1}/{cfg.steps} loss {np.mean(recent):.4f}{parts} "
                f"lr {_lr_at(step, cfg):.2e} {elapsed:.0f} s, eta {eta:.0f} s"
            )
    else:
        step = cfg.steps
    model.eval()
    return TrainResult(
        steps_done=step,
        seconds=time.monotonic() - started,
        final_loss=float(np.mean(recent)) if recent else float("nan"),
        stopped_early=stopped_early,
        final_loss_by_part={k: float(np.mean(v)) for k, v in by_part.items()},
    )
