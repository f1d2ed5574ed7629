"""Write the JSON Schema of the control request and the status record:
``python -m server.serve.control_schema [PATH]`` (default docs/control.schema.json).

Generated from the pydantic models, so the file cannot drift from what the
session accepts (tests/test_control_api.py checks the committed file is current).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from pydantic.json_schema import models_json_schema

from server.session.session_control import StatusRecord
from server.session.viewer_input import ControlMessage

DEFAULT_PATH = Path(__file__).resolve().parents[2] / "docs" / "control.schema.json"


def control_schema() -> dict[str, Any]:
    # One $defs for all models, so the status record's reference to ControlResult resolves.
    _, schema = models_json_schema(
        [(ControlMessage, "validation"), (StatusRecord, "serialization")],
        title="upcast control API",
        description=(
            "A control request (ControlMessage) is one JSON frame of type 'control' on a viewer "
            "input track (broadcast '<session>/input/<id>', track 'input'). The session answers "
            "on its 'status' track (one StatusRecord per group, a new group per change); "
            "last_control carries the request's seq and source."
        ),
    )
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", **schema}


def render() -> str:
    return json.dumps(control_schema(), indent=2, sort_keys=True) + "\n"


def main(argv: list[str]) -> int:
    path = Path(argv[0]) if argv else DEFAULT_PATH
    path.write_text(render())
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
