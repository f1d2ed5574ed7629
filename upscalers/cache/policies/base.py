"""The one policy interface: ``decide(signals) -> bool`` ("refresh now?")."""

from __future__ import annotations

from abc import ABC, abstractmethod

from upscalers.cache.signals import FrameSignals


class CachePolicy(ABC):
    """Decides per frame whether to run the whole network (refresh) or reuse the cache.

    ``decide`` applies the rules no policy may overrule (``FrameSignals.must_refresh``:
    the first frame, a scene cut, non-finite input, a cold cache) before asking the
    policy's own rule, so a cut refreshes on the very frame that carries it."""

    name: str = "policy"
    # A late-deciding policy is asked again after the cached path has run, with the
    # input delta at the cache points (refresh_late), and learns from audits.
    decides_late: bool = False

    def decide(self, signals: FrameSignals) -> bool:
        if signals.must_refresh:
            self._restart()
            return True
        return self._refresh_now(signals)

    @abstractmethod
    def _refresh_now(self, signals: FrameSignals) -> bool:
        """The policy's own rule, for a frame the cache could serve."""

    def _restart(self) -> None:  # noqa: B027 - stateless policies have nothing to restart
        """A forced refresh happened (first frame, cut, bad input): restart any schedule."""

    def reset(self) -> None:
        """A new stream: forget everything learned or counted."""
        self._restart()

    def refresh_late(self, input_delta: float) -> bool:
        """For a frame the early rule let the cache serve, after the cached path ran:
        refresh after all? ``input_delta`` is ``LayerCache.input_delta()``. Only
        asked of a policy that ``decides_late``."""
        return False

    def observe_audit(self, input_delta: float, stale_psnr_db: float) -> None:  # noqa: B027
        """After a late refresh: the PSNR of the cached output (already computed, then
        discarded) against the full one, and the input delta it was cached at."""

    def describe(self) -> str:
        return self.name
