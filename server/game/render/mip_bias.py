"""The ``--mip-bias`` option of the commands that render for an upscaler.

'game' leaves the choice to the renderer, as the live game does: jittered
renders (for temporal upscalers) pick the display size's mips, unjittered ones
the render size's (see ``Renderer``). 'auto' gives every render the display
size's mips, log2(render / display); a number fixes the bias.
"""

from __future__ import annotations

import math

from server.frames.frame import Size

MIP_BIAS_HELP = (
    "texture LOD bias of the render-size frames: 'game' (the default) as the live game "
    "renders: jittered frames for temporal upscalers pick the display size's mips "
    "(log2(render / display), -1 at 2x, as the FSR and DLSS integration guides ask), "
    "unjittered frames for spatial ones the render size's; 'auto' gives every method the "
    "display size's mips; a number fixes the bias (0: the render size's mips for all). "
    "The ground truth always picks the display size's mips"
)


def game_lod_bias(jitter: bool, scale: float) -> float:
    """The game's choice: the display size's mips for a jittered render, log2(render /
    display) = -log2(scale); the render size's (0) for an unjittered one."""
    return -math.log2(scale) if jitter and scale > 0 else 0.0


def parse_mip_bias(text: str, render: Size, display: Size) -> float | None:
    """The fixed bias ``text`` asks for, or None for the renderer's own choice ('game')."""
    word = text.strip()
    if word == "game":
        return None
    if word == "auto":
        return math.log2(render.width / display.width)
    try:
        bias = float(word)
    except ValueError:
        raise ValueError(f"--mip-bias: expected 'game', 'auto' or a number, got {text!r}") from None
    if not math.isfinite(bias):
        raise ValueError(f"--mip-bias must be finite, got {text!r}")
    return bias
