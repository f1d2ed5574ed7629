"""Config errors as a person reads them: the field, what is wrong, what is allowed."""

from __future__ import annotations

import sys
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

Model = TypeVar("Model", bound=BaseModel)


def format_validation_error(what: str, exc: ValidationError) -> str:
    lines = [f"invalid {what} configuration:"]
    for err in exc.errors(include_url=False):
        field = ".".join(str(p) for p in err["loc"]) or "(root)"
        lines.append(f"  {field}: {err['msg']}")
    return "\n".join(lines)


def validated(model: type[Model], what: str, **fields: Any) -> Model | None:
    """``model(**fields)``, or None after printing which field is wrong to stderr
    (the commands then exit with status 2)."""
    try:
        return model(**fields)
    except ValidationError as exc:
        print(format_validation_error(what, exc), file=sys.stderr)
        return None
