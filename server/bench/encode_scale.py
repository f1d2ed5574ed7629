"""``upcast bench encode_scale``: what encoding below the display size costs and saves.

Adaptive quality's last resort before the frame rate is the encoded size: the
upscaled picture is scaled down in the encoder's RGB->YUV pass (VideoEncoder's
``set_encoded_size``) and the viewer's browser scales it back up when it draws. This
benchmark measures both sides of that trade on the real code path, for each scene,
render scale and encoded scale:

- *speed*: the encoder's whole call per frame (swscale + x264 + boxing), median and
  p95, after a warm-up;
- *error*: the game renders at the render scale, the upscaler upscales to the display
  size (the worker's code path, UpscalerHost), the encoder encodes at the encoded
  size, PyAV decodes the fragments with the catalog's init segment, and the decoded
  picture is scaled to the display size bilinearly (what a browser's canvas does):
  PSNR against the game's ground truth at the display size;
- and the bytes per frame at the same bitrate.

Encoded scale 1 is the reference of every row: the picture lost (dB) and the encode
time saved (ratio) by each smaller size. The adaptive-quality table
(server/session/quality/figures.py) takes the loss and the time ratio from this
report. Encoded sizes are kept at or above the render size (a picture encoded
smaller than it was rendered wastes the upscaler).
"""

from __future__ import annotations

import argparse
import io
import time
from pathlib import Path
from typing import Any

import av
import numpy as np
import numpy.typing as npt
import torch
import torch.nn.functional as F

from server.frames.frame import Size
from server.game.render.renderer import Renderer, RenderTargets
from server.media.encode import EncodedFrame, EncoderConfig, VideoEncoder, encoded_size
from server.ops.progress import elapsed_and_left, progress
from server.ops.report import BenchReport, summarize_ms
from upscalers import metrics
from upscalers.host import UpscalerHost
from upscalers.output import to_uint8

WARMUP_FRAMES = 3  # encoder calls left out of the timings (the first allocates)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, required=True, help="JSON report path")
    parser.add_argument("--display-size", default="1280x720")
    parser.add_argument("--scenes", default="static,slow_pan,fast_yaw")
    parser.add_argument("--render-scales", default="2,3,4")
    parser.add_argument("--encode-scales", default="1,1.5,2,3")
    parser.add_argument("--method", default="bilinear", help="the upscaler (spatial)")
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument(
        "--bitrate", type=int, default=None, help="bit/s (default: the encoder's for the display)"
    )
    parser.add_argument("--frames", type=int, default=24, help="frames encoded per case")
    parser.add_argument("--truth-every", type=int, default=4, help="ground truth every N frames")
    parser.add_argument("--supersample", type=int, default=2, help="ground truth supersampling")


def _floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x.strip()]


def _size(text: str) -> Size:
    w, h = text.lower().split("x")
    return Size(int(w), int(h))


def browser_upscale(decoded: npt.NDArray[np.uint8], display: Size) -> npt.NDArray[np.uint8]:
    """A decoded picture drawn at the display size with bilinear filtering."""
    if decoded.shape[:2] == (display.height, display.width):
        return decoded
    t = torch.from_numpy(decoded).permute(2, 0, 1)[None].float()
    up = F.interpolate(
        t, size=(display.height, display.width), mode="bilinear", align_corners=False
    )
    return up.round().clamp(0, 255)[0].permute(1, 2, 0).to(torch.uint8).numpy()


def decode_fragments(init: bytes, frames: list[EncodedFrame]) -> list[npt.NDArray[np.uint8]]:
    data = init + b"".join(f.fragment for f in frames)
    with av.open(io.BytesIO(data), mode="r") as container:
        return [
            np.asarray(f.to_ndarray(format="rgb24"), dtype=np.uint8)
            for f in container.decode(video=0)
        ]


def _upscaled(
    scene: str, display: Size, scale: float, times: list[float], method: str
) -> list[npt.NDArray[np.uint8]]:
    render = Size(round(display.width / scale), round(display.height / scale))
    renderer = Renderer(scene, render, scale=scale, jitter=False)
    host = UpscalerHost(method, display, {})
    out = []
    for i, t in enumerate(times):
        frame = renderer.render(i, t, RenderTargets.allocate(render))
        out.append(np.ascontiguousarray(to_uint8(host.upscale(frame))))
    return out


