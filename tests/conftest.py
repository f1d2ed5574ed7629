from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Iterator

import pytest


@pytest.fixture
def ring_name() -> Iterator[str]:
    """A unique shared-memory name, removed after the test whatever happened."""
    name = f"upcast-test-{os.getpid()}-{uuid.uuid4().hex[:10]}"
    yield name
    for suffix in ("", "-r", "-u"):
        with contextlib.suppress(FileNotFoundError):
            os.unlink(f"/dev/shm/{name}{suffix}")
