"""``upcast serve``: N game sessions on one host against one relay.

Each session (rings, game, worker, encoder, broadcast ``<prefix>-<i>``) runs
in its own OS process, the body ``upcast up`` runs (server/serve/). A session
whose process dies is restarted without touching the others; a dead worker
inside a session is restarted by the session itself. The supervisor answers
``GET /sessions``, ``/metrics`` and ``/healthz`` on ``--http-port``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

from server.commands.link_flags import add_link_arguments
from server.commands.quality_flags import add_quality_arguments, quality_fields
from server.ops.browser_paths import WEB_ROOT
from server.stack.args import add_session_arguments, session_config_from

if TYPE_CHECKING:
    from server.auth.keys import AuthKey
    from server.serve.supervisor import ServedSession

log = logging.getLogger(__name__)

CHECK_INTERVAL_S = 0.5
METRICS_PORTS_PER_SESSION = 3  # session, game, worker
ALL_UP_TIMEOUT_S = 180.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_session_arguments(parser)
    parser.add_argument("--sessions", type=int, default=None, help="number of sessions (default 1)")
    parser.add_argument(
        "--config", type=Path, default=None, help="JSON or TOML list of per-session overrides"
    )
    parser.add_argument(
        "--broadcast-prefix", default="game", help="sessions publish <prefix>-1 ... (default game)"
    )
    parser.add_argument(
        "--relay", default=None, help="publish to this relay URL instead of starting one"
    )
    parser.add_argument("--host", default="::", help="bind address of the relay and HTTP side")
    parser.add_argument("--port", type=int, default=4443, help="relay port, UDP (QUIC) and TCP")
    parser.add_argument(
        "--http-port",
        type=int,
        default=None,
        help="TCP port of /sessions, /metrics, /healthz (default: relay port + 1); "
        "session i's Prometheus metrics are on http-port + 3i - 2, its game's and "
        "worker's on the next two ports",
    )
    parser.add_argument("--bitrate-kbps", type=int, default=None, help="video bitrate")
    parser.add_argument("--gop-seconds", type=float, default=2.0, help="keyframe interval")
    add_link_arguments(parser)
    add_quality_arguments(parser)
    parser.add_argument(
        "--auth-key", type=Path, default=None, help="JWK key that signs the sessions' tokens"
    )
    parser.add_argument(
        "--web-root", type=Path, default=WEB_ROOT, help="built web client (client_web/dist)"
    )
    parser.add_argument(
        "--admission",
        choices=("refuse", "queue", "admit"),
        default="refuse",
        help="refuse (default) or queue a session while a running one cannot hold its frame "
        "rate even at its cheapest setting (adaptive quality's floor); under both, sessions "
        "start one after the other as each settles. admit: start every session at once",
    )
    parser.add_argument(
        "--cpu-shares",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="give each session a cgroup (v1 cpu) weighted by its target's cost (fps x "
        "display pixels), so under contention none takes more than its part; where "
        "cgroups cannot be written the sessions run without (said in /sessions)",
    )
    parser.add_argument("--duration", type=float, default=None, help="stop after SECONDS")
    parser.add_argument(
        "--frame-tap-port",
        type=int,
        default=0,
        metavar="PORT",
        help="debugging: session i serves thumbnails of its last 300 encoded frames by "
        "frame id on http://HOST:PORT+i-1/frames/ID, for picture checks against what a "
        "viewer shows (deploy/smoke.sh); costs ~2 ms a frame. Default 0: off",
    )


def _problem(args: argparse.Namespace) -> str | None:
    if args.sessions is not None and not 1 <= args.sessions <= 64:
        return f"--sessions must be in [1, 64], got {args.sessions}"
    if args.duration is not None and args.duration <= 0:
        return f"--duration must be positive, got {args.duration}"
    if args.relay is not None and not args.relay.startswith(("http://", "https://")):
        return f"--relay must be an http(s):// URL, got {args.relay}"
    if args.relay is None and not (args.web_root / "index.html").is_file():
        return (
            f"the web client is not built ({args.web_root}/index.html missing): "
            "run ./dev up, or cd client_web && npm ci && npm run build"
        )
    if not 0 <= args.frame_tap_port <= 65535 - 64:
        return f"--frame-tap-port must be in [0, 65471], got {args.frame_tap_port}"
    if args.auth_key is not None and not args.auth_key.is_file():
        return f"--auth-key {args.auth_key} is not a file"
    return None


def _sessions(args: argparse.Namespace) -> list[ServedSession] | None:
    """The sessions of the flags and the config file (None: refused, reason printed)."""
    from server.config_errors import validated
    from server.serve.config import ConfigFileError, load_overrides, session_configs
    from server.serve.supervisor import ServedSession
    from server.stream_config import StreamConfig

    base = session_config_from(args, sessions=args.sessions or 1)
    stream = validated(
        StreamConfig,
        "stream",
        host=args.host,
        port=args.port,
        broadcast=args.broadcast_prefix,
        bitrate_kbps=args.bitrate_kbps,
        gop_seconds=args.gop_seconds,
        rate_control=args.rate_control,
        intra_refresh=args.intra_refresh,
        ladder=list(args.ladder),
        **quality_fields(args),
    )
    if base is None or stream is None:
        return None
    try:
        overrides = [] if args.config is None else load_overrides(args.config)
        count = args.sessions if args.sessions is not None else max(1, len(overrides))
        configs = session_configs(base, stream, overrides, count, args.broadcast_prefix)
    except ConfigFileError as exc:
        print(f"upcast serve: {exc}", file=sys.stderr)
        return None
    http_port = _http_port(args)
    status_dir = Path(tempfile.mkdtemp(prefix="upcast-serve-status-"))
    return [
        ServedSession(
            index=i,
            config=config,
            stream=session_stream,
            metrics_port=http_port + 1 + METRICS_PORTS_PER_SESSION * (i - 1) if http_port else 0,
            status_path=status_dir / f"session-{i}.status.json",
            frame_tap_port=args.frame_tap_port + i - 1 if args.frame_tap_port else 0,
            frame_tap_host=args.host or "::",  # where serve's HTTP side listens
        )
        for i, (config, session_stream) in enumerate(configs, start=1)
    ]


def _http_port(args: argparse.Namespace) -> int:
    return int(args.http_port) if args.http_port is not None else int(args.port) + 1


def run(args: argparse.Namespace) -> int:
    problem = _problem(args)
    if problem is not None:
        print(f"upcast serve: {problem}", file=sys.stderr)
        return 2
    sessions = _sessions(args)
    if sessions is None:
        return 2
    from server.auth.keys import KeyFileError
    from server.auth.stack_key import stack_key
    from server.ops.event_loop import install_uvloop

    install_uvloop()
    if args.relay is not None and args.auth_key is None:
        return asyncio.run(_main(args, sessions, None))  # an open relay somewhere else
    try:
        with stack_key(args.auth_key) as key:
            return asyncio.run(_main(args, sessions, key))
    except KeyFileError as exc:
        print(f"upcast serve: --auth-key: {exc}", file=sys.stderr)
        return 2


def _browser_host(bind: str) -> str:
    if bind in ("::", ""):
        return "localhost"
    if bind == "0.0.0.0":
        return "127.0.0.1"
    return f"[{bind}]" if ":" in bind else bind


async def _main(
    args: argparse.Namespace, sessions: list[ServedSession], key: tuple[Path, AuthKey] | None
) -> int:
    """``key``: the relay's key file and key (tokens are minted with it), None for an
    open external relay."""
    from server.ops.cpu_shares import CpuShares, supervisor_group_name
    from server.relay.process import RelayProcess
    from server.serve.admission import Admission
    from server.serve.http_api import ServeHttp
    from server.serve.supervisor import Supervisor
    from server.serve.tokens import no_token, player_minter, publisher_minter, with_token

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    relay: RelayProcess | None = None
    host = _browser_host(args.host)
    if args.relay is None:
        relay = RelayProcess(
            args.host, args.port, args.web_root, auth_key=None if key is None else key[0]
        )
        try:
            endpoint = await loop.run_in_executor(None, relay.start)
        except (RuntimeError, TimeoutError) as exc:
            print(f"upcast serve: relay failed on port {args.port}: {exc}", file=sys.stderr)
            return 1
        # Not pinned to this certificate: a restarted relay has a new one, and an
        # http:// URL makes each (re)connect fetch the current hash.
        relay_url = f"http://127.0.0.1:{endpoint.port}/"
        watch_base = f"http://{host}:{endpoint.port}/"
    else:
        relay_url = watch_base = args.relay if args.relay.endswith("/") else args.relay + "/"
    publisher = no_token if key is None else publisher_minter(key[1])
    player = no_token if key is None else player_minter(key[1])
    supervisor = Supervisor(
        sessions,
        relay_url=relay_url,
        token_for=publisher,
        admission=Admission(args.admission),
        cpu=CpuShares(supervisor_group_name()) if args.cpu_shares else None,
    )
    http = ServeHttp(supervisor, relay)
    code = 0
    try:
        http_port = await http.start(args.host, _http_port(args))
        supervisor.start_all()
        deadline = None if args.duration is None else time.monotonic() + args.duration
        announced = False
        up_by = time.monotonic() + ALL_UP_TIMEOUT_S
        while not stop.is_set():
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(CHECK_INTERVAL_S):
                    await stop.wait()
            supervisor.check()
            if relay is not None and relay.check():
                log.warning("relay restarted (restart #%d)", relay.restarts)
                supervisor.relay_restarted()
            if not announced and supervisor.all_up():
                announced = True
                up = 0
                for s in supervisor.sessions:
                    if s.admission in ("refused", "queued"):
                        print(f"session {s.index} {s.admission}: {s.admission_reason}", flush=True)
                        continue
                    up += 1
                    page = with_token(f"{watch_base}?broadcast={s.broadcast}", player(s.broadcast))
                    print(f"session {s.index} up: watch at {page}", flush=True)
                print(
                    f"upcast serve: {up} of {len(sessions)} sessions up; "
                    f"status http://{host}:{http_port}/sessions (Ctrl-C to stop)",
                    flush=True,
                )
            elif not announced and time.monotonic() > up_by:
                log.warning("not every session is up after %.0f s", ALL_UP_TIMEOUT_S)
                up_by = float("inf")
            if deadline is not None and time.monotonic() >= deadline:
                log.info("duration of %.0f s reached: stopping", args.duration)
                break
    except OSError as exc:
        print(f"upcast serve: {exc}", file=sys.stderr)
        code = 1
    finally:
        await loop.run_in_executor(None, supervisor.stop_all)
        await http.close()
        if relay is not None:
            relay.stop()
        status_dirs = {s.status_path.parent for s in sessions}
        for d in status_dirs:
            for p in d.iterdir():
                p.unlink(missing_ok=True)
            with contextlib.suppress(OSError):
                d.rmdir()
    return code
