"""CachedUpscaler around a NeuralUpscaler-like toy: the hard cases of issue 5."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from server.frames.frame import FrameFlags, RenderFrame, Size
from tests.cache_toys import ToyNested, ToyNeuralUpscaler, ToyUNet, display_of, make_frame
from upscalers.cache.cached_upscaler import CachedUpscaler
from upscalers.cache.layer_cache import CachedBranch
from upscalers.cache.policies import CachePolicy, make_policy
from upscalers.cache.policies.budget import BudgetPolicy
from upscalers.cache.signals import FrameSignals

SIZE = Size(32, 24)
DISPLAY = display_of(SIZE)


class Never(CachePolicy):
    """Reuses whenever allowed: shows what the forced-refresh rules do on their own."""

    name = "never"

    def _refresh_now(self, signals: FrameSignals) -> bool:
        return False


def _pair(
    arch: type[nn.Module] = ToyUNet,
    policy: CachePolicy | str = "every_1",
    config: str | None = None,
    *,
    feedback: bool = True,
) -> tuple[ToyNeuralUpscaler, CachedUpscaler]:
    """An uncached upscaler and a cached one with the same weights."""
    plain = ToyNeuralUpscaler(arch().eval(), feedback=feedback)
    cached = CachedUpscaler(ToyNeuralUpscaler(arch().eval(), feedback=feedback), policy, config)
    return plain, cached


def _same(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Bit-identical, NaN where NaN."""
    return bool(torch.equal(a.isnan(), b.isnan()) and torch.equal(a.nan_to_num(), b.nan_to_num()))


def _frames(n: int, shift: int = 1) -> list[RenderFrame]:
    return [make_frame(i, SIZE, shift=shift) for i in range(n)]


@pytest.mark.parametrize(("arch", "config"), [(ToyUNet, "1"), (ToyUNet, "3"), (ToyNested, "A")])
def test_refresh_every_frame_is_bit_exact_with_the_uncached_upscaler(
    arch: type[nn.Module], config: str
) -> None:
    plain, cached = _pair(arch, "every_1", config)
    for frame in _frames(6):
        assert torch.equal(cached.upscale(frame, DISPLAY), plain.upscale(frame, DISPLAY))
    assert cached.stats.cached == 0 and cached.stats.refreshes == 6


@pytest.mark.parametrize(
    "name", ["every_2", "every_5", "deepcache", "delta_h", "delta_l", "motion", "budget"]
)
def test_first_frame_is_always_full(name: str) -> None:
    plain, cached = _pair(policy=name)
    frame = make_frame(0, SIZE)
    assert torch.equal(cached.upscale(frame, DISPLAY), plain.upscale(frame, DISPLAY))
    assert cached.last_action == "forced"


def test_cached_frames_skip_the_deep_branch_and_stay_close() -> None:
    plain, cached = _pair(policy=Never())
    errors = []
    for frame in _frames(5, shift=0):
        a, b = cached.upscale(frame, DISPLAY), plain.upscale(frame, DISPLAY)
        errors.append(float((a - b).abs().max()))
    # A still scene: only the fed-back previous output changes the input, a little.
    assert cached.stats.cached == 4 and errors[0] == 0.0 and max(errors) < 1e-3
    for frame in _frames(5, shift=3)[1:]:
        cached.upscale(frame, DISPLAY)
        plain.upscale(frame, DISPLAY)
    assert cached.stats.cached == 8
    assert cached.stats.cache_bytes > 0 and cached.stats.reference_bytes > 0


ADAPTIVE = ["delta_h", "delta_l", "motion", "budget", "delta@0.5", "motion@100", "budget@10"]


