"""``upcast eval content``: the real photographs and game pictures of the evaluation.

``--fetch`` downloads the pinned Debian packages of ``real_content_sources`` and
unpacks their images, split per source into ``train`` and ``held_out``; without
it the command lists what the directory holds.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from server.eval.real_content_sources import HELD_OUT_DIR, SOURCES, TRAIN_DIR

DEFAULT_DIR = Path.home() / ".cache" / "upcast" / "content"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--fetch", action="store_true", help="download and unpack the sources")
    parser.add_argument("--dir", type=Path, default=DEFAULT_DIR, help="content directory")


def run(args: argparse.Namespace) -> int:
    if args.fetch:
        from server.eval.real_content_fetch import fetch_all

        fetch_all(args.dir)
    for s in SOURCES:
        counts = [len(list((args.dir / s.name / d).glob("*"))) for d in (TRAIN_DIR, HELD_OUT_DIR)]
        print(
            f"{s.name:16} {s.package} {s.version} ({s.kind}): "
            f"{counts[0]} train, {counts[1]} held out"
        )
    return 0
