"""Training sequences over real pictures: pans, zooms and rotations with exact motion.

The game's eight scenes are all the networks saw until now, and on photographs
they fell below bicubic (issue 19). This module makes sequences from the
*training* pictures of the fetched content (``upcast eval content --fetch``:
Debian's wallpaper photographs and Neverball's level screenshots; the held-out
quarter of each source never comes here) in the same arrays as the game's
dataset (``server.train.dataset.Dataset``), so the loop trains on both.

A camera over a flat picture is an affine map per frame from display
coordinates (continuous, pixel (i, j) centred at (i + 0.5, j + 0.5)) to source
pixels, ``source = A @ display + b``, with ``A`` a scale times a rotation. As in
the evaluation's photo sequences (``server.eval.real_content_sequences``),
every pixel is a box average of its footprint in the source: the display
pixel's for the truth, the render pixel's shifted by the frame's Halton jitter
for the render; motion follows from the maps alone (``prev = p + motion``),
depth is constant. Each sequence draws its own source scale, pan velocity,
zoom rate and rotation rate, so the networks see sub-pixel and fast motion,
radial and rotational fields, and a still camera where only the jitter moves.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from server.eval.real_content import load_rgb
from server.eval.real_content_sequences import area_sample_affine
from server.eval.real_content_sources import IMAGE_SUFFIXES, TRAIN_DIR
from server.frames.frame import Camera, Size
from server.game.render.transforms import jitter_offset, jitter_phase_count
from server.ops.progress import elapsed_and_left
from server.ops.progress import progress as report_progress
from server.train.dataset import Dataset, load_cached, save

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
U8 = npt.NDArray[np.uint8]

# The depth every photo frame carries and the camera range it is read with
# (Camera.identity's, what the evaluation's photo frames get).
PHOTO_DEPTH = 0.5
PHOTO_NEAR_FAR = (Camera.identity().near, Camera.identity().far)
# Motion kinds drawn per sequence and their shares: a still camera (only the jitter
# moves), a pan, a pan with a zoom, a pan with a rotation.
MOTION_KINDS = ("still", "pan", "zoom", "rotate")
MOTION_SHARES = (0.2, 0.4, 0.2, 0.2)
MAX_PAN = 4.0  # display px a frame
MAX_ZOOM_STEP = 0.02  # magnification change a frame
MAX_ROTATION_DEG = 1.0  # a frame


@dataclass(frozen=True)
class PictureSource:
    """Pictures of one fetched source, drawn at ``scale_range`` source px per display px."""

    name: str  # folder under the content directory
    render_size: str  # one size for every sequence of this source
    scale_range: tuple[float, float]


# Photographs are large: a display pixel covers 1.5-2.5 of their pixels, so the truth
# holds detail the render cannot (the evaluation uses 2). The screenshots are 256 px.
PHOTO_SOURCES = (
    PictureSource("mate-nature", "128x128", (1.5, 2.5)),
    PictureSource("plasma-photos", "128x128", (1.5, 2.5)),
    PictureSource("lxqt-photos", "128x128", (1.5, 2.5)),
)
SCREENSHOT_SOURCES = (PictureSource("neverball-shots", "64x64", (1.25, 1.6)),)


@dataclass(frozen=True)
class PhotoSpec:
    sequences: int = 192
    frames: int = 10
    truth_frames: int = 3
    render_size: str = "128x128"
    scale: int = 2
    seed: int = 0
    scale_range: tuple[float, float] = (1.5, 2.5)

    def key(self, pictures: list[Path]) -> str:
        """Every parameter and the pictures' names and sizes: another fetch, another key."""
        fields = asdict(self)
        fields["pictures"] = [
            f"{p.parent.parent.name}/{p.name}:{p.stat().st_size}" for p in pictures
        ]
        text = json.dumps(fields, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def training_pictures(content_dir: Path, source: str) -> list[Path]:
    """The training pictures of one fetched source (never its held-out ones), sorted."""
    folder = content_dir / source / TRAIN_DIR
    found = sorted(p for p in folder.glob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
    if not found:
        raise FileNotFoundError(
            f"no training pictures in {folder}; fetch them with "
            f"`upcast eval content --fetch --dir {content_dir}`"
        )
    return found


@dataclass(frozen=True)
class Camera2D:
    """source = a @ display + b for one frame."""

    a: F64  # (2, 2)
    b: F64  # (2,)


def _cameras(
    rng: np.random.Generator,
    frames: int,
    picture: Size,
    display: Size,
    scale_range: tuple[float, float],
) -> list[Camera2D]:
    """A random camera path that stays inside the picture."""
    kind = MOTION_KINDS[int(rng.choice(len(MOTION_KINDS), p=MOTION_SHARES))]
    fit = min(picture.width / display.width, picture.height / display.height)
    d0 = min(float(rng.uniform(*scale_range)), fit)
    speed = 0.0 if kind == "still" else MAX_PAN * float(rng.random()) ** 2  # mostly slow
    heading = float(rng.uniform(0.0, 2.0 * math.pi))
    velocity = speed * np.array([math.cos(heading), math.sin(heading)])
    zoom = float(rng.uniform(-MAX_ZOOM_STEP, MAX_ZOOM_STEP)) if kind == "zoom" else 0.0
    turn = math.radians(float(rng.uniform(-MAX_ROTATION_DEG, MAX_ROTATION_DEG)))
    turn = turn if kind == "rotate" else 0.0
    angle0 = float(rng.uniform(-math.pi, math.pi)) if kind == "rotate" else 0.0
    half_display = np.array([display.width / 2.0, display.height / 2.0])
    steps = np.arange(frames) - (frames - 1) / 2.0
    dmax = d0 * (1.0 + abs(zoom)) ** (frames / 2.0)
    # The view's corners reach |half| * dmax * sqrt(2) from its centre when rotated.
    reach = float(np.abs(half_display).max()) * dmax * (math.sqrt(2.0) if turn else 1.0)
    travel = np.abs(velocity) * dmax * (frames - 1) / 2.0
    lo = reach + travel + 2.0
    hi = np.array([picture.width, picture.height]) - lo
    if np.any(hi < lo):  # the path does not fit: a still view of the centre
        velocity, zoom, turn, angle0 = np.zeros(2), 0.0, 0.0, 0.0
        lo = np.abs(half_display) * d0
        hi = np.array([picture.width, picture.height]) - lo
    centre0 = np.array([rng.uniform(lo[i], max(lo[i], hi[i])) for i in (0, 1)])
    cams = []
    for t in steps:
        d = d0 * (1.0 + zoom) ** (-t)
        ang = angle0 + turn * t
        rot = np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]])
        a = d * rot
        centre = centre0 + d0 * velocity * t
        cams.append(Camera2D(a, centre - a @ half_display))
    return cams


