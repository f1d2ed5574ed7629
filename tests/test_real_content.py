"""The real-content suite: content manifest and split, photo sequences, the eval command."""

from __future__ import annotations

import io
import json
import tarfile
import urllib.error
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from PIL import Image

from server.cli import main
from server.eval import real_content_fetch
from server.eval.real_content import large_enough, load_rgb
from server.eval.real_content_fetch import data_tarball, fetch_all
from server.eval.real_content_sequences import PAN_PER_FRAME, build_sequence
from server.eval.real_content_sources import (
    SOURCES,
    held_out_images,
    image_source,
    pick_members,
    source_named,
    split_names,
)
from server.frames.frame import FrameFlags, Size
from upscalers import metrics
from upscalers.host import UpscalerHost
from upscalers.output import to_uint8


def _photo(seed: int, shape: tuple[int, int] = (220, 300)) -> np.ndarray:
    """Texture with detail at every scale: noise blurred at two radii, plus edges."""
    rng = np.random.default_rng(seed)
    noise = rng.random((*shape, 3)).astype(np.float32)
    img = 0.6 * cv2.GaussianBlur(noise, (0, 0), 6) + 0.4 * cv2.GaussianBlur(noise, (0, 0), 1.2)
    img = (img - img.min()) / (img.max() - img.min())
    img[60:70, :, 0] = 1.0  # a hard edge band
    return (img * 255).astype(np.uint8)


def test_split_is_deterministic_disjoint_and_covers_the_names() -> None:
    names = [f"img{i:02d}" for i in range(13)]
    train, held = split_names(names, 0.25)
    assert (train, held) == split_names(list(reversed(names)), 0.25)
    assert not set(train) & set(held)
    assert sorted(train + held) == names
    assert len(held) == 4  # ceil(13 / 4)
    assert split_names(["a", "b"], 0.25)[1] and split_names(["a", "b"], 0.25)[0]


def test_manifest_picks_the_largest_size_and_names_game_shots_by_set() -> None:
    plasma = source_named("plasma-photos")
    members = [
        "./usr/share/wallpapers/Kite/contents/images/1280x800.jpg",
        "./usr/share/wallpapers/Kite/contents/images/2560x1600.jpg",
        "./usr/share/wallpapers/Kite/contents/images/1920x1200.jpg",
        "./usr/share/wallpapers/Altai/contents/images/5120x2880.png",  # drawn, not listed
        "./usr/share/wallpapers/Kite/contents/screenshot.png",
    ]
    assert pick_members(plasma, members) == {"Kite": members[1]}
    shots = pick_members(
        source_named("neverball-shots"), ["./usr/share/games/neverball/shot-easy/peasy.jpg"]
    )
    assert list(shots) == ["easy_peasy"]
    lxqt = pick_members(
        source_named("lxqt-photos"),
        [
            "./usr/share/lxqt/wallpapers/fog.jpg",
            "./usr/share/lxqt/wallpapers/triangles.png",  # drawn, not listed
            "./usr/share/lxqt/wallpapers/fog-logo.png",
            "./usr/share/lxqt/themes/frost/preview.png",
        ],
    )
    assert list(lxqt) == ["fog"]
    assert all(len(s.sha256) == 64 and s.url.endswith(".deb") for s in SOURCES)


def _ar(members: dict[str, bytes]) -> bytes:
    out = b"!<arch>\n"
    for name, data in members.items():
        out += f"{name:<16}{0:<12}{0:<6}{0:<6}{100644:<8}{len(data):<10}`\n".encode() + data
        out += b"\n" if len(data) % 2 else b""
    return out


def test_data_tarball_is_found_in_the_ar_archive() -> None:
    deb = _ar({"debian-binary": b"2.0\n", "control.tar.xz": b"x" * 5, "data.tar.xz": b"DATA"})
    assert data_tarball(deb) == b"DATA"
    with pytest.raises(ValueError, match="ar magic"):
        data_tarball(b"PK\x03\x04")


