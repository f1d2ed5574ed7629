"""Spectator pages, each on an emulated link of its own, for ``upcast bench network``.

A spectator is the player page opened without a token: it only watches
(client_web/src/player.ts). ``--spectators lan,lte`` gives each listed profile its own
emulator process (server/bench/network/link.py) in front of the relay, with the profile's
schedule and a loss seed of its own, and its own headless Chromium page in a browser
context of its own whose ``port`` parameter makes it connect to that emulator: every
spectator's packets go through its own shaper, the player's through the run's.

The emulators start with the stack; the spectators join when the measurement window
opens, right after its first sample (each one's schedule restarts as it joins), so
the join itself is measured. Per spectator:

- ``first_picture_ms``: from the start of the page's navigation (``performance.now()``
  = 0) to the first video frame drawn on its canvas, timed in the page (the draw watch of
  server/bench/network/page.py). It includes loading the page from the relay (loopback,
  not shaped), the certificate hash and QUIC handshake through its link, the catalog,
  the subscription, the first keyframe's group and its decode;
- ``delivered_ratio``: frames the page presented (its ``framesPresented``) against the
  frames the session published on the rendition it plays, both counted from the first
  read of the page after its first picture (at most ``READ_EVERY_S`` later) to the
  window's end. Between two reads the published frames counted are those of the track
  the page named at the second read (``published_frames``: the player's track's count,
  or a ladder rung's, which gets every game frame even while rate control thins the
  player's track); a page that names none plays the catalog's first track, the
  player's. As for the player, frames in flight at the window's edges can put it a
  little over 1;
- ``freezes``: gaps of more than 200 ms between frames drawn on its canvas, from its first
  picture to the window's end (``starts_s``: seconds after its first picture);
- ``rendition`` (the track it plays at the end), ``rendition_seconds`` (track name ->
  seconds, since its join) and ``rendition_switches``: the page's own figures
  (``renditionSeconds``, ``renditionSwitches``; null from a page without them), and
  its ``abr`` state (server/bench/network/renditions.py);
- ``glass_to_glass``: render_end -> client_present as for the player, from the page's
  samples after the base read;
- ``page_counters``: the page's own counters (lost, skipped, late, ...) over the same
  window as the delivered ratio, as for the player.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlencode

from server.bench.latency import StageCollector, percentiles
from server.bench.network.link import EmulatorProcess
from server.bench.network.page import DRAW_WATCH, READ_DRAWS, ShownFrames, counter_deltas
from server.bench.network.renditions import RenditionTime
from server.net import resolve

READ_EVERY_S = 1.0  # a spectator's draws and stats; the player's are read every 0.5 s
VIEWPORT = {"width": 960, "height": 600}
# The whole stats() object as one JSON string, or null while the page's script has not
# run yet (right after the navigation committed).
_STATS = "() => window.upcast ? JSON.stringify(window.upcast.stats()) : null"


def spectator_url(relay_port: int, broadcast: str, link_port: int) -> str:
    """The page the relay serves, without a token, connecting through ``link_port``."""
    query = {"broadcast": broadcast, "overlay": "0", "port": str(link_port)}
    return f"http://localhost:{relay_port}/?" + urlencode(query)


def _number(value: Any) -> float | None:
    return float(value) if isinstance(value, int | float) else None


PLAYER_TRACK = ""  # published_frames' key for the player's track, whatever its name


def published_frames(session: Any) -> dict[str, int]:
    """Frames published so far per video track: the player's (under its name and under
    PLAYER_TRACK) and each ladder rung's, when the session has a ladder."""
    broadcast = session.broadcast
    player = int(broadcast.stats.frames_published)
    out = {PLAYER_TRACK: player, str(broadcast.video_track): player}
    ladder = getattr(session, "ladder", None)
    for rung in getattr(ladder, "rungs", None) or []:
        out[str(rung.track)] = int(rung.frames)
    return out


def _count(published: dict[str, int], track: str | None) -> int:
    return published.get(track or PLAYER_TRACK, published[PLAYER_TRACK])


def _refetches(start: dict[str, Any], end: dict[str, Any]) -> dict[str, int]:
    """A page without a token cannot ask for a keyframe: it fetches its track again from
    the latest group instead (client_web/src/recovery.ts); how often, over the window."""
    a, b = (s.get("recovery", {}).get("refetches") for s in (start, end))
    return {"recovery_refetches": b - a} if isinstance(a, int) and isinstance(b, int) else {}


@dataclass
class _Base:
    """The first read after the first picture: where the delivered count starts."""

    at: float
    presented: float
    stats: dict[str, Any]


