"""The frame rate and render size ``upcast up`` uses when none is given: what this
machine's cores can hold with the built-in CPU renderer.

Why cores, not a start-up benchmark: every stage shares the same cores (the game's
torch ray caster, the upscaler worker, x264 and the relay), so the renderer alone
measures fast and the stack still falls short; the figures below are the whole stack
measured on 2 cores (docs/measurements/streaming.md, "Latency budget": 640x360 at a
60 fps target held 25-28 fps, 52 budget warnings in 90 s). The render cost grows with
render pixels, so with fewer cores the render scale drops before the frame rate does.
``--fps`` and ``--render-size`` override either choice.
"""

from __future__ import annotations

from dataclasses import dataclass

from server.frames.frame import Size
from server.ops.machine import usable_cores

# (fewest usable cores per session, fps, render scale of the display size); first match.
_TIERS: tuple[tuple[int, float, float], ...] = (
    (8, 60.0, 0.5),
    (4, 30.0, 0.5),
    (0, 30.0, 0.375),
)


@dataclass(frozen=True)
class FittedDefaults:
    fps: float
    render_size: Size
    reason: str


def _even(value: float) -> int:
    return max(2, round(value / 2.0) * 2)


def fitted_defaults(display: Size, cores: int | None = None, sessions: int = 1) -> FittedDefaults:
    """fps and render size for ``sessions`` streams sharing ``cores`` (default: this machine's)."""
    total = usable_cores() if cores is None else cores
    per_session = total / max(1, sessions)
    fps, scale = next((f, s) for fewest, f, s in _TIERS if per_session >= fewest)
    render = Size(_even(display.width * scale), _even(display.height * scale))
    share = f"{total} cores" if sessions == 1 else f"{total} cores for {sessions} sessions"
    reason = (
        f"{share} with the CPU renderer: {fps:g} fps at render scale {scale:g} of the "
        f"{display.width}x{display.height} display is what the whole stack holds there"
    )
    return FittedDefaults(fps, render, reason)
