"""README.md stays true: its config reference and its two commands."""

from __future__ import annotations

from pathlib import Path

from server.config_doc import markdown

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()


def test_config_reference_matches_the_models() -> None:
    begin = README.index("<!-- config:begin")
    start = README.index("\n", begin) + 1
    end = README.index("<!-- config:end -->")
    assert README[start:end] == markdown(), "regenerate with: python -m server.config_doc"


def test_the_two_commands_are_documented_and_ci_runs_the_test_one() -> None:
    assert "./dev up" in README and "./dev test" in README
    assert "./dev test" in (ROOT / ".ci" / "run").read_text()
    assert (ROOT / "dev").stat().st_mode & 0o111
