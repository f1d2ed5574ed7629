"""UpscalerHost: runs the configured upscaler on frames, in or out of process.

It owns what a method should not have to think about: sanitizing input,
resetting history on RESET frames, size changes and scene cuts the frames do not
flag (``cut_detector.py``), switching methods at run time. The worker process
and in-process callers use this same class, which is why the decoupled path gives
the same bits as a direct call.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from typing import Any

import torch

from server.frames.frame import FrameFlags, RenderFrame, Size
from upscalers import registry
from upscalers.base import Upscaler
from upscalers.cache.policies import make_policy
from upscalers.sanitize import SanitizeReport, sanitize_frame
from upscalers.temporal.cut_detector import CutDetector

log = logging.getLogger(__name__)

_WARN_EVERY_S = 5.0
# What upscales predicted frames while a temporal method runs (see UpscalerHost.upscale).
PREDICTED_STAND_IN = "bicubic"
# What a temporal method gives way to when the frames carry colour only (FrameFlags
# COLOR_ONLY): the best spatial method on the game's scenes and on photographs
# (docs/reports/eval_upscalers.md, eval_real_content.md).
COLOR_ONLY_STAND_IN = "easu_rcas"


def needs_gbuffers(name: str) -> bool:
    """Whether the method reads depth, motion or jitter (every temporal one does)."""
    return registry.is_temporal(name)


def color_only_methods() -> list[str]:
    """The methods that work from the colour plane alone."""
    return [m for m in registry.available() if not needs_gbuffers(m)]


class UpscalerHost:
    def __init__(
        self,
        name: str,
        display_size: Size,
        options: Mapping[str, Any] | None = None,
        *,
        compile: bool = False,
        cache_policy: str | None = None,
        detect_cuts: bool = True,
    ) -> None:
        # compile=True: every method that has a compiled path (the start one and any
        # switched to) uses it; the others run as usual.
        self.compile = compile
        # The layer-cache policy chosen (at start or at run time): every method with a
        # cache started later runs it too, so a switch away and back keeps the choice.
        if cache_policy is not None:
            make_policy(cache_policy)  # a bad name fails at start, cache or not
        self.chosen_cache_policy = cache_policy
        # Constructor options (e.g. RCAS sharpness) of the method started with; a
        # run-time switch starts the new method with its defaults.
        self.upscaler: Upscaler = self._create(name, options)
        self.display_size = display_size
        self._last_input_size: Size | None = None
        # Spatial stand-in for predicted frames while a temporal method runs (see upscale).
        self._predicted_stand_in: Upscaler | None = None
        self.sanitized_values = 0
        self.sanitized_frames = 0
        self._last_warning = 0.0
        # Set by the last frame: its source gave colour only (no depth, motion, jitter).
        self.color_only = False
        # Scene cuts the frames do not flag, found before a temporal method blends
        # across them (upscalers/temporal/cut_detector.py); None: trust the RESET flag alone.
        self._cuts = CutDetector() if detect_cuts else None
        self.cuts_found = 0

    @property
    def name(self) -> str:
        return self.upscaler.name

    def switch(self, name: str) -> None:
        """Use another method from the next frame on (raises ValueError if unknown)."""
        if name == self.upscaler.name:
            return
        if self.color_only and needs_gbuffers(name):
            raise ValueError(
                f"upscaler {name!r} needs depth, motion and jitter, which this source does "
                f"not give (its frames carry colour only); methods for it: "
                + ", ".join(color_only_methods())
            )
        new = self._create(name)
        log.info("upscaler switched: %s -> %s", self.upscaler.name, name)
        self.upscaler = new
        self._last_input_size = None
        if self._cuts is not None:
            self._cuts.reset()  # the last frame it saw may be long ago

    def _create(self, name: str, options: Mapping[str, Any] | None = None) -> Upscaler:
        opts = dict(options or {})
        if self.compile and registry.takes_option(name, "compile"):
            opts.setdefault("compile", True)
            log.info("%s: compiled path on; the first frame of each size compiles", name)
        if self.chosen_cache_policy is not None and registry.takes_option(name, "policy"):
            opts.setdefault("policy", self.chosen_cache_policy)
        return registry.create(name, **opts)

    @property
    def cache_policy(self) -> str | None:
        """The policy the current method's layer cache runs (None: it has no cache)."""
        return self.upscaler.cache_policy

    def set_cache_policy(self, policy: str) -> None:
        """Run ``policy`` from the next frame on, and in every cached method started
        later. ValueError for a bad name, or when the current method has no cache
        (nothing changes then: a refused request is not half-applied)."""
        if self.upscaler.cache_policy is None:
            cached = [m for m in registry.available() if registry.takes_option(m, "policy")]
            raise ValueError(
                f"upscaler {self.name!r} has no layer cache; cache policies apply to "
                + ", ".join(cached)
            )
        self.upscaler.set_cache_policy(policy)
        self.chosen_cache_policy = policy.strip()
        log.info("cache policy of %s: %s", self.name, self.chosen_cache_policy)

    def upscale(self, frame: RenderFrame) -> torch.Tensor:
        """Sanitize, reset history when needed, upscale. Returns the method's tensor."""
        if frame.meta.flags & FrameFlags.COLOR_ONLY:
            return self._upscale_color_only(frame)
        self.color_only = False
        frame, report = sanitize_frame(frame)
        if report.total:
            self._note_sanitized(frame.meta.frame_id, report)
        if frame.meta.flags & FrameFlags.PREDICTED and self.upscaler.temporal:
            return self._upscale_predicted_stand_in(frame)
        # The detector sees every frame first (it keeps the last one to compare with).
        cut = self._unflagged_cut(frame)
        if cut or frame.meta.flags & FrameFlags.RESET or frame.size != self._last_input_size:
            self.upscaler.reset()
            self._last_input_size = frame.size
        return self.upscaler.upscale(frame, self.display_size)

    def _unflagged_cut(self, frame: RenderFrame) -> bool:
        """Whether a temporal method is about to blend across a scene cut that the frame
        does not flag (a spatial method keeps no history: nothing to look for)."""
        if self._cuts is None or not self.upscaler.temporal:
            return False
        if not self._cuts.observe(frame) or frame.meta.flags & FrameFlags.RESET:
            return False
        self.cuts_found += 1
        log.info(
            "frame %d: scene cut without the RESET flag (%.0f %% of the picture changed "
            "past its neighbourhood); %s starts its history afresh",
            frame.meta.frame_id,
            100.0 * (self._cuts.last_changed or 0.0),
            self.upscaler.name,
        )
        return True

    def _upscale_color_only(self, frame: RenderFrame) -> torch.Tensor:
        """A colour-only frame's depth and motion planes are undefined: nothing reads
        them (no sanitizing either), and a method that needs them gives way for good."""
        self.color_only = True
        if needs_gbuffers(self.upscaler.name):
            log.warning(
                "frames carry colour only (no depth, motion or jitter): upscaler %s needs "
                "them, switching to %s",
                self.upscaler.name,
                COLOR_ONLY_STAND_IN,
            )
            self.upscaler = self._create(COLOR_ONLY_STAND_IN)
            self._last_input_size = None
        if frame.size != self._last_input_size:
            self.upscaler.reset()
            self._last_input_size = frame.size
        return self.upscaler.upscale(frame, self.display_size)

    def _upscale_predicted_stand_in(self, frame: RenderFrame) -> torch.Tensor:
        """A predicted frame has no jitter and no motion from the frame before it, so it
        must not enter a temporal method's history; it gets a spatial method instead."""
        if self._predicted_stand_in is None:
            log.warning(
                "frame generation with temporal upscaler %s: predicted frames use %s",
                self.upscaler.name,
                PREDICTED_STAND_IN,
            )
            self._predicted_stand_in = registry.create(PREDICTED_STAND_IN)
        return self._predicted_stand_in.upscale(frame, self.display_size)

    def _note_sanitized(self, frame_id: int, report: SanitizeReport) -> None:
        self.sanitized_values += report.total
        self.sanitized_frames += 1
        now = time.monotonic()
        if now - self._last_warning >= _WARN_EVERY_S:
            self._last_warning = now
            log.warning(
                "frame %d: replaced %d non-finite depth, %d motion, %d camera values "
                "(%d frames sanitized so far)",
                frame_id,
                report.depth_fixed,
                report.motion_fixed,
                report.meta_fixed,
                self.sanitized_frames,
            )
