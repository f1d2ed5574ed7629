"""Quality metrics and the upscaler evaluation command."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from server.cli import main
from server.eval.methods import compiled_variants, eager_torch_variants, parse_method
from server.eval.upscalers import _frames_per_method, must_show_checks
from server.frames.frame import RenderFrame, Size
from server.game.render.mip_bias import parse_mip_bias
from upscalers import metrics


def _img(seed: int, shape: tuple[int, int] = (32, 48)) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (*shape, 3), dtype=np.uint8)


def test_psnr_known_values() -> None:
    a = np.zeros((8, 8, 3), np.uint8)
    assert metrics.psnr(a, a) == float("inf")
    b = a.copy()
    b[...] = 10  # mse 100 -> 10 log10(65025 / 100)
    assert metrics.psnr(a, b) == pytest.approx(28.1308, abs=1e-3)


def test_ssim_bounds_and_order() -> None:
    a = _img(0)
    assert metrics.ssim(a, a) == pytest.approx(1.0)
    noisy = np.clip(a.astype(int) + np.random.default_rng(1).integers(-20, 21, a.shape), 0, 255)
    very = np.clip(a.astype(int) + np.random.default_rng(1).integers(-80, 81, a.shape), 0, 255)
    s1 = metrics.ssim(a, noisy.astype(np.uint8))
    s2 = metrics.ssim(a, very.astype(np.uint8))
    assert 1.0 > s1 > s2


def test_flip_zero_for_identical_and_validates() -> None:
    a = _img(2)
    assert metrics.flip(a, a) == pytest.approx(0.0, abs=1e-6)
    assert metrics.flip(a, _img(3)) > 0.1
    with pytest.raises(ValueError, match=r"both"):
        metrics.flip(a, a[:10])
    with pytest.raises(ValueError, match="at least"):
        metrics.flip(a[:4, :4], a[:4, :4])


def test_flicker_ignores_constant_error_and_sees_changing_error() -> None:
    ref = _img(4)
    steady = [metrics.signed_error(ref, np.clip(ref.astype(int) + 5, 0, 255).astype(np.uint8))] * 4
    assert metrics.flicker(steady) == 0.0
    changing = [metrics.signed_error(ref, _img(10 + i)) for i in range(4)]
    assert metrics.flicker(changing) > 0.1
    assert np.isnan(metrics.flicker(steady[:1]))


def _case(scene: str, method: str, psnr: float, flip: float, flicker: float) -> dict[str, object]:
    return {"scene": scene, "scale": 2.0, "method": method, "psnr_db": psnr, "flip": flip,
            "flicker": flicker}  # fmt: skip


def test_time_checks_use_the_720p_medians() -> None:
    cases = [
        {**_case(s, "easu_rcas", 30.0, 0.1, 0.02), "render_size": "640x360", "median_ms": ms}
        for s, ms in (("a", 14.0), ("b", 16.0), ("c", 15.0))
    ]
    slow = [{**c, "method": "temporal", "median_ms": 21.0} for c in cases]
    variants = [{**c, "method": "easu_rcas+torch", "median_ms": 80.0} for c in cases]
    results = dict(must_show_checks(cases + slow + variants))  # type: ignore[arg-type]
    assert results["640x360 -> 1280x720: easu_rcas median 15.0 ms <= 15 ms"]
    assert not results["640x360 -> 1280x720: temporal median 21.0 ms <= 20 ms"]
    # The targets hold the pipeline's default path; variants are only compared.
    assert not any("+torch" in text for text in results)


def test_must_show_checks_evaluate_the_statements() -> None:
    cases = [
        _case("static", "bicubic", 30.0, 0.10, 0.02),
        _case("static", "easu_rcas", 30.5, 0.09, 0.02),
        _case("static", "temporal", 32.1, 0.07, 0.01),
        _case("fast_yaw", "bilinear", 25.0, 0.2, 0.05),
        _case("fast_yaw", "bicubic", 25.2, 0.2, 0.05),
        _case("fast_yaw", "easu_rcas", 25.1, 0.21, 0.05),
        _case("fast_yaw", "temporal", 24.0, 0.2, 0.04),
    ]
    results = dict(must_show_checks(cases))  # type: ignore[arg-type]
    assert results["static 2x: easu_rcas PSNR and FLIP better than bicubic"]
    assert not results["fast_yaw 2x: easu_rcas PSNR and FLIP better than bicubic"]
    assert results["static 2x: temporal >= easu_rcas + 1.5 dB"]
    assert not results["fast_yaw 2x: temporal PSNR not below bilinear"]


def test_the_network_must_earn_one_db_over_bicubic_and_easu_rcas_on_each_scene() -> None:
    cases = [
        _case("static", "bicubic", 30.0, 0.10, 0.02),
        _case("static", "easu_rcas", 30.5, 0.09, 0.02),
        _case("static", "unet", 31.5, 0.08, 0.02),
        _case("dolly", "bicubic", 28.0, 0.10, 0.02),
        _case("dolly", "easu_rcas", 28.0, 0.10, 0.02),
        _case("dolly", "unet", 28.9, 0.09, 0.02),
    ]
    results = dict(must_show_checks(cases))  # type: ignore[arg-type]
    assert results["static 2x: unet >= bicubic + 1 dB (+1.50)"]
    assert results["static 2x: unet >= easu_rcas + 1 dB (+1.00)"]
    assert not results["dolly 2x: unet >= bicubic + 1 dB (+0.90)"]
    assert sum("unet" in label for label in results) == 4


def test_eval_command_writes_report_table_and_plot(tmp_path: Path) -> None:
    out = tmp_path / "eval.json"
    code = main(
        ["eval", "upscalers", "--json", str(out), "--plot", str(tmp_path / "p.png"),
         "--table", str(tmp_path / "t.md"), "--scenes", "static,scene_cut", "--scales", "2",
         "--methods", "bilinear,bicubic", "--frames", "5", "--measure-from", "3",
         "--flip-frames", "1", "--flip-scales", "2", "--display-size", "192x108",
         "--supersample", "2"]
    )  # fmt: skip
    assert code == 0
    report = json.loads(out.read_text())
    assert report["machine"]["cpu_count"] >= 1
    assert {c["method"] for c in report["cases"]} == {"bilinear", "bicubic"}
    for case in report["cases"]:
        assert case["median_ms"] > 0 and case["p95_ms"] >= case["median_ms"]
        assert 10 < case["psnr_db"] < 60 and 0 < case["ssim"] <= 1 and 0 <= case["flip"] < 1
    ratio = {r["name"]: r["ratio"] for r in report["ratios"]}
    assert ratio["2x bicubic / bilinear time"] > 0
    assert (tmp_path / "p.png").read_bytes()[:4] == b"\x89PNG"
    assert "| bilinear |" in (tmp_path / "t.md").read_text()


def test_eval_refuses_unknown_names(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="allowed"):
        main(["eval", "upscalers", "--json", str(tmp_path / "x.json"), "--methods", "magic"])


def test_spatial_methods_get_unjittered_frames_temporal_jittered() -> None:
    # What the pipeline sends: the game jitters only for temporal upscalers.
    times = [0.0, 1 / 60, 2 / 60]
    specs = [parse_method("bicubic"), parse_method("temporal")]
    frames = _frames_per_method("static", Size(32, 18), 2.0, times, specs, None)
    assert all(f.meta.jitter == (0.0, 0.0) for f in frames["bicubic"])
    assert any(f.meta.jitter != (0.0, 0.0) for f in frames["temporal"])
    # Same scene at the same times: the unjittered and jittered renders stay close.
    diff = np.abs(
        frames["bicubic"][2].color.astype(int) - frames["temporal"][2].color.astype(int)
    ).mean()
    assert diff < 20


def test_mip_bias_game_auto_and_numbers() -> None:
    render, display = Size(640, 360), Size(1280, 720)
    assert parse_mip_bias("game", render, display) is None  # the renderer's own choice
    assert parse_mip_bias("auto", render, display) == -1.0
    assert parse_mip_bias("-0.5", render, display) == -0.5
    for bad in ("sharp", "nan", "inf", ""):
        with pytest.raises(ValueError, match="mip-bias"):
            parse_mip_bias(bad, render, display)


def test_game_mips_give_temporal_methods_the_display_mips_and_spatial_the_render_mips() -> None:
    specs = [parse_method("bicubic"), parse_method("temporal")]

    def frames(bias: float | None) -> dict[str, list[RenderFrame]]:
        return _frames_per_method("static", Size(160, 90), 2.0, [0.0], specs, bias)

    game, render_mips, display_mips = frames(None), frames(0.0), frames(-1.0)
    assert np.array_equal(game["bicubic"][0].color, render_mips["bicubic"][0].color)
    assert np.array_equal(game["temporal"][0].color, display_mips["temporal"][0].color)

    # A finer mip keeps more texture contrast: neighbouring pixels differ more.
    def detail(c: np.ndarray) -> float:
        return float(np.abs(np.diff(c.astype(np.float32), axis=1)).mean())

    plain, biased = render_mips["bicubic"][0], display_mips["bicubic"][0]
    assert detail(biased.color) > 1.1 * detail(plain.color)
    assert np.array_equal(plain.depth, biased.depth)  # geometry is the same


def test_eval_refuses_a_bad_mip_bias(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="mip-bias"):
        main(["eval", "upscalers", "--json", str(tmp_path / "x.json"), "--mip-bias", "x"])


def test_method_labels_carry_rcas_sharpness() -> None:
    spec = parse_method("easu_rcas@1.5")
    assert (spec.name, spec.options) == ("easu_rcas", {"sharpness": 1.5})
    with pytest.raises(ValueError, match="no option sharpness"):
        parse_method("bicubic@1")
    with pytest.raises(ValueError, match="must be a number"):
        parse_method("easu_rcas@sharp")
    with pytest.raises(ValueError, match=">= 0 stops"):
        parse_method("easu_rcas@-1")


def test_sharpness_sweep_adds_easu_rcas_variants(tmp_path: Path) -> None:
    out = tmp_path / "sweep.json"
    code = main(
        ["eval", "upscalers", "--json", str(out), "--scenes", "static", "--scales", "2",
         "--methods", "easu", "--rcas-sharpness", "0,2", "--frames", "3", "--measure-from", "2",
         "--flip-frames", "0", "--display-size", "64x36", "--supersample", "1"]
    )  # fmt: skip
    assert code == 0
    cases = {c["method"]: c for c in json.loads(out.read_text())["cases"]}
    assert set(cases) == {"easu", "easu_rcas@0", "easu_rcas@2"}
    # Distinct methods, not one run three times: the strongest sharpening moves furthest.
    assert cases["easu_rcas@0"]["psnr_db"] != cases["easu_rcas@2"]["psnr_db"]


def test_compile_flag_adds_compiled_variants() -> None:
    assert compiled_variants(["bicubic", "easu_rcas@1", "temporal", "easu"]) == [
        "easu_rcas@1+compiled",
        "easu+compiled",
    ]
    spec = parse_method("easu_rcas@1+compiled")
    assert spec.options == {"sharpness": 1.0, "compile": True}
    with pytest.raises(ValueError, match="no compiled path"):
        parse_method("bicubic+compiled")


def test_eager_torch_flag_adds_torch_variants() -> None:
    assert eager_torch_variants(["bicubic", "easu_rcas@1", "easu", "easu+compiled"]) == [
        "easu_rcas@1+torch",
        "easu+torch",
    ]
    assert parse_method("easu_rcas@1+torch").options == {"sharpness": 1.0, "backend": "torch"}
    with pytest.raises(ValueError, match="no numba kernel"):
        parse_method("bicubic+torch")
