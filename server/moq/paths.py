"""Broadcast path rules of @moq/lite (`path.js`): '/'-separated, trimmed, prefix on segments."""

from __future__ import annotations

import re

_SLASHES = re.compile(r"/+")


def normalize(path: str) -> str:
    """Collapse repeated slashes and trim them at both ends, as `Path.from` does."""
    return _SLASHES.sub("/", path).strip("/")


def strip_prefix(prefix: str, path: str) -> str | None:
    """Suffix of `path` below `prefix`, or None when `prefix` is not a segment prefix.

    "foo" is a prefix of "foo" and "foo/bar" but not of "foobar".
    """
    if prefix == "":
        return path
    if not path.startswith(prefix):
        return None
    if len(path) == len(prefix):
        return ""
    if path[len(prefix)] != "/":
        return None
    return path[len(prefix) + 1 :]


def join(prefix: str, suffix: str) -> str:
    if prefix == "":
        return suffix
    if suffix == "":
        return prefix
    return f"{prefix}/{suffix}"