@pytest.mark.parametrize("name", ADAPTIVE)
def test_scene_cut_forces_a_refresh_on_the_very_next_frame(name: str) -> None:
    plain, cached = _pair(policy=name, feedback=False)
    for frame in _frames(5, shift=0):  # still frames: cached after the first (or an audit)
        cached.upscale(frame, DISPLAY)
        plain.upscale(frame, DISPLAY)
    assert cached.last_action == "cached"
    # The cut: a different picture whose input delta alone might not trigger.
    cut = make_frame(4, SIZE, shift=0, flags=FrameFlags.RESET, seed=7)
    out = cached.upscale(cut, DISPLAY)
    assert cached.last_action == "forced"
    assert torch.equal(out, plain.upscale(cut, DISPLAY))
    after = make_frame(5, SIZE, shift=0, seed=7)
    cached.upscale(after, DISPLAY)
    # The budget policy refreshes once more where history appears (frame after a forced one).
    assert cached.last_action == ("refresh" if name.startswith("budget") else "cached")


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_input_refreshes_and_never_reaches_the_cache(bad: float) -> None:
    plain, cached = _pair(policy=Never(), feedback=False)
    frames = _frames(6)
    for frame in frames[:3]:
        cached.upscale(frame, DISPLAY)
        plain.upscale(frame, DISPLAY)
    poisoned = make_frame(3, SIZE)
    poisoned.depth[5:9, 5:9] = bad
    out = cached.upscale(poisoned, DISPLAY)
    assert cached.last_action == "nonfinite"
    assert _same(out, plain.upscale(poisoned, DISPLAY))  # the full network ran
    assert cached.stats.cache_bytes == 0 and cached.stats.reference_bytes == 0
    for branch in cached.cache.branches.values():
        assert branch.kept is None
    # The next (clean) frame cannot reuse anything: a forced refresh, finite cache.
    cached.upscale(frames[4], DISPLAY)
    assert cached.last_action == "forced"
    for branch in cached.cache.branches.values():
        assert branch.kept is not None and bool(torch.isfinite(branch.kept).all())
    poisoned_motion = make_frame(5, SIZE)
    poisoned_motion.motion[0, 0, 1] = bad
    cached.upscale(poisoned_motion, DISPLAY)
    assert cached.last_action == "nonfinite"


def test_resolution_change_invalidates_the_cache() -> None:
    plain, cached = _pair(policy=Never(), feedback=False)
    for frame in _frames(3, shift=0):
        cached.upscale(frame, DISPLAY)
        plain.upscale(frame, DISPLAY)
    big = Size(48, 36)
    invalidations = cached.stats.invalidations
    frame = make_frame(3, big, shift=0)
    out = cached.upscale(frame, display_of(big))
    assert cached.last_action == "forced"
    assert cached.stats.invalidations == invalidations + 1
    assert torch.equal(out, plain.upscale(frame, display_of(big)))
    kept = cached.cache.branches["body.inner"].kept
    assert kept is not None and kept.shape[-2:] == (36, 48)
    # Only the display size changes: also a new geometry, also a refresh.
    cached.upscale(make_frame(4, big, shift=0), Size(96, 72))
    assert cached.last_action == "cached"
    cached.upscale(make_frame(5, big, shift=0), Size(100, 75))
    assert cached.last_action == "forced"


def test_budget_policy_audits_its_own_refreshes() -> None:
    policy = make_policy("budget@150")  # a budget no stale output meets
    _, cached = _pair(policy=policy)
    for frame in _frames(12, shift=2):
        cached.upscale(frame, DISPLAY)
    # Nothing unaudited is served: the first candidate was audited, and failed.
    assert cached.stats.audits >= 1 and cached.stats.cached == 0
    assert policy.run_limit == 0  # type: ignore[attr-defined]


def test_a_late_refresh_gives_the_full_output_and_audits_the_cached_one() -> None:
    """Run limit 0: a frame the cache could serve is refreshed after the cached path ran,
    so every output equals the uncached network's, bit for bit; each failed audit is
    followed by a cooldown of 1, 2, 4 ... frames that refresh without the cached pass."""
    plain, cached = _pair(policy=BudgetPolicy(150.0, start_run=0, max_cooldown=2))
    actions = []
    for frame in _frames(10, shift=2):
        assert torch.equal(cached.upscale(frame, DISPLAY), plain.upscale(frame, DISPLAY))
        actions.append("a" if cached.stats.audits > actions.count("a") else "r")
    # Frame 0 forced; frame 1 refreshed early (history appears); then audit, cooldown 1;
    # audit, cooldown 2; audit, cooldown 2 (the cap).
    assert "".join(actions) == "rr" + "ar" + "arr" + "arr"
    assert cached.stats.refreshes == 10 and cached.stats.cached == 0