@dataclass
class Spectator:
    profile: str
    seed: int
    name: str = ""
    net: EmulatorProcess | None = None
    joined_at: float | None = None  # time.monotonic() as its navigation began
    joined_at_s: float | None = None  # the same, seconds into the window
    first_picture_ms: float | None = None
    shown: ShownFrames = field(default_factory=ShownFrames)
    collector: StageCollector = field(default_factory=StageCollector.empty)
    renditions: RenditionTime = field(default_factory=RenditionTime)
    base: _Base | None = None
    end: tuple[float, float] | None = None  # at, presented
    # Frames published on the track it played, read to read, since the base.
    published: int = 0
    published_by_track: dict[str, int] = field(default_factory=dict)
    _published_last: dict[str, int] | None = None
    counters: dict[str, Any] | None = None  # the page's own, over the delivered window
    link_end: dict[str, Any] | None = None
    errors: list[str] = field(default_factory=list)
    _context: Any = None
    _page: Any = None
    _next_read: float = 0.0

    def start_link(self, relay_port: int) -> None:
        self.net = EmulatorProcess(
            listen=("localhost", 0),
            upstream=("127.0.0.1", relay_port),
            schedule=resolve(self.profile),
            tcp_passthrough=True,
            seed=self.seed,
        ).start()

    def prepare(self, browser: Any) -> None:
        """A blank page in a context of its own, made ahead: on a loaded machine making
        one took about 2 s, which would have come out of the window."""
        self._context = browser.new_context(viewport=VIEWPORT)
        page = self._page = self._context.new_page()
        page.add_init_script(DRAW_WATCH)
        page.on("console", self._console)

    def join(self, relay_port: int, broadcast: str, window_t0: float) -> None:
        assert self.net is not None and self._page is not None
        self.net.restart_schedule()
        self.joined_at = time.monotonic()
        self.joined_at_s = round(self.joined_at - window_t0, 2)
        # "commit": the navigation has started the document; the page loads and joins
        # while the benchmark goes on (its own clock times the first picture).
        url = spectator_url(relay_port, broadcast, self.net.port)
        self._page.goto(url, wait_until="commit")
        self._next_read = time.monotonic()

    def _console(self, message: Any) -> None:
        if message.type == "error":
            print(f"spectator {self.name}:", message.text, file=sys.stderr)
            if len(self.errors) < 20:
                self.errors.append(str(message.text))

    def read(self, now: float, published: dict[str, int]) -> None:
        """Read the page when its turn has come."""
        if self._page is None or self.joined_at is None or now < self._next_read:
            return
        self._next_read = now + READ_EVERY_S
        self._take_draws(self._page.evaluate(READ_DRAWS)["draws"])
        if self.first_picture_ms is not None:
            self._read_stats(now, published)

    def _read_stats(self, now: float, published: dict[str, int]) -> dict[str, Any] | None:
        """The page's stats: renditions, latency samples, and the base of the delivered
        count at the first read after the first picture."""
        text = self._page.evaluate(_STATS)
        stats = json.loads(text) if isinstance(text, str) else None
        if not isinstance(stats, dict):
            return None
        self.renditions.update(stats)
        latency = stats.get("latency")
        if isinstance(latency, dict):
            self.collector.update(latency, keep=self.base is not None)
        presented = _number(stats.get("framesPresented"))
        if self.base is None and presented is not None:
            self.base = _Base(now, presented, stats)
        elif self._published_last is not None:
            track = self.renditions.current
            frames = _count(published, track) - _count(self._published_last, track)
            self.published += frames
            key = track or PLAYER_TRACK
            self.published_by_track[key] = self.published_by_track.get(key, 0) + frames
        if self.base is not None:
            self._published_last = published
        return stats

    def _take_draws(self, draws: list[float]) -> None:
        if draws and self.first_picture_ms is None:
            self.first_picture_ms = float(draws[0])
            print(
                f"  spectator {self.name}: first picture {self.first_picture_ms:.0f} ms",
                file=sys.stderr,
                flush=True,
            )
        self.shown.add(draws)

    def finish(self, published: dict[str, int]) -> None:
        """The window's end: the last draws, counts and the link's totals."""
        if self._page is not None and self.joined_at is not None:
            now = time.monotonic()
            tail = self._page.evaluate(READ_DRAWS)
            self._take_draws(tail["draws"])
            if self.first_picture_ms is not None:
                self.shown.finish(float(tail["now"]))
                had_base = self.base is not None
                stats = self._read_stats(now, published)
                presented = None if stats is None else _number(stats.get("framesPresented"))
                if had_base and presented is not None and stats is not None:
                    self.end = (now, presented)
                    assert self.base is not None
                    self.counters = counter_deltas(self.base.stats, stats)
                    self.counters.update(_refetches(self.base.stats, stats))
        if self.net is not None:
            self.link_end = self.net.stats()

    def close(self) -> None:
        """The page first (its TCP connections go through the emulator), then the link."""
        context, self._context, self._page = self._context, None, None
        try:
            if context is not None:
                context.close()
        finally:
            if self.net is not None:
                self.net.stop()

    def summary(self) -> dict[str, Any]:
        keys = ("seconds", "frames_published", "frames_published_by_track", "frames_shown")
        delivered: dict[str, Any] = dict.fromkeys((*keys, "server_fps", "page_fps"))
        ratio = None
        if self.base is not None and self.end is not None:
            published = self.published
            presented = int(self.end[1] - self.base.presented)
            seconds = self.end[0] - self.base.at
            delivered = {
                "seconds": round(seconds, 2),
                "frames_published": published,
                # "": the player's track (the page named no rendition).
                "frames_published_by_track": self.published_by_track,
                "frames_shown": presented,
                "server_fps": round(published / seconds, 2) if seconds > 0 else None,
                "page_fps": round(presented / seconds, 2) if seconds > 0 else None,
            }
            ratio = round(presented / published, 4) if published else None
        g2g = percentiles(self.collector.samples["total"])
        link = self.link_end or {}
        return {
            "name": self.name,
            "profile": self.profile,
            "link": resolve(self.profile).description,
            "joined_at_s": self.joined_at_s,
            "first_picture_ms": None
            if self.first_picture_ms is None
            else round(self.first_picture_ms, 1),
            "delivered_ratio": ratio,
            **delivered,
            "frames_drawn": self.shown.shown,
            "freezes": self.shown.summary(),
            **self.renditions.summary(),
            "glass_to_glass": g2g,
            "median_ms": g2g["p50_ms"],
            "p95_ms": g2g["p95_ms"],
            "page_counters": self.counters,
            "link_down_bytes": (link.get("down") or {}).get("bytes_delivered"),
            "link_release_late_ms": link.get("release_late_ms"),
            "page_errors": self.errors,
        }