def motion_field(cam: Camera2D, prev: Camera2D, render: Size, scale: float) -> F32:
    """(h, w, 2) render pixels: each unjittered render pixel centre through this
    frame's map to the source and back through the previous frame's."""
    ys, xs = np.mgrid[0 : render.height, 0 : render.width].astype(np.float64) + 0.5
    p = np.stack([xs, ys], axis=-1)
    source = (p * scale) @ cam.a.T + cam.b
    p_prev = ((source - prev.b) @ np.linalg.inv(prev.a).T) / scale
    return np.asarray(p_prev - p, dtype=np.float32)


def _to_u8(image: F32) -> U8:
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def generate(
    spec: PhotoSpec, pictures: list[Path], label: str = "photos", progress: bool = True
) -> Dataset:
    render = Size.parse(spec.render_size)
    s, n, nt = spec.scale, spec.frames, spec.truth_frames
    display = Size(render.width * s, render.height * s)
    h, w = render.height, render.width
    data = Dataset(
        color=np.empty((spec.sequences, n, h, w, 3), np.uint8),
        depth=np.full((spec.sequences, n, h, w), PHOTO_DEPTH, np.float16),
        motion=np.empty((spec.sequences, n, h, w, 2), np.float16),
        jitter=np.empty((spec.sequences, n, 2), np.float32),
        near_far=np.tile(np.array(PHOTO_NEAR_FAR, np.float32), (spec.sequences, 1)),
        truth=np.empty((spec.sequences, nt, display.height, display.width, 3), np.uint8),
    )
    rng = np.random.default_rng(spec.seed)
    phases = jitter_phase_count(s)
    loaded: dict[Path, F32] = {}
    started = time.monotonic()
    for i in range(spec.sequences):
        path = pictures[int(rng.integers(0, len(pictures)))]
        if path not in loaded:
            loaded[path] = load_rgb(path).astype(np.float32)
        src = loaded[path]
        if rng.random() < 0.5:  # mirrored pictures double the content
            src = np.ascontiguousarray(src[:, ::-1])
        cams = _cameras(rng, n, Size(src.shape[1], src.shape[0]), display, spec.scale_range)
        first_phase = int(rng.integers(0, phases))
        for f, cam in enumerate(cams):
            jit = jitter_offset(first_phase + f, phases)
            # A render pixel is s display pixels wide; its sample sits at its centre + jitter.
            a_render = cam.a * s
            b_render = cam.b + a_render @ np.array(jit)
            data.color[i, f] = _to_u8(area_sample_affine(src, a_render, b_render, render))
            data.jitter[i, f] = jit
            data.motion[i, f] = 0.0 if f == 0 else motion_field(cam, cams[f - 1], render, float(s))
            k = f - (n - nt)
            if k >= 0:
                data.truth[i, k] = _to_u8(area_sample_affine(src, cam.a, cam.b, display))
        if progress and ((i + 1) % 16 == 0 or i + 1 == spec.sequences):
            elapsed, eta = elapsed_and_left(i + 1, spec.sequences, started)
            report_progress(
                f"[data] {label} sequence {i + 1}/{spec.sequences} {elapsed:.0f} s, eta {eta:.0f} s"
            )
    return data


def load_or_generate_photos(
    spec: PhotoSpec, pictures: list[Path], data_dir: Path, label: str, progress: bool = True
) -> Dataset:
    """The picture dataset of ``spec`` from ``data_dir`` if cached there, else made and saved."""
    path = data_dir / f"train-{label}-{spec.key(pictures)}.npz"
    data = load_cached(path)
    if data is None:
        data = generate(spec, pictures, label, progress)
        save(data, path)
    return data