def test_budget_policy_lengthens_its_runs_when_the_audits_have_headroom() -> None:
    policy = BudgetPolicy(10.0, start_run=2)  # every stale output meets 10 dB
    _, cached = _pair(policy=policy)
    actions = []
    for frame in _frames(14, shift=0):
        cached.upscale(frame, DISPLAY)
        actions.append(cached.last_action[0])
    # Frame 1 refreshes (history appears); run 3 > 2: audit at run 3, far above budget
    # -> at most doubled (6); then the audit at run 7 -> 14.
    assert "".join(actions) == "fr" + "ccr" + "c" * 6 + "r" + "cc"
    assert policy.run_limit == 14 and cached.stats.audits == 2


def test_budget_policy_refreshes_on_a_structural_change_within_its_run() -> None:
    policy = BudgetPolicy(10.0, start_run=100, structure_limit=0.2)
    _, cached = _pair(policy=policy, feedback=False)
    for frame in _frames(3, shift=0):
        cached.upscale(frame, DISPLAY)
    assert cached.last_action == "cached"
    # Another picture without a cut flag: the branch input changes wholesale.
    cached.upscale(make_frame(3, SIZE, shift=5, seed=11), DISPLAY)
    assert cached.cache.input_delta() == 0.0  # measured against the new kept input
    assert cached.last_action == "refresh" and policy.run_limit == 100


def test_input_delta_compares_the_branch_input_with_the_kept_one() -> None:
    _, cached = _pair(policy=Never(), feedback=False)
    assert cached.cache.probe_inputs is False  # only a late-deciding policy pays for it
    cached.cache.probe_inputs = True
    assert cached.cache.input_delta() == float("inf")  # nothing kept yet
    frame = make_frame(0, SIZE, shift=0)
    cached.upscale(frame, DISPLAY)
    assert cached.cache.input_delta() == 0.0  # the refresh frame against itself
    cached.upscale(make_frame(1, SIZE, shift=0), DISPLAY)  # same picture
    assert cached.cache.input_delta() == 0.0
    cached.upscale(make_frame(2, SIZE, shift=3, seed=5), DISPLAY)
    assert cached.last_action == "cached" and cached.cache.input_delta() > 0.01
    cached.cache.invalidate()
    assert cached.cache.input_delta() == float("inf")


def test_close_restores_the_network() -> None:
    model = ToyUNet().eval()
    inner = model.body.inner
    cached = CachedUpscaler(ToyNeuralUpscaler(model), "delta_l")
    assert isinstance(model.body.inner, CachedBranch)
    cached.close()
    assert model.body.inner is inner


def test_reset_forgets_the_cache_but_not_what_the_policy_learned() -> None:
    policy = make_policy("budget@150")
    _, cached = _pair(policy=policy)
    for frame in _frames(8, shift=2):
        cached.upscale(frame, DISPLAY)
    limit = policy.run_limit  # type: ignore[attr-defined]
    assert policy.audits > 0  # type: ignore[attr-defined]
    cached.reset()
    assert not cached.cache.warm
    cached.upscale(make_frame(9, SIZE), DISPLAY)
    assert cached.last_action == "forced"
    assert policy.run_limit == limit  # type: ignore[attr-defined]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_float16_on_cuda() -> None:
    model = ToyUNet().eval().cuda().half()
    plain = ToyNeuralUpscaler(ToyUNet().eval().cuda().half(), dtype=torch.float16)
    cached = CachedUpscaler(ToyNeuralUpscaler(model, dtype=torch.float16), "every_1")
    for frame in _frames(3):
        a, b = cached.upscale(frame, DISPLAY), plain.upscale(frame, DISPLAY)
        assert a.dtype == torch.float16 and a.is_cuda
        assert torch.equal(a, b)
    never = CachedUpscaler(
        ToyNeuralUpscaler(ToyUNet().eval().cuda().half(), dtype=torch.float16), Never()
    )
    for frame in _frames(4):
        out = never.upscale(frame, DISPLAY)
        assert bool(torch.isfinite(out).all())
    assert never.stats.cached == 3
    kept = never.cache.branches["body.inner"].kept
    assert kept is not None and kept.dtype == torch.float16 and kept.is_cuda
    assert never.stats.cache_bytes == kept.numel() * 2