def test_fetch_unpacks_and_splits_a_package(tmp_path: Path, monkeypatch: Any) -> None:
    """A .deb built here, served by a stand-in urlopen: the hash is checked, the images
    decoded and split, a file Pillow cannot read is skipped."""
    tar_bytes = io.BytesIO()
    with tarfile.open(fileobj=tar_bytes, mode="w:xz") as tar:
        for i in range(6):
            png = io.BytesIO()
            Image.fromarray(_photo(i, (20, 30))).save(png, format="PNG")
            _add(tar, f"./usr/share/backgrounds/mate/nature/p{i}.jpg", png.getvalue())
        _add(tar, "./usr/share/backgrounds/mate/nature/broken.jpg", b"not an image")
    deb = _ar({"debian-binary": b"2.0\n", "data.tar.xz": tar_bytes.getvalue()})
    import hashlib

    source = replace(
        source_named("mate-nature"), sha256=hashlib.sha256(deb).hexdigest(), size=len(deb)
    )
    monkeypatch.setattr(
        real_content_fetch.urllib.request, "urlopen", lambda *a, **k: io.BytesIO(deb)
    )
    counts = fetch_all(tmp_path, (source,))
    assert counts == {"mate-nature": 6}
    held = sorted(p.name for p in (tmp_path / "mate-nature" / "held_out").iterdir())
    train = sorted(p.name for p in (tmp_path / "mate-nature" / "train").iterdir())
    assert len(held) == 2 and len(train) == 4 and not set(held) & set(train)
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert "broken" not in manifest["mate-nature"]["train"] + manifest["mate-nature"]["held_out"]
    bad = replace(source, sha256="0" * 64)
    (tmp_path / ".debs" / Path(source.pool_path).name).unlink()
    with pytest.raises(SystemExit, match="SHA-256"):
        fetch_all(tmp_path, (bad,))


def _add(tar: tarfile.TarFile, name: str, data: bytes) -> None:
    info = tarfile.TarInfo(name)
    info.size = len(data)
    tar.addfile(info, io.BytesIO(data))


def test_fetch_offline_says_what_it_needs(tmp_path: Path, monkeypatch: Any) -> None:
    def offline(*args: Any, **kwargs: Any) -> Any:
        raise urllib.error.URLError("no route")

    monkeypatch.setattr(real_content_fetch.urllib.request, "urlopen", offline)
    with pytest.raises(SystemExit, match="needs the network"):
        fetch_all(tmp_path, SOURCES[:1])


def test_pan_motion_is_exact_for_a_temporal_method() -> None:
    """The right motion beats the negated motion by far: the vectors point where the
    frame contract says (the surface at p was at p + motion)."""
    display = Size(96, 64)
    seq = build_sequence("pan", "t", _photo(0), _photo(1), display, 2.0, 12)
    mx, my = seq.jittered[3].motion[5, 7]
    assert (mx, my) == pytest.approx((PAN_PER_FRAME[0] / 2, PAN_PER_FRAME[1] / 2), abs=1e-5)
    scores = {}
    for sign in (1, -1):
        host = UpscalerHost("temporal", display, {})
        psnr = []
        for frame, truth in zip(seq.jittered, seq.truth, strict=True):
            f = replace(frame, motion=np.ascontiguousarray(sign * frame.motion))
            psnr.append(metrics.psnr(truth, to_uint8(host.upscale(f))))
        scores[sign] = float(np.mean(psnr[4:]))
    assert scores[1] > scores[-1] + 1.0


def test_truth_is_the_render_at_scale_one() -> None:
    """At 1x an unjittered render pixel's footprint is its display pixel's."""
    for kind in ("pan", "zoom"):
        seq = build_sequence(kind, "t", _photo(2), _photo(3), Size(64, 48), 1.0, 5)
        for frame, truth in zip(seq.unjittered, seq.truth, strict=True):
            assert np.array_equal(frame.color, truth)
        # The jittered render samples elsewhere, so it differs.
        assert not np.array_equal(seq.jittered[1].color, seq.truth[1])


