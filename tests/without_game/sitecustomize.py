"""A base install inside the full one: tests/test_base_install.py puts this folder
on PYTHONPATH, so Python runs it at start in every process of a test, children
included (they inherit the environment), and refuses to import the modules that
UPCAST_REFUSE_MODULES names (the extra ``game``'s: torch, numba, ...), exactly as
if they were not installed.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence
from importlib.abc import MetaPathFinder
from importlib.machinery import ModuleSpec
from types import ModuleType


class RefuseModules(MetaPathFinder):
    def __init__(self, refused: frozenset[str]) -> None:
        self.refused = refused

    def find_spec(
        self,
        fullname: str,
        path: Sequence[str] | None,
        target: ModuleType | None = None,
    ) -> ModuleSpec | None:
        if fullname.partition(".")[0] in self.refused:
            # What a missing package raises; name= is what server.cli reads.
            raise ModuleNotFoundError(f"No module named {fullname!r}", name=fullname)
        return None  # not ours: the next finder looks


_refused = frozenset(filter(None, os.environ.get("UPCAST_REFUSE_MODULES", "").split(",")))
if _refused:
    sys.meta_path.insert(0, RefuseModules(_refused))
