"""The help format of every ``upcast`` command: each option's default is shown.

argparse's ArgumentDefaultsHelpFormatter appends ``(default: ...)`` to every option,
including flags (``default: False``) and options whose help already names its default
in words; this one appends it only where the help does not mention a default and
there is a value to show, and also for options declared without any help text
(argparse would print nothing for those). Descriptions and epilogs keep their line
breaks (the ``bench``/``eval`` choice lists).
"""

from __future__ import annotations

import argparse
import copy


def _has_value_default(action: argparse.Action) -> bool:
    if action.default is None or action.default is argparse.SUPPRESS:
        return False
    if action.nargs == 0:  # store_true/false, help, version: the flag itself says it
        return False
    return bool(action.option_strings) or action.nargs in (argparse.OPTIONAL, "*")


class DefaultsHelpFormatter(argparse.RawDescriptionHelpFormatter):
    def _format_action(self, action: argparse.Action) -> str:
        if not (action.help or "").strip() and _has_value_default(action):
            action = copy.copy(action)
            action.help = "default: %(default)s"  # argparse prints no column for no help
        return super()._format_action(action)

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if action.help == argparse.SUPPRESS or "default" in text.lower():
            return action.help
        if not _has_value_default(action):
            return action.help
        return f"{text} (default: %(default)s)"
