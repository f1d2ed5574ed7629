"""LayerCache on two toy architectures: wrapping, reuse, fallbacks, restore, FLOPs."""

from __future__ import annotations

from typing import ClassVar

import pytest
import torch
from torch import nn

from tests.cache_toys import IN_CHANNELS, ToyNested, ToyUNet
from upscalers.cache.flops import count_flops, path_flops
from upscalers.cache.layer_cache import CachedBranch, CacheMode, LayerCache
from upscalers.cache.points import CachePointError, cache_points


def _input(h: int = 24, w: int = 32, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(1, IN_CHANNELS, h, w, generator=g)


def _calls(module: nn.Module) -> list[int]:
    calls = [0]

    def hook(*_: object) -> None:
        calls[0] += 1

    module.register_forward_hook(hook)
    return calls


ARCHS = [(ToyUNet, "1"), (ToyUNet, "2"), (ToyUNet, "3"), (ToyNested, "A"), (ToyNested, "B")]


@pytest.mark.parametrize(("arch", "config"), ARCHS)
def test_refresh_is_bit_exact_and_reuse_skips_the_branches(
    arch: type[nn.Module], config: str
) -> None:
    model = arch().eval()
    x1, x2 = _input(seed=1), _input(seed=2)
    with torch.no_grad():
        plain1, plain2 = model(x1), model(x2)
    originals = {p: model.get_submodule(p) for p in cache_points(model, config)}
    counters = {p: _calls(m) for p, m in originals.items()}
    with LayerCache(model, config) as cache, torch.no_grad():
        assert all(isinstance(model.get_submodule(p), CachedBranch) for p in originals)
        cache.mode = CacheMode.REFRESH
        assert torch.equal(model(x1), plain1)
        assert cache.warm and cache.nbytes > 0
        cache.mode = CacheMode.REUSE
        reused = model(x2)
        assert cache.last_forward_reused
        # The branches did not run on the cached frame ...
        assert all(c[0] == 1 for c in counters.values())
        # ... and the result is neither the fresh one nor the old one: shallow work ran.
        assert not torch.equal(reused, plain2) and not torch.equal(reused, plain1)
        cache.mode = CacheMode.REFRESH
        assert torch.equal(model(x2), plain2)
    # restore() put the very same modules back and the network is as before.
    for p, m in originals.items():
        assert model.get_submodule(p) is m
    with torch.no_grad():
        assert torch.equal(model(x1), plain1)


def test_reuse_of_unchanged_input_equals_full_run() -> None:
    model = ToyUNet().eval()
    x = _input()
    with LayerCache(model) as cache, torch.no_grad():
        full = model(x)
        cache.mode = CacheMode.REUSE
        assert torch.equal(model(x), full)


def test_reuse_with_nothing_kept_or_another_size_runs_everything() -> None:
    model = ToyUNet().eval()
    small, big = _input(24, 32), _input(48, 64)
    with torch.no_grad():
        plain_small, plain_big = model(small), model(big)
    with LayerCache(model) as cache, torch.no_grad():
        cache.mode = CacheMode.REUSE
        assert torch.equal(model(small), plain_small)  # nothing kept: it ran and kept
        assert not cache.last_forward_reused and cache.warm
        assert torch.equal(model(big), plain_big)  # kept output is for another size
        assert not cache.last_forward_reused
        kept = cache.branches["body.inner"].kept
        assert kept is not None and kept.shape[-2:] == (48, 64)
        assert torch.equal(model(big.double().float()), plain_big)
        assert cache.last_forward_reused


def test_dtype_change_is_not_served_from_the_cache() -> None:
    model = ToyUNet().eval()
    x = _input()
    with LayerCache(model) as cache, torch.no_grad():
        model(x)
        cache.mode = CacheMode.REUSE
        model.double()
        out = model(x.double())
        assert not cache.last_forward_reused
        assert out.dtype == torch.float64


def test_non_finite_branch_outputs_are_never_kept() -> None:
    model = ToyUNet().eval()
    x = _input()
    x[0, 0, 3, 3] = float("nan")
    with LayerCache(model) as cache, torch.no_grad():
        model(x)
        assert not cache.warm and cache.nbytes == 0
        x[0, 0, 3, 3] = float("inf")
        cache.mode = CacheMode.REUSE
        model(x)
        assert cache.branches["body.inner"].kept is None


def test_passthrough_leaves_the_cache_alone() -> None:
    model = ToyUNet().eval()
    x1, x2 = _input(seed=1), _input(seed=2)
    with LayerCache(model) as cache, torch.no_grad():
        model(x1)
        kept = cache.branches["body.inner"].kept
        with cache.using(CacheMode.PASSTHROUGH):
            model(x2)
        assert cache.branches["body.inner"].kept is kept
        assert cache.mode is CacheMode.REFRESH


def test_in_place_change_of_a_reused_tensor_is_detected() -> None:
    class Mutating(ToyUNet):
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            h = self.head(x)
            inner = self.body.inner(self.body.enc(h))
            inner.add_(1.0)  # a parent that scribbles on the branch output
            return self.tail(self.body.dec(torch.cat([self.body.enc(h), inner], dim=1)))

    model = Mutating().eval()
    x = _input()
    with LayerCache(model) as cache, torch.no_grad():
        first = model(x)  # refresh; the parent then scribbles on the branch output
        cache.mode = CacheMode.REUSE
        second = model(x)  # what was kept changed after it was kept: recomputed
        assert not cache.last_forward_reused
        assert torch.equal(first, second)
        model(x)
        assert not cache.last_forward_reused


def test_in_place_change_under_inference_mode_cannot_reach_the_kept_copy() -> None:
    class Mutating(ToyUNet):
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            h = self.body.enc(self.head(x))
            inner = self.body.inner(h)
            out = self.tail(self.body.dec(torch.cat([h, inner], dim=1)))
            inner.mul_(0.0)  # after use: only what is kept could suffer
            return out

    model = Mutating().eval()
    x = _input()
    with LayerCache(model) as cache, torch.inference_mode():
        first = model(x)
        cache.mode = CacheMode.REUSE
        assert torch.equal(model(x), first)  # reused a copy the parent never saw
        assert cache.last_forward_reused


def test_invalidate_and_restore_are_idempotent() -> None:
    model = ToyNested().eval()
    keys = list(model.state_dict())
    cache = LayerCache(model, "A")
    with torch.no_grad():
        model(_input())
    assert cache.warm
    cache.invalidate()
    assert not cache.warm and cache.nbytes == 0
    cache.restore()
    cache.restore()
    assert list(model.state_dict()) == keys
    assert not any(isinstance(m, CachedBranch) for m in model.modules())


def test_double_wrapping_is_refused() -> None:
    model = ToyUNet()
    with LayerCache(model), pytest.raises(ValueError, match="already wrapped"):
        LayerCache(model)


def test_cache_point_errors_name_the_problem() -> None:
    model = ToyUNet()
    with pytest.raises(CachePointError, match="allowed: 1, 2, 3"):
        cache_points(model, "7")
    assert cache_points(model) == ("body.inner",)

    class Broken(ToyUNet):
        cache_configs: ClassVar[dict[str, tuple[str, ...]]] = {
            "1": ("body.nowhere",),
            "2": ("body.inner", "body.inner.level"),
        }

    with pytest.raises(CachePointError, match="not a submodule"):
        cache_points(Broken(), "1")
    with pytest.raises(CachePointError, match="inside"):
        cache_points(Broken(), "2")
    with pytest.raises(CachePointError, match="declares no cache_configs"):
        LayerCache(nn.Conv2d(1, 1, 1))


@pytest.mark.parametrize(("arch", "config"), ARCHS)
def test_flops_of_the_cached_path(arch: type[nn.Module], config: str) -> None:
    model = arch().eval()
    x = _input()
    # Each branch's own work: catch its real inputs in a plain forward, run it alone.
    inputs: dict[str, tuple[tuple[object, ...], dict[str, object]]] = {}
    handles = []
    for point in cache_points(model, config):

        def grab(
            _m: nn.Module, args: tuple[object, ...], kwargs: dict[str, object], p: str = point
        ) -> None:
            inputs[p] = (args, kwargs)

        handles.append(model.get_submodule(point).register_forward_pre_hook(grab, with_kwargs=True))
    with torch.no_grad():
        full = count_flops(lambda: model(x))
        for h in handles:
            h.remove()
        branch_flops = sum(
            count_flops(lambda p=p, a=a, k=k: model.get_submodule(p)(*a, **k))
            for p, (a, k) in inputs.items()
        )
        with LayerCache(model, config) as cache:
            flops = path_flops(cache, model, x)
            assert not cache.warm  # measuring left the (empty) cache as it was
    assert flops.full == full
    assert 0 < flops.cached < flops.full
    # What a cached frame saves is exactly the cached branches' own work.
    assert flops.full - flops.cached == branch_flops


def test_deeper_levels_eliminate_fewer_flops() -> None:
    model = ToyUNet().eval()
    x = _input()
    shares = []
    for config in ("1", "2", "3"):
        with torch.no_grad(), LayerCache(model, config) as cache:
            shares.append(path_flops(cache, model, x).eliminated_share)
    assert shares[0] > shares[1] > shares[2] > 0
