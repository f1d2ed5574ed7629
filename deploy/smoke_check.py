"""The browser half of deploy/smoke.sh: the containerised stack, watched from the host.

Run by deploy/smoke.sh with the project's venv once ``docker compose up`` is healthy
(host networking, everything on 127.0.0.1). It checks, printing one ``smoke:`` line
a step:

1. every endpoint Prometheus would scrape (deploy/prometheus/prometheus.yml, its hosts
   read as 127.0.0.1) answers 200 with upcast's metrics: Prometheus and Grafana
   themselves cannot be pulled here;
2. the player page the relay serves plays in the host's headless Chromium, and the
   time from ``up`` to its first presented frame;
3. what its canvas shows is the frame the session encoded with the same id: the
   session container serves thumbnails of its frames before encoding by frame id
   (``upcast serve --frame-tap-port``, on in the host-network override), and canvas
   snapshots are compared with them as the e2e tests do (``snapshot_psnr``), with a
   control (the same snapshot against the frame a second earlier must be worse);
4. killing the session container's upscaler worker: ``upcast serve`` restarts it
   (server/stack/local.py ``check_children``) and the page presents frames again.

Exit status 0 only if all of it held; the reason otherwise, on stderr.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np
import yaml  # type: ignore[import-untyped]
from playwright.sync_api import ConsoleMessage, sync_playwright
from playwright.sync_api import TimeoutError as PlaywrightTimeout

from server.ops.browser_paths import CHROMIUM, CHROMIUM_ARGS
from server.serve.snapshots import (
    Thumb,
    ThumbSource,
    decode_data_url,
    psnr,
    snapshot_psnr,
    thumbnail,
)

ROOT = Path(__file__).resolve().parents[1]
PROMETHEUS = ROOT / "deploy" / "prometheus" / "prometheus.yml"
MIN_PSNR_DB = 35.0  # issue 23's bar: the canvas against the server's frame with its id
SNAPSHOTS = 8
CONTROL_FRAMES = 30  # a second at the stack's 30 fps: another picture of the orbit
MIN_MARGIN_DB = 6.0  # the e2e tests' margin between the same and another frame
RESUMED_FRAMES = 30  # presented after the worker's restart: the stream is back
DEFAULT_TAP_PORT = 4460  # session 1's frame tap (deploy/docker-compose.hostnet.yml)


class SmokeFailure(Exception):
    pass


def say(message: str) -> None:
    print(f"smoke: {message}", flush=True)


# -- the session's frames, from its frame tap -------------------------------------------


class TappedFrames:
    """The session's own thumbnails of the frames it encoded, by frame id, read from its
    frame tap (``upcast serve --frame-tap-port``, server/serve/frame_tap.py): what the
    in-process tests compare the canvas with (FrameThumbs), across the container."""

    def __init__(self, url: str) -> None:
        self.url = url.rstrip("/")
        self._known: dict[int, Thumb] = {}

    def get(self, frame_id: int) -> Thumb | None:
        if frame_id in self._known:
            return self._known[frame_id]
        try:
            with urllib.request.urlopen(f"{self.url}/{frame_id}", timeout=5) as response:
                thumb: Thumb = np.load(io.BytesIO(response.read()), allow_pickle=False)
        except urllib.error.HTTPError as exc:
            if exc.code == 404:
                return None  # not encoded yet, or no longer kept
            raise SmokeFailure(f"frame tap {self.url}/{frame_id}: {exc}") from None
        except OSError as exc:
            raise SmokeFailure(f"frame tap {self.url}/{frame_id}: {exc}") from None
        self._known[frame_id] = thumb
        return thumb


# -- HTTP -------------------------------------------------------------------------------


def get(url: str, timeout_s: float = 5.0) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as response:
            return int(response.status), bytes(response.read())
    except OSError as exc:
        raise SmokeFailure(f"GET {url}: {exc}") from None


def sessions(serve_url: str) -> dict[str, dict[str, Any]]:
    _, body = get(serve_url + "/sessions")
    return {str(row["broadcast"]): row for row in json.loads(body)["sessions"]}


# A session's game opens its metrics port once its renderer is built, which can be after
# the supervisor's /healthz says the session is up: a CI run found the first game's port
# closed right after that. Prometheus keeps scraping; the check keeps trying as long.
SCRAPE_PATIENCE_S = 30.0


def scrape(url: str, deadline: float) -> tuple[int, bytes]:
    while True:
        try:
            return get(url)
        except SmokeFailure:
            if time.monotonic() > deadline:
                raise
            time.sleep(1.0)


def check_scrape_targets() -> None:
    """Every target of the Prometheus configuration, as Prometheus would scrape it."""
    config = yaml.safe_load(PROMETHEUS.read_text())
    checked = 0
    deadline = time.monotonic() + SCRAPE_PATIENCE_S
    for job in config["scrape_configs"]:
        path = job.get("metrics_path", "/metrics")
        for group in job["static_configs"]:
            for target in group["targets"]:
                port = str(target).rsplit(":", 1)[1]
                url = f"http://127.0.0.1:{port}{path}"
                status, body = scrape(url, deadline)
                if status != 200 or b"upcast_" not in body:
                    raise SmokeFailure(f"{job['job_name']} target {target}: {url} gave {status}")
                checked += 1
    say(f"metrics: all {checked} Prometheus scrape targets answer with upcast metrics")


# -- the page ---------------------------------------------------------------------------


def presented(page: Any) -> int:
    return int(page.evaluate("() => window.upcast ? window.upcast.stats().framesPresented : 0"))


def wait_presented(page: Any, count: int, timeout_s: float) -> None:
    try:
        page.wait_for_function(
            "n => window.upcast && window.upcast.stats().framesPresented >= n",
            arg=count,
            timeout=timeout_s * 1000,
        )
    except PlaywrightTimeout:
        raise SmokeFailure(
            f"the page presented {presented(page)} frames, not {count}, in {timeout_s:.0f} s"
        ) from None


def check_picture(page: Any, thumbs: ThumbSource, when: str) -> None:
    try:
        samples = snapshot_psnr(page, thumbs, count=SNAPSHOTS)
    except RuntimeError as exc:
        raise SmokeFailure(f"{when}: {exc}") from None
    shown = ", ".join(f"{db:.1f}" for db in samples)
    say(f"picture {when}: PSNR against the session's frame with the same id: {shown} dB")
    if min(samples) < MIN_PSNR_DB:
        raise SmokeFailure(f"{when}: a snapshot under {MIN_PSNR_DB:g} dB ({shown})")


def check_ids_matter(page: Any, thumbs: ThumbSource, attempts: int = 50) -> None:
    """The control of the picture check: the same snapshot against the frame a second
    earlier must be clearly worse, or the check would pass on any frame of the stream
    (the default scene's camera orbits; the e2e tests measure 16-20 dB there)."""
    for _ in range(attempts):
        snap = page.evaluate("() => window.upcast.snapshot()")
        frame_id = snap["frameId"]
        sent = thumbs.get(frame_id) if frame_id is not None else None
        earlier = thumbs.get(frame_id - CONTROL_FRAMES) if frame_id is not None else None
        if sent is not None and earlier is not None:
            shown = thumbnail(decode_data_url(snap["dataUrl"]))
            same, other = psnr(shown, sent), psnr(shown, earlier)
            say(
                f"picture control: frame {frame_id} {same:.1f} dB against its own, "
                f"{other:.1f} dB against frame {frame_id - CONTROL_FRAMES}"
            )
            if same < other + MIN_MARGIN_DB:
                raise SmokeFailure(
                    f"the picture check cannot tell frames apart ({same=}, {other=})"
                )
            return
        page.wait_for_timeout(100)
    raise SmokeFailure("no snapshot whose frame and the frame a second earlier were both known")


def kill_worker(serve_url: str, broadcast: str, page: Any, timeout_s: float) -> None:
    before = sessions(serve_url)[broadcast]
    pid, restarts = before["worker_pid"], int(before["worker_restarts"])
    if not pid:
        raise SmokeFailure(f"/sessions gives no worker pid for {broadcast}: {before}")
    # The pid is the container's (its own pid namespace): kill it in there, as the
    # image's user (sh's builtin kill: the slim images have no procps).
    subprocess.run(
        ["docker", "compose", "exec", "-T", "session", "sh", "-c", f"kill -9 {int(pid)}"],
        check=True,
    )
    killed_at = time.monotonic()
    shown_at_kill = presented(page)
    say(f"worker: killed pid {pid} of {broadcast} (SIGKILL in the session container)")
    deadline = killed_at + timeout_s
    while True:
        row = sessions(serve_url)[broadcast]
        if int(row["worker_restarts"]) > restarts and row["worker_pid"] not in (None, pid):
            break
        if time.monotonic() > deadline:
            raise SmokeFailure(f"worker of {broadcast} not restarted in {timeout_s:.0f} s: {row}")
        time.sleep(0.1)
    restarted_s = time.monotonic() - killed_at
    wait_presented(page, shown_at_kill + RESUMED_FRAMES, max(1.0, deadline - time.monotonic()))
    resumed_s = time.monotonic() - killed_at
    say(
        f"worker: restarted as pid {row['worker_pid']} {restarted_s:.1f} s after the kill; "
        f"the page presented {RESUMED_FRAMES} new frames {resumed_s:.1f} s after it"
    )


def console_errors(message: ConsoleMessage) -> None:
    if message.type == "error":
        say(f"page console: {message.text}")


def run(args: argparse.Namespace) -> None:
    relay_url = f"http://127.0.0.1:{args.relay_port}/"
    serve_url = f"http://127.0.0.1:{args.serve_port}"
    check_scrape_targets()
    states = {name: row["state"] for name, row in sessions(serve_url).items()}
    say(f"sessions: {states}")
    if args.broadcast not in states:
        raise SmokeFailure(f"no session publishes {args.broadcast}")

    thumbs = TappedFrames(f"http://127.0.0.1:{args.tap_port}/frames")
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=list(CHROMIUM_ARGS))
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 900})
            page.on("console", console_errors)
            # The pictures are compared with the frames the session tapped from the
            # player's track, so the page plays that track (abr=off: the catalog's
            # first), not a spectator's rung (tests/e2e/test_spectator_ladder_e2e.py).
            page.goto(f"{relay_url}?broadcast={args.broadcast}&overlay=0&abr=off")
            wait_presented(page, 1, args.timeout)
            say(f"first frame in the browser {time.time() - args.up_at:.1f} s after `up`")
            stats = page.evaluate("() => window.upcast.stats()")
            say(
                f"page: {stats['version']}, {stats['width']}x{stats['height']}, "
                f"errors {stats['errors']}"
            )
            if stats["errors"]:
                raise SmokeFailure(f"the page reports errors: {stats['errors']}")
            wait_presented(page, 60, args.timeout)
            check_picture(page, thumbs, "playing")
            check_ids_matter(page, thumbs)
            kill_worker(serve_url, args.broadcast, page, args.timeout)
            check_picture(page, thumbs, "after the worker's restart")
        finally:
            browser.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--up-at", type=float, required=True, help="epoch s of `compose up`")
    parser.add_argument("--broadcast", default="game-1")
    parser.add_argument("--relay-port", type=int, default=4443)
    parser.add_argument("--serve-port", type=int, default=4444)
    parser.add_argument(
        "--tap-port", type=int, default=DEFAULT_TAP_PORT, help="the broadcast's frame tap"
    )
    parser.add_argument("--timeout", type=float, default=90.0, help="seconds a step may take")
    args = parser.parse_args(argv)
    if "COMPOSE_FILE" not in os.environ:
        parser.error("run from deploy/smoke.sh (COMPOSE_FILE names the stack's files)")
    try:
        run(args)
    except SmokeFailure as exc:
        print(f"smoke: FAILED: {exc}", file=sys.stderr, flush=True)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
