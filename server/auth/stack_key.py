"""The key of a command that owns its relay (``upcast up``, ``upcast serve``).

Given ``--auth-key PATH`` it is that file; otherwise a fresh key in a private
temporary directory that is removed when the command ends, so a local stack is
never an open relay and no secret outlives it.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from .keys import AuthKey, generate_key, load_key


@contextmanager
def stack_key(given: Path | None) -> Iterator[tuple[Path, AuthKey]]:
    """The key file and its key; raises KeyFileError (naming the file) when ``given`` is bad."""
    if given is not None:
        yield given, load_key(given)
        return
    with tempfile.TemporaryDirectory(prefix="upcast-key-") as tmp:
        path = Path(tmp) / "relay.jwk"
        generate_key(path)
        yield path, load_key(path)
