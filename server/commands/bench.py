"""``upcast bench NAME ...``: benchmarks in server/bench/ that write DESIGN.md's JSON report."""

from __future__ import annotations

import argparse

from server.commands.dispatch import add_choice_arguments, run_choice

BENCHMARKS: dict[str, str] = {
    "transfer": "ring handoff (READY -> usable views) against a memcpy of the same bytes",
    "pipeline": "game -> worker -> ring U for a while: fps, drops, per-stage latency",
    "render": "reference renderer speed per scene",
    "framegen": "frame prediction (MPE and baselines): quality against cost per scene",
    "encode": "x264 + CMAF per frame: ms, bytes, PSNR, keyframe cost, mux delay",
    "latency": "render_end -> client_present per stage, real stack + headless Chromium",
    "serve": "upcast serve with N sessions: fps each holds, before and after a worker is killed",
    "adaptive": "adaptive quality against fixed settings, 1-N sessions, a CPU hog mid-run: "
    "viewer fps held, switches, the table's expected picture",
    "ladder": "the spectators' rendition ladder: encode CPU per rung against the player's "
    "track, bitrate against cap, PSNR each rung shows at the display size",
    "encode_scale": "encoding below the display size: encode ms saved against PSNR lost "
    "(the decoded picture drawn at display size) per scene and render scale",
    "compile_start": "upscaler compile=True at a worker start: inductor cache cold and warm",
    "reframe": "layer caching on the neural upscaler: policies, levels, speedup against FLIP",
    "adversary": "relay under attack scenarios: good viewers' fps, relay CPU and RSS, refusals",
    "resample": "our plain resamplers against OpenCV's resize: level difference and time",
    "capture": "X11 screen capture (Xvfb) per grabber against memcpy: ms per frame, exact pixels",
    "app": "real programs (SuperTux, Neverball) as source x11 in headless Chromium: fps, "
    "capture ms, input-to-photon, received PSNR, a screenshot",
    "network": "the player over emulated links (lan, cable, wifi, lte, drop, blackout): "
    "delivered fps, freezes, glass-to-glass, bitrate against capacity, received PSNR; "
    "--spectators: view-only pages each on its own link, first picture and renditions too",
    "congestion": "QUIC congestion controllers (reno, cubic, upcast-media) over lossy links: "
    "goodput and chunks on time for a video-like sender",
    "relay": "relay data-plane CPU per viewer, upcast relay (aioquic) against moq-dev's Rust "
    "relay core (moq-rs): idle and loaded CPU, viewers' fps, loss, latency, RSS",
}

# Benchmarks that live in a family's package (server/bench/<family>/), by name; the
# others are server/bench/<name>.py.
BENCH_MODULES: dict[str, str] = {
    "adaptive": "adaptive.bench",
    "adversary": "adversary.bench",
    "app": "app.bench",
    "capture": "app.capture",
    "congestion": "network.congestion",
    "network": "network.bench",
    "reframe": "reframe.bench",
    "relay": "relay.bench",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_choice_arguments(parser, "benchmark", BENCHMARKS)


def run(args: argparse.Namespace) -> int:
    return run_choice("bench", "server.bench", BENCHMARKS, args, BENCH_MODULES)