def test_zoom_motion_is_radial() -> None:
    """Zooming in, the surface at p came from nearer the centre: motion points inwards,
    grows with the distance and vanishes at the centre."""
    seq = build_sequence("zoom", "t", _photo(4), _photo(5), Size(96, 64), 2.0, 4)
    m = seq.jittered[2].motion  # 48x32 render pixels, centre between 23 and 24
    assert m[0, 0, 0] > 0 and m[0, 0, 1] > 0 and m[-1, -1, 0] < 0 and m[-1, -1, 1] < 0
    assert abs(m[16, 0, 0]) > abs(m[16, 12, 0]) > abs(m[16, 23, 0])
    assert abs(m[16, 23, 0] + m[16, 24, 0]) < 1e-5  # symmetric about the centre


def test_cut_frame_carries_reset_and_a_new_picture() -> None:
    seq = build_sequence("cut", "t", _photo(6), _photo(7), Size(64, 48), 2.0, 8)
    # Every frame says its samples are area averages (how build_sequence makes them).
    flags = [f.meta.flags & ~FrameFlags.AREA_SAMPLES for f in seq.jittered + seq.unjittered]
    assert all(f.meta.flags & FrameFlags.AREA_SAMPLES for f in seq.jittered + seq.unjittered)
    assert seq.cut == 4
    assert flags[0] == flags[4] == FrameFlags.RESET
    assert flags[8] == flags[12] == FrameFlags.RESET  # the unjittered frames
    assert all(f == FrameFlags.NONE for i, f in enumerate(flags) if i % 8 not in (0, 4))
    assert not seq.jittered[4].motion.any()
    before, after = seq.truth[3].astype(int), seq.truth[4].astype(int)
    assert np.abs(before - after).mean() > 10  # another photograph, not a small pan step
    first = build_sequence("first", "t", _photo(6), _photo(7), Size(64, 48), 2.0, 8)
    assert len(first.truth) == 1
    assert first.jittered[0].meta.flags == FrameFlags.RESET | FrameFlags.AREA_SAMPLES


def test_only_photograph_sources_are_evaluated(tmp_path: Path) -> None:
    for folder in ("neverball-shots", "mate-nature", "mine"):
        (tmp_path / folder / "held_out").mkdir(parents=True)
        Image.fromarray(_photo(0, (8, 8))).save(tmp_path / folder / "held_out" / "a.png")
    found = held_out_images(tmp_path)
    assert [image_source(p) for p in found] == ["mate-nature", "mine"]


def test_a_folder_of_your_own_pictures_is_evaluated_whole(tmp_path: Path) -> None:
    """A user's folder: its own images and a subfolder's, in any mode PIL reads (grey,
    RGBA), reported under their folder; a fetched source gives only its held-out images,
    never the ones training uses; other files are ignored."""
    mine = tmp_path / "holiday"
    (mine / "trip").mkdir(parents=True)
    Image.fromarray(_photo(0)).convert("L").save(mine / "grey.jpg")
    Image.fromarray(_photo(1)).convert("RGBA").save(mine / "alpha.png")
    Image.fromarray(_photo(2)).save(mine / "trip" / "beach.JPG")
    (mine / "notes.txt").write_text("not a picture")
    for split in ("train", "held_out"):
        (mine / "mate-nature" / split).mkdir(parents=True)
        Image.fromarray(_photo(3)).save(mine / "mate-nature" / split / f"{split}.png")
    found = held_out_images(mine)
    names = [f"{image_source(p)}/{p.name}" for p in found]
    assert names == [
        "holiday/alpha.png", "holiday/grey.jpg", "mate-nature/held_out.png", "trip/beach.JPG"
    ]  # fmt: skip
    assert all(load_rgb(p).shape[2] == 3 for p in found)


