"""Frames that carry colour only (FrameFlags.COLOR_ONLY: a captured X11 display).

Their depth and motion planes are undefined (whatever the slot held), so the host
must neither read them (no sanitizing, no temporal method) nor let a viewer switch
to a method that needs them; the worker says which methods work for the source.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from server.frames.frame import Camera, FrameFlags, FrameMeta, RenderFrame, Size
from upscalers import registry
from upscalers.host import COLOR_ONLY_STAND_IN, UpscalerHost, color_only_methods, needs_gbuffers
from upscalers.output import to_uint8

RENDER = Size(64, 36)
DISPLAY = Size(128, 72)


def color_only_frame(seed: int = 0, *, garbage: bool = True) -> RenderFrame:
    rng = np.random.default_rng(seed)
    w, h = RENDER
    depth = np.full((h, w), np.nan, np.float32) if garbage else np.ones((h, w), np.float32)
    motion = np.full((h, w, 2), np.inf, np.float32) if garbage else np.zeros((h, w, 2), np.float32)
    return RenderFrame(
        color=rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
        depth=depth,
        motion=motion,
        dynamic_mask=np.zeros((h, w), np.uint8),
        meta=FrameMeta(frame_id=seed, camera=Camera.identity(), flags=FrameFlags.COLOR_ONLY),
    )


def test_the_colour_only_list_is_every_method_without_gbuffers() -> None:
    methods = color_only_methods()
    assert "temporal" not in methods and "unet" not in methods
    assert {"bilinear", "bicubic", "easu_rcas", "cv_lanczos4"} <= set(methods)
    assert set(methods) | {m for m in registry.available() if needs_gbuffers(m)} == set(
        registry.available()
    )


@pytest.mark.parametrize("name", ["bilinear", "easu_rcas", "lanczos2"])
def test_undefined_gbuffers_are_not_read(name: str) -> None:
    """NaN depth and Inf motion in a colour-only slot: the same picture as clean planes,
    and nothing counted as sanitized (they are not values, they are absent)."""
    host = UpscalerHost(name, DISPLAY)
    dirty = to_uint8(host.upscale(color_only_frame(3, garbage=True)))
    clean = to_uint8(UpscalerHost(name, DISPLAY).upscale(color_only_frame(3, garbage=False)))
    assert np.array_equal(dirty, clean)
    assert host.sanitized_frames == 0
    assert host.color_only and host.name == name


def test_a_temporal_method_gives_way_on_colour_only_frames(
    caplog: pytest.LogCaptureFixture,
) -> None:
    host = UpscalerHost("temporal", DISPLAY)
    with caplog.at_level(logging.WARNING):
        out = host.upscale(color_only_frame(1))
        host.upscale(color_only_frame(2))
    assert host.name == COLOR_ONLY_STAND_IN
    assert tuple(out.shape) == (3, DISPLAY.height, DISPLAY.width)
    warnings = [r.getMessage() for r in caplog.records if "colour only" in r.getMessage()]
    assert len(warnings) == 1 and "temporal" in warnings[0]


def test_switching_to_a_method_that_needs_gbuffers_is_refused_with_the_choices() -> None:
    host = UpscalerHost("bilinear", DISPLAY)
    host.upscale(color_only_frame(0))
    with pytest.raises(ValueError, match=r"needs depth, motion and jitter.*easu_rcas"):
        host.switch("temporal")
    assert host.name == "bilinear"
    host.switch("bicubic")  # a spatial one is fine
    assert host.name == "bicubic"


def test_a_rendered_frame_after_colour_only_ones_allows_temporal_again() -> None:
    host = UpscalerHost("bilinear", DISPLAY)
    host.upscale(color_only_frame(0))
    frame = color_only_frame(1, garbage=False)
    frame.meta.flags = FrameFlags.NONE
    host.upscale(frame)
    assert not host.color_only
    host.switch("temporal")
    assert host.name == "temporal"
