"""The base install (no extra ``game``) runs the relay side: relay, token, control,
loadtest and the synthetic publisher, and a game command on it names the extra.

Every process here runs with the extra's modules refused at import
(``tests/without_game/sitecustomize.py``), as on ``pip install upcast`` without
``[game]``: a relay, a synthetic publisher and load-test viewers stream frames
through real QUIC, ``upcast control`` sends a request through that relay, and the
relay-side commands import all they name.
"""

from __future__ import annotations

import ast
import json
import os
import re
import subprocess
import sys
import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest

from server.commands.extras import GAME_MODULES, INSTALL
from server.relay.process import RelayProcess

ROOT = Path(__file__).resolve().parents[1]
WITHOUT_GAME = ROOT / "tests" / "without_game"
BASE_COMMANDS = ("relay", "token", "control", "loadtest")
# The packages the relay side is made of: every module in them imports on the base.
BASE_PACKAGES = ("auth", "frames", "loadtest", "media", "moq", "quic", "relay")


def _base_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(WITHOUT_GAME), env.get("PYTHONPATH")]))
    env["UPCAST_REFUSE_MODULES"] = ",".join(sorted(GAME_MODULES))
    return env


def _python(*argv: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, *argv],
        env=_base_env(),
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _requirement_name(requirement: str) -> str:
    return re.split(r"[\s<>=!~\[;]", requirement, maxsplit=1)[0].lower()


def test_the_game_modules_are_the_extra_s_packages() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    game = {_requirement_name(r) for r in project["optional-dependencies"]["game"]}
    base = {_requirement_name(r) for r in project["dependencies"]}
    assert set(GAME_MODULES.values()) == game
    assert not base & game


def test_the_manual_says_which_install_brings_each_package() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    wanted = {_requirement_name(r): "base" for r in project["dependencies"]}
    for extra, requirements in project["optional-dependencies"].items():
        wanted |= {_requirement_name(r): extra for r in requirements}
    manual = (ROOT / "docs" / "dependencies.md").read_text()
    table = manual[manual.index("# Dependencies and why") :].split("\n\n")[2]
    said: dict[str, str] = {}
    for row in table.splitlines()[2:]:
        packages, install = (cell.strip() for cell in row.split("|")[1:3])
        said |= {p.split()[0].lower(): install for p in packages.split(",")}
    assert said == wanted


@pytest.mark.parametrize("module", sorted(GAME_MODULES))
def test_each_game_module_is_refused(module: str) -> None:
    # A module loaded before the refusal (by a .pth file, say) would slip through.
    result = _python("-c", f"import sys; assert {module!r} not in sys.modules; import {module}")
    assert "ModuleNotFoundError" in result.stderr, result.stderr


def _named_modules(command: str) -> Iterator[str]:
    """Every server.*/upscalers.* module the command's file imports, functions included."""
    path = ROOT / "server" / "commands" / f"{command}.py"
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        else:
            continue
        yield from (n for n in names if n.partition(".")[0] in ("server", "upscalers"))


@pytest.mark.parametrize("command", BASE_COMMANDS)
def test_a_base_command_imports_all_it_names(command: str) -> None:
    modules = sorted({f"server.commands.{command}", *_named_modules(command)})
    result = _python("-c", "; ".join(f"import {m}" for m in modules))
    assert result.returncode == 0, result.stderr
    result = _python("-m", "server.cli", command, "--help")
    assert result.returncode == 0, result.stderr


def test_every_module_of_the_relay_side_packages_imports_on_the_base() -> None:
    modules = [
        ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        for package in BASE_PACKAGES
        for path in sorted((ROOT / "server" / package).rglob("*.py"))
    ]
    result = _python("-c", "; ".join(f"import {m}" for m in modules))
    assert result.returncode == 0, result.stderr


@pytest.mark.parametrize(
    "argv",
    [["render", "--scene", "static", "--out", "unused"], ["eval", "upscalers", "--help"]],
    ids=lambda argv: argv[0],
)
def test_a_game_command_names_the_extra(argv: list[str]) -> None:
    result = _python("-m", "server.cli", *argv)
    assert result.returncode == 2
    assert f"upcast {argv[0]}: needs the extra 'game'" in result.stderr
    assert INSTALL in result.stderr and "Traceback" not in result.stderr


def test_relay_synthetic_publisher_and_viewers_stream_without_the_game_extra(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The relay child inherits os.environ: the same refusal as every process here.
    for name, value in _base_env().items():
        monkeypatch.setenv(name, value)
    relay = RelayProcess("127.0.0.1", 0)
    endpoint = relay.start()
    try:
        report_path = tmp_path / "loadtest.json"
        # upcast loadtest starts the synthetic publisher (python -m
        # server.loadtest.synthetic, its own process) and runs the viewers. The verdict's
        # fps and latency bars are lowered: 2 shared cores are not the point here.
        result = _python(
            "-m", "server.cli", "loadtest",
            "--relay", f"http://127.0.0.1:{endpoint.port}/",
            "--cert-hash", endpoint.cert_sha256,
            "--synthetic-publisher", "--size", "320x180", "--fps", "30",
            "--viewers", "2", "--duration", "3", "--warmup", "1",
            "--min-fps", "1", "--max-p95-ms", "10000",
            "--json", str(report_path), "--quiet",
            timeout=120.0,
        )  # fmt: skip
        # upcast control checks its request here and sends it through the relay; no
        # session is left to answer it (the synthetic publisher has none).
        control = ["-m", "server.cli", "control", "--relay", f"http://127.0.0.1:{endpoint.port}/"]
        control += ["--cert-sha256", endpoint.cert_sha256, "--broadcast", "game"]
        refused = _python(*control, "--cache-policy", "delta@-1")
        unanswered = _python(*control, "--cache-policy", "delta_l", "--timeout", "1")
    finally:
        relay.stop()
    assert refused.returncode == 2 and "cache_policy" in refused.stderr, refused.stderr
    assert unanswered.returncode == 1, unanswered.stderr
    assert "broadcast 'game' has no status track" in unanswered.stderr, unanswered.stderr
    assert result.returncode == 0, result.stdout + result.stderr
    assert "ModuleNotFoundError" not in result.stderr
    cases = {case["name"]: case for case in json.loads(report_path.read_text())["cases"]}
    summary = cases["summary"]
    assert summary["connected"] == 2 and summary["failed"] == 0, summary
    for viewer in ("viewer 0", "viewer 1"):
        assert cases[viewer]["frames"] > 0, cases[viewer]