def test_pictures_smaller_than_the_crop_are_left_out_with_the_reason(tmp_path: Path) -> None:
    """A picture smaller than the crop would be compared with an upsample of itself:
    left out, named; with none left the evaluation stops before rendering."""
    Image.fromarray(_photo(0, (220, 300))).save(tmp_path / "big.png")
    Image.fromarray(_photo(1, (60, 80))).save(tmp_path / "small.png")
    kept, left_out = large_enough(held_out_images(tmp_path), Size(160, 96))
    assert [p.name for p in kept] == ["big.png"]
    assert len(left_out) == 1 and "small.png (80x60): smaller than the 160x96 crop" in left_out[0]
    (tmp_path / "broken.jpg").write_bytes(b"not a jpeg")
    kept, left_out = large_enough(held_out_images(tmp_path), Size(160, 96))
    assert [p.name for p in kept] == ["big.png"] and "broken.jpg: not a picture" in left_out[0]
    (tmp_path / "big.png").unlink()
    with pytest.raises(SystemExit, match=r"small\.png"):
        main(
            ["eval", "upscalers", "--json", str(tmp_path / "x.json"), "--scenes", "none",
             "--real-content", str(tmp_path), "--real-display-size", "160x96"]
        )  # fmt: skip


def test_eval_refuses_a_missing_content_dir(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="upcast eval content --fetch"):
        main(
            ["eval", "upscalers", "--json", str(tmp_path / "x.json"), "--scenes", "none",
             "--real-content", str(tmp_path / "absent")]
        )  # fmt: skip
    with pytest.raises(SystemExit, match="nothing to evaluate"):
        main(["eval", "upscalers", "--json", str(tmp_path / "x.json"), "--scenes", "none"])


def test_eval_real_content_writes_json_table_and_plots(tmp_path: Path) -> None:
    for i in range(2):
        (tmp_path / "c" / "pics" / "held_out").mkdir(parents=True, exist_ok=True)
        Image.fromarray(_photo(10 + i)).save(tmp_path / "c" / "pics" / "held_out" / f"{i}.png")
    out = tmp_path / "r.json"
    code = main(
        ["eval", "upscalers", "--json", str(out), "--table", str(tmp_path / "r.md"),
         "--plot", str(tmp_path / "r.png"), "--scenes", "none", "--scales", "2",
         "--methods", "bicubic,easu_rcas,temporal", "--real-content", str(tmp_path / "c"),
         "--real-frames", "8", "--real-measure-from", "3", "--real-display-size", "96x64"]
    )  # fmt: skip
    assert code == 0
    report = json.loads(out.read_text())
    section = report["real_content"]
    assert section["images"] == ["pics/0.png", "pics/1.png"]
    temporal = section["scales"]["2"]["methods"]["temporal"]
    assert temporal["temporal"] and temporal["median_ms"] > 0
    assert len(temporal["kinds"]["pan"]["psnr_per_frame"]) == 8
    assert len(temporal["kinds"]["first"]["psnr_per_frame"]) == 1
    assert temporal["kinds"]["cut"]["measured_frames"] == [4, 8]
    # One source folder ("pics"): its mean is the mean over both photographs.
    by_source = temporal["kinds"]["pan"]["psnr_by_source"]
    assert list(by_source) == ["pics"]
    assert by_source["pics"] == pytest.approx(temporal["kinds"]["pan"]["psnr_db"])
    by_image = temporal["kinds"]["pan"]["psnr_by_image"]
    assert list(by_image) == ["pics/0.png", "pics/1.png"]
    assert sum(by_image.values()) / 2 == pytest.approx(temporal["kinds"]["pan"]["psnr_db"])
    assert any("on every photograph (" in n for n in report["notes"])
    cases = [c for c in report["cases"] if c.get("suite") == "real_content"]
    assert len(cases) == 3 * 5 and all(15 < c["psnr_db"] < 60 for c in cases)
    assert any("cut: temporal's frames 0-3 after the cut" in n for n in report["notes"])
    table = (tmp_path / "r.md").read_text()
    assert "| temporal |" in table and "pan (f3-7)" in table
    for png in ("r.png", "r_cut.png"):
        assert (tmp_path / png).read_bytes()[:4] == b"\x89PNG"


