#!/usr/bin/env python3
"""Container health check: exit 0 when GET URL answers 200 within 3 s, else 1.

Installed as /usr/local/bin/upcast-healthcheck in the images (slim images have no
curl; Python is there anyway). Standard library only.
"""

import sys
import urllib.request


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: upcast-healthcheck URL", file=sys.stderr)
        return 2
    try:
        with urllib.request.urlopen(argv[0], timeout=3) as response:
            return 0 if response.status == 200 else 1
    except OSError as exc:
        print(f"unhealthy: {argv[0]}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
