"""Commands with a second level (``upcast bench NAME``, ``upcast eval NAME``).

The chosen module under ``package`` provides ``add_arguments(parser)`` and
``run(args)``; only that module is imported, so each keeps its dependencies
to itself.
"""

from __future__ import annotations

import argparse
import importlib
from types import ModuleType

from server.commands.help_format import DefaultsHelpFormatter


def add_choice_arguments(
    parser: argparse.ArgumentParser, kind: str, choices: dict[str, str]
) -> None:
    parser.formatter_class = DefaultsHelpFormatter
    parser.epilog = f"{kind}s:\n" + "\n".join(f"  {k:10} {v}" for k, v in choices.items())
    parser.add_argument(
        "choice", metavar=kind.upper(), choices=sorted(choices), help=f"which {kind}"
    )
    parser.add_argument("options", nargs=argparse.REMAINDER, help="its options (NAME --help)")


def choice_module(package: str, name: str, modules: dict[str, str] | None = None) -> ModuleType:
    """Choice NAME's module: ``package.NAME``, or ``package.modules[NAME]`` for one that
    lives in a family's package."""
    return importlib.import_module(f"{package}.{(modules or {}).get(name, name)}")


def run_choice(
    command: str,
    package: str,
    choices: dict[str, str],
    args: argparse.Namespace,
    modules: dict[str, str] | None = None,
) -> int:
    name: str = args.choice
    module = choice_module(package, name, modules)
    sub = argparse.ArgumentParser(
        prog=f"upcast {command} {name}",
        description=choices[name],
        formatter_class=DefaultsHelpFormatter,
    )
    module.add_arguments(sub)
    return int(module.run(sub.parse_args(args.options)))