def test_the_frame_delta_reference_is_a_copy_of_the_refresh_colour() -> None:
    _, cached = _pair(policy="delta@0.01", feedback=False)
    frame = make_frame(0, SIZE, shift=0)
    cached.upscale(frame, DISPLAY)
    kept = frame.color.copy()
    frame.color[:] = 0  # the ring slot is overwritten by a later frame
    cached.upscale(make_frame(1, SIZE, shift=0), DISPLAY)  # same picture as frame 0
    assert cached.last_action == "cached"
    assert cached.stats.reference_bytes == kept.nbytes


def test_unet_cached_from_the_registry_skips_work_on_a_still_scene() -> None:
    from server.game.render.renderer import Renderer, RenderTargets
    from upscalers import registry

    size = Size(96, 54)
    up = registry.create("unet_cached", policy="delta_l")
    assert registry.is_temporal("unet_cached")
    renderer = Renderer("static", size, scale=2.0)
    outputs = [
        up.upscale(renderer.render(i, i / 30, RenderTargets.allocate(size)), Size(192, 108))
        for i in range(6)
    ]
    assert all(o.shape == (3, 108, 192) and torch.isfinite(o).all() for o in outputs)
    stats = up.stats  # type: ignore[attr-defined]  # the registry hands out the base type
    assert stats.refreshes >= 1 and stats.cached >= 3, stats
    with pytest.raises(ValueError, match="policy"):
        registry.create("unet_cached", policy="no_such_policy")


def test_the_host_sets_a_cache_policy_at_run_time_and_keeps_it_across_switches() -> None:
    from server.game.render.renderer import Renderer, RenderTargets
    from upscalers.cache.policies.schedule import EveryNPolicy
    from upscalers.host import UpscalerHost

    size, display = Size(48, 28), Size(96, 56)
    renderer = Renderer("static", size, scale=2.0)
    frames = [renderer.render(i, i / 30, RenderTargets.allocate(size)) for i in range(4)]
    host = UpscalerHost("unet_cached", display)
    assert host.cache_policy == "delta_l"  # the method's default
    for frame in frames[:2]:
        host.upscale(frame)
    host.set_cache_policy("every_2")
    cached = host.upscaler.cached  # type: ignore[attr-defined]
    assert isinstance(cached.policy, EveryNPolicy) and host.cache_policy == "every_2"
    host.upscale(frames[2])
    assert cached.last_action == "forced"  # a new policy starts from a full pass
    host.upscale(frames[3])
    assert cached.last_action == "cached"
    with pytest.raises(ValueError, match="unknown cache policy"):
        host.set_cache_policy("sometimes")
    assert host.cache_policy == "every_2"
    # A method without a cache refuses, and the choice survives a switch away and back.
    host.switch("bicubic")
    with pytest.raises(ValueError, match="no layer cache; cache policies apply to unet_cached"):
        host.set_cache_policy("budget")
    host.switch("unet_cached")
    assert host.cache_policy == "every_2"


def test_a_cache_policy_chosen_at_start_applies_to_cached_methods_only() -> None:
    from upscalers import registry
    from upscalers.host import UpscalerHost

    host = UpscalerHost("bilinear", Size(96, 56), cache_policy="budget@43")
    assert host.cache_policy is None  # bilinear has no cache
    host.switch("unet_cached")
    assert host.cache_policy == "budget@43"
    with pytest.raises(ValueError, match="unknown cache policy"):
        UpscalerHost("bilinear", Size(96, 56), cache_policy="reuse")
    assert registry.cache_policy_at_start("unet_cached", None) == "delta_l"
    assert registry.cache_policy_at_start("unet_cached", "every_5") == "every_5"
    assert registry.cache_policy_at_start("bicubic", "every_5") is None
