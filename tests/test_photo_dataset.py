"""Training sequences over real pictures (server/train/photo_dataset.py, mix.py)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

from server.frames.frame import Size
from server.train.loop import DataMix, TrainConfig, train
from server.train.mix import build_mix
from server.train.photo_dataset import (
    PHOTO_SOURCES,
    SCREENSHOT_SOURCES,
    Camera2D,
    PhotoSpec,
    area_sample_affine,
    generate,
    load_or_generate_photos,
    motion_field,
    training_pictures,
)
from upscalers.neural.network import build_model


def _noise_picture(seed: int, size: int = 400) -> np.ndarray:
    """Smooth random texture: detail at every scale, like a photograph."""
    rng = np.random.default_rng(seed)
    base = rng.random((size // 8, size // 8, 3)).astype(np.float32) * 255
    fine = rng.random((size, size, 3)).astype(np.float32) * 60
    big = cv2.resize(base, (size, size), interpolation=cv2.INTER_CUBIC)
    return np.clip(big + fine - 30, 0, 255).astype(np.uint8)


@pytest.fixture
def content(tmp_path: Path) -> Path:
    """A content folder like `upcast eval content --fetch` makes: train and held_out
    pictures per source; the held-out ones pure red, so any leak shows."""
    sizes = [(s.name, 400) for s in PHOTO_SOURCES] + [(s.name, 256) for s in SCREENSHOT_SOURCES]
    for source, size in sizes:
        for i in range(2):
            train_dir = tmp_path / source / "train"
            train_dir.mkdir(parents=True, exist_ok=True)
            Image.fromarray(_noise_picture(i, size)).save(train_dir / f"p{i}.png")
        held = tmp_path / source / "held_out"
        held.mkdir(parents=True, exist_ok=True)
        red = np.zeros((size, size, 3), np.uint8)
        red[..., 0] = 255
        Image.fromarray(red).save(held / "red.png")
    return tmp_path


def test_affine_box_sampling_is_the_box_mean_on_whole_pixels() -> None:
    # Two source pixels a display pixel from the origin: each output pixel is the mean
    # of a 2x2 block, what OpenCV's area resize computes; shifted by whole pixels, the
    # blocks move with it.
    src = _noise_picture(3).astype(np.float32)
    out = area_sample_affine(src, np.diag([2.0, 2.0]), np.array([0.0, 0.0]), Size(64, 48))
    boxes = cv2.resize(src[:96, :128], (64, 48), interpolation=cv2.INTER_AREA)
    assert np.abs(out - boxes).max() < 1e-3
    shifted = area_sample_affine(src, np.diag([2.0, 2.0]), np.array([6.0, 4.0]), Size(64, 48))
    assert np.abs(shifted - cv2.resize(src[4:100, 6:134], (64, 48),
                                       interpolation=cv2.INTER_AREA)).max() < 1e-3  # fmt: skip


def test_a_rotated_box_keeps_the_mean_of_a_smooth_picture() -> None:
    # A linear ramp: the box mean of any footprint is the ramp at its centre.
    ys, xs = np.mgrid[0:300, 0:300].astype(np.float32)
    ramp = np.stack([xs * 0.5, ys * 0.5, xs * 0.25 + ys * 0.25], axis=-1)
    ang = math.radians(30)
    a = 2.0 * np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]])
    b = np.array([150.0, 60.0])
    out = area_sample_affine(ramp, a, b, Size(40, 40))
    u = np.array([10.5, 20.5])  # display pixel (10, 20)
    centre = a @ u + b  # continuous source position; the ramp is at pixel centres
    expect = np.array([(centre[0] - 0.5) * 0.5, (centre[1] - 0.5) * 0.5])
    assert np.allclose(out[20, 10, :2], expect, atol=1e-3)


def test_motion_points_where_the_surface_was_in_the_previous_frame() -> None:
    ang = math.radians(0.8)
    rot = np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]])
    prev = Camera2D(np.diag([2.0, 2.0]), np.array([40.0, 30.0]))
    cam = Camera2D(1.98 * rot, np.array([41.3, 29.2]))
    render = Size(20, 16)
    motion = motion_field(cam, prev, render, 2.0)
    # Render pixel (5, 7)'s centre, through this frame's map, lands in the previous
    # frame at p + motion: the previous map sends that point to the same source spot.
    p = np.array([5.5, 7.5])
    source = cam.a @ (p * 2.0) + cam.b
    q = p + motion[7, 5].astype(np.float64)
    assert np.allclose(prev.a @ (q * 2.0) + prev.b, source, atol=1e-4)


def test_sequences_warp_into_each_other_with_their_motion(content: Path) -> None:
    pictures = training_pictures(content, "mate-nature")
    data = generate(PhotoSpec(sequences=8, frames=5, render_size="64x64"), pictures, progress=False)
    h, w = data.color.shape[2:4]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    moving = 0
    for i in range(data.sequences):
        m = data.motion[i].astype(np.float32)
        if np.abs(m).max() < 0.25:
            continue
        moving += 1
        for f in range(1, data.frames):
            err = {}
            for sign in (1.0, -1.0):
                # The sample of pixel p sits at p + jitter: the same surface point in the
                # previous frame is at p + motion + this jitter - the previous jitter.
                jx, jy = data.jitter[i, f] - data.jitter[i, f - 1]
                mx, my = xs + sign * m[f, ..., 0] + jx, ys + sign * m[f, ..., 1] + jy
                prev = data.color[i, f - 1].astype(np.float32)
                warped = cv2.remap(prev, mx, my, cv2.INTER_CUBIC)
                diff = (warped - data.color[i, f].astype(np.float32))[6:-6, 6:-6]
                err[sign] = float(np.sqrt((diff**2).mean()))
            assert err[1.0] < 0.6 * err[-1.0] or err[1.0] < 2.0, err
    assert moving >= 3  # most sequences move


def test_held_out_pictures_never_reach_training(content: Path, tmp_path: Path) -> None:
    pictures = training_pictures(content, "plasma-photos")
    assert all(p.parent.name == "train" for p in pictures)
    data = generate(PhotoSpec(sequences=6, frames=3, render_size="48x48"), pictures, progress=False)
    red = (data.truth[..., 0] > 240) & (data.truth[..., 1] < 15) & (data.truth[..., 2] < 15)
    assert red.mean() < 0.01
    with pytest.raises(FileNotFoundError, match="upcast eval content --fetch"):
        training_pictures(tmp_path / "nowhere", "plasma-photos")


def test_generation_is_deterministic_and_cached_by_its_key(content: Path, tmp_path: Path) -> None:
    pictures = training_pictures(content, "mate-nature")
    spec = PhotoSpec(sequences=3, frames=3, render_size="32x32")
    a = load_or_generate_photos(spec, pictures, tmp_path / "cache", "photos", progress=False)
    b = load_or_generate_photos(spec, pictures, tmp_path / "cache", "photos", progress=False)
    assert len(list((tmp_path / "cache").glob("train-photos-*.npz"))) == 1
    assert np.array_equal(a.color, b.color) and np.array_equal(a.truth, b.truth)
    other = dataclasses.replace(spec, seed=1)
    assert other.key(pictures) != spec.key(pictures)
    assert not np.array_equal(generate(other, pictures, progress=False).color, a.color)


def test_mix_trains_on_every_part_and_refuses_bad_shares(content: Path, tmp_path: Path) -> None:
    from server.train.dataset import DatasetSpec
    from server.train.dataset import generate as generate_game

    game = generate_game(
        DatasetSpec(sequences=1, frames=4, render_size="32x24", scenes=("static",)),
        progress=False,
    )
    spec = PhotoSpec(frames=4, truth_frames=3)
    assert build_mix(game, None, 0.5, spec, tmp_path) is game
    mix = build_mix(game, content, 0.5, spec, tmp_path / "cache")
    assert isinstance(mix, DataMix)
    assert [label for label, _, _ in mix.parts] == ["game", "photos", "screenshots"]
    assert np.allclose(mix.probabilities(), [0.5, 0.375, 0.125])
    torch.manual_seed(0)
    # Equal weights here, so a dozen steps draw every part (the draws are seeded).
    even = DataMix(tuple((label, data, 1.0) for label, data, _ in mix.parts))
    result = train(build_model("unet", 2), even, TrainConfig(steps=12, batch=2, crop=16), 2,
                   progress=False)  # fmt: skip
    assert set(result.final_loss_by_part) == {"game", "photos", "screenshots"}
    assert all(math.isfinite(v) for v in result.final_loss_by_part.values())
    with pytest.raises(ValueError, match="share"):
        build_mix(game, content, 1.0, spec, tmp_path)
    with pytest.raises(ValueError, match="weights"):
        DataMix((("game", game, 0.0),))
