"""Cache policies on hand-made signals: SMAPE, schedules, thresholds, the budget loop."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from upscalers.cache.policies import available, make_policy
from upscalers.cache.policies.budget import BudgetPolicy, psnr_db
from upscalers.cache.policies.delta import DeltaPolicy
from upscalers.cache.policies.motion import MotionPolicy
from upscalers.cache.policies.schedule import EveryNPolicy, NonUniformPolicy, nonuniform_schedule
from upscalers.cache.signals import FrameSignals, mean_motion_px, smape


def _signals(
    x: torch.Tensor,
    ref: torch.Tensor | None,
    *,
    since: int = 1,
    cut: bool = False,
    ready: bool = True,
    motion: np.ndarray | None = None,
) -> FrameSignals:
    """Signals whose network input and colour are both ``x`` (``ref``: colour at refresh)."""
    return FrameSignals(
        inputs=x,
        image=x,
        reference=ref,
        since_refresh=since,
        scene_cut=cut,
        cache_ready=ready,
        motion=motion,
    )


def test_smape_values_and_all_zero_frames() -> None:
    zero = torch.zeros(1, 4, 8, 8)
    assert smape(zero, zero) == 0.0  # 0/0 is "no change", not NaN
    assert smape(zero.half(), zero.half()) == 0.0
    one = torch.ones(1, 4, 8, 8)
    assert smape(one, zero) == pytest.approx(2.0)  # the largest possible change
    assert smape(one, one) == 0.0
    assert smape(2 * one, one) == pytest.approx(2 * 1 / 3)
    # float16 values whose sum overflows float16 still give a finite answer
    big = torch.full((1, 1, 256, 256), 60000.0, dtype=torch.float16)
    assert smape(big, big * 0.5) == pytest.approx(2 * 30000 / 90000, rel=1e-3)
    with pytest.raises(ValueError, match="different shapes"):
        smape(one, torch.ones(1, 4, 8, 9))
    # uint8 frame colour as the policies get it: no wrap-around of 0 - 255
    black, white = np.zeros((4, 4, 3), np.uint8), np.full((4, 4, 3), 255, np.uint8)
    assert smape(black, black) == 0.0
    assert smape(white, black) == pytest.approx(2.0)
    assert smape(black, white) == pytest.approx(2.0)


def test_must_refresh_rules() -> None:
    x = torch.rand(1, 3, 4, 4)
    assert not _signals(x, x).must_refresh
    assert _signals(x, None).must_refresh  # first frame: nothing to compare against
    assert _signals(x, x, ready=False).must_refresh  # cold cache
    assert _signals(x, x, cut=True).must_refresh
    assert _signals(x, torch.rand(1, 3, 4, 5)).must_refresh  # resolution changed
    bad = x.clone()
    bad[0, 0, 0, 0] = float("inf")
    assert _signals(bad, x).must_refresh
    nan_motion = np.zeros((4, 4, 2), np.float32)
    nan_motion[1, 1, 0] = np.nan
    assert _signals(x, x, motion=nan_motion).must_refresh


ALL = ["every_2", "every_5", "deepcache", "delta_h", "delta_l", "motion", "budget"]


@pytest.mark.parametrize("name", ALL)
def test_every_policy_refreshes_on_first_frame_cut_and_bad_input(name: str) -> None:
    policy = make_policy(name)
    x = torch.rand(1, 3, 8, 8)
    still = np.zeros((8, 8, 2), np.float32)
    assert policy.decide(_signals(x, None, motion=still))
    # An unchanged frame is cached; the budget policy first refreshes once more, where
    # history appears (the frame after a forced refresh).
    assert policy.decide(_signals(x, x, motion=still)) == (name == "budget")
    assert policy.decide(_signals(x, x, since=1, cut=True, motion=still))
    bad = x.clone()
    bad[0, 1, 2, 3] = float("nan")
    assert policy.decide(_signals(bad, x, motion=still))


def test_every_n_counts_frames_since_refresh() -> None:
    x = torch.rand(1, 3, 4, 4)
    p = EveryNPolicy(3)
    assert [p.decide(_signals(x, x, since=s)) for s in (1, 2, 3, 1)] == [False, False, True, False]
    assert EveryNPolicy(1).decide(_signals(x, x, since=1))
    with pytest.raises(ValueError):
        EveryNPolicy(0)


def test_nonuniform_schedule_is_real_and_matches_hand_computation() -> None:
    # Python's power of a negative base is complex: what the original fed to linspace.
    assert isinstance((-5.0) ** (1 / 1.4), complex)
    # By hand, T=10, k=3, c=5, p=1.4: r = 5**(1/1.4) = 3.157; linspace(-r, r, 4) =
    # -3.157, -1.052, 1.052, 3.157; signed x**1.4 = -5, -1.074, 1.074, 5; truncated
    # -5, -1, 1, 5; inner points -1, 1 -> steps 4, 6; with step 0: (0, 4, 6).
    assert nonuniform_schedule(10, 3, 5, 1.4) == (0, 4, 6)
    steps = nonuniform_schedule(220, 44, 110, 1.4)
    assert len(steps) == 44 and all(isinstance(s, int) for s in steps)
    assert steps[0] == 0 and max(steps) < 220
    gaps = np.diff(steps)
    mid = steps.index(110) if 110 in steps else len(steps) // 2
    assert gaps[mid - 1] < gaps[0] and gaps[mid] < gaps[-1]  # denser at the centre
    # rounding collisions lower the power until k distinct steps remain
    assert len(nonuniform_schedule(12, 10, 6, 3.0)) == 10
    with pytest.raises(ValueError):
        nonuniform_schedule(10, 11, 5, 1.4)


def test_nonuniform_policy_follows_its_schedule_from_the_forced_refresh() -> None:
    x = torch.rand(1, 3, 4, 4)
    p = NonUniformPolicy(center=5, power=1.4, period=10, mean_interval=3)
    assert p.steps == frozenset({0, 4, 6})
    decisions = [p.decide(_signals(x, None if t == 0 else x)) for t in range(21)]
    assert [t for t, d in enumerate(decisions) if d] == [0, 4, 6, 10, 14, 16, 20]
    assert p.decide(_signals(x, x, cut=True))  # a cut restarts the period
    assert [p.decide(_signals(x, x)) for _ in range(4)] == [False, False, False, True]


def test_delta_policy_threshold() -> None:
    ref = torch.ones(1, 3, 4, 4)
    p = DeltaPolicy(0.1)
    assert not p.decide(_signals(ref * 1.1, ref))  # SMAPE 0.095
    assert p.decide(_signals(ref * 1.12, ref))  # SMAPE 0.113
    h, low = make_policy("delta_h"), make_policy("delta_l")
    assert 0 < h.tau < low.tau  # type: ignore[attr-defined]
    assert make_policy("delta@0.2").tau == 0.20  # type: ignore[attr-defined]


def test_motion_policy_accumulates_since_refresh() -> None:
    x = torch.rand(1, 3, 4, 4)
    mv = np.zeros((4, 4, 2), np.float32)
    mv[..., 0], mv[..., 1] = 0.3, 0.4  # 0.5 px a frame
    assert mean_motion_px(mv) == pytest.approx(0.5)
    p = MotionPolicy(1.0)
    got = [p.decide(_signals(x, x, motion=mv)) for _ in range(6)]
    assert got == [False, False, True, False, False, True]


def test_budget_policy_sets_its_run_from_the_audits() -> None:
    p = BudgetPolicy(35.0, start_run=4, margin_db=1.0, db_per_doubling=3.0)
    x = torch.ones(1, 3, 4, 4)

    def late(run: int, delta: float = 0.1) -> bool:
        assert not p.decide(_signals(x * 1.9, x, since=run))  # colour: not its signal
        return p.refresh_late(delta)

    assert not late(4) and late(5)  # serves 4 cached frames in a row, then refreshes
    assert late(1, delta=1.6) and late(1, math.inf) and late(1, math.nan)  # structural
    assert not late(1, delta=1.0)  # the jitter alone changes the branch input this much
    late(1, delta=1.6)
    p.observe_audit(1.6, 10.0)  # a structural refresh's audit does not move the run
    assert p.run_limit == 4 and p.audits == 1
    late(5)
    p.observe_audit(0.1, 33.0)  # 3 dB short at run 5: half the run, and below 5
    assert p.run_limit == 2
    late(3)
    p.observe_audit(0.1, 37.5)  # 1.5 dB headroom at run 3: 3 * 2 ** 0.5 -> 4
    assert p.run_limit == 4
    late(5)
    p.observe_audit(0.1, math.inf)  # identical: at most doubled
    assert p.run_limit == 10
    late(11)
    p.observe_audit(0.1, 35.5)  # inside the margin: 11 * 2 ** (-0.5 / 3) -> 9
    assert p.run_limit == 9
    late(11)
    p.observe_audit(0.1, float("nan"))  # counted, learns nothing
    assert p.run_limit == 9 and p.audits == 6
    p.reset()
    assert p.run_limit == 4 and p.audits == 0


def test_budget_policy_audits_first_and_backs_off_where_the_cache_cannot_serve() -> None:
    p = BudgetPolicy(35.0, margin_db=1.0)
    x = torch.ones(1, 3, 4, 4)

    def early(run: int) -> bool:
        return p.decide(_signals(x, x, since=run))

    assert not early(1) and p.refresh_late(0.1)  # run limit 0: the first candidate is audited
    p.observe_audit(0.1, 30.0)  # misses: the next frame refreshes without a cached pass
    assert early(1) and not early(1) and p.refresh_late(0.1)
    p.observe_audit(0.1, 30.0)  # misses again: two frames now
    assert early(1) and early(1) and not early(1) and p.refresh_late(0.1)
    p.observe_audit(0.1, 37.5)  # 1.5 dB headroom at run 1: serve one, and the backoff ends
    assert p.run_limit == 1 and not early(1) and not p.refresh_late(0.1)
    assert not early(2) and p.refresh_late(0.1)
    p.observe_audit(0.1, 20.0)
    assert p.run_limit == 0 and early(1) and not early(1)  # a cooldown of 1 again


def test_psnr_of_tensors() -> None:
    a = torch.zeros(3, 4, 4)
    assert psnr_db(a, a) == math.inf
    assert psnr_db(a, a + 0.1) == pytest.approx(20.0)


def test_registry_names_and_errors() -> None:
    assert set(ALL) <= set(available())
    assert make_policy("delta@0.07").tau == 0.07  # type: ignore[attr-defined]
    assert make_policy("every@3").n == 3  # type: ignore[attr-defined]
    assert make_policy("budget@30").budget_db == 30  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="allowed"):
        make_policy("sometimes")
    with pytest.raises(ValueError, match="not a number"):
        make_policy("delta@x")
    with pytest.raises(ValueError, match="whole number"):
        make_policy("every@2.5")
    with pytest.raises(ValueError):
        make_policy("delta@-1")
