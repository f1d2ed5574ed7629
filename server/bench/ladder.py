"""``upcast bench ladder``: what the rendition ladder costs, and what each rung shows.

Real code path: the session's player-track encoder (:class:`VideoEncoder` at the
display size with intra refresh, as ``upcast up`` opens it) and the
:class:`RenditionLadder` on the same frames, in one run, one after the other on each
frame. Content: the encode benchmark's photo pan with a moving block.

Per case (the player's track alone, then each rung) it reports:

- encode ms per frame (median, p95) and the CPU seconds of the calls (CPU time, not
  wall time: on a loaded host wall time would blame the rung for its neighbours);
- the bitrate it made against its cap;
- what a viewer of it sees: PSNR of the decoded picture drawn at the display size
  (bilinear, as a browser scales a video element) against the display frame, and the
  rung's own PSNR against the frame scaled down by area (what the scaler aimed at);
- ratios: each rung's and the whole ladder's CPU against the player's track alone.

The closing line says what the ladder costs of one core at the stream's frame rate,
which is what to weigh before leaving it on (``--ladder off``) on a busy host.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import av
import numpy as np
import numpy.typing as npt
from av.video.codeccontext import VideoCodecContext
from PIL import Image

from server.bench.encode import photo_mosaic, psnr, render_frame
from server.frames.frame import Size
from server.media.cmaf_read import parse_fragment
from server.media.encode import EncodedFrame, EncoderConfig, VideoEncoder
from server.media.ladder import RenditionLadder
from server.ops.report import BenchReport, summarize_ms
from server.stream_config import DEFAULT_DIVISORS, parse_divisors

U8Image = npt.NDArray[np.uint8]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", type=Path, required=True, help="report path")
    parser.add_argument("--display-size", default="1280x720", help="the player's track size")
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument(
        "--ladder",
        default=",".join(map(str, DEFAULT_DIVISORS)),
        help="rung divisors, as upcast up --ladder (default: %(default)s)",
    )
    parser.add_argument(
        "--share-conversion",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="scale the rungs from the player's YUV frame, as the session does (default);"
        " --no-share-conversion: convert the RGB frame again",
    )
    parser.add_argument("--frames", type=int, default=240, help="measured frames")
    parser.add_argument("--warmup", type=int, default=10, help="frames left out")
    parser.add_argument("--psnr-every", type=int, default=4, help="PSNR on every Nth frame")


class _Case:
    """One track's measurements: encode calls, their thread CPU, bytes, PSNR."""

    def __init__(self, name: str, width: int, height: int, cap: int, decoder: VideoCodecContext):
        self.name = name
        self.size = (width, height)
        self.cap = cap
        self.decoder = decoder
        self.encode_ms: list[float] = []
        self.cpu_s = 0.0
        self.bytes = 0
        self.frames = 0
        self.keyframes = 0
        self.psnr_display: list[float] = []
        self.psnr_own: list[float] = []

    def add(self, encoded: EncodedFrame, cpu_s: float, measured: bool) -> list[U8Image]:
        pictures = self.decoder.decode(av.Packet(parse_fragment(encoded.fragment).sample))
        if measured:
            self.encode_ms.append(encoded.encode_ms)
            self.cpu_s += cpu_s
            self.bytes += len(encoded.fragment)
            self.frames += 1
            self.keyframes += int(encoded.keyframe)
        return [np.asarray(p.to_ndarray(format="rgb24"), np.uint8) for p in pictures]

    def summary(self, fps: float, player_cpu_s: float) -> dict[str, Any]:
        bitrate = self.bytes * 8 * fps / max(1, self.frames)
        return {
            "name": self.name,
            "size": f"{self.size[0]}x{self.size[1]}",
            "bitrate_cap": self.cap,
            "achieved_bitrate": round(bitrate),
            "frames": self.frames,
            "keyframes": self.keyframes,
            "encode_ms": summarize_ms(self.encode_ms),
            "cpu_ms_per_frame": round(1000 * self.cpu_s / max(1, self.frames), 3),
            "cpu_vs_player": round(self.cpu_s / player_cpu_s, 3) if player_cpu_s else None,
            "psnr_at_display_db": _mean(self.psnr_display),
            "psnr_own_size_db": _mean(self.psnr_own),
        }


def _mean(values: list[float]) -> float | None:
    return round(float(np.mean(values)), 2) if values else None


def _decoder(encoder: VideoEncoder) -> VideoCodecContext:
    decoder = av.CodecContext.create("h264", "r")
    decoder.extradata = encoder.avc.avcc()
    decoder.thread_count = 1
    return decoder


def _resize(image: U8Image, width: int, height: int, method: Image.Resampling) -> U8Image:
    return np.asarray(Image.fromarray(image).resize((width, height), method))


