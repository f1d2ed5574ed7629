"""Config errors as a person reads them: the field, what is wrong, what is allowed."""

from __future__ import annotations

from pydantic import ValidationError


def format_validation_error(what: str, exc: ValidationError) -> str:
    lines = [f"invalid {what} configuration:"]
    for err in exc.errors(include_url=False):
        field = ".".join(str(p) for p in err["loc"]) or "(root)"
        lines.append(f"  {field}: {err['msg']}")
    return "\n".join(lines)
