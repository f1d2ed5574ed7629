"""``upcast bench relay``: the relay's data-plane CPU per viewer, ours against moq-rs.

For each engine (``upcast relay`` on aioquic; moq-dev's Rust relay core, moq.Server)
and each viewer count, one after the other, on a fresh relay process each time:

1. the relay starts on a free loopback port, then the synthetic publisher
   (server/loadtest/synthetic.py: same size, fps and bitrate for both engines);
2. once the broadcast is there, the relay's CPU over ``--idle-s`` with only the
   publisher is the idle level;
3. N load-test viewers run in their own process (server/bench/relay/viewers.py,
   ``upcast loadtest``'s run); the relay's CPU (utime + stime from /proc, every
   thread) is read over exactly the load test's measured window (after the ramp and
   ``--warmup``), and its RSS at the end.

CPU per viewer = (CPU during - idle) / N, in % of one core. moq-lite is pulled, so
the idle relay forwards nothing (~0 %) and that figure also carries the publisher's
ingest, shared by the N viewers; CPU per *added* viewer, the slope between two viewer
counts, leaves it out. Per viewer count the report has the ratio upcast / moq-rs of
both. The viewers' fps (min, mean), lost
frames and publish -> receive p50/p95 come from the load test. With ``--profile DIR``
py-spy records our relay during the window and the report lists the functions
with the most own time.

On a machine with few cores the viewers and the publisher share them with the
relay: the report keeps the load test's own CPU and the load average, so a run
where the viewers were the bottleneck reads as one.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.metadata
import itertools
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from server.frames.frame import Size
from server.media.encode import default_bitrate
from server.ops.process import stop_child
from server.ops.report import BenchReport

from .engines import ENGINES, HOST, MOQ_RS_PIP, RunningRelay, moq_rs_available, start_relay
from .probe import CpuTrace, cpu_percent_over
from .profile import Profiler, find_py_spy
from .table import header, ratio_line, row

BROADCAST = "game"
WAIT_BROADCAST_S = 30.0
FPS_HELD = 0.95  # a run whose slowest viewer got less than this of --fps fell behind
SETTLE_S = 1.0  # after the broadcast appears: the publisher's first GOP is through
RAMP_PER_S = 20.0  # the load test's default ramp
# --processes 0: one viewer process per this many viewers (at most one per core): an
# aioquic viewer of a 720p30 stream costs ~7 % of a core, so 20 saturate one process.
VIEWERS_PER_PROCESS = 10
VIEWERS_START_S = 1.5  # a viewer process's imports before its plan starts (for py-spy)
VIEWERS_SLACK_S = 60.0  # connect timeouts, workers' results, the report


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--engines", default=",".join(ENGINES), help=f"comma-separated, from: {', '.join(ENGINES)}"
    )
    parser.add_argument("--viewers", default="10,20,40", help="comma-separated viewer counts")
    parser.add_argument("--duration", type=float, default=15.0, help="measured seconds per run")
    parser.add_argument(
        "--warmup", type=float, default=3.0, help="seconds after the viewers' ramp, unmeasured"
    )
    parser.add_argument(
        "--idle-s", type=float, default=5.0, help="seconds of the relay's idle CPU (publisher only)"
    )
    parser.add_argument("--size", default="1280x720", help="synthetic publisher's frame size")
    parser.add_argument("--fps", type=float, default=30.0, help="synthetic publisher's frame rate")
    parser.add_argument(
        "--bitrate-kbps",
        type=int,
        default=None,
        help="publisher's video bitrate, the same for both engines (default: the encoder's"
        " for --size and --fps, 3000 at 1280x720 30 fps)",
    )
    parser.add_argument(
        "--processes",
        type=int,
        default=0,
        help=f"load-test viewer processes (0: one per {VIEWERS_PER_PROCESS} viewers)",
    )
    parser.add_argument("--json", type=Path, default=None, help="write the JSON report here")
    parser.add_argument(
        "--profile",
        type=Path,
        default=None,
        help="py-spy our relay during each window; raw profiles go to this folder",
    )


def progress(message: str) -> None:
    sys.stderr.write(f"[bench relay] {message}\n")
    sys.stderr.flush()


def viewer_processes(args: argparse.Namespace, viewers: int) -> int:
    if args.processes > 0:
        return min(int(args.processes), viewers)
    return max(1, min(-(-viewers // VIEWERS_PER_PROCESS), os.cpu_count() or 1))


def start_publisher(relay: RunningRelay, args: argparse.Namespace) -> subprocess.Popen[bytes]:
    argv = [sys.executable, "-m", "server.loadtest.synthetic", "--relay", relay.url]
    argv += ["--cert-hash", relay.cert_sha256, "--broadcast", BROADCAST]
    argv += ["--size", args.size, "--fps", f"{args.fps:g}"]
    argv += ["--bitrate-kbps", str(args.bitrate_kbps), "--duration", "3600"]
    return subprocess.Popen(argv, stdout=subprocess.DEVNULL)


def wait_for_broadcast(relay: RunningRelay, publisher: subprocess.Popen[bytes]) -> None:
    """Until the relay has the broadcast; an error as soon as the publisher is gone."""
    deadline = time.monotonic() + WAIT_BROADCAST_S
    while True:
        try:
            relay.wait_broadcast(BROADCAST, 1.0)
            return
        except TimeoutError:
            code = publisher.poll()
            if code is not None:
                raise RuntimeError(f"the synthetic publisher exited with code {code}") from None
            if time.monotonic() > deadline:
                raise TimeoutError(
                    f"no broadcast {BROADCAST!r} on the relay after {WAIT_BROADCAST_S:g} s"
                ) from None


def run_viewers(
    relay: RunningRelay, viewers: int, processes: int, args: argparse.Namespace, out: Path
) -> dict[str, Any]:
    argv = [sys.executable, "-m", "server.bench.relay.viewers", "--relay", relay.url]
    argv += ["--cert-hash", relay.cert_sha256, "--viewers", str(viewers)]
    argv += ["--duration", f"{args.duration:g}", "--warmup", f"{args.warmup:g}"]
    argv += ["--processes", str(processes), "--broadcast", BROADCAST, "--json", str(out)]
    bound = viewers / RAMP_PER_S + args.warmup + args.duration + VIEWERS_SLACK_S
    proc = subprocess.Popen(argv)
    try:
        code = proc.wait(bound)
    except subprocess.TimeoutExpired:
        stop_child(proc, 5.0)
        raise TimeoutError(f"the load-test viewers did not finish in {bound:.0f} s") from None
    if code != 0:
        raise RuntimeError(f"the load-test viewers exited with code {code}")
    result: dict[str, Any] = json.loads(out.read_text())
    return result


def _profiler(relay: RunningRelay, viewers: int, args: argparse.Namespace) -> Profiler | str | None:
    """A py-spy run timed to the window, or why there is none."""
    if args.profile is None or relay.engine != "upcast":
        return None
    py_spy = find_py_spy()
    if py_spy is None:
        return "py-spy is not installed (pip install py-spy): no profile"
    args.profile.mkdir(parents=True, exist_ok=True)
    # The window opens after the viewers' start, ramp and warmup; a second's margin
    # at each end keeps the ramp's handshakes and the closing out of the profile.
    delay = VIEWERS_START_S + (viewers - 1) / RAMP_PER_S + args.warmup
    return Profiler(
        py_spy,
        relay.pid,
        args.profile / f"upcast-{viewers}-viewers.raw.txt",
        delay,
        max(1, int(args.duration - 2)),
    )


def summarize(
    engine: str, viewers: int, loadtest: dict[str, Any], during: float, idle: float, rss: float
) -> dict[str, Any]:
    per_viewer = [c for c in loadtest["cases"] if c["name"].startswith("viewer ")]
    total = next(c for c in loadtest["cases"] if c["name"] == "summary")
    fps = [float(c["fps"]) for c in per_viewer]
    return {
        "engine": engine,
        "viewers": viewers,
        "relay_cpu_percent": round(during, 1),
        "relay_cpu_percent_idle": round(idle, 1),
        "cpu_per_viewer_percent": round((during - idle) / viewers, 3),
        "fps_min": round(min(fps, default=0.0), 2),
        "fps_mean": round(sum(fps) / len(fps), 2) if fps else 0.0,
        "viewer_fps": fps,
        "lost_frames": int(total["lost_total"]),
        "lost_per_viewer": [int(c["lost"]) for c in per_viewer],
        "median_ms": total["median_ms"],
        "p95_ms": total["p95_ms"],
        "relay_rss_mb": round(rss, 1),  # at the window's end
        "connected": total["connected"],
        "failed": total["failed"],
        "publisher_fps": total["publisher_fps"],
        "mbit_s_total": total["mbit_s_total"],
        "loadtest_cpu_percent": total["loadtest_cpu_percent"],
        # Ours also reports its CPU on /metrics (the load test reads it): a cross-check.
        "relay_cpu_percent_metrics": total["relay_cpu_percent"],
        "window_s": total["window_s"],
        "verdict": loadtest["verdict"],
        "loadtest_notes": loadtest["notes"],
    }


def measure(engine: str, viewers: int, args: argparse.Namespace, workdir: Path) -> dict[str, Any]:
    relay = start_relay(engine, workdir)
    publisher: subprocess.Popen[bytes] | None = None
    try:
        progress(f"{engine}, {viewers} viewers: relay pid {relay.pid} at {relay.url}")
        publisher = start_publisher(relay, args)
        wait_for_broadcast(relay, publisher)
        time.sleep(SETTLE_S)
        idle = cpu_percent_over(relay.pid, args.idle_s)
        processes = viewer_processes(args, viewers)
        progress(
            f"{engine}, {viewers} viewers: idle {idle:.1f} %; viewers in {processes}"
            f" process(es), {args.warmup:g} s warmup + {args.duration:g} s measured"
        )
        profiler = _profiler(relay, viewers, args)
        load_average_start = os.getloadavg()
        with CpuTrace(relay.pid) as trace:
            if isinstance(profiler, Profiler):
                profiler.start()
            try:
                loadtest = run_viewers(relay, viewers, processes, args, workdir / "viewers.json")
            except BaseException:
                if isinstance(profiler, Profiler):
                    profiler.cancel()
                raise
        start, end = loadtest["window_monotonic"]
        during = trace.percent(start, end)
        case = summarize(engine, viewers, loadtest, during, idle, trace.rss_at(end))
        case["processes"] = processes
        case["fps_held"] = case["fps_min"] >= FPS_HELD * args.fps
        case["load_average"] = [round(load_average_start[0], 2), round(os.getloadavg()[0], 2)]
        if isinstance(profiler, Profiler):
            case["profile"] = profiler.finish()
        elif isinstance(profiler, str):
            case["profile"] = {"error": profiler}
        return case
    finally:
        if publisher is not None:
            stop_child(publisher, 5.0)
        relay.stop()


def _parse(args: argparse.Namespace) -> tuple[list[str], list[int]] | str:
    """(engines, viewer counts), or what is wrong with the options."""
    engines = [e.strip() for e in args.engines.split(",") if e.strip()]
    unknown = [e for e in engines if e not in ENGINES]
    if not engines or unknown:
        return f"--engines: choose from {', '.join(ENGINES)} (got {args.engines!r})"
    try:
        counts = [int(v) for v in args.viewers.split(",") if v.strip()]
    except ValueError:
        return f"--viewers must be comma-separated numbers, got {args.viewers!r}"
    if not counts or min(counts) < 1 or max(counts) > 1000:
        return f"--viewers must be 1..1000 each, got {args.viewers!r}"
    if args.duration < 2 or args.idle_s <= 0 or args.warmup < 0:
        return "--duration must be >= 2 s, --idle-s positive and --warmup >= 0"
    try:
        Size.parse(args.size)
    except ValueError as exc:
        return f"--size: {exc}"
    if not 0 < args.fps <= 240:
        return f"--fps must be in (0, 240], got {args.fps:g}"
    if args.bitrate_kbps is not None and args.bitrate_kbps < 10:
        return f"--bitrate-kbps must be at least 10, got {args.bitrate_kbps}"
    return engines, counts


def _config(args: argparse.Namespace, engines: list[str], counts: list[int]) -> dict[str, Any]:
    moq_rs = None
    with contextlib.suppress(importlib.metadata.PackageNotFoundError):
        moq_rs = importlib.metadata.version("moq-rs")
    return {
        "engines": {
            "upcast": "upcast relay --no-auth (aioquic), its own process",
            "moq-rs": f"moq.Server from moq-rs {moq_rs} (moq-dev's Rust relay core), one"
            " shared origin, its own process (python -m server.bench.relay.rust_relay)",
        },
        "engines_run": engines,
        "viewers": counts,
        "duration_s": args.duration,
        "warmup_s": args.warmup,
        "idle_s": args.idle_s,
        "ramp_per_s": RAMP_PER_S,
        "publisher": f"synthetic {args.size} {args.fps:g} fps, {args.bitrate_kbps} kbit/s"
        " (python -m server.loadtest.synthetic, loop encode, its own process)",
        "bitrate_kbps": args.bitrate_kbps,
        "viewer_processes": {str(n): viewer_processes(args, n) for n in counts},
        "host": HOST,
        "cpu": "utime + stime of /proc/PID/stat over the load test's measured window, % of"
        " one core; per viewer = (during - idle) / viewers",
    }


def _add_marginal(report: BenchReport) -> None:
    """CPU per added viewer between consecutive viewer counts of an engine.

    moq-lite is pulled: with no viewer the relay subscribes to nothing and the idle
    level is ~0, so (during - idle) / N also carries the publisher's ingest, shared by
    all N. The slope between two counts leaves that fixed share out; only runs whose
    viewers all kept up count."""
    # A run where viewers fell behind had the relay do less than its viewers asked.
    done = [c for c in report.cases if not c.get("error") and c["fps_held"]]
    for engine in ENGINES:
        runs = sorted((c for c in done if c["engine"] == engine), key=lambda c: c["viewers"])
        for low, high in itertools.pairwise(runs):
            added = high["viewers"] - low["viewers"]
            if added > 0:
                slope = (high["relay_cpu_percent"] - low["relay_cpu_percent"]) / added
                high["cpu_per_added_viewer_percent"] = round(slope, 3)


def _add_ratios(report: BenchReport, counts: list[int]) -> list[str]:
    lines = []
    for n in counts:
        found = {c["engine"]: c for c in report.cases if c["viewers"] == n and not c.get("error")}
        if "upcast" not in found or "moq-rs" not in found:
            continue
        for key, what in (
            ("cpu_per_viewer_percent", "CPU per viewer"),
            ("cpu_per_added_viewer_percent", "CPU per added viewer"),
        ):
            ours, theirs = found["upcast"].get(key), found["moq-rs"].get(key)
            if ours is None or theirs is None:
                continue
            ratio = round(ours / theirs, 2) if theirs > 0 else None
            if ratio is not None:
                report.add_ratio(f"{what} at {n} viewers", "upcast", "moq-rs", ratio)
            lines.append(ratio_line(n, what, ratio, ours, theirs))
    return lines


def run(args: argparse.Namespace) -> int:
    parsed = _parse(args)
    if isinstance(parsed, str):
        sys.stderr.write(f"upcast bench relay: {parsed}\n")
        return 2
    engines, counts = parsed
    if "moq-rs" in engines and not moq_rs_available():
        sys.stderr.write(
            "upcast bench relay: moq-rs is not installed (the Rust relay to compare with):\n"
            f"  {MOQ_RS_PIP}\nor measure ours alone: --engines upcast\n"
        )
        return 2
    if args.bitrate_kbps is None:
        size = Size.parse(args.size)
        args.bitrate_kbps = default_bitrate(size.width, size.height, args.fps) // 1000
    report = BenchReport("relay", _config(args, engines, counts))
    started = time.monotonic()
    print(header(), flush=True)
    with tempfile.TemporaryDirectory(prefix="upcast-bench-relay-") as tmp:
        for engine in engines:
            for n in counts:
                try:
                    case = measure(engine, n, args, Path(tmp))
                except (OSError, RuntimeError, TimeoutError, ValueError, KeyError) as exc:
                    case = {"engine": engine, "viewers": n, "error": f"{type(exc).__name__}: {exc}"}
                report.add_case(f"{engine} {n} viewers", **case)
                print(row(case), flush=True)
    _add_marginal(report)
    for line in _add_ratios(report, counts):
        print(line)
    _add_notes(report)
    report.config["wall_s"] = round(time.monotonic() - started, 1)
    if args.json is not None:
        report.write(args.json)
        progress(f"report written to {args.json}")
    return 1 if any(c.get("error") for c in report.cases) else 0


def _add_notes(report: BenchReport) -> None:
    for case in report.cases:
        if case.get("error"):
            report.notes.append(f"{case['name']}: FAILED: {case['error']}")
            continue
        if not case["fps_held"]:
            report.notes.append(f"{case['name']}: a viewer held only {case['fps_min']} fps")
        if case["lost_frames"]:
            report.notes.append(f"{case['name']}: {case['lost_frames']} frames lost")
        busiest = case["loadtest_cpu_percent"]
        if busiest is not None and busiest >= 85.0 * case["processes"]:
            report.notes.append(
                f"{case['name']}: the viewers' processes used {busiest:.0f} % of a core:"
                " they, not the relay, may have been the limit"
            )
        # The load test's own warnings (a worker lost, a viewer process saturated); its
        # other notes (how latency is measured, moq-rs having no /stats) stay in the case.
        report.notes.extend(
            f"{case['name']}: {n}"
            for n in case["loadtest_notes"]
            if "worker" in n or "bottleneck" in n
        )