def _measure(args: argparse.Namespace) -> tuple[list[_Case], _Case]:
    display = Size.parse(args.display_size)
    player = VideoEncoder(
        EncoderConfig(display.width, display.height, fps=args.fps, intra_refresh=True)
    )
    ladder = RenditionLadder(display, args.fps, parse_divisors(args.ladder))
    if not ladder.rungs:
        raise SystemExit("upcast bench ladder: --ladder gives no rung for this display size")
    player_case = _Case(
        "player", display.width, display.height, player.config.target_bitrate, _decoder(player)
    )
    rung_cases = {
        r.track: _Case(r.track, r.width, r.height, r.bitrate, _decoder(r.encoder))
        for r in ladder.rungs
    }
    # The ladder's one RGB -> YUV pass per frame, shared by its rungs.
    convert = _Case("ladder conversion", display.width, display.height, 0, _decoder(player))
    canvas = photo_mosaic(display.width, display.height)
    frame = np.empty((display.height, display.width, 3), np.uint8)
    frame_us = 1e6 / args.fps
    total = args.warmup + args.frames
    for i in range(total):
        render_frame(canvas, i, frame)
        measured = i >= args.warmup
        check = measured and i % args.psnr_every == 0
        pts = round(i * frame_us)
        # Process CPU: x264 may slice a frame over threads of its own (threads=0, as the
        # session opens it), which a thread clock would leave out. The rungs run one
        # thread each (RenditionLadder), and their calls below are timed by the ladder.
        start = time.process_time()
        encoded = player.encode(frame, frame_id=i, pts_us=pts)
        cpu = time.process_time() - start
        pictures = player_case.add(encoded, cpu, measured)
        if check and pictures:
            player_case.psnr_display.append(psnr(pictures[-1], frame))
        before = {r.track: r.cpu_s_total for r in ladder.rungs}
        converted = ladder.stats.convert_cpu_s
        # As the session does: the player's converted frame, when at the display size.
        shared = player.last_yuv if args.share_conversion else None
        rung_frames, failed = ladder.encode(
            frame if shared is None else shared, i, pts, align=encoded.keyframe
        )
        if measured:
            convert.cpu_s += ladder.stats.convert_cpu_s - converted
            convert.frames += 1
        if failed:
            raise SystemExit(f"upcast bench ladder: rung {', '.join(failed)} failed (see the log)")
        for rung_frame in rung_frames:
            rung = next(r for r in ladder.rungs if r.track == rung_frame.track)
            case = rung_cases[rung.track]
            cpu = rung.cpu_s_total - before[rung.track]
            pictures = case.add(rung_frame.encoded, cpu, measured)
            if check and pictures:
                shown = pictures[-1]
                target = _resize(frame, rung.width, rung.height, Image.Resampling.BOX)
                case.psnr_own.append(psnr(shown, target))
                drawn = _resize(shown, display.width, display.height, Image.Resampling.BILINEAR)
                case.psnr_display.append(psnr(drawn, frame))
        if (i + 1) % 60 == 0:
            print(f"  frame {i + 1}/{total}", file=sys.stderr)
    return [player_case, *rung_cases.values()], convert


def run(args: argparse.Namespace) -> int:
    cases, convert = _measure(args)
    player, rungs = cases[0], cases[1:]
    player_cpu = player.cpu_s
    ladder_cpu = sum(c.cpu_s for c in rungs) + convert.cpu_s
    report = BenchReport(
        "ladder",
        {
            "display_size": args.display_size,
            "fps": args.fps,
            "ladder": args.ladder,
            "frames": args.frames,
            "warmup": args.warmup,
            "content": "photo pan with a moving block (bench encode's)",
            "player_track": "x264 ultrafast zerolatency, intra refresh, as upcast up",
            "share_conversion": args.share_conversion,
        },
    )
    report.add_case(
        "ladder conversion",
        cpu_ms_per_frame=round(1000 * convert.cpu_s / max(1, convert.frames), 3),
        cpu_vs_player=round(convert.cpu_s / player_cpu, 3),
    )
    for case in cases:
        values = case.summary(args.fps, player_cpu)
        timing = values["encode_ms"]
        report.add_case(
            values.pop("name"), median_ms=timing["median_ms"], p95_ms=timing["p95_ms"], **values
        )
    frame_budget_ms = 1000 / args.fps
    ladder_ms = 1000 * ladder_cpu / max(1, player.frames)
    report.add_ratio("ladder_cpu", "every rung", "player", round(ladder_cpu / player_cpu, 3))
    for case in rungs:
        report.add_ratio(f"{case.name}_cpu", case.name, "player", round(case.cpu_s / player_cpu, 3))
    report.notes.append(
        f"the ladder ({', '.join(c.name for c in rungs)}) adds {ladder_ms:.2f} ms of CPU per"
        f" frame, {100 * ladder_ms / frame_budget_ms:.1f} % of one core at {args.fps:g} fps,"
        f" {100 * ladder_cpu / player_cpu:.0f} % of the player's track's encode"
    )
    report.write(args.json)
    print(f"{'track':<16} {'size':>10} {'cpu ms':>8} {'x player':>9} {'kbit/s':>8}"
          f" {'cap':>8} {'dB@display':>11} {'dB own':>7}")  # fmt: skip
    for case in cases:
        s = case.summary(args.fps, player_cpu)
        print(
            f"{s['name']:<16} {s['size']:>10} {s['cpu_ms_per_frame']:>8.2f}"
            f" {s['cpu_vs_player']:>9.3f} {s['achieved_bitrate'] / 1000:>8.0f}"
            f" {s['bitrate_cap'] / 1000:>8.0f} {s['psnr_at_display_db'] or 0:>11.2f}"
            f" {s['psnr_own_size_db'] or 0:>7.2f}"
        )
    convert_ms = 1000 * convert.cpu_s / max(1, convert.frames)
    print(f"{'(conversion)':<16} {args.display_size:>10} {convert_ms:>8.2f}")
    print(report.notes[-1])
    print(f"report written to {args.json}")
    return 0