def _encode_case(
    frames: list[npt.NDArray[np.uint8]],
    display: Size,
    encode_scale: float,
    fps: float,
    bitrate: int | None,
) -> tuple[list[EncodedFrame], bytes, tuple[int, int]]:
    encoder = VideoEncoder(EncoderConfig(display.width, display.height, fps=fps, bitrate=bitrate))
    init = encoder.init_segment
    size = encoded_size(display, encode_scale)
    if size != encoder.encoded_size:
        encoder.set_encoded_size(*size)
    out = []
    for i, rgb in enumerate(frames):
        encoded = encoder.encode(rgb, i, round(i * 1e6 / fps))
        if encoded.new_config is not None:
            init = encoded.new_config.init_segment
        out.append(encoded)
    return out, init, size


def run(args: argparse.Namespace) -> int:
    display = _size(args.display_size)
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    render_scales = _floats(args.render_scales)
    encode_scales = sorted(set(_floats(args.encode_scales)) | {1.0})
    times = [i / args.fps for i in range(args.frames)]
    measured = list(range(WARMUP_FRAMES, args.frames, max(1, args.truth_every)))
    report = BenchReport(
        "encode_scale",
        {
            "display_size": str(display),
            "scenes": scenes,
            "render_scales": render_scales,
            "encode_scales": encode_scales,
            "method": args.method,
            "fps": args.fps,
            "bitrate": args.bitrate,
            "frames": args.frames,
            "measured_frames": measured,
            "supersample": args.supersample,
            "reference": f"game ground truth at {display}, unjittered, supersampled "
            f"{args.supersample}x; decoded pictures drawn at that size bilinearly",
        },
    )
    started = time.monotonic()
    total = len(scenes) * len(render_scales)
    done = 0
    for scene in scenes:
        truth_renderer = Renderer(scene, display, scale=1.0, jitter=False)
        truth = {i: truth_renderer.render_ground_truth(times[i], display, args.supersample)
                 for i in measured}  # fmt: skip
        for scale in render_scales:
            upscaled = _upscaled(scene, display, scale, times, args.method)
            for e in encode_scales:
                if e > scale + 1e-9:
                    continue  # encoded below the render size: the upscaler's work thrown away
                encoded, init, size = _encode_case(upscaled, display, e, args.fps, args.bitrate)
                decoded = decode_fragments(init, encoded)
                psnr = [metrics.psnr(truth[i], browser_upscale(decoded[i], display))
                        for i in measured]  # fmt: skip
                report.add_case(
                    f"{scene} render {scale:g}x encode {e:g}x",
                    scene=scene,
                    render_scale=scale,
                    encode_scale=e,
                    encoded_size=f"{size[0]}x{size[1]}",
                    psnr_db=round(float(np.mean(psnr)), 3),
                    bytes_per_frame=round(float(np.mean([len(f.fragment) for f in encoded])), 1),
                    **summarize_ms(f.encode_ms for f in encoded[WARMUP_FRAMES:]),
                )
            done += 1
            elapsed, left = elapsed_and_left(done, total, started)
            progress(
                f"encode_scale: {scene} at {scale:g}x done ({done}/{total}, "
                f"{elapsed:.0f} s, about {left:.0f} s left)"
            )
    _add_ratios(report, encode_scales)
    report.notes.append(
        "psnr_db: the decoded picture against the ground truth, the whole chain (render, "
        "upscale, encoded size, x264 at the bitrate, decode, bilinear draw)"
    )
    report.write(args.json)
    print(f"wrote {args.json} ({len(report.cases)} cases)")
    return 0


def _add_ratios(report: BenchReport, encode_scales: list[float]) -> None:
    """Per encoded scale: encode time against scale 1, and the picture lost (dB) against
    scale 1 at the same scene and render scale, averaged over the cases."""
    reference = {
        (c["scene"], c["render_scale"]): c for c in report.cases if c["encode_scale"] == 1.0
    }
    for e in encode_scales:
        if e == 1.0:
            continue
        pairs = [
            (c, reference[key])
            for c in report.cases
            if c["encode_scale"] == e and (key := (c["scene"], c["render_scale"])) in reference
        ]
        if not pairs:
            continue
        time_ratio = float(np.mean([c["median_ms"] / r["median_ms"] for c, r in pairs]))
        report.add_ratio(f"encode ms at {e:g}x / at 1x", f"encode {e:g}x", "encode 1x", time_ratio)
        for scale in sorted({c["render_scale"] for c, _ in pairs}):
            loss = [r["psnr_db"] - c["psnr_db"] for c, r in pairs if c["render_scale"] == scale]
            report.add_ratio(
                f"PSNR lost at encode {e:g}x, render {scale:g}x (dB)",
                f"encode {e:g}x",
                "encode 1x",
                round(float(np.mean(loss)), 3),
            )


def summary(report: dict[str, Any]) -> dict[str, Any]:
    """The report's ratios by name (for the figures table and the tests)."""
    return {r["name"]: r["ratio"] for r in report.get("ratios", [])}
