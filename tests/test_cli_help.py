"""Every ``upcast`` command's ``--help`` shows each option's default value."""

from __future__ import annotations

import argparse
import importlib

import pytest

from server.cli import COMMANDS, build_parser
from server.commands.dispatch import choice_module
from server.commands.help_format import DefaultsHelpFormatter


def _subparser(parser: argparse.ArgumentParser, name: str) -> argparse.ArgumentParser:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            sub: argparse.ArgumentParser = action.choices[name]
            return sub
    raise KeyError(name)


def _missing_defaults(parser: argparse.ArgumentParser) -> list[str]:
    """Options with a value default whose help text does not show it."""
    formatter = parser._get_formatter()
    missing = []
    for action in parser._actions:
        if not action.option_strings or action.nargs == 0 or action.help == argparse.SUPPRESS:
            continue
        if action.default is None or action.default is argparse.SUPPRESS:
            continue
        if "default" not in formatter._format_action(action).lower():
            missing.append(action.option_strings[-1])
    return missing


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_command_shows_its_defaults(command: str) -> None:
    sub = _subparser(build_parser(command), command)
    assert sub.formatter_class is DefaultsHelpFormatter
    assert _missing_defaults(sub) == []


@pytest.mark.parametrize(
    ("command", "table", "modules"),
    [("bench", "BENCHMARKS", "BENCH_MODULES"), ("eval", "EVALUATIONS", None)],
)
def test_every_bench_and_eval_shows_its_defaults(
    command: str, table: str, modules: str | None
) -> None:
    package = f"server.{command}"
    commands = importlib.import_module(f"server.commands.{command}")
    choices: dict[str, str] = getattr(commands, table)
    where: dict[str, str] | None = getattr(commands, modules) if modules else None
    missing = {}
    for name in choices:
        sub = argparse.ArgumentParser(prog=name, formatter_class=DefaultsHelpFormatter)
        choice_module(package, name, where).add_arguments(sub)
        missing[name] = _missing_defaults(sub)
    assert {name: opts for name, opts in missing.items() if opts} == {}


def test_the_value_itself_is_printed() -> None:
    text = _subparser(build_parser("up"), "up").format_help()
    for shown in ("(default: 4443)", "(default: bilinear)", "(default: 1280x720)"):
        assert shown in " ".join(text.split()), shown
    assert "(default: False)" not in text
