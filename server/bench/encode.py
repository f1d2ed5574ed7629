"""``upcast bench encode``: what encoding a display frame into a CMAF fragment costs.

Real code path: :class:`server.media.encode.VideoEncoder` on contiguous uint8 RGB
frames (like a ring U slot): RGB->YUV420 (swscale) + x264 + our fMP4 boxes.
Content: a pan across a mosaic of photographs shipped with scikit-image plus a
moving block, so there is texture, global motion and object motion.

Per size it reports encode time (median/p95, with the convert/x264/boxing
split), bytes per frame and the bitrate they make, PSNR of the decoded picture
against the input, keyframes (periodic and forced) separately from delta frames,
and the mux delay in frames measured two ways: fragments out minus frames in
after each call, and pictures a zero-delay decoder gets out of each fragment.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path
from typing import Any

import av
import numpy as np
import numpy.typing as npt
from av.video.codeccontext import VideoCodecContext
from PIL import Image

from server.frames.frame import Size
from server.media.cmaf import MOOF_SIZE
from server.media.cmaf_read import parse_fragment
from server.media.encode import EncodedFrame, EncoderConfig, VideoEncoder
from server.ops.report import BenchReport, summarize_ms

U8Image = npt.NDArray[np.uint8]
PHOTOS = ("coffee.png", "astronaut.png", "chelsea.png", "brick.png", "rocket.jpg", "grass.png")
PAN_PX_PER_FRAME = (3, 1)  # a slow camera pan, the common case in a game


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, required=True, help="report path")
    parser.add_argument("--sizes", default="640x360,1280x720,1920x1080", help="comma list")
    parser.add_argument("--frames", type=int, default=300, help="measured frames per size")
    parser.add_argument("--warmup", type=int, default=10, help="frames left out per size")
    parser.add_argument("--fps", type=float, default=60.0)
    parser.add_argument("--preset", default="ultrafast")
    parser.add_argument("--bitrate", type=int, default=None, help="bit/s; default scales")
    parser.add_argument("--gop-seconds", type=float, default=2.0)
    parser.add_argument("--threads", type=int, default=0, help="x264 threads (0 = auto)")
    parser.add_argument("--convert-threads", type=int, default=1, help="swscale threads")
    parser.add_argument(
        "--vbv-frames", type=float, default=1.0, help="VBV buffer in frame intervals"
    )
    parser.add_argument(
        "--force-keyframe-every", type=int, default=45, help="request an IDR every N frames"
    )
    parser.add_argument("--psnr-every", type=int, default=3, help="PSNR on every Nth frame")


def photo_mosaic(width: int, height: int) -> U8Image:
    """Photos tiled into a canvas twice the frame size (room to pan), from the
    scikit-image wheel's data folder (never downloaded)."""
    spec = importlib.util.find_spec("skimage")
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError("scikit-image is not installed; it ships the photos")
    data = Path(next(iter(spec.submodule_search_locations))) / "data"
    tile = max(64, height // 2)
    cols, rows = -(-2 * width // tile), -(-2 * height // tile)
    canvas = np.zeros((rows * tile, cols * tile, 3), np.uint8)
    for r in range(rows):
        for c in range(cols):
            name = PHOTOS[(r * cols + c + r) % len(PHOTOS)]
            with Image.open(data / name) as im:
                photo = im.convert("RGB").resize((tile, tile), Image.Resampling.BILINEAR)
            canvas[r * tile : (r + 1) * tile, c * tile : (c + 1) * tile] = np.asarray(photo)
    return canvas


def render_frame(canvas: U8Image, index: int, out: U8Image) -> None:
    """Frame ``index`` of the pan into ``out`` (contiguous, like a ring slot)."""
    h, w, _ = out.shape
    span_x, span_y = canvas.shape[1] - w, canvas.shape[0] - h
    x = (index * PAN_PX_PER_FRAME[0]) % (2 * span_x)
    y = (index * PAN_PX_PER_FRAME[1]) % (2 * span_y)
    x, y = min(x, 2 * span_x - x), min(y, 2 * span_y - y)  # bounce back at the edges
    np.copyto(out, canvas[y : y + h, x : x + w])
    # A block moving against the pan: object motion and disocclusion.
    side = h // 6
    bx = int((w - side) * (0.5 + 0.5 * np.sin(index / 40.0)))
    by = int((h - side) * (0.5 + 0.5 * np.cos(index / 55.0)))
    out[by : by + side, bx : bx + side] = (230, 60, 40)


def psnr(a: npt.NDArray[Any], b: U8Image) -> float:
    mse = float(np.mean((a.astype(np.float32) - b.astype(np.float32)) ** 2))
    return float(10 * np.log10(255.0**2 / max(mse, 1e-12)))


def _zero_delay_decoder(encoder: VideoEncoder) -> VideoCodecContext:
    decoder = av.CodecContext.create("h264", "r")
    decoder.extradata = encoder.avc.avcc()
    decoder.thread_count = 1  # frame threads would hold pictures back
    return decoder


def _measure(size: Size, args: argparse.Namespace) -> dict[str, Any]:
    cfg = EncoderConfig(
        size.width,
        size.height,
        fps=args.fps,
        bitrate=args.bitrate,
        preset=args.preset,
        gop_seconds=args.gop_seconds,
        threads=args.threads,
        convert_threads=args.convert_threads,
        vbv_frames=args.vbv_frames,
    )
    encoder = VideoEncoder(cfg)
    decoder = _zero_delay_decoder(encoder)
    canvas = photo_mosaic(size.width, size.height)
    frame = np.empty((size.height, size.width, 3), np.uint8)
    frame_us = 1e6 / args.fps
    results: list[tuple[EncodedFrame, float | None]] = []
    max_lag = 0
    pictures_per_fragment: set[int] = set()
    total = args.warmup + args.frames
    for i in range(total):
        render_frame(canvas, i, frame)
        if args.force_keyframe_every and i % args.force_keyframe_every == 0 and i:
            encoder.request_keyframe()
        encoded = encoder.encode(frame, frame_id=i, pts_us=round(i * frame_us))
        max_lag = max(max_lag, encoder.frames_in - encoder.fragments_out)
        pictures = decoder.decode(av.Packet(parse_fragment(encoded.fragment).sample))
        pictures_per_fragment.add(len(pictures))
        quality = None
        if pictures and (i % args.psnr_every == 0 or encoded.keyframe):
            quality = psnr(pictures[-1].to_ndarray(format="rgb24"), frame)
        if i >= args.warmup:
            results.append((encoded, quality))
        if (i + 1) % 100 == 0:
            print(f"  {size} {i + 1}/{total}", file=sys.stderr)
    return _summarize(cfg, results, max_lag, pictures_per_fragment)


def _summarize(
    cfg: EncoderConfig,
    results: list[tuple[EncodedFrame, float | None]],
    max_lag: int,
    pictures_per_fragment: set[int],
) -> dict[str, Any]:
    def group(frames: list[tuple[EncodedFrame, float | None]]) -> dict[str, Any]:
        if not frames:
            return {"count": 0}
        sizes = np.array([len(f.fragment) for f, _ in frames], dtype=np.float64)
        qualities = [q for _, q in frames if q is not None]
        return {
            "count": len(frames),
            "encode": summarize_ms(f.encode_ms for f, _ in frames),
            "convert": summarize_ms(f.convert_ms for f, _ in frames),
            "x264": summarize_ms(f.x264_ms for f, _ in frames),
            "boxing": summarize_ms(f.encode_ms - f.convert_ms - f.x264_ms for f, _ in frames),
            "bytes_median": float(np.median(sizes)),
            "bytes_mean": float(sizes.mean()),
            "bytes_max": int(sizes.max()),
            "psnr_db_mean": float(np.mean(qualities)) if qualities else None,
            "psnr_db_min": float(np.min(qualities)) if qualities else None,
            "psnr_frames": len(qualities),
        }

    keys = [r for r in results if r[0].keyframe]
    deltas = [r for r in results if not r[0].keyframe]
    every = group(results)
    return {
        "size": f"{cfg.width}x{cfg.height}",
        "target_bitrate": cfg.target_bitrate,
        "vbv_bufsize_bits": round(cfg.target_bitrate * cfg.vbv_frames / cfg.fps),
        "achieved_bitrate": every["bytes_mean"] * 8 * cfg.fps,
        "box_overhead_bytes": MOOF_SIZE + 8,
        "all": every,
        "keyframes": group(keys),
        "delta_frames": group(deltas),
        # 0 = the call that takes frame k returns frame k's fragment.
        "mux_delay_frames_max": max_lag,
        # {1} = each fragment alone decodes to its own picture (no decoder-side wait).
        "pictures_per_fragment": sorted(pictures_per_fragment),
    }


def run(args: argparse.Namespace) -> int:
    sizes = [Size.parse(s) for s in args.sizes.split(",")]
    report = BenchReport(
        "encode",
        {
            "sizes": args.sizes,
            "frames": args.frames,
            "warmup": args.warmup,
            "fps": args.fps,
            "preset": args.preset,
            "tune": "zerolatency",
            "bitrate": args.bitrate or "scaled from 6 Mbit/s at 1280x720@60",
            "vbv_frames": args.vbv_frames,
            "vbv": "vbv-maxrate = bitrate, vbv-bufsize = bitrate * vbv_frames / fps",
            "gop_seconds": args.gop_seconds,
            "force_keyframe_every": args.force_keyframe_every,
            "threads": args.threads,
            "convert_threads": args.convert_threads,
            "psnr_every": args.psnr_every,
            "content": "pan over a mosaic of scikit-image photos plus a moving block",
            "timed": "VideoEncoder.encode: RGB->YUV420 + x264 + fMP4 boxing (one thread)",
            "psnr_reference": "the RGB input frame; decoded with FFmpeg h264, BT.709",
        },
    )
    header = f"{'size':>10} {'enc p50':>8} {'p95':>7} {'key p50':>8} {'KB/fr':>6} {'Mbit/s':>7}"
    print(f"{header} {'PSNR':>6} {'keyPSNR':>7} {'delay':>5}")
    for size in sizes:
        m = _measure(size, args)
        enc, key = m["all"]["encode"], m["keyframes"]
        report.add_case(
            f"encode_{size}",
            median_ms=enc["median_ms"],
            p95_ms=enc["p95_ms"],
            psnr_db=m["all"]["psnr_db_mean"],
            **m,
        )
        if key["count"] and m["delta_frames"]["count"]:
            report.add_ratio(
                f"keyframe_over_delta_encode_median_{size}",
                f"encode_{size} keyframes",
                f"encode_{size} delta_frames",
                key["encode"]["median_ms"] / m["delta_frames"]["encode"]["median_ms"],
            )
            report.add_ratio(
                f"keyframe_over_delta_bytes_median_{size}",
                f"encode_{size} keyframes",
                f"encode_{size} delta_frames",
                key["bytes_median"] / m["delta_frames"]["bytes_median"],
            )
        key_med = key["encode"]["median_ms"] if key["count"] else float("nan")
        key_psnr = key["psnr_db_mean"] if key["count"] else float("nan")
        print(
            f"{size!s:>10} {enc['median_ms']:8.2f} {enc['p95_ms']:7.2f} {key_med:8.2f} "
            f"{m['all']['bytes_mean'] / 1e3:6.1f} {m['achieved_bitrate'] / 1e6:7.2f} "
            f"{m['all']['psnr_db_mean']:6.1f} {key_psnr:7.1f} {m['mux_delay_frames_max']:5d}"
        )
    report.notes.append(
        "mux_delay_frames_max is frames_in - fragments_out after each encode call;"
        " pictures_per_fragment counts what a thread_count=1 FFmpeg decoder returns"
        " for each fragment's sample."
    )
    report.write(args.json)
    print(f"report written to {args.json}")
    return 0
