"""False-colour images of G-buffers for people: depth as grey, motion as hue/brightness."""

from __future__ import annotations

import numpy as np

from server.frames.frame import F32Array, U8Array


def depth_image(depth: F32Array) -> U8Array:
    """Near = white, sky = black; NDC z bunches up near 1, so stretch it first."""
    lin = np.clip(1.0 - depth, 0.0, 1.0) ** 0.25
    out: U8Array = (lin * 255.0 + 0.5).astype(np.uint8)
    return out


def motion_image(motion: F32Array, max_px: float = 8.0) -> U8Array:
    """Direction as hue, length (saturating at ``max_px``) as brightness; zero = black."""
    mx, my = motion[..., 0], motion[..., 1]
    angle = (np.arctan2(my, mx) + np.pi) / (2 * np.pi)
    mag = np.clip(np.hypot(mx, my) / max_px, 0.0, 1.0)
    phase = angle[..., None] * 6.0 - np.array([3.0, 1.0, 5.0]) * 1.0
    rgb = np.clip(np.abs(np.mod(phase + 6.0, 6.0) - 3.0) - 1.0, 0.0, 1.0)
    return (rgb * mag[..., None] * 255.0 + 0.5).astype(np.uint8)
