"""Markdown reference of the pydantic configuration models, for docs/configuration.md.

``python -m server.config_doc`` prints it; tests/test_readme.py keeps the block in
docs/configuration.md in step with the models.
"""

from __future__ import annotations

from pydantic import BaseModel
from pydantic_core import PydanticUndefined

from server.relay.settings import RelaySettings
from server.serve.config import SessionOverride
from server.session.session_control import SessionControl
from server.stack.local import SessionConfig
from server.stream_config import StreamConfig
from server.worker.upscale import WorkerConfig

DOCUMENTED: tuple[tuple[str, type[BaseModel]], ...] = (
    ("upcast up / serve, the game session (SessionConfig)", SessionConfig),
    ("upcast up, streaming (StreamConfig)", StreamConfig),
    ("upcast serve --config, one entry per session (SessionOverride)", SessionOverride),
    ("upcast relay (RelaySettings; flags are the field names with dashes)", RelaySettings),
    ("upcast worker (WorkerConfig)", WorkerConfig),
    ("control request, run time (SessionControl; docs/control.schema.json)", SessionControl),
)


def _default(model: type[BaseModel], name: str) -> str:
    info = model.model_fields[name]
    if info.default_factory is not None:
        return "(generated)"
    if info.default is PydanticUndefined:
        return "(required)"
    return f"`{info.default}`"


def markdown() -> str:
    lines: list[str] = []
    for title, model in DOCUMENTED:
        lines += [f"**{title}**", "", "| field | default | meaning |", "|---|---|---|"]
        for name, info in model.model_fields.items():
            lines.append(f"| `{name}` | {_default(model, name)} | {info.description or ''} |")
        lines.append("")
    return "\n".join(lines).rstrip() + "\n"


if __name__ == "__main__":
    print(markdown(), end="")
