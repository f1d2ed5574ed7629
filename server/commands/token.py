"""``upcast token generate|sign``: make the relay's key file and mint tokens with it.

The key and tokens are moq-token's (JWK, JWT HS256), so they also work with moq-dev's
``moq-relay``. The token goes to stdout alone, for ``$(upcast token sign ...)``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DEFAULT_EXPIRES_IN_S = 24 * 3600


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    gen = sub.add_parser("generate", help="write a new random key file (JWK, mode 0600)")
    gen.add_argument("--key", type=Path, required=True, help="where to write the key")
    signer = sub.add_parser("sign", help="print a token signed with a key file")
    signer.add_argument("--key", type=Path, required=True, help="the relay's key file")
    signer.add_argument(
        "--root", required=True, help="broadcast path prefix the token is for (e.g. game)"
    )
    signer.add_argument(
        "--publish",
        action="append",
        default=[],
        metavar="SUFFIX",
        help='path under --root the holder may publish ("" = all of it); repeatable',
    )
    signer.add_argument(
        "--subscribe",
        action="append",
        default=[],
        metavar="SUFFIX",
        help='path under --root the holder may watch ("" = all of it); repeatable',
    )
    signer.add_argument(
        "--expires-in",
        type=int,
        default=DEFAULT_EXPIRES_IN_S,
        metavar="SECONDS",
        help=f"lifetime (default {DEFAULT_EXPIRES_IN_S}; 0 = never expires)",
    )


def run(args: argparse.Namespace) -> int:
    from server.auth import Claims, KeyFileError, generate_key, load_key, sign

    if args.action == "generate":
        try:
            generate_key(args.key)
        except FileExistsError:
            print(f"upcast token: {args.key} exists; not overwriting a key", file=sys.stderr)
            return 2
        except OSError as exc:
            print(f"upcast token: cannot write {args.key}: {exc.strerror}", file=sys.stderr)
            return 2
        print(f"upcast token: wrote key {args.key}", file=sys.stderr)
        return 0
    if not args.publish and not args.subscribe:
        print("upcast token: --publish or --subscribe is required", file=sys.stderr)
        return 2
    if args.expires_in < 0:
        print(f"upcast token: --expires-in must be >= 0, got {args.expires_in}", file=sys.stderr)
        return 2
    try:
        key = load_key(args.key)
    except KeyFileError as exc:
        print(f"upcast token: {exc}", file=sys.stderr)
        return 2
    claims = Claims.for_(
        args.root,
        put=tuple(args.publish),
        get=tuple(args.subscribe),
        expires_in_s=args.expires_in or None,
    )
    print(sign(key, claims))
    return 0
