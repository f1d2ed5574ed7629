"""``upcast bench reframe`` end to end on toy networks at a tiny size."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from server.bench.reframe import bench as reframe
from server.bench.reframe.tables import budget_comparison, must_show_checks
from tests.cache_toys import ToyNested, ToyNeuralUpscaler, ToyUNet


def _load(name: str) -> ToyNeuralUpscaler:
    return ToyNeuralUpscaler((ToyUNet if name == "unet" else ToyNested)().eval())


def _args(tmp_path: Path, **over: object) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    reframe.add_arguments(parser)
    args = parser.parse_args(
        [
            "--json",
            str(tmp_path / "r.json"),
            "--plot",
            str(tmp_path / "r.png"),
            "--scenes",
            "static,scene_cut",
            "--frames",
            "6",
            "--display-size",
            "64x48",
            "--policies",
            "every_1,delta_l,budget,motion,deepcache",
            "--sweep",
            "delta@0.001",
            "--levels",
            "unet:2,unetpp:A,unetpp:B",
            "--ablation-scenes",
            "static",
            "--flip-frames",
            "2",
            "--gt-every",
            "2",
            "--supersample",
            "1",
        ]
    )
    for k, v in over.items():
        setattr(args, k, v)
    return args


def test_bench_runs_and_reports(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert reframe.run(_args(tmp_path), load=_load) == 0
    report = json.loads((tmp_path / "r.json").read_text())
    cases = {c["name"]: c for c in report["cases"]}
    # Two scenes x (5 policies + 1 sweep) + ablation (3) on one scene + uncached refs.
    assert len([c for c in cases.values() if c["group"] != "uncached"]) == 2 * 6 + 3
    assert {"static/unet_uncached", "static/unetpp_uncached", "scene_cut/unet_uncached"} <= set(
        cases
    )
    # Refreshing every frame: the same bits as the uncached network, nothing saved.
    exact = cases["static/every_1"]
    assert exact["psnr_db"] == reframe.PSNR_CAP_DB and exact["worst_psnr_db"] == reframe.PSNR_CAP_DB
    assert exact["flip"] == 0.0 and exact["skipped_share"] == 0.0
    assert exact["eliminated_flops_share"] == pytest.approx(0.0)
    # A still camera under Delta_L (only the jitter moves): mostly cached.
    still = cases["static/delta_l"]
    assert still["actions"][0] == "f" and still["cached_frames"] >= 3
    assert 0 < still["eliminated_flops_share"] < 1 and still["cache_bytes"] > 0
    # The cut falls mid-run and forces a refresh there.
    assert "f" in cases["scene_cut/delta_l"]["actions"][1:]
    for c in cases.values():
        if c["group"] != "uncached":
            assert c["speedup"] > 0 and c["flip"] is not None and c["gt_psnr_db"] is not None
    out = capsys.readouterr().out
    for title in ("Table 1 form", "Table 4 form", "Table 5 form", "Quality budget", "Checks"):
        assert title in out
    assert (tmp_path / "r.md").read_text().startswith("## Table 1 form")
    assert (tmp_path / "r.png").stat().st_size > 0
    assert any(n.startswith(("PASS", "FAIL")) for n in report["notes"])


def _case(scene: str, case: str, group: str, **v: object) -> dict[str, object]:
    base: dict[str, object] = {
        "scene": scene,
        "case": case,
        "group": group,
        "flip": 0.01,
        "speedup": 1.0,
    }
    base.update(v)
    return base


def test_budget_check_compares_with_the_best_fixed_threshold_that_holds() -> None:
    cases = []
    for scene, worst_fixed in (("a", 40.0), ("b", 30.0)):
        cases.append(
            _case(
                scene,
                "budget",
                "policy",
                budget_db=35.0,
                worst_psnr_db=36.0,
                cached_frames=10,
                speedup=1.5,
            )
        )
        cases.append(
            _case(scene, "delta@0.01", "sweep", worst_psnr_db=38.0, cached_frames=4, speedup=1.1)
        )
        cases.append(
            _case(
                scene,
                "delta@0.05",
                "sweep",
                worst_psnr_db=worst_fixed,
                cached_frames=12,
                speedup=1.8,
            )
        )
    text, checks = budget_comparison(cases)
    assert "no (b)" in text
    assert [ok for _, ok in checks] == [True, True]
    assert "delta@0.01: 8" in checks[1][0]
    cases[0]["worst_psnr_db"] = 34.0
    assert [ok for _, ok in budget_comparison(cases)[1]] == [False, True]
    cases[0]["cached_frames"] = cases[3]["cached_frames"] = 3  # 6 < 8
    assert [ok for _, ok in budget_comparison(cases)[1]] == [False, False]


def test_budget_check_also_compares_with_the_fixed_schedules_that_hold() -> None:
    cases = [
        _case(s, "budget", "policy", budget_db=35.0, worst_psnr_db=36.0, cached_frames=10)
        for s in ("a", "b")
    ]
    cases += [_case(s, "every_2", "policy", worst_psnr_db=37.0, cached_frames=6) for s in "ab"]
    cases += [_case(s, "every_5", "policy", worst_psnr_db=33.0, cached_frames=9) for s in "ab"]
    text, checks = budget_comparison(cases)
    assert "| every_5 | 18 | 33.00 | no (a, b) |" in text
    # No threshold in the run: that check falls back to "held"; every_2 is the best holder.
    assert [ok for _, ok in checks] == [True, True, True]
    assert "(every_2: 12)" in checks[2][0]
    cases[2]["cached_frames"] = cases[3]["cached_frames"] = 11  # 22 > 20
    assert [ok for _, ok in budget_comparison(cases)[1]] == [True, True, False]


def test_must_show_speed_and_flip_targets() -> None:
    cases = [
        _case("a", "delta_l", "policy", speedup=1.6, flip=0.04),
        _case("b", "delta_l", "policy", speedup=1.5, flip=0.05),
        _case("a", "delta_h", "policy", speedup=1.3, flip=0.03),
    ]
    got = dict((text.split(":")[0], ok) for text, ok in must_show_checks(cases))
    assert got == {"delta_l": True, "delta_h": False}


def test_bad_options_fail_before_rendering(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="unknown cache policy"):
        reframe.run(_args(tmp_path, policies="sometimes"), load=_load)
    with pytest.raises(SystemExit, match="unet:LEVEL"):
        reframe.run(_args(tmp_path, levels="resnet:1"), load=_load)
    with pytest.raises(SystemExit, match="multiples of 16"):
        reframe.run(_args(tmp_path, display_size="100x50"), load=_load)
