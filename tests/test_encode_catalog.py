"""The hang catalog we publish, checked against @moq/hang 0.3.5's zod schema."""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from server.media.catalog import catalog_for, video_catalog
from server.media.cmaf import iter_boxes
from server.media.encode import EncoderConfig, VideoEncoder

# Field -> JSON type, from moq-hang-0.3.5/package/catalog/video.js (VideoConfigSchema):
# u53 fields are non-negative integers, framerate a number, optimizeForLatency a boolean.
RENDITION_TYPES: dict[str, type | tuple[type, ...]] = {
    "codec": str,
    "container": dict,
    "codedWidth": int,
    "codedHeight": int,
    "framerate": (int, float),
    "bitrate": int,
    "optimizeForLatency": bool,
    "jitter": int,
}
CLIENT_MODULES = Path(__file__).resolve().parents[1] / "client_web" / "node_modules"
HANG_VIDEO_JS = CLIENT_MODULES / "@moq" / "hang" / "catalog" / "video.js"
# ./dev test installs client_web's npm packages (with node) before the tests, so in
# CI a missing @moq/hang is a broken setup and must fail, not skip.
HANG_MISSING = not os.environ.get("CI") and (
    not HANG_VIDEO_JS.exists() or shutil.which("node") is None
)
HANG_REASON = "needs node and client_web/node_modules (npm ci in client_web)"
# The client's own modules bundled with its esbuild and run in node (run_in_node): the
# same rule.
ESBUILD = CLIENT_MODULES / ".bin" / "esbuild"
NEEDS_NODE = pytest.mark.skipif(
    not os.environ.get("CI") and (not ESBUILD.exists() or shutil.which("node") is None),
    reason=HANG_REASON,
)


def emitted() -> dict[str, Any]:
    enc = VideoEncoder(EncoderConfig(640, 360, fps=60))
    parsed: dict[str, Any] = json.loads(catalog_for(enc).to_json())
    return parsed


def test_catalog_shape_and_types() -> None:
    cat = emitted()
    assert set(cat) == {"video"}
    assert set(cat["video"]) == {"renditions"}
    assert set(cat["video"]["renditions"]) == {"video"}  # key = track name
    r = cat["video"]["renditions"]["video"]
    assert set(r) == set(RENDITION_TYPES)
    for key, kind in RENDITION_TYPES.items():
        assert isinstance(r[key], kind), key
        if kind is int:
            assert not isinstance(r[key], bool) and r[key] >= 0, key
    assert re.fullmatch(r"avc1\.[0-9a-f]{6}", r["codec"])
    assert (r["codedWidth"], r["codedHeight"], r["framerate"]) == (640, 360, 60.0)
    assert r["jitter"] == 17  # ceil(1000 / 60)
    assert r["optimizeForLatency"] is True
    assert set(r["container"]) == {"kind", "init"} and r["container"]["kind"] == "cmaf"


def test_init_is_strict_base64_of_the_init_segment() -> None:
    init_b64 = emitted()["video"]["renditions"]["video"]["container"]["init"]
    init = base64.b64decode(init_b64, validate=True)  # zod's z.base64(): standard alphabet
    assert [b.kind for b in iter_boxes(init)] == [b"ftyp", b"moov"]


def test_optional_fields_left_out_when_unset() -> None:
    cat = video_catalog(codec="avc1.42c01f", init_segment=b"x", width=2, height=2, fps=30)
    r = json.loads(cat.to_json())["video"]["renditions"]["video"]
    assert "bitrate" not in r and "description" not in r


@pytest.mark.skipif(HANG_MISSING, reason=HANG_REASON)
def test_field_names_exist_in_hang_schema() -> None:
    source = HANG_VIDEO_JS.read_text()
    schema = source[source.index("VideoConfigSchema = z.object(") :]
    schema = schema[: schema.index("});")]
    declared = set(re.findall(r"^\s{4}(\w+):", schema, re.MULTILINE))
    assert set(RENDITION_TYPES) <= declared


def run_with_hang(tmp_path: Path, script: str, *args: Path) -> Any:
    """Bundle ``script`` (its ``HANG`` standing for the installed @moq/hang) for node
    with the client's esbuild, run it on ``args`` and return the JSON it prints."""
    src = tmp_path / "check.mjs"
    src.write_text(script.replace("HANG", str(CLIENT_MODULES / "@moq" / "hang")))
    return run_in_node(tmp_path, src, *args)


def run_in_node(tmp_path: Path, entry: Path, *args: Path | str) -> Any:
    """Bundle ``entry`` (JS or TS, importing the client's packages) for node with the
    client's esbuild, run it on ``args`` and return the JSON it prints."""
    bundle = tmp_path / "bundle.mjs"
    subprocess.run(
        [str(ESBUILD), str(entry), "--bundle", "--platform=node",
         "--format=esm", f"--outfile={bundle}", "--log-level=error"],
        check=True, env={**os.environ, "NODE_PATH": str(CLIENT_MODULES)},
    )  # fmt: skip
    result = subprocess.run(
        ["node", str(bundle), *map(str, args)], check=True, capture_output=True, text=True
    )
    return json.loads(result.stdout)


_HANG_CHECK_JS = """
import { readFileSync } from "node:fs";
import * as Catalog from "HANG/catalog/index.js";
import * as Cmaf from "HANG/container/cmaf/decode.js";
const parsed = Catalog.RootSchema.parse(JSON.parse(readFileSync(process.argv[2], "utf8")));
const r = parsed.video.renditions.video;
const init = Cmaf.decodeInitSegment(new Uint8Array(Buffer.from(r.container.init, "base64")));
const samples = process.argv.slice(3).flatMap((f) =>
  Cmaf.decodeDataSegment(new Uint8Array(readFileSync(f)), init));
console.log(JSON.stringify({codec: r.codec, timescale: init.timescale,
  avcc: init.description.length, samples: samples.map((s) => [s.timestamp, s.keyframe])}));
"""


@pytest.mark.skipif(HANG_MISSING, reason=HANG_REASON)
def test_hang_itself_accepts_catalog_and_fragments(tmp_path: Path) -> None:
    """Run @moq/hang's own zod schema and CMAF parser (what @moq/watch uses) on our bytes."""
    enc = VideoEncoder(EncoderConfig(320, 180, fps=30))
    (tmp_path / "catalog.json").write_bytes(catalog_for(enc).to_json())
    frags = []
    for i in range(3):
        frame = enc.encode(np.full((180, 320, 3), 60 * i, np.uint8), i, 5_000_000_000 + i * 33_333)
        frags.append(tmp_path / f"frag{i}.m4s")
        frags[-1].write_bytes(frame.fragment)
    out = run_with_hang(tmp_path, _HANG_CHECK_JS, tmp_path / "catalog.json", *frags)
    assert out["codec"] == enc.codec_string()
    assert out["timescale"] == 1_000_000
    assert out["avcc"] == len(enc.avc.avcc())
    assert out["samples"] == [
        [5_000_000_000, True],
        [5_000_033_333, False],
        [5_000_066_666, False],
    ]
