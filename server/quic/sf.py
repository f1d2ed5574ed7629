"""The sliver of RFC 9651 structured fields that WebTransport protocol negotiation needs.

`wt-available-protocols` is an sf-list of sf-strings and `wt-protocol` one sf-string.
Items that are not strings (tokens, numbers, inner lists) are skipped rather than
rejected: a client offering something odd still gets a fair pick among the rest.
"""

from __future__ import annotations


def parse_string_list(value: str) -> list[str]:
    """Return the sf-string members of an sf-list, in order; parameters are ignored."""
    out: list[str] = []
    i, n = 0, len(value)
    while i < n:
        while i < n and value[i] in " \t":
            i += 1
        if i >= n:
            break
        if value[i] == '"':
            i += 1
            chars: list[str] = []
            closed = False
            while i < n:
                c = value[i]
                if c == "\\" and i + 1 < n:
                    chars.append(value[i + 1])
                    i += 2
                    continue
                i += 1
                if c == '"':
                    closed = True
                    break
                chars.append(c)
            if closed:
                out.append("".join(chars))
        # Skip parameters or a non-string member up to the next list separator.
        in_quote = False
        while i < n and (in_quote or value[i] != ","):
            if value[i] == '"':
                in_quote = not in_quote
            i += 1
        i += 1
    return out


def serialize_string(value: str) -> str:
    """Encode one sf-string (printable ASCII only, per the RFC)."""
    if any(not (0x20 <= ord(c) <= 0x7E) for c in value):
        raise ValueError(f"not a valid sf-string: {value!r}")
    return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'


def parse_string(value: str) -> str | None:
    """Decode one sf-string item, or None when the value is not a string."""
    items = parse_string_list(value)
    return items[0] if len(items) == 1 else None
