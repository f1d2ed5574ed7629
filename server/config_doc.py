"""Markdown references generated from the code: the pydantic configuration models for
docs/configuration.md, and every command's options (argparse) for docs/commands.md.

``python -m server.config_doc`` prints the first, ``--cli`` the second;
tests/test_readme.py keeps both blocks in step with the code.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

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


def _cell(text: str) -> str:
    """Table-safe: a pipe would end the cell, and ``<name>`` would read as an HTML tag."""
    return " ".join(text.split()).replace("|", "\\|").replace("<", "&lt;")


CHECKOUT = Path(__file__).resolve().parents[1]


def _portable(value: object) -> str:
    """Paths in the checkout as relative ones and under the home folder as ``~/...``:
    the same page wherever the project is checked out, whoever runs it."""
    text = str(value).replace(f"{CHECKOUT}/", "")
    return text.replace(f"{Path.home()}/", "~/")


def _options(parser: argparse.ArgumentParser) -> list[str]:
    rows = ["| option | default | meaning |", "|---|---|---|"]
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        flag = action.default is False and not action.option_strings[1:]
        shown = action.default in (None, argparse.SUPPRESS) or flag
        default = "" if shown else f"`{_portable(action.default)}`"
        meaning = action.help or ""
        if "%(" in meaning:
            meaning = meaning % {"default": action.default, "prog": parser.prog}
        names = ", ".join(f"`{name}`" for name in action.option_strings) or f"`{action.dest}`"
        rows.append(f"| {names} | {default} | {_cell(_portable(meaning))} |")
    return rows


def cli_markdown() -> str:
    """Every ``upcast`` command's options, and the names ``bench`` and ``eval`` take."""
    from server.cli import COMMANDS, build_parser
    from server.commands.bench import BENCHMARKS
    from server.commands.eval import EVALUATIONS

    lines: list[str] = []
    for name in COMMANDS:
        parser = build_parser(name)
        subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        lines += [f"### upcast {name}", "", *_options(subparsers.choices[name]), ""]
        choices = {"bench": BENCHMARKS, "eval": EVALUATIONS}.get(name)
        if choices:
            lines += [f"| {name} NAME | what it measures |", "|---|---|"]
            lines += [f"| `{key}` | {_cell(text)} |" for key, text in choices.items()]
            lines.append("")
    return "\n".join(lines).rstrip() + "\n"


if __name__ == "__main__":
    print(cli_markdown() if "--cli" in sys.argv[1:] else markdown(), end="")