class Spectators:
    """Every spectator of one profile's run: their links, pages and figures."""

    def __init__(self, profiles: list[str] | tuple[str, ...]) -> None:
        counts: dict[str, int] = {}
        self.members: list[Spectator] = []
        for i, profile in enumerate(profiles):
            counts[profile] = counts.get(profile, 0) + 1
            name = profile if profiles.count(profile) == 1 else f"{profile}#{counts[profile]}"
            # Loss seeds differ from the player's (0) and between spectators: links
            # with the same profile do not lose the same packets.
            self.members.append(Spectator(profile, seed=i + 1, name=name))
        self.joined = False

    def start_links(self, relay_port: int) -> Spectators:
        try:
            for member in self.members:
                member.start_link(relay_port)
        except BaseException:
            self.close()
            raise
        return self

    def __enter__(self) -> Spectators:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def prepare(self, browser: Any) -> None:
        for member in self.members:
            member.prepare(browser)

    def join(self, relay_port: int, broadcast: str, window_t0: float) -> None:
        self.joined = True
        for member in self.members:
            member.join(relay_port, broadcast, window_t0)

    def read(self, now: float, published: dict[str, int]) -> None:
        for member in self.members:
            member.read(now, published)

    def finish(self, published: dict[str, int]) -> None:
        for member in self.members:
            member.finish(published)

    def close(self) -> None:
        errors: list[BaseException] = []
        for member in self.members:
            try:
                member.close()
            except Exception as exc:  # close the others all the same
                errors.append(exc)
        if errors:
            raise errors[0]

    def summary(self) -> list[dict[str, Any]]:
        return [member.summary() for member in self.members]

    def notes(self, late_note_ms: float) -> list[str]:
        notes = []
        for m in self.members:
            if m.first_picture_ms is None:
                notes.append(f"spectator {m.name} showed no picture in the window")
            late = ((m.link_end or {}).get("release_late_ms") or {}).get("p99")
            if isinstance(late, int | float) and late > late_note_ms:
                notes.append(
                    f"spectator {m.name}'s emulator released packets late (p99 {late:.0f} ms)"
                )
        return notes


def worst(cases: list[dict[str, Any]]) -> dict[str, Any]:
    """The report's top-level ``spectators``: the worst first picture, delivered ratio and
    longest freeze over every spectator of every profile, and who had it."""
    entries = [(case["name"], s) for case in cases for s in case.get("spectators") or []]

    def pick(value: Callable[[dict[str, Any]], Any], highest: bool) -> dict[str, Any] | None:
        known = [(value(s), player, s) for player, s in entries if value(s) is not None]
        if not known:
            return None
        v, player, s = max(known, key=lambda k: k[0] if highest else -k[0])
        return {"value": v, "spectator": s["name"], "player_profile": player}

    return {
        "count": len(entries),
        "worst_first_picture_ms": pick(lambda s: s["first_picture_ms"], True),
        "worst_delivered_ratio": pick(lambda s: s["delivered_ratio"], False),
        "worst_longest_freeze_ms": pick(lambda s: s["freezes"]["longest_ms"], True),
        "without_picture": [
            {"spectator": s["name"], "player_profile": player}
            for player, s in entries
            if s["first_picture_ms"] is None
        ],
    }
