"""moq-dev's Rust relay core as a process of its own, so /proc reads its CPU alone.

``python -m server.bench.relay.rust_relay [--host H] [--port P] [--cert PEM --key PEM]``
runs ``moq.Server`` (the ``moq-rs`` package: the core moq-dev's ``moq-relay`` is built
on) with one shared origin, as tests/test_moq_rs_relay.py does: what a publisher
announces is what every subscriber finds. Without ``--cert`` it generates a
certificate for localhost. It runs until killed and writes JSON lines on stdout:

- ``{"url": "https://127.0.0.1:P/", "port": P, "cert_sha256": HEX}`` once listening,
- ``{"announced": PATH, "active": true|false}`` as broadcasts come and go,

so the parent learns where to point the publisher and viewers, and when the
broadcast is there, without a side channel (this relay has no HTTP port).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import importlib
import json
import signal
import sys
from typing import Any


def emit(record: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(record) + "\n")
    sys.stdout.flush()


async def serve(host: str, port: int, cert: str | None, key: str | None) -> None:
    moq: Any = importlib.import_module("moq")  # no stubs for its FFI half: typed as Any
    origin = moq.OriginProducer()
    tls: dict[str, list[str]] = (
        {"tls_cert": [cert], "tls_key": [key]}
        if cert is not None and key is not None
        else {"tls_generate": ["localhost"]}
    )
    held: set[asyncio.Task[None]] = set()

    async def hold(request: Any) -> None:
        session = await request.accept()
        # A peer's close surfaces as a moq error here; it is the normal end.
        with contextlib.suppress(moq.Error):
            await session.closed()

    async def watch_announcements() -> None:
        async with origin.consume().announced() as updates:
            async for update in updates:
                emit({"announced": update.prefix, "active": update.active})

    async with moq.Server(f"{host}:{port}", publish=origin, subscribe=origin, **tls) as server:
        bound = int(server.local_addr.rsplit(":", 1)[1])
        emit(
            {
                "url": f"https://{host}:{bound}/",
                "port": bound,
                "cert_sha256": server.cert_fingerprints()[0],
            }
        )
        watcher = asyncio.create_task(watch_announcements())
        try:
            async for request in server:
                task = asyncio.create_task(hold(request))
                held.add(task)  # dropping a session's handle would close it
                task.add_done_callback(held.discard)
        finally:
            watcher.cancel()
            for task in list(held):
                task.cancel()
            await asyncio.gather(watcher, *held, return_exceptions=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m server.bench.relay.rust_relay")
    parser.add_argument("--host", default="127.0.0.1", help="address to bind")
    parser.add_argument("--port", type=int, default=0, help="UDP port (0: a free one)")
    parser.add_argument("--cert", default=None, help="certificate PEM (default: generated)")
    parser.add_argument("--key", default=None, help="private key PEM for --cert")
    args = parser.parse_args(argv)
    if (args.cert is None) != (args.key is None):
        parser.error("--cert and --key go together")
    try:
        importlib.import_module("moq")
    except ImportError:
        sys.stderr.write("moq-rs is not installed: pip install 'moq-rs==0.5.1'\n")
        return 2

    async def until_terminated() -> None:
        loop = asyncio.get_running_loop()
        stopping = asyncio.Event()
        loop.add_signal_handler(signal.SIGTERM, stopping.set)
        serving = asyncio.create_task(serve(args.host, args.port, args.cert, args.key))
        waiting = asyncio.create_task(stopping.wait())
        done, _ = await asyncio.wait({serving, waiting}, return_when=asyncio.FIRST_COMPLETED)
        waiting.cancel()
        if serving in done:
            await serving  # it ended by itself: raise what ended it
        serving.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await serving

    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(until_terminated())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
