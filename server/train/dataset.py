"""Training data: short jittered sequences of the game's own scenes with ground truth.

Each sequence is ``frames`` consecutive renders (jittered with the Halton
phases the game uses at 2x, at 60 or 30 frames a second) of one scene, and the
supersampled ground truth of its last ``truth_frames`` frames. The first frames
without truth warm up the network's history during training.

Kept apart from the evaluation (``upcast eval upscalers``): that renders seed 0
at game times 0 to 0.4 s (scene_cut: around its cut at 1 s); training uses
seeds 1 and up and times from 1.5 s on, so no evaluated frame is trained on.
The world itself (buildings, textures, the sign) is the same game, as it would
be for a network trained per game.

Generation is deterministic from the seed and cached as an .npz keyed by every
parameter, so a rerun loads it instead of rendering again.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import multiprocessing as mp
import sys
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from server.frames.frame import Size
from server.game.render.renderer import Renderer
from server.game.render.scenes import DEFAULT_SCENE_NAMES, SCENE_NAMES
from server.ops.progress import elapsed_and_left
from server.ops.progress import progress as report_progress

TRAIN_TIME_RANGE = (1.5, 9.0)
FRAME_STEPS = (1.0 / 60.0, 1.0 / 30.0)


@dataclass(frozen=True)
class DatasetSpec:
    sequences: int = 96
    frames: int = 5
    truth_frames: int = 3
    render_size: str = "640x360"
    scale: int = 2
    supersample: int = 3
    seed: int = 0
    scenes: tuple[str, ...] = DEFAULT_SCENE_NAMES
    # Texture LOD bias of the renders (the ground truth picks its own mips at display size);
    # 0 in the key's absence: datasets cached before the field were rendered with it.
    texture_lod_bias: float = 0.0

    def key(self) -> str:
        fields = asdict(self)
        if fields["texture_lod_bias"] == 0.0:
            del fields["texture_lod_bias"]  # datasets cached before the field keep their key
        text = json.dumps(fields, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def check(self) -> None:
        if self.sequences < 1:
            raise ValueError(f"sequences must be >= 1, got {self.sequences}")
        if not 1 <= self.truth_frames <= self.frames:
            raise ValueError(
                f"truth_frames must be in [1, frames={self.frames}], got {self.truth_frames}"
            )
        unknown = [s for s in self.scenes if s not in SCENE_NAMES]
        if unknown or not self.scenes:
            raise ValueError(f"unknown scenes {unknown}; choose from {', '.join(SCENE_NAMES)}")
        Size.parse(self.render_size)


@dataclass
class Dataset:
    """Arrays indexed [sequence, frame]; truth is for the last ``truth_frames`` frames."""

    color: npt.NDArray[np.uint8]  # (S, F, h, w, 3)
    depth: npt.NDArray[np.float16]  # (S, F, h, w)
    motion: npt.NDArray[np.float16]  # (S, F, h, w, 2)
    jitter: npt.NDArray[np.float32]  # (S, F, 2)
    near_far: npt.NDArray[np.float32]  # (S, 2)
    truth: npt.NDArray[np.uint8]  # (S, T, s h, s w, 3)

    @property
    def sequences(self) -> int:
        return int(self.color.shape[0])

    @property
    def frames(self) -> int:
        return int(self.color.shape[1])

    @property
    def first_truth(self) -> int:
        return int(self.color.shape[1] - self.truth.shape[1])


def _sequence_plan(spec: DatasetSpec) -> list[tuple[str, int, float, float, int]]:
    """(scene, scene seed, start time, frame step, first frame index) per sequence."""
    rng = np.random.default_rng(spec.seed)
    plan = []
    for i in range(spec.sequences):
        scene = spec.scenes[i % len(spec.scenes)]
        scene_seed = 1 + int(rng.integers(0, 1000))
        t0 = float(rng.uniform(*TRAIN_TIME_RANGE))
        dt = FRAME_STEPS[int(rng.integers(0, len(FRAME_STEPS)))]
        first_index = 1 + int(rng.integers(0, 64))
        plan.append((scene, scene_seed, t0, dt, first_index))
    return plan


def generate(spec: DatasetSpec, progress: bool = True, workers: int = 1) -> Dataset:
    """Render every sequence of ``spec``; ``workers`` > 1 renders sequences in that many
    processes (one torch thread each). Each sequence depends on its own plan entry
    alone, so the data are the same whatever the number of workers."""
    spec.check()
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    render = Size.parse(spec.render_size)
    w, h = render
    s, n, nt = spec.scale, spec.frames, spec.truth_frames
    data = Dataset(
        color=np.empty((spec.sequences, n, h, w, 3), np.uint8),
        depth=np.empty((spec.sequences, n, h, w), np.float16),
        motion=np.empty((spec.sequences, n, h, w, 2), np.float16),
        jitter=np.empty((spec.sequences, n, 2), np.float32),
        near_far=np.empty((spec.sequences, 2), np.float32),
        truth=np.empty((spec.sequences, nt, h * s, w * s, 3), np.uint8),
    )
    plan = _sequence_plan(spec)
    jobs = [(spec, entry) for entry in plan]
    started = time.monotonic()
    with contextlib.ExitStack() as stack:
        if workers == 1:
            rendered: Iterator[_Rendered] = map(_render_sequence, jobs)
        else:
            pool = stack.enter_context(
                mp.get_context("spawn").Pool(workers, initializer=_one_thread)
            )
            rendered = pool.imap(_render_sequence, jobs)
        for i, seq in enumerate(rendered):
            for name in Dataset.__dataclass_fields__:
                getattr(data, name)[i] = getattr(seq, name)
            if progress:
                elapsed, eta = elapsed_and_left(i + 1, spec.sequences, started)
                report_progress(
                    f"[data] sequence {i + 1}/{spec.sequences} ({plan[i][0]}) "
                    f"{elapsed:.0f} s, eta {eta:.0f} s"
                )
    return data


@dataclass
class _Rendered:
    """One sequence's arrays (a worker's answer): Dataset's fields without the sequence
    axis."""

    color: npt.NDArray[np.uint8]
    depth: npt.NDArray[np.float16]
    motion: npt.NDArray[np.float16]
    jitter: npt.NDArray[np.float32]
    near_far: npt.NDArray[np.float32]
    truth: npt.NDArray[np.uint8]


def _one_thread() -> None:
    import torch

    torch.set_num_threads(1)  # the workers share the cores between them


def _render_sequence(job: tuple[DatasetSpec, tuple[str, int, float, float, int]]) -> _Rendered:
    spec, (scene, scene_seed, t0, dt, first) = job
    render = Size.parse(spec.render_size)
    s, n, nt = spec.scale, spec.frames, spec.truth_frames
    display = Size(render.width * s, render.height * s)
    renderer = Renderer(
        scene,
        render,
        seed=scene_seed,
        jitter=True,
        scale=float(s),
        texture_lod_bias=spec.texture_lod_bias,
    )
    frames = []
    for f in range(n):
        t = t0 + f * dt
        frames.append(renderer.render(first + f, t, prev_t=t - dt))
    cam = frames[-1].meta.camera
    truth = [
        # The truth picks the display size's mips whatever the renders' bias.
        renderer.render_ground_truth(t0 + (n - nt + k) * dt, display, spec.supersample)
        for k in range(nt)
    ]
    return _Rendered(
        color=np.stack([f.color for f in frames]),
        depth=np.stack([f.depth for f in frames]).astype(np.float16),
        motion=np.stack([f.motion for f in frames]).astype(np.float16),
        jitter=np.array([f.meta.jitter for f in frames], np.float32),
        near_far=np.array((cam.near, cam.far), np.float32),
        truth=np.stack(truth),
    )


def load_cached(path: Path) -> Dataset | None:
    """The dataset saved at ``path``, or None when there is none or it is unreadable
    (said on stderr: the caller makes it again)."""
    if not path.is_file():
        return None
    try:
        with np.load(path) as z:
            return Dataset(**{k: z[k] for k in Dataset.__dataclass_fields__})
    except (OSError, ValueError, KeyError) as e:
        print(f"[data] cached {path} unreadable ({e}); making it again", file=sys.stderr)
        return None


def save(data: Dataset, path: Path) -> None:
    """Write ``data`` to ``path`` through a temporary file, so a killed run never leaves
    a truncated cache behind."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **{k: getattr(data, k) for k in Dataset.__dataclass_fields__})
    tmp.replace(path)


def load_or_generate(
    spec: DatasetSpec, data_dir: Path, progress: bool = True, workers: int = 1
) -> Dataset:
    """The dataset of ``spec`` from ``data_dir`` if cached there, else rendered (by
    ``workers`` processes) and saved."""
    path = data_dir / f"train-{spec.key()}.npz"
    data = load_cached(path)
    if data is None:
        data = generate(spec, progress, workers)
        save(data, path)
    return data
