"""Good viewers for ``bench adversary``, in their own process (their CPU is not the
relay's nor the attacker's): N load-test viewers that print, every 0.25 s, one JSON line
``{"t": monotonic, "frames": [video frames so far, per viewer]}`` on stdout until
stdin closes.

``python -m server.bench.adversary.viewers URL CERT_SHA256 N``
"""

from __future__ import annotations

import asyncio
import json
import math
import sys
import time

from server.loadtest.viewer import LoadViewer, ViewerConfig
from server.ops.event_loop import install_uvloop

REPORT_INTERVAL_S = 0.25


async def _main(url: str, cert_hash: str, count: int) -> None:
    config = ViewerConfig(url, "game", cert_hash, connect_timeout_s=10.0)
    viewers = [LoadViewer(i, config, (0.0, math.inf)) for i in range(count)]
    await asyncio.gather(*(v.connect() for v in viewers))
    loop = asyncio.get_running_loop()
    stdin_closed = loop.run_in_executor(None, sys.stdin.read)
    try:
        while not stdin_closed.done():
            line = {"t": time.monotonic(), "frames": [v.stats.received_total for v in viewers]}
            sys.stdout.write(json.dumps(line) + "\n")
            sys.stdout.flush()
            await asyncio.sleep(REPORT_INTERVAL_S)
    finally:
        for viewer in viewers:
            viewer.close()
        await asyncio.sleep(0.1)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 3:
        sys.stderr.write(__doc__ or "")
        return 2
    install_uvloop()
    asyncio.run(_main(args[0], args[1], int(args[2])))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
