"""LayerCache: keep the deep branches' outputs on refresh frames, reuse them on cached ones.

It works on any network that declares cache points (see ``points``): each named
submodule is replaced in its parent by a ``CachedBranch`` that holds the
original. The network's ``forward`` is never edited; the parent calls the
wrapper exactly where it called the branch. ``restore()`` puts the originals
back.

Modes (``LayerCache.mode``):

- ``REFRESH``: run the branch and keep a detached clone of its output.
- ``REUSE``: return the kept output without running the branch. A branch with
  nothing usable kept (first frame, invalidated, or its input changed shape,
  dtype or device: a resolution change) runs and keeps instead, so a reuse
  request never fails; ``last_forward_reused`` tells whether it really reused.
- ``PASSTHROUGH``: run the branch, keep nothing, leave the cache as it is.

Non-finite branch outputs are never kept: the branch is emptied instead, and
the next reuse falls back to running it.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from upscalers.cache.points import cache_points, default_config_of
from upscalers.cache.signals import all_finite, smape


class CacheMode(enum.Enum):
    REFRESH = "refresh"
    REUSE = "reuse"
    PASSTHROUGH = "passthrough"


class BranchAction(enum.Enum):
    NOT_RUN = "not_run"
    COMPUTED = "computed"
    REUSED = "reused"


@dataclass(frozen=True)
class _InputSignature:
    """What a kept output is valid for: the tensor inputs' shapes, dtypes and devices."""

    tensors: tuple[tuple[tuple[int, ...], torch.dtype, torch.device], ...]

    @staticmethod
    def of(args: tuple[Any, ...], kwargs: dict[str, Any]) -> _InputSignature:
        values = [*args, *kwargs.values()]
        return _InputSignature(
            tuple(
                (tuple(v.shape), v.dtype, v.device) for v in values if isinstance(v, torch.Tensor)
            )
        )


@dataclass(frozen=True)
class KeptOutput:
    """A branch output kept on a refresh frame, and the input signature it is valid for."""

    tensor: torch.Tensor
    valid_for: _InputSignature
    version: int | None


class CachedBranch(nn.Module):
    """Stands in for one deep branch; ``original`` is the branch itself."""

    _cache: LayerCache

    def __init__(self, original: nn.Module, cache: LayerCache, name: str) -> None:
        super().__init__()
        self.original = original
        self.point = name
        # Not a submodule: the cache owns its wrappers, not the other way round.
        object.__setattr__(self, "_cache", cache)
        self.entry: KeptOutput | None = None
        self.last_action = BranchAction.NOT_RUN
        # With LayerCache.probe_inputs: a subsample of this frame's branch input and of
        # the one the kept output was computed from (see LayerCache.input_delta).
        self.input_probe: torch.Tensor | None = None
        self.kept_probe: torch.Tensor | None = None

    @property
    def kept(self) -> torch.Tensor | None:
        return None if self.entry is None else self.entry.tensor

    def forward(self, *args: Any, **kwargs: Any) -> Any:
        mode: CacheMode = self._cache.mode
        if self._cache.probe_inputs:
            self.input_probe = _probe(args)
        if mode is CacheMode.REUSE and self._usable(_InputSignature.of(args, kwargs)):
            self.last_action = BranchAction.REUSED
            return self.kept
        out = self.original(*args, **kwargs)
        self.last_action = BranchAction.COMPUTED
        if mode is not CacheMode.PASSTHROUGH:
            self._keep(out, _InputSignature.of(args, kwargs))
        return out

    def _usable(self, signature: _InputSignature) -> bool:
        e = self.entry
        if e is None or signature != e.valid_for:
            return False
        # A parent that modified the reused tensor in place would have changed what
        # later frames reuse; the version counter shows it (inference tensors have none).
        return e.version is None or _version_of(e.tensor) == e.version

    def _keep(self, out: Any, signature: _InputSignature) -> None:
        if not isinstance(out, torch.Tensor):
            raise TypeError(
                f"cache point {self.point!r} returned {type(out).__name__}; "
                "a cacheable branch must return one tensor"
            )
        if not all_finite(out):
            self.clear()
            return
        # No copy when the version counter can tell an in-place change by the parent
        # (then _usable refuses the tensor): a refresh frame saves a full copy of the
        # branch output (11 MB at level 1 of the U-Net at 640x360). Inference tensors
        # have no counter, so those are copied.
        kept = out.detach()
        version = _version_of(kept)
        if version is None:
            kept = kept.clone()
        self.entry = KeptOutput(kept, signature, version)
        self.kept_probe = self.input_probe

    def clear(self) -> None:
        self.entry = None
        self.kept_probe = None

    @property
    def nbytes(self) -> int:
        return 0 if self.kept is None else self.kept.numel() * self.kept.element_size()