def test_networks_are_checked_against_bicubic_on_every_source() -> None:
    from server.eval.real_content_report import real_content_checks

    def method(first: float, by_source: dict[str, float]) -> dict[str, object]:
        kind = {"psnr_db": first, "psnr_per_frame": [first], "measured_frames": [0, 1],
                "psnr_by_source": by_source}  # fmt: skip
        return {"temporal": False, "kinds": {"first": kind}}

    section = {"scales": {"2": {"methods": {
        "bicubic": method(30.0, {"a": 29.0, "b": 31.0}),
        "unet": method(31.0, {"a": 30.5, "b": 30.9}),
    }}}}  # fmt: skip
    checks = dict(real_content_checks(section))
    assert checks["photos 2x first frame: unet >= bicubic + 0.5 dB (+1.00)"]
    assert checks["photos 2x first on a: unet >= bicubic (+1.50)"]
    assert not checks["photos 2x first on b: unet >= bicubic (-0.10)"]


def test_temporal_is_checked_on_every_photograph_not_only_the_mean() -> None:
    """A mean over photographs can pass while one photograph misses the margin."""
    from server.eval.real_content_report import real_content_checks

    def method(temporal: bool, by_image: dict[str, float]) -> dict[str, object]:
        mean = sum(by_image.values()) / len(by_image)
        kinds = {
            kind: {"psnr_db": mean, "psnr_per_frame": [mean] * 4, "measured_frames": [1, 4],
                   "psnr_by_image": by_image}
            for kind in ("first", "pan", "still", "cut")
        }  # fmt: skip
        return {"temporal": temporal, "kinds": kinds}

    section = {"scales": {"2": {"methods": {
        "bicubic": method(False, {"s/a.jpg": 30.0, "s/b.jpg": 34.0}),
        "easu_rcas": method(False, {"s/a.jpg": 30.6, "s/b.jpg": 33.6}),
        "temporal": method(True, {"s/a.jpg": 35.0, "s/b.jpg": 35.9}),
    }}}}  # fmt: skip
    checks = real_content_checks(section)
    by_text = dict(checks)
    # The mean gains +3.35 over the best spatial method on the mean (easu_rcas, 32.1)...
    mean_check = "photos 2x pan (frames 1-3): temporal >= best spatial (easu_rcas) + 2 dB (+3.35)"
    assert by_text[mean_check]
    # ...but b.jpg gains +1.9 over its own best spatial method (bicubic, 34.0).
    every = [(text, ok) for text, ok in checks if text.startswith("photos 2x pan: temporal >=")]
    assert every == [
        (
            "photos 2x pan: temporal >= best spatial + 2 dB on every photograph "
            "(1 of 2; below: s/b.jpg +1.90)",
            False,
        )
    ]
    still = [text for text, ok in checks if text.startswith("photos 2x still: temporal >=")]
    assert still == [
        "photos 2x still: temporal >= best spatial + 2.5 dB on every photograph "
        "(1 of 2; below: s/b.jpg +1.90)"
    ]
    # All above the margin: a pass, naming the closest photograph.
    section["scales"]["2"]["methods"]["temporal"] = method(True, {"s/a.jpg": 35.0, "s/b.jpg": 37.0})
    passed = [(t, ok) for t, ok in real_content_checks(section) if "every photograph" in t]
    assert passed[0] == (
        "photos 2x pan: temporal >= best spatial + 2 dB on every photograph "
        "(2 of 2; closest: s/b.jpg +3.00)",
        True,
    )
