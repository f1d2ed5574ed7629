"""Log output for every upcast process: human text or one JSON object per line.

JSON lines are what log shippers (Loki, Vector, CloudWatch, ``docker logs``
pipelines) parse without a regex: each line has ``ts`` (RFC 3339, UTC, ms),
``level``, ``logger``, ``msg``, ``process`` (name) and ``pid``; fields a caller
passes with ``log.info(..., extra={"broadcast": "game-1"})`` appear under
``extra``, and an exception under ``exc``.

The format comes from ``--log-format`` or else ``UPCAST_LOG_FORMAT``; the CLI
writes the choice back into the environment so the game and worker processes a
command starts log the same way.
"""

from __future__ import annotations

import datetime
import json
import logging
import os
from collections.abc import Mapping
from typing import Any

from server.ops.redact import redact_text

LOG_FORMATS = ("text", "json")
ENV_VAR = "UPCAST_LOG_FORMAT"
# "1": debug logging, written back by a -v command so the processes it starts
# (relay, game, worker) log at DEBUG too.
VERBOSE_ENV_VAR = "UPCAST_VERBOSE"
TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"

# Attributes every LogRecord has; anything else on a record came from `extra=`.
_STANDARD = frozenset(logging.makeLogRecord({}).__dict__) | {"message", "asctime"}


class JsonLineFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, Any] = {
            "ts": datetime.datetime.fromtimestamp(record.created, datetime.UTC).isoformat(
                timespec="milliseconds"
            ),
            "level": record.levelname,
            "logger": record.name,
            "msg": record.getMessage(),
            "process": record.processName,
            "pid": record.process,
        }
        extra = {k: v for k, v in record.__dict__.items() if k not in _STANDARD}
        if extra:
            entry["extra"] = extra
        if record.exc_text:  # RedactingFilter's masked copy, when it ran
            entry["exc"] = record.exc_text
        elif record.exc_info:
            entry["exc"] = self.formatException(record.exc_info)
        elif record.stack_info:
            entry["stack"] = record.stack_info
        # default=repr: an odd extra value must never cost the log line.
        return json.dumps(entry, default=repr, ensure_ascii=False)


class RedactingFilter(logging.Filter):
    """Masks tokens and passwords in every record a handler writes: the last line of
    defence for a secret that a log call formats by mistake (callers still redact
    URLs themselves). The message is formatted once, masked and stored back with no
    args; a traceback is formatted into ``exc_text`` and masked too, which both
    formatters then print instead of formatting ``exc_info`` again; string
    ``extra=`` fields are masked as well."""

    _exc_formatter = logging.Formatter()

    def filter(self, record: logging.LogRecord) -> bool:
        try:
            message = record.getMessage()
        except Exception:  # a bad %-format: leave it for the handler to report
            return True
        masked = redact_text(message)
        if masked != message:
            record.msg, record.args = masked, None
        if record.exc_info and not record.exc_text:
            record.exc_text = self._exc_formatter.formatException(record.exc_info)
        if record.exc_text:
            record.exc_text = redact_text(record.exc_text)
        if record.stack_info:
            record.stack_info = redact_text(record.stack_info)
        for name, value in record.__dict__.items():  # `extra=` fields the JSON lines show
            if isinstance(value, str) and name not in _STANDARD:
                record.__dict__[name] = redact_text(value)
        return True


def install_redaction(logger: logging.Logger | None = None) -> None:
    """Put a RedactingFilter on every handler of ``logger`` (the root by default)
    that lacks one; for processes that set up logging with ``basicConfig``."""
    for handler in (logger or logging.getLogger()).handlers:
        if not any(isinstance(f, RedactingFilter) for f in handler.filters):
            handler.addFilter(RedactingFilter())


def default_log_format(environ: Mapping[str, str] = os.environ) -> str:
    """``UPCAST_LOG_FORMAT`` or "text"; ValueError naming the variable if unknown."""
    value = environ.get(ENV_VAR, "text").strip().lower() or "text"
    if value not in LOG_FORMATS:
        raise ValueError(f"{ENV_VAR} must be one of {', '.join(LOG_FORMATS)}, got {value!r}")
    return value


def default_verbose(environ: Mapping[str, str] = os.environ) -> bool:
    return environ.get(VERBOSE_ENV_VAR, "").strip() == "1"


def configure_logging(level: int, log_format: str) -> None:
    """One stderr handler in ``log_format`` on the root logger, and the choice in
    the environment for child processes. Like ``logging.basicConfig`` it leaves a
    root logger that already has handlers alone (pytest's capture, an embedding app)."""
    if log_format not in LOG_FORMATS:
        raise ValueError(f"log format must be one of {', '.join(LOG_FORMATS)}, got {log_format!r}")
    handler = logging.StreamHandler()
    formatter = JsonLineFormatter() if log_format == "json" else logging.Formatter(TEXT_FORMAT)
    handler.setFormatter(formatter)
    handler.addFilter(RedactingFilter())
    logging.basicConfig(level=level, handlers=[handler])
    os.environ[ENV_VAR] = log_format
    if level <= logging.DEBUG:
        os.environ[VERBOSE_ENV_VAR] = "1"