# Every PROBE_STRIDE-th row and column of a branch input: 1/16 of a level-1 input
# of the U-Net (12 x 360 x 640) is 0.17 M values, a fraction of a millisecond.
PROBE_STRIDE = 4


def _probe(args: tuple[Any, ...]) -> torch.Tensor | None:
    first = next((a for a in args if isinstance(a, torch.Tensor)), None)
    if first is None:
        return None
    return first.detach()[..., ::PROBE_STRIDE, ::PROBE_STRIDE].float().clone()


def probe_delta(current: torch.Tensor | None, kept: torch.Tensor | None) -> float:
    """ReFrame's SMAPE (``signals.smape``) of two probes; inf when one is missing or the
    shapes differ."""
    if current is None or kept is None or current.shape != kept.shape:
        return math.inf
    return smape(current, kept)


def _version_of(t: torch.Tensor) -> int | None:
    try:
        return int(t._version)
    except RuntimeError:  # inference tensors track no version
        return None


class LayerCache:
    """Installs ``CachedBranch`` wrappers on ``model``'s cache points for ``config``.

    ``config`` is one of the network's ``cache_configs`` (None: its default).
    Use as a context manager or call ``restore()`` to take the wrappers out."""

    def __init__(self, model: nn.Module, config: str | None = None) -> None:
        self.model = model
        self.points = cache_points(model, config)
        self.config = config if config is not None else default_config_of(model)
        self.mode = CacheMode.REFRESH
        # Whether branches keep input probes (only a policy that reads input_delta pays).
        self.probe_inputs = False
        self.branches: dict[str, CachedBranch] = {}
        for point in self.points:
            parent_name, _, attr = point.rpartition(".")
            parent = model.get_submodule(parent_name)
            original = getattr(parent, attr)
            if isinstance(original, CachedBranch):
                raise ValueError(f"{point!r} is already wrapped by another LayerCache")
            wrapper = CachedBranch(original, self, point)
            setattr(parent, attr, wrapper)
            self.branches[point] = wrapper
        self._installed = True

    @property
    def installed(self) -> bool:
        return self._installed

    def restore(self) -> None:
        """Put the original branches back in their parents; idempotent."""
        if not self._installed:
            return
        for point, wrapper in self.branches.items():
            parent_name, _, attr = point.rpartition(".")
            setattr(self.model.get_submodule(parent_name), attr, wrapper.original)
            wrapper.clear()
        self._installed = False

    def __enter__(self) -> LayerCache:
        return self

    def __exit__(self, *exc: object) -> None:
        self.restore()

    @contextmanager
    def using(self, mode: CacheMode) -> Iterator[None]:
        previous, self.mode = self.mode, mode
        try:
            yield
        finally:
            self.mode = previous

    def invalidate(self) -> None:
        """Forget every kept output; the next forward runs everything."""
        for wrapper in self.branches.values():
            wrapper.clear()

    @property
    def warm(self) -> bool:
        """Whether every branch holds a kept output (a reuse can skip them all)."""
        return all(w.kept is not None for w in self.branches.values())

    def snapshot(self) -> dict[str, KeptOutput | None]:
        """What every branch holds now (for measuring without disturbing the cache)."""
        return {name: b.entry for name, b in self.branches.items()}

    def put_back(self, snapshot: dict[str, KeptOutput | None]) -> None:
        for name, entry in snapshot.items():
            self.branches[name].entry = entry

    @property
    def nbytes(self) -> int:
        """Memory held by the kept outputs."""
        return sum(w.nbytes for w in self.branches.values())

    def input_delta(self) -> float:
        """How far the cached branches' inputs of the last forward are from the inputs
        their kept outputs were computed from: the largest SMAPE over the branches
        (``probe_delta``, on every 4th row and column). It is the input delta measured
        where the cache acts, so it sees what the colour's delta cannot: a change of
        history, depth or motion, and what the shallow layers make of them. Needs
        ``probe_inputs``; inf when a branch has nothing to compare."""
        if not self.branches:
            return math.inf
        return max(probe_delta(b.input_probe, b.kept_probe) for b in self.branches.values())

    @property
    def last_forward_reused(self) -> bool:
        """Whether the last forward skipped every cached branch."""
        return all(w.last_action is BranchAction.REUSED for w in self.branches.values())
