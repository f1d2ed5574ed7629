"""The contract of a cacheable network: which submodules' outputs may be reused.

A cacheable network is an ``nn.Module`` whose class declares

- ``cache_configs: ClassVar[dict[str, tuple[str, ...]]]``: a cache config name
  ("1", "2", "3" for a U-Net; "A", "B" for a U-Net++) -> the dotted names of
  submodules (``model.get_submodule(name)``) whose OUTPUTS are reused on cached
  frames;
- ``default_cache_config: ClassVar[str]``: the config used when none is named.

Each named submodule must be a *deep branch*: its parent's forward calls it
exactly once per forward, and everything that only feeds it is computed inside
it, so skipping the call skips that work. A U-Net is therefore written
recursively, ``UNetLevel(enc, inner, dec)`` with ``inner`` = downsample ->
deeper level -> upsample as ONE submodule and ``dec(cat(enc_out, inner(enc_out)))``
in the parent. ReFrame's level 1 ("cache the last block", the most FLOPs
removed) caches the outermost ``inner``; level 2 the next one down; level 3 the
deepest. For a U-Net++ each nested node's input branch off the foundational
U-Net path is a cacheable submodule.

Nothing here edits a network: ``LayerCache`` replaces the named submodules in
their parents with wrappers (see ``layer_cache``).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from torch import nn


@runtime_checkable
class CacheableNetwork(Protocol):
    """What ``LayerCache`` needs from a network class besides being an ``nn.Module``."""

    cache_configs: dict[str, tuple[str, ...]]
    default_cache_config: str


class CachePointError(ValueError):
    """A cache config that names nothing usable (unknown config, missing submodule)."""


def cache_configs_of(model: nn.Module) -> dict[str, tuple[str, ...]]:
    configs = getattr(type(model), "cache_configs", None)
    if not isinstance(configs, dict) or not configs:
        raise CachePointError(
            f"{type(model).__name__} declares no cache_configs; a cacheable network "
            "maps config names to the dotted names of its deep branches"
        )
    return configs


def default_config_of(model: nn.Module) -> str:
    configs = cache_configs_of(model)
    default = getattr(type(model), "default_cache_config", None)
    if isinstance(default, str) and default in configs:
        return default
    raise CachePointError(
        f"{type(model).__name__}.default_cache_config must name one of "
        f"{', '.join(sorted(configs))}, got {default!r}"
    )


def cache_points(model: nn.Module, config: str | None = None) -> tuple[str, ...]:
    """The dotted submodule names that ``config`` (default: the network's own) caches.

    Raises ``CachePointError`` naming the allowed configs for an unknown one, and
    the missing name for a config that points at no submodule. Names must not
    nest (a cached branch inside another cached branch would never run)."""
    configs = cache_configs_of(model)
    name = default_config_of(model) if config is None else str(config)
    if name not in configs:
        raise CachePointError(
            f"{type(model).__name__} has no cache config {name!r}; "
            f"allowed: {', '.join(sorted(configs))}"
        )
    points = tuple(configs[name])
    if not points:
        raise CachePointError(f"cache config {name!r} of {type(model).__name__} names nothing")
    for point in points:
        try:
            model.get_submodule(point)
        except AttributeError:
            raise CachePointError(
                f"cache config {name!r} of {type(model).__name__} names {point!r}, "
                "which is not a submodule"
            ) from None
        if point == "":
            raise CachePointError("the whole network cannot be a cache point")
    if len(set(points)) != len(points):
        raise CachePointError(f"cache config {name!r} names a submodule twice: {points}")
    for a in points:
        for b in points:
            if a != b and b.startswith(a + "."):
                raise CachePointError(
                    f"cache config {name!r}: {b!r} lies inside {a!r} and would never run"
                )
    return points
