"""Mask secrets (tokens, keys, passwords) in URLs and free text before they are logged.

JWTs travel as ``?jwt=`` in WebTransport URLs (browsers cannot set headers on a
CONNECT), so any log line or exception message that formats a URL can leak one.
Everything that formats a URL into a log line or an error calls ``redact_url`` or
``redact_text``; the logging filter in ``server.logging_setup`` calls
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
# name=value anywhere in text (a URL inside a message, a "jwt=..." in a str(exc)).
_NAMES = "|".join(
    re.escape(n).replace("_", "[_-]") for n in sorted(SECRET_NAMES, key=len, reverse=True)
)
_PARAM = re.compile(rf"(?i)(?<![A-Za-z0-9_-])((?:{_NAMES})=)[^&\s'\"<>#;,)\]}}]+")
# Userinfo with a password in a URL: scheme://user:password@host.
_USERINFO = re.compile(r"(?i)([a-z][a-z0-9+.-]*://[^/\s:@]*:)[^/\s@]+@")
# Cheap pre-check: text without any of these cannot hold what the regexes look for.
_HINTS = ("eyJ", "=", "@")


def _is_secret_name(name: str) -> bool:
    return name.strip().lower().replace("-", "_") in SECRET_NAMES


def redact_url(url: str) -> str:
    """``url`` with the values of secret query parameters (and a userinfo password)
    replaced by ``REDACTED``; anything that does not parse as a URL goes through
    ``redact_text`` instead, so a malformed URL never escapes unmasked."""
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
    """``text`` with JWT-shaped strings, ``jwt=...``-style parameters and URL
    passwords replaced by ``REDACTED``. Cheap on text that holds none of them."""
    if not any(h in text for h in _HINTS):
        return text
    text = _JWT.sub(REDACTED, text)
    text = _PARAM.sub(rf"\g<1>{REDACTED}", text)
    return _USERINFO.sub(rf"\g<1>{REDACTED}@", text)


__all__ = ["REDACTED", "SECRET_NAMES", "redact_text", "redact_url"]
