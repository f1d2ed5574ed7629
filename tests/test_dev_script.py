"""``./dev``: help answers at once, before any setup (no .venv, no npm, no numba)."""

from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
def fresh_clone(tmp_path: Path) -> Path:
    """The dev script and the CLI package, without .venv: what a fresh clone has."""
    shutil.copy2(ROOT / "dev", tmp_path / "dev")
    shutil.copytree(
        ROOT / "server", tmp_path / "server", ignore=shutil.ignore_patterns("__pycache__")
    )
    return tmp_path


def _dev(root: Path, *args: str) -> tuple[subprocess.CompletedProcess[str], float]:
    t0 = time.perf_counter()
    # System python3, as on a machine where nothing was installed yet.
    done = subprocess.run(
        [str(root / "dev"), *args], capture_output=True, text=True, timeout=30, check=False
    )
    return done, time.perf_counter() - t0


@pytest.mark.parametrize("args", [("up", "--help"), ("up", "-h", "--fps", "30")])
def test_up_help_answers_at_once_without_setup(fresh_clone: Path, args: tuple[str, ...]) -> None:
    done, took = _dev(fresh_clone, *args)
    assert done.returncode == 0, done.stderr
    assert "usage: upcast up" in done.stdout
    assert "--render-size" in done.stdout and "default" in done.stdout
    assert not (fresh_clone / ".venv").exists(), "help must not set anything up"
    assert "setup:" not in done.stderr
    assert took < 5.0


def test_test_help_and_bare_dev_say_what_each_command_does(fresh_clone: Path) -> None:
    done, _ = _dev(fresh_clone, "test", "--help")
    assert done.returncode == 0
    assert "pytest" in done.stdout and "up " in done.stdout
    for args, code in (((), 2), (("--help",), 0)):
        done, _ = _dev(fresh_clone, *args)
        assert done.returncode == code
        assert "up     start the game" in done.stdout
        assert "test   run the whole test suite" in done.stdout
        assert "g++" in done.stdout  # the prerequisites
    assert not (fresh_clone / ".venv").exists()
