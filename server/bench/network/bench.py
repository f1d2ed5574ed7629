"""``upcast bench network``: play over emulated real networks (issue 21).

For each ``--profile`` (server/net/profiles.py: lan, cable, wifi, lte, drop,
blackout, or a schedule file) the whole stack starts afresh, the user-space
network emulator goes between the relay and a headless Chromium player (and
``--viewers`` load-test viewers), and ``--seconds`` are measured
(server/bench/network/measure.py). Reported per profile:

- delivered fps: frames the page presented in the window against the frames the
  session published in the same window (``delivered_ratio``);
- freezes: gaps of more than 200 ms between frames drawn on the page's canvas
  (count, total, longest, each gap), timed in the page where they are drawn;
- glass-to-glass p50 / p95: render_end -> client_present, the latency benchmark's
  method (the page joins the timing track with its present stamps);
- bitrate against capacity every 0.5 s: the encoder's bitrate target, the
  emulated downlink's rate in force, what the link delivered and what the page
  counted (server/bench/network/series.py);
- received PSNR: canvas snapshots (one a second) against the thumbnail of the
  frame the session encoded with the same id (server/serve/snapshots.py);
- the page's own counters over the window (lost, skipped, freezes, late, ...)
  where the page exposes them, and the load-test viewers' counts;
- with ``--spectators lte,wifi``: a tokenless spectator page per listed profile, each
  behind an emulated link of its own, joining as the window opens: its first picture,
  delivered ratio, freezes, renditions played and glass-to-glass
  (server/bench/network/spectators.py), and the worst of them at the report's top.

The JSON report (DESIGN.md), a table, and with ``--plot`` a figure of bitrate and
capacity over time per profile.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from server.frames.frame import Size
from server.ops.browser_paths import CHROMIUM, CHROMIUM_ARGS, WEB_ROOT
from server.ops.report import BenchReport

MAX_VIEWERS = 200
MAX_SPECTATORS = 8  # each one is a Chromium page and an emulator process of its own


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--profile",
        action="append",
        default=None,
        help="link profile or schedule file, repeatable (default: lan cable wifi lte drop)",
    )
    parser.add_argument("--seconds", type=float, default=30.0, help="seconds measured per profile")
    parser.add_argument("--warmup", type=float, default=3.0, help="seconds played before measuring")
    parser.add_argument("--viewers", type=int, default=0, help="load-test viewers on the link too")
    parser.add_argument(
        "--spectators",
        action="append",
        default=None,
        metavar="PROFILE[,PROFILE...]",
        help="beside the player, a view-only page (no token) per listed link profile or "
        "schedule file, each behind an emulated link of its own, joining as the window "
        f"opens; repeatable, at most {MAX_SPECTATORS} (default: none)",
    )
    parser.add_argument(
        "--ladder",
        default=None,
        metavar="DIVISORS",
        help="the session's rendition ladder for spectators, as upcast up --ladder (2,4 or "
        "'off'; default: as upcast up with --spectators, off without them)",
    )
    parser.add_argument("--json", type=Path, default=None, help="write the JSON report here")
    parser.add_argument("--plot", type=Path, default=None, help="PNG: bitrate and capacity")
    parser.add_argument("--render-size", default="640x360")
    parser.add_argument("--display-size", default=None, help="default: twice the render size")
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--scene", default="default")
    parser.add_argument("--upscaler", default="bilinear")
    parser.add_argument(
        "--bitrate-kbps", type=int, default=None, help="encoder bitrate (default: as upcast up)"
    )
    parser.add_argument(
        "--rate-control",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="the session's bitrate follows the page's feedback (default: on, as upcast up)",
    )
    parser.add_argument(
        "--intra-refresh",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="intra refresh instead of periodic keyframes (default: on, as upcast up)",
    )
    parser.add_argument(
        "--congestion-control",
        default=None,
        help="the relay's QUIC congestion controller (default: the relay's, upcast-media)",
    )


DEFAULT_PROFILES = ("lan", "cable", "wifi", "lte", "drop")


def spectator_profiles(values: list[str] | None) -> list[str]:
    """``--spectators`` values (repeated, each a comma list) -> profile names in order."""
    return [name.strip() for value in values or [] for name in value.split(",") if name.strip()]


def ladder_divisors(text: str | None, spectators: list[str] | tuple[str, ...]) -> tuple[int, ...]:
    """The rendition ladder the session runs: ``--ladder``, else upcast up's default when
    there are spectators (the rungs are theirs), else none (the player alone, as before)."""
    from server.stream_config import DEFAULT_DIVISORS, parse_divisors

    if text is None:
        return DEFAULT_DIVISORS if spectators else ()
    return parse_divisors(text)


def _problem(args: argparse.Namespace) -> str | None:
    from server.net import ProfileError, resolve

    for name in args.profile or DEFAULT_PROFILES:
        try:
            resolve(name)
        except ProfileError as exc:
            return f"--profile: {exc}"
    spectators = spectator_profiles(args.spectators)
    if args.spectators is not None and not spectators:
        return "--spectators: name at least one profile"
    for name in spectators:
        try:
            resolve(name)
        except ProfileError as exc:
            return f"--spectators: {exc}"
    if len(spectators) > MAX_SPECTATORS:
        return f"--spectators: at most {MAX_SPECTATORS}, got {len(spectators)}"
    try:
        ladder_divisors(args.ladder, spectators)
    except ValueError as exc:
        return f"--ladder: {exc}"
    try:
        Size.parse(args.render_size)
        if args.display_size is not None:
            Size.parse(args.display_size)
    except ValueError as exc:
        return f"--render-size/--display-size: {exc}"
    if not 1.0 <= args.seconds <= 3600:
        return f"--seconds must be 1..3600, got {args.seconds:g}"
    if not 0 <= args.warmup <= 60:
        return f"--warmup must be 0..60, got {args.warmup:g}"
    if not 0 <= args.viewers <= MAX_VIEWERS:
        return f"--viewers must be 0..{MAX_VIEWERS}, got {args.viewers}"
    if not 1 <= args.fps <= 240:
        return f"--fps must be 1..240, got {args.fps:g}"
    if not CHROMIUM.exists():
        return "needs /usr/bin/chromium"
    if not (WEB_ROOT / "index.html").is_file():
        return "build client_web first (./dev build)"
    return None


def _display_size(args: argparse.Namespace) -> str:
    if args.display_size is not None:
        return str(args.display_size)
    render = Size.parse(args.render_size)
    return f"{render.width * 2}x{render.height * 2}"


def run(args: argparse.Namespace) -> int:
    problem = _problem(args)
    if problem is not None:
        print(f"upcast bench network: {problem}", file=sys.stderr)
        return 2
    from playwright.sync_api import sync_playwright

    from server.bench.network.measure import NetworkRun, measure
    from server.bench.network.spectators import worst
    from server.bench.network.table import spectator_table, table
    from server.stack.local import SessionConfig

    profiles = list(args.profile or DEFAULT_PROFILES)
    spectators = tuple(spectator_profiles(args.spectators))
    ladder = ladder_divisors(args.ladder, spectators)
    session = SessionConfig(
        scene=args.scene,
        render_size=args.render_size,
        display_size=_display_size(args),
        fps=args.fps,
        upscaler=args.upscaler,
    )
    bitrate = None if args.bitrate_kbps is None else args.bitrate_kbps * 1000
    report = BenchReport(
        "network",
        {
            "profiles": profiles,
            "seconds": args.seconds,
            "warmup": args.warmup,
            "viewers": args.viewers,
            "scene": args.scene,
            "render_size": args.render_size,
            "display_size": session.display_size,
            "fps": args.fps,
            "upscaler": args.upscaler,
            "bitrate_kbps": args.bitrate_kbps,
            "rate_control": args.rate_control,
            "intra_refresh": args.intra_refresh,
            "congestion_control": args.congestion_control or "relay default",
            "transport": "headless Chromium (WebTransport) -> user-space network emulator "
            "(server/net, loopback) -> relay process",
            # Only with --spectators: a report without them keeps its earlier shape.
            **({"spectators": list(spectators)} if spectators else {}),
            **({"ladder": list(ladder)} if spectators or args.ladder is not None else {}),
        },
    )
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=list(CHROMIUM_ARGS))
        try:
            for profile in profiles:
                print(f"upcast bench network: {profile} for {args.seconds:g} s", file=sys.stderr)
                run_ = NetworkRun(
                    profile,
                    args.seconds,
                    args.warmup,
                    args.viewers,
                    session,
                    bitrate,
                    rate_control=args.rate_control,
                    intra_refresh=args.intra_refresh,
                    congestion_control=args.congestion_control,
                    spectators=spectators,
                    ladder=ladder,
                )
                case = report.add_case(**measure(run_, browser))
                if case["delivered_ratio"] is not None:
                    report.add_ratio(
                        f"{profile}: delivered fps",
                        "page_fps",
                        "server_fps",
                        case["delivered_ratio"],
                    )
                for watcher in case.get("spectators") or []:
                    if watcher["delivered_ratio"] is not None:
                        report.add_ratio(
                            f"{profile}: spectator {watcher['name']}: delivered fps",
                            "page_fps",
                            "server_fps",
                            watcher["delivered_ratio"],
                        )
        finally:
            browser.close()
    report.notes.extend(_notes())
    print(table(report.cases))
    if spectators:
        report.sections["spectators"] = worst(report.cases)
        report.notes.extend(_spectator_notes())
        print(spectator_table(report.cases))
    if args.json is not None:
        report.write(args.json)
        print(f"wrote {args.json}")
    if args.plot is not None:
        from server.bench.network.plot import plot

        note = plot(report.cases, args.plot)
        print(note if note else f"wrote {args.plot}")
    return 0


def _notes() -> list[str]:
    return [
        "delivered_ratio = frames the page presented / frames the session published, same "
        "window (frames in flight at the window's edges can put it a little over 1); "
        "freezes: gaps > 200 ms between frames drawn on the canvas (page clock)",
        "median_ms / p95_ms: glass-to-glass render_end -> client_present (page stats, one "
        "machine's wall clocks), as in upcast bench latency",
        "series every 0.5 s: bitrate_target_bps = the session encoder's target; capacity_bps"
        " = the emulated downlink's rate in force (null: unlimited); link_delivered_bps = "
        "bytes the emulator delivered downstream (all viewers, all tracks, QUIC overhead)",
        "received_psnr_db: canvas snapshots (1/s, 4x box thumbnails) against the frame the "
        "session encoded with the same id",
        "page_counters: differences over the window of the page's own stats() counters, "
        "where the page has them",
    ]


def _spectator_notes() -> list[str]:
    return [
        "spectators: a page without a token per --spectators profile, each behind its own "
        "emulator (own schedule, restarted at its join, own loss seed), joining right after "
        "the window's first sample (joined_at_s); first_picture_ms = navigation start -> "
        "first video frame drawn on its canvas (page clock: loading the page, certificate, "
        "QUIC handshake, catalog, subscription, first group, decode)",
        "spectators' delivered_ratio = frames the page presented / frames the session "
        "published on the rendition it played (per read interval, the track it named; a "
        "ladder rung gets every game frame), from its first read after its first picture "
        "(reads 1 s apart) to the window's end; freezes from its first picture to the "
        "window's end (starts_s after the first picture)",
        "spectators' rendition, rendition_seconds (since its join), rendition_switches and "
        "abr: the page's own stats (null from a page without them)",
        "top-level spectators: the worst first picture, delivered ratio and longest freeze "
        "over every spectator of every profile",
    ]
