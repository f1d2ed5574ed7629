"""Mask secrets (tokens, keys, passwords) in URLs and free text before they are logged.

JWTs travel as ``?jwt=`` in WebTransport URLs (browsers cannot set headers on a
CONNECT), so any log line or exception message that formats a URL can leak one.
Everything that formats a URL into a log line or an error calls ``redact_url`` or
``redact_text``; the logging filter in ``server.ops.logging_setup`` calls
``redact_text`` on every record as the last line of defence.

A leaf module (standard library only) so every layer, server/quic included, may
import it.
"""

from __future__ import annotations

import re
from urllib.parse import parse_qsl, quote, urlsplit, urlunsplit

REDACTED = "REDACTED"

# Query parameter names whose value is a secret (compared lower-case, "-" as "_").
SECRET_NAMES = frozenset(
    {
        "jwt",
        "token",
        "access_token",
        "refresh_token",
        "id_token",
        "auth",
        "authorization",
        "key",
        "api_key",
        "apikey",
        "secret",
        "client_secret",
        "password",
        "passwd",
        "pwd",
        "signature",
        "sig",
    }
)

# Three base64url segments, the first two starting with eyJ (base64 of '{"'): a JWS.
_JWT = re.compile(r"eyJ[A-Za-z0-9_-]*\.eyJ[A-Za-z0-9_-]*\.[A-Za-z0-9_-]*")
# name=value anywhere in text (a URL inside a message, a "jwt=..." in a str(exc)); the
# name is checked against SECRET_NAMES in Python: one alternation of every name tried
# at every position made a log line with an "=" cost 14 us, this costs 3.
_PARAM = re.compile(r"(?<![A-Za-z0-9_-])([A-Za-z_-]{2,16})=([^&\s'\"<>#;,)\]}]+)")
# 'name': 'value' as a dict's repr or JSON writes it (headers, claims, settings).
_QUOTED = re.compile(r"""(["'])([A-Za-z_-]{1,16})\1(\s*:\s*)(["'])(?:\\.|(?!\4).)*\4""")
# Userinfo with a password in a URL: scheme://user:password@host.
_USERINFO = re.compile(r"(?i)([a-z][a-z0-9+.-]*://[^/\s:@]*:)[^/\s@]+@")


def _mask_param(match: re.Match[str]) -> str:
    name = match.group(1)
    return f"{name}={REDACTED}" if _is_secret_name(name) else match.group(0)


def _mask_quoted(match: re.Match[str]) -> str:
    quote_, name, colon, value_quote = match.group(1, 2, 3, 4)
    if not (_is_secret_name(name) or name == "k"):  # "k": a JWK's secret (server.auth.keys)
        return match.group(0)
    return f"{quote_}{name}{quote_}{colon}{value_quote}{REDACTED}{value_quote}"


def _is_secret_name(name: str) -> bool:
    return name.strip().lower().replace("-", "_") in SECRET_NAMES


def redact_url(url: str) -> str:
    """``url`` with the values of secret query parameters (and a userinfo password)
    replaced by ``REDACTED``, then through ``redact_text`` as well, so a malformed
    URL (or a JWT in its path or fragment) never escapes unmasked."""
    try:
        parts = urlsplit(url)
        netloc = parts.netloc
        if parts.password is not None:
            userinfo, _, hostport = netloc.rpartition("@")
            user = userinfo.split(":", 1)[0]
            netloc = f"{user}:{REDACTED}@{hostport}"
        query = parts.query
        if query:
            pairs = parse_qsl(query, keep_blank_values=True)
            if any(_is_secret_name(k) for k, _ in pairs):
                query = "&".join(
                    f"{quote(k, safe='')}={REDACTED if _is_secret_name(k) else quote(v, safe='')}"
                    for k, v in pairs
                )
        rebuilt = urlunsplit(parts._replace(netloc=netloc, query=query))
    except ValueError:
        rebuilt = url
    # The fragment, the path or an unparsed query may still hold a JWT or name=value.
    return redact_text(rebuilt)


def redact_text(text: str) -> str:
    """``text`` with JWT-shaped strings, ``jwt=...``-style parameters, ``'jwt': '...'``
    dict or JSON entries (and a JWK's ``"k"``) and URL passwords replaced by
    ``REDACTED``. Cheap on text that holds none of them."""
    # Each pass only where its literal is present: most log lines skip them all.
    if "eyJ" in text:
        text = _JWT.sub(REDACTED, text)
    if "=" in text:
        text = _PARAM.sub(_mask_param, text)
    if ":" in text and ("'" in text or '"' in text):
        text = _QUOTED.sub(_mask_quoted, text)
    if "@" in text and "://" in text:
        text = _USERINFO.sub(rf"\g<1>{REDACTED}@", text)
    return text


__all__ = ["REDACTED", "SECRET_NAMES", "redact_text", "redact_url"]
