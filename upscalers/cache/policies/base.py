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
    # Whether the policy learns from audits (see observe_audit).
    wants_audit: bool = False

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

    def observe_audit(self, signals: FrameSignals, stale_psnr_db: float) -> None:  # noqa: B027
        """On a refresh the policy chose (not a forced one), the PSNR of what the stale
        cache would have given against the full output; only called if wants_audit."""

    def describe(self) -> str:
        return self.name
