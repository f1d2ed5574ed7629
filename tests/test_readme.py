"""README.md and the manual stay true: the config reference and the two commands."""

from __future__ import annotations

from pathlib import Path

from server.config_doc import cli_markdown, markdown

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()
CONFIGURATION = (ROOT / "docs" / "configuration.md").read_text()
COMMANDS = (ROOT / "docs" / "commands.md").read_text()


def test_config_reference_matches_the_models() -> None:
    begin = CONFIGURATION.index("<!-- config:begin")
    start = CONFIGURATION.index("\n", begin) + 1
    end = CONFIGURATION.index("<!-- config:end -->")
    assert CONFIGURATION[start:end] == markdown(), (
        "regenerate the block in docs/configuration.md with: python -m server.config_doc"
    )


def test_command_reference_matches_the_parsers() -> None:
    begin = COMMANDS.index("<!-- cli:begin")
    start = COMMANDS.index("\n", begin) + 1
    end = COMMANDS.index("<!-- cli:end -->")
    assert COMMANDS[start:end] == cli_markdown(), (
        "regenerate the block in docs/commands.md with: python -m server.config_doc --cli"
    )


def test_the_two_commands_are_documented_and_ci_runs_the_test_one() -> None:
    assert "./dev up" in README and "./dev test" in README
    assert "./dev test" in (ROOT / ".ci" / "run").read_text()
    assert (ROOT / "dev").stat().st_mode & 0o111


def test_the_prerequisites_are_all_named() -> None:
    """A newcomer's machine needs each of these before ./dev runs; .ci/run installs them."""
    setup = README[README.index("## The two commands") : README.index("## What is here")]
    for need in ("Python 3.11", "venv", "Node.js", "npm", "g++", "Chromium"):
        assert need in setup, need
    ci = (ROOT / ".ci" / "run").read_text()
    for package in ("g++", "chromium", "npm"):
        assert package in ci and package in setup


def test_one_url_parameter_names_the_broadcast_and_the_alias_is_said() -> None:
    """The page takes ?broadcast= (documented) and ?name= (an alias, said so); every
    URL in the docs uses the documented one."""
    config = (ROOT / "client_web" / "src" / "config.ts").read_text()
    assert 'query.get("broadcast") ?? query.get("name")' in config
    assert "`name` is accepted as an alias" in README
    docs = [README, (ROOT / "deploy" / "README.md").read_text()]
    docs.append((ROOT / "docker-compose.yml").read_text())
    docs += [page.read_text() for page in sorted((ROOT / "docs").rglob("*.md"))]
    for text in docs:
        for line in text.splitlines():
            if "localhost:" in line and "?" in line:
                assert "?name=" not in line and "&name=" not in line, line
