"""``upcast worker``: the upscaler worker process on existing rings."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from server.config_errors import format_validation_error


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--ring-in", required=True, help="ring R name (G-buffers)")
    parser.add_argument("--ring-out", required=True, help="ring U name (display frames)")
    parser.add_argument("--upscaler", default="bilinear", help="initial upscaler")
    parser.add_argument("--display-size", default="1280x720", help="WIDTHxHEIGHT")
    parser.add_argument("--control", type=Path, default=None, help="Unix control socket path")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    parser.add_argument("--newest", action="store_true", help="skip to the newest frame")
    parser.add_argument(
        "--metrics-port", type=int, default=0, help="Prometheus /metrics TCP port (0: off)"
    )
    parser.add_argument(
        "--predictor",
        default="mpe",
        help="frame predictor for the game's predicted ticks (frame generation; default: mpe)",
    )
    parser.add_argument(
        "--cache-policy",
        default=None,
        help="layer-cache policy of unet_cached (delta_l, delta_h, budget, budget@DB, every_N, "
        "deepcache, motion; default delta_l)",
    )
    parser.add_argument(
        "--compile",
        action="store_true",
        help="torch.compile easu and easu_rcas (the first frame of a size waits for it; "
        "on the CPU the default numba kernels are faster: for CUDA)",
    )


def run(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from server.worker.run import run_worker
    from server.worker.upscale import WorkerConfig

    try:
        config = WorkerConfig(
            ring_in=args.ring_in,
            ring_out=args.ring_out,
            upscaler=args.upscaler,
            display_size=args.display_size,
            control_path=args.control,
            threads=args.threads,
            newest=args.newest,
            metrics_port=args.metrics_port,
            compile=args.compile,
            predictor=args.predictor,
            cache_policy=args.cache_policy,
        )
    except ValidationError as exc:
        print(format_validation_error("worker", exc), file=sys.stderr)
        return 2
    return run_worker(config)
