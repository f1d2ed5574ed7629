"""The docker compose stack's files, checked without a Docker engine.

deploy/smoke.sh builds and runs the stack for real (.ci/run runs it after the test
suite); these checks run everywhere, fast. What they cover is listed in
deploy/README.md: the compose files parse and
have the shape used, every `upcast ...` command in them and in the Dockerfiles is
parsed by the real CLI parser, every COPY source exists, the health-check URLs are
routes the processes serve, ports agree between flags, mappings, health checks and
the Prometheus targets, the moq-relay cluster TOMLs parse and share the key, and
every metric the Grafana dashboard queries is exported by a process; the offline
build arguments (base image, wheelhouse, prebuilt web client) are wired the same way
in every Dockerfile and override, and the smoke test's host-network override runs
the base file's commands on loopback.
"""

from __future__ import annotations

import asyncio
import importlib.util
import json
import re
import shlex
import tomllib
import urllib.parse
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from prometheus_client import CollectorRegistry

from server.cli import COMMANDS, build_parser
from server.commands.serve import METRICS_PORTS_PER_SESSION
from server.serve.http_api import ServeHttp

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "docker-compose.yml"
CUDA_OVERRIDE = ROOT / "deploy" / "docker-compose.cuda.yml"
CLUSTER_OVERRIDE = ROOT / "deploy" / "cluster" / "docker-compose.cluster.yml"
OFFLINE_OVERRIDE = ROOT / "deploy" / "docker-compose.offline.yml"
HOSTNET_OVERRIDE = ROOT / "deploy" / "docker-compose.hostnet.yml"
OVERRIDES = (CUDA_OVERRIDE, CLUSTER_OVERRIDE, OFFLINE_OVERRIDE, HOSTNET_OVERRIDE)
DOCKERFILES = sorted((ROOT / "deploy").rglob("*.Dockerfile"))
KEY_PATH = "/secrets/auth.key"
WEB_DIST = "client_web/dist"  # where ./dev (client_web/build.mjs) writes the web client

# Every upcast subcommand the deployment runs.
EXPECTED_COMMANDS = {"relay", "serve", "token"}

DOCKERFILE_INSTRUCTIONS = {
    "FROM", "RUN", "CMD", "LABEL", "EXPOSE", "ENV", "ADD", "COPY", "ENTRYPOINT",
    "VOLUME", "USER", "WORKDIR", "ARG", "ONBUILD", "STOPSIGNAL", "HEALTHCHECK", "SHELL",
}  # fmt: skip
SHELL_SEPARATORS = {"&&", "||", ";", "|"}


class Reset:
    """Compose's ``!reset`` tag: the override clears the base file's value."""

    def __repr__(self) -> str:
        return "!reset"


class ComposeLoader(yaml.SafeLoader):
    pass


ComposeLoader.add_constructor("!reset", lambda loader, node: Reset())


def load_yaml(path: Path) -> dict[str, Any]:
    # ComposeLoader is a SafeLoader with one more tag: as safe as safe_load.
    data = yaml.load(path.read_text(), Loader=ComposeLoader)
    assert isinstance(data, dict), path
    return data


def services(path: Path) -> dict[str, dict[str, Any]]:
    found = load_yaml(path)["services"]
    assert isinstance(found, dict) and found
    return found


def merged_services(*paths: Path) -> dict[str, dict[str, Any]]:
    """Compose's merge rules, as far as these files need them: mappings merge key by
    key, volumes merge by mount target, ports and expose add up, other fields
    (command, entrypoint, image) are replaced."""
    result: dict[str, dict[str, Any]] = {}
    for path in paths:
        for name, service in services(path).items():
            base = result.setdefault(name, {})
            for key, value in service.items():
                if isinstance(value, Reset):
                    base.pop(key, None)
                elif isinstance(value, dict) and isinstance(base.get(key), dict):
                    base[key] = {**base[key], **value}
                elif key == "volumes" and key in base:
                    by_target = {v.split(":")[1]: v for v in [*base[key], *value]}
                    base[key] = list(by_target.values())
                elif key in ("ports", "expose") and key in base:
                    base[key] = list(dict.fromkeys([*base[key], *value]))
                else:
                    base[key] = value
    return result


# -- the commands ------------------------------------------------------------------


def upcast_argvs(command: Any) -> Iterator[list[str]]:
    """Each ``upcast ...`` argv in a compose command or Dockerfile exec form, also
    inside ``sh -c "..."`` (split at shell separators and redirections)."""
    if command is None:
        return
    argv = shlex.split(command) if isinstance(command, str) else [str(a) for a in command]
    if argv[:1] == ["upcast"]:
        yield argv
        return
    for i, arg in enumerate(argv):
        if arg == "-c" and i + 1 < len(argv):
            yield from _upcast_in_shell(argv[i + 1])


def _upcast_in_shell(script: str) -> Iterator[list[str]]:
    lexer = shlex.shlex(script, posix=True, punctuation_chars=";&|>")
    lexer.whitespace_split = True
    current: list[str] = []
    for token in [*lexer, ";"]:
        if token in SHELL_SEPARATORS or token.startswith(">"):
            if current[:1] == ["upcast"]:
                yield current
            current = [] if token in SHELL_SEPARATORS else ["<redirect>"]
        else:
            current.append(token)


def dockerfile_instructions(path: Path) -> list[tuple[str, str]]:
    """(KEYWORD, arguments) per instruction, continuation lines joined."""
    out: list[tuple[str, str]] = []
    pending = ""
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not pending and (not line or line.startswith("#")):
            continue
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        line, pending = pending + line, ""
        keyword, _, rest = line.partition(" ")
        out.append((keyword, rest.strip()))
    assert not pending, f"{path.name}: a continuation line ends the file"
    return out


def exec_form(path: Path, keyword: str, arguments: str) -> list[str]:
    try:
        value = json.loads(arguments)
    except json.JSONDecodeError as exc:
        raise AssertionError(f"{path.name}: {keyword} {arguments!r} is not JSON: {exc}") from None
    assert isinstance(value, list) and all(isinstance(v, str) for v in value), arguments
    return value


def dockerfile_commands(path: Path) -> list[list[str]]:
    commands = []
    for keyword, arguments in dockerfile_instructions(path):
        if keyword in ("CMD", "ENTRYPOINT"):
            commands.append(exec_form(path, keyword, arguments))
        elif keyword == "HEALTHCHECK":
            _, _, cmd = arguments.partition("CMD ")
            commands.append(exec_form(path, keyword, cmd.strip()))
    return commands


def compose_commands() -> list[tuple[str, list[str]]]:
    found = []
    for path in (COMPOSE, *OVERRIDES):
        for name, service in services(path).items():
            for argv in upcast_argvs(service.get("command")):
                found.append((f"{path.name}:{name}", argv))
    for path in DOCKERFILES:
        for command in dockerfile_commands(path):
            for argv in upcast_argvs(command):
                found.append((path.name, argv))
    return found


def subcommand_of(argv: list[str]) -> str:
    words = [a for a in argv[1:] if not a.startswith("-")]
    # `upcast --log-format json relay ...`: the option's value is not the command.
    if "--log-format" in argv:
        words.remove(argv[argv.index("--log-format") + 1])
    return words[0]


ALL_COMMANDS = compose_commands()


def test_the_deployment_runs_the_expected_commands() -> None:
    used = {subcommand_of(argv) for _, argv in ALL_COMMANDS}
    assert used == EXPECTED_COMMANDS, used


@pytest.mark.parametrize(
    "argv", [argv for _, argv in ALL_COMMANDS], ids=[where for where, _ in ALL_COMMANDS]
)
def test_every_upcast_command_parses_with_the_real_cli(argv: list[str]) -> None:
    name = subcommand_of(argv)
    assert name in EXPECTED_COMMANDS and name in COMMANDS
    parser = build_parser(name)
    args = parser.parse_args([a for a in argv[1:] if a != "<redirect>"])
    assert args.command == name


# -- compose shape -----------------------------------------------------------------


@pytest.mark.parametrize("path", [COMPOSE, *OVERRIDES], ids=lambda p: p.name)
def test_compose_file_shape(path: Path) -> None:
    data = load_yaml(path)
    assert set(data) <= {"name", "services", "volumes", "networks", "configs", "secrets"}
    merged = merged_services(COMPOSE, path) if path != COMPOSE else services(COMPOSE)
    declared = set(load_yaml(COMPOSE).get("volumes", {}))
    for name, service in merged.items():
        assert "image" in service or "build" in service, name
        build = service.get("build")
        if build is not None:
            # Paths resolve from the project directory (the first file's), the repo root.
            assert (ROOT / build["context"]).is_dir(), name
            assert (ROOT / build["context"] / build["dockerfile"]).is_file(), name
        for volume in service.get("volumes", []):
            source = volume.split(":")[0]
            if source.startswith((".", "/")):
                assert (ROOT / source).exists(), f"{name}: {source} missing"
            else:
                assert source in declared, f"{name}: volume {source} not declared"
        depends_on = service.get("depends_on") or {}
        if isinstance(depends_on, list):  # the short form: started, no condition
            depends_on = dict.fromkeys(depends_on)
        for target, condition in depends_on.items():
            assert target in merged, f"{name} depends on unknown {target}"
            wanted = condition["condition"] if isinstance(condition, dict) else None
            assert wanted in (
                "service_healthy",
                "service_completed_successfully",
                "service_started",
                None,
            )
            if wanted == "service_healthy":
                assert "test" in merged[target].get("healthcheck", {}), target
        for port in service.get("ports", []):
            assert re.fullmatch(r"\d+:\d+(/(tcp|udp))?", port), port


def flag(argv: list[str], name: str) -> str:
    return argv[argv.index(name) + 1]


def compose_argv(service: str, path: Path = COMPOSE) -> list[str]:
    (argv,) = upcast_argvs(services(path)[service]["command"])
    return argv


def test_ports_agree_between_flags_mappings_health_checks_and_prometheus() -> None:
    all_services = services(COMPOSE)
    relay_port = flag(compose_argv("relay"), "--port")
    assert set(all_services["relay"]["ports"]) == {
        f"{relay_port}:{relay_port}/udp",
        f"{relay_port}:{relay_port}/tcp",
    }
    relay_health = urllib.parse.urlsplit(all_services["relay"]["healthcheck"]["test"][-1])
    assert str(relay_health.port) == relay_port
    session_argv = compose_argv("session")
    http_port = flag(session_argv, "--http-port")
    sessions = int(flag(session_argv, "--sessions"))
    assert all_services["session"]["expose"] == [http_port]
    session_health = urllib.parse.urlsplit(all_services["session"]["healthcheck"]["test"][-1])
    assert str(session_health.port) == http_port
    relay_url = urllib.parse.urlsplit(flag(session_argv, "--relay"))
    assert relay_url.hostname == "relay" and str(relay_url.port) == relay_port
    # The session pins the relay's self-signed certificate: http:// fetches its hash.
    assert relay_url.scheme == "http"

    scrape = load_yaml(ROOT / "deploy" / "prometheus" / "prometheus.yml")
    targets = {
        job["job_name"]: sorted(target for c in job["static_configs"] for target in c["targets"])
        for job in scrape["scrape_configs"]
    }
    # serve's port scheme (server/commands/serve.py): session i's block of three ports
    # (session, game, worker) starts at http-port + 3i - 2.
    blocks = [int(http_port) + 1 + METRICS_PORTS_PER_SESSION * i for i in range(sessions)]
    assert targets == {
        "relay": [f"relay:{relay_port}"],
        "serve": [f"session:{http_port}"],
        "session": [f"session:{b}" for b in blocks],
        "game": [f"session:{b + 1}" for b in blocks],
        "worker": [f"session:{b + 2}" for b in blocks],
    }


def test_the_key_file_is_made_once_and_shared() -> None:
    all_services = services(COMPOSE)
    (generate,) = upcast_argvs(all_services["keys"]["command"])
    assert generate[1:3] == ["token", "generate"] and flag(generate, "--key") == KEY_PATH
    assert "test -s /secrets/auth.key ||" in all_services["keys"]["command"][-1]
    for name in ("relay", "session"):
        assert flag(compose_argv(name), "--auth-key") == KEY_PATH
        assert "secrets:/secrets:ro" in all_services[name]["volumes"]
        assert all_services[name]["depends_on"]["keys"] == {
            "condition": "service_completed_successfully"
        }


# -- Dockerfiles -------------------------------------------------------------------


@pytest.mark.parametrize("path", DOCKERFILES, ids=lambda p: p.name)
def test_dockerfile_syntax_and_copied_files(path: Path) -> None:
    instructions = dockerfile_instructions(path)
    keywords = [k for k, _ in instructions]
    assert set(keywords) <= DOCKERFILE_INSTRUCTIONS, set(keywords) - DOCKERFILE_INSTRUCTIONS
    assert keywords[0] in ("FROM", "ARG"), "a Dockerfile starts with FROM (or ARG)"
    stages: set[str] = set()
    for keyword, arguments in instructions:
        if keyword == "FROM":
            words = arguments.split()
            if len(words) == 3 and words[1].upper() == "AS":
                stages.add(words[2])
        elif keyword in ("COPY", "ADD"):
            words = shlex.split(arguments)
            options = [w for w in words if w.startswith("--")]
            *sources, _dest = [w for w in words if not w.startswith("--")]
            assert sources, arguments
            from_stage = [o.split("=", 1)[1] for o in options if o.startswith("--from=")]
            if from_stage:
                assert from_stage[0] in stages, f"{path.name}: unknown stage {from_stage}"
                continue
            for source in sources:
                # The web client's build output is not in a fresh clone: ./dev builds it.
                built = source.rstrip("/") == WEB_DIST
                assert built or (ROOT / source).exists(), (
                    f"{path.name}: COPY {source}: not in the repo"
                )
                assert not _docker_ignored(source), f"{path.name}: {source} is .dockerignored"
        elif keyword in ("CMD", "ENTRYPOINT"):
            exec_form(path, keyword, arguments)
        elif keyword == "HEALTHCHECK":
            assert "CMD " in arguments, arguments
            exec_form(path, keyword, arguments.partition("CMD ")[2].strip())


def _docker_ignored(source: str) -> bool:
    patterns = [
        line.strip()
        for line in (ROOT / ".dockerignore").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    source = source.rstrip("/")
    return any(source == p or source.startswith(p + "/") for p in patterns)


def test_the_relay_serves_the_web_client_its_image_builds() -> None:
    web_root = flag(compose_argv("relay"), "--web-root")
    relay_dockerfile = ROOT / "deploy" / "relay.Dockerfile"
    copies = [a for k, a in dockerfile_instructions(relay_dockerfile) if k == "COPY"]
    assert f"--from=web /src/client_web/dist/ {web_root}/" in copies
    (cmd,) = [c for c in dockerfile_commands(relay_dockerfile) if c[0] == "upcast"]
    assert flag(cmd, "--web-root") == web_root


def _pip_installs(path: Path) -> list[tuple[str, list[str]]]:
    """(the RUN's arguments, the words after ``pip install``) for every ``pip install``
    in a RUN, also after ``&&`` or inside ``if ...; fi &&``."""
    found = []
    for keyword, arguments in dockerfile_instructions(path):
        if keyword != "RUN":
            continue
        words = shlex.split(arguments.replace(";", " ; "))
        for i in range(len(words) - 1):
            if words[i : i + 2] == ["pip", "install"]:
                rest = words[i + 2 :]
                end = next((j for j, w in enumerate(rest) if w in SHELL_SEPARATORS), len(rest))
                found.append((arguments, rest[:end]))
    return found


def _project_installs(path: Path) -> list[str]:
    """What each ``pip install`` of the project itself installs: ``.`` or ``.[extra]``."""
    return [w for _, words in _pip_installs(path) for w in words if w == "." or w.startswith(".[")]


@pytest.mark.parametrize(
    ("name", "install"),
    [("relay", "."), ("session", ".[game]"), ("session-cuda", ".[game]")],
)
def test_each_image_installs_the_extra_its_commands_need(name: str, install: str) -> None:
    # The relay image runs relay and token: the base install, no torch at all.
    path = ROOT / "deploy" / f"{name}.Dockerfile"
    assert _project_installs(path) == [install]
    if install == ".":
        assert "torch" not in " ".join(a for k, a in dockerfile_instructions(path) if k == "RUN")


# -- offline builds (build arguments) ----------------------------------------------------

# The images of the default stack: what deploy/docker-compose.offline.yml builds offline.
OFFLINE_DOCKERFILES = [ROOT / "deploy" / "relay.Dockerfile", ROOT / "deploy" / "session.Dockerfile"]
ONLINE_BASE = "python:3.11-slim-bookworm"
WHEELHOUSE = "deploy/wheelhouse"
BUILD_ARG_VALUES = {"PYTHON_SOURCE": {"pypi", "wheelhouse"}, "WEB_SOURCE": {"npm", "prebuilt"}}


def _arg_defaults(path: Path) -> dict[str, str]:
    """ARG NAME=default of a Dockerfile (global and per stage; no default: "")."""
    found = {}
    for keyword, arguments in dockerfile_instructions(path):
        if keyword == "ARG":
            name, _, default = arguments.partition("=")
            found[name] = default
    return found


def _offline_args() -> dict[str, dict[str, str]]:
    return {
        name: service["build"]["args"]
        for name, service in services(OFFLINE_OVERRIDE).items()
        if "build" in service
    }


@pytest.mark.parametrize("path", OFFLINE_DOCKERFILES, ids=lambda p: p.name)
def test_python_stages_take_the_base_image_argument(path: Path) -> None:
    # A `# syntax=` line makes BuildKit pull its frontend image: offline, the build fails.
    assert not path.read_text().startswith("# syntax"), path.name
    instructions = dockerfile_instructions(path)
    assert instructions[0] == ("ARG", f"BASE_IMAGE={ONLINE_BASE}")
    froms = [a.split()[0] for k, a in instructions if k == "FROM"]
    # Every stage is the base, the Node image (online web build) or a stage chosen
    # by WEB_SOURCE; the final (runtime) stage is always the base.
    assert froms[-1] == "${BASE_IMAGE}"
    assert set(froms) <= {"${BASE_IMAGE}", "${NODE_IMAGE}", "web-${WEB_SOURCE}"}, froms
    assert "python:" not in " ".join(froms)


@pytest.mark.parametrize("path", OFFLINE_DOCKERFILES, ids=lambda p: p.name)
def test_every_pip_install_can_take_the_wheelhouse(path: Path) -> None:
    assert _arg_defaults(path)["PYTHON_SOURCE"] == "pypi"
    installs = _pip_installs(path)
    assert installs
    for run, _words in installs:
        # Bind-mounted (no wheel in a layer) from the folder the smoke test fills, and
        # pip told to use only it when PYTHON_SOURCE=wheelhouse.
        assert run.startswith(f"--mount=type=bind,source={WHEELHOUSE},target=/wheelhouse "), run
        offline = 'if [ "$PYTHON_SOURCE" = wheelhouse ]; then'
        assert f"{offline} export PIP_NO_INDEX=1 PIP_FIND_LINKS=/wheelhouse;" in " ".join(
            run.split()
        ), run
    # The folder is in the build context (a bind mount of a missing source fails the
    # build, online too) while its wheels stay out of git.
    assert (ROOT / WHEELHOUSE).is_dir() and not _docker_ignored(WHEELHOUSE)
    gitignore = (ROOT / ".gitignore").read_text().splitlines()
    assert f"/{WHEELHOUSE}/*" in gitignore and f"!/{WHEELHOUSE}/README.md" in gitignore


def test_the_relay_web_stage_is_built_or_taken_prebuilt() -> None:
    path = ROOT / "deploy" / "relay.Dockerfile"
    assert _arg_defaults(path)["WEB_SOURCE"] == "npm"
    instructions = dockerfile_instructions(path)
    stages = {a.split()[2]: a.split()[0] for k, a in instructions if k == "FROM" and " AS " in a}
    assert stages["web"] == "web-${WEB_SOURCE}"
    for value in BUILD_ARG_VALUES["WEB_SOURCE"]:
        assert f"web-{value}" in stages, value
    # prebuilt: the host's ./dev build (build.mjs writes WEB_ROOT), where npm puts it.
    from server.ops.browser_paths import WEB_ROOT

    assert WEB_ROOT == ROOT / WEB_DIST
    assert f"{WEB_DIST}/ /src/client_web/dist/" in [a for k, a in instructions if k == "COPY"]
    assert not _docker_ignored(WEB_DIST)


def test_the_offline_override_sets_every_build_argument() -> None:
    args = _offline_args()
    merged = merged_services(COMPOSE, OFFLINE_OVERRIDE)
    # Every image the default stack builds; the optional `web` (profile static-web)
    # serves from nginx's upstream image and has no offline build.
    built = {name for name, s in merged.items() if "build" in s and not s.get("profiles")}
    assert set(args) == built
    base_default = re.search(r'tag="\$\{1:-([^}]+)\}"', (ROOT / "deploy/base-image.sh").read_text())
    assert base_default is not None
    for name, service_args in args.items():
        dockerfile = ROOT / merged[name]["build"]["dockerfile"]
        declared = _arg_defaults(dockerfile)
        assert set(service_args) <= set(declared), (name, set(service_args) - set(declared))
        assert service_args["BASE_IMAGE"] == f"${{UPCAST_BASE_IMAGE:-{base_default[1]}}}"
        assert service_args["PYTHON_SOURCE"] == "wheelhouse"
        for arg, values in BUILD_ARG_VALUES.items():
            if arg in service_args:
                assert service_args[arg] in values, (name, arg)


# -- the smoke test's stack ---------------------------------------------------------------


def test_the_host_network_override_runs_the_base_commands_on_loopback() -> None:
    base = services(COMPOSE)
    merged = merged_services(COMPOSE, HOSTNET_OVERRIDE)
    assert {n for n, s in services(HOSTNET_OVERRIDE).items()} == {"keys", "relay", "session"}
    for name in ("keys", "relay", "session"):
        assert merged[name]["network_mode"] == "host", name
        assert "ports" not in merged[name] and "expose" not in merged[name], name
    assert merged["keys"]["command"] == base["keys"]["command"]
    # The relay: the base command with its bind address on loopback.
    relay = compose_argv("relay", HOSTNET_OVERRIDE)
    want = compose_argv("relay")
    want[want.index("--host") + 1] = "127.0.0.1"
    assert relay == want
    # The session: the base command plus --host (its HTTP side and metrics ports) and
    # the frame tap the smoke test's picture check reads.
    session = compose_argv("session", HOSTNET_OVERRIDE)
    tap = ["--frame-tap-port", flag(session, "--frame-tap-port")]
    assert session == [*compose_argv("session"), "--host", "127.0.0.1", *tap]
    relay_host = urllib.parse.urlsplit(flag(session, "--relay")).hostname
    assert merged["session"]["extra_hosts"] == [f"{relay_host}:127.0.0.1"]


def test_the_smoke_test_knows_the_stack_it_runs() -> None:
    script = (ROOT / "deploy" / "smoke.sh").read_text()
    files = re.search(r'COMPOSE_FILE="([^"]+)"', script)
    assert files is not None
    assert [ROOT / f for f in files[1].split(":")] == [COMPOSE, OFFLINE_OVERRIDE, HOSTNET_OVERRIDE]
    # The ports it checks are free: the relay's, serve's, every session's block and
    # every session's frame tap.
    ports = re.search(r"PORTS=\(([\d ]+)\)", script)
    assert ports is not None
    session = compose_argv("session", HOSTNET_OVERRIDE)
    http_port = int(flag(session, "--http-port"))
    count = int(flag(session, "--sessions"))
    tap_port = int(flag(session, "--frame-tap-port"))
    expected = [
        int(flag(compose_argv("relay"), "--port")),
        *range(http_port, http_port + 1 + count * METRICS_PORTS_PER_SESSION),
        *range(tap_port, tap_port + count),
    ]
    assert [int(p) for p in ports[1].split()] == expected
    # The picture check reads session 1's tap, which serves game-1.
    check = (ROOT / "deploy" / "smoke_check.py").read_text()
    assert f"DEFAULT_TAP_PORT = {tap_port} " in check
    assert 'parser.add_argument("--broadcast", default="game-1")' in check
    images = re.search(r"IMAGES=\(([^)]+)\)", script)
    assert images is not None
    assert set(images[1].split()) == {
        s["image"] for s in services(COMPOSE).values() if "build" in s and not s.get("profiles")
    }


# -- health checks are real routes ---------------------------------------------------


def test_relay_health_check_path_answers_200(tmp_path: Path) -> None:
    from server.quic.certs import generate_cert
    from server.quic.http_fetch import fetch_cert_hash
    from server.relay.relay import Relay, RelayConfig

    url = urllib.parse.urlsplit(services(COMPOSE)["relay"]["healthcheck"]["test"][-1])
    assert url.path == "/certificate.sha256"

    spec = importlib.util.spec_from_file_location("healthcheck", ROOT / "deploy/healthcheck.py")
    assert spec is not None and spec.loader is not None
    healthcheck = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(healthcheck)

    async def probe() -> tuple[str, int, int]:
        relay = Relay(RelayConfig(host="127.0.0.1", port=0), generate_cert(directory=tmp_path))
        await relay.start()
        base = f"http://127.0.0.1:{relay.port}"
        try:
            # fetch_cert_hash is a GET of /certificate.sha256 that insists on 200.
            cert_hash = await fetch_cert_hash("127.0.0.1", relay.port, timeout=5.0)
            # The images' health-check program, on the compose path and on a wrong one.
            good = await asyncio.to_thread(healthcheck.main, [base + url.path])
            bad = await asyncio.to_thread(healthcheck.main, [base + "/no-such-route"])
            return cert_hash, good, bad
        finally:
            await relay.close()

    cert_hash, good, bad = asyncio.run(probe())
    assert re.fullmatch(r"[0-9a-f]{64}", cert_hash)
    assert (good, bad) == (0, 1)


def test_session_health_check_path_is_served_by_upcast_serve() -> None:
    url = urllib.parse.urlsplit(services(COMPOSE)["session"]["healthcheck"]["test"][-1])
    assert url.path == "/healthz"

    class Sessions:  # what ServeHttp reads of the supervisor
        relay_url = "http://relay:4443/"

        def __init__(self, up: bool) -> None:
            self.up = up

        def all_up(self) -> bool:
            return self.up

        def snapshot(self) -> list[dict[str, object]]:
            return []

    healthy = ServeHttp(Sessions(True)).respond(url.path)  # type: ignore[arg-type]
    down = ServeHttp(Sessions(False)).respond(url.path)  # type: ignore[arg-type]
    assert (healthy[0], down[0]) == (200, 503)


# -- clustered moq-relay -----------------------------------------------------------


def test_cluster_nodes_share_the_key_and_find_each_other() -> None:
    cluster = ROOT / "deploy" / "cluster"
    node_a = tomllib.loads((cluster / "relay-a.toml").read_text())
    node_b = tomllib.loads((cluster / "relay-b.toml").read_text())
    for node in (node_a, node_b):
        assert node["auth"]["key"] == KEY_PATH
        assert node["server"]["listen"].endswith(":4443")
        assert node["web"]["http"]["listen"] == node["server"]["listen"]
        assert node["cluster"]["token"] == "/secrets/cluster.jwt"
    assert "connect" not in node_a["cluster"], "node A is the root"
    assert node_b["cluster"]["connect"] == node_a["cluster"]["node"]

    merged = merged_services(COMPOSE, CLUSTER_OVERRIDE)
    # Node A takes the `relay` service's name: the session command is unchanged.
    assert merged["session"]["command"] == services(COMPOSE)["session"]["command"]
    assert node_a["cluster"]["node"].split(":")[0] == "relay"
    assert node_b["cluster"]["node"].split(":")[0] == "relay-b" and "relay-b" in merged
    mounts = {
        name: [v.split(":")[0] for v in merged[name]["volumes"]] for name in ("relay", "relay-b")
    }
    assert "./deploy/cluster/relay-a.toml" in mounts["relay"]
    assert "./deploy/cluster/relay-b.toml" in mounts["relay-b"]
    assert all("secrets" in m for m in mounts.values())


# -- Grafana -------------------------------------------------------------------------


def exported_sample_names(registry: CollectorRegistry) -> set[str]:
    """Every series name a registry can expose, children or not yet."""
    suffixes = {
        "counter": ("_total", "_created"),
        "histogram": ("_bucket", "_sum", "_count", "_created"),
        "gauge": ("",),
        "summary": ("", "_sum", "_count", "_created"),
        "info": ("_info",),
    }
    return {m.name + s for m in registry.collect() for s in suffixes.get(m.type, ("",))}


def every_process_metric(tmp_path: Path, ring_name: str) -> set[str]:
    from server.frames.frame import Size
    from server.frames.monitor import MonitorMetrics
    from server.frames.ring_frames import create_display_ring, create_render_ring
    from server.game.loop import GameLoop
    from server.game.metrics import game_registry
    from server.game.render.renderer import Renderer
    from server.quic.certs import generate_cert
    from server.relay.relay import Relay, RelayConfig
    from server.session.quality.adapter import QualityMetrics
    from server.worker.metrics import worker_registry
    from server.worker.upscale import UpscaleWorker
    from upscalers.host import UpscalerHost

    relay = Relay(RelayConfig(host="127.0.0.1", port=0), generate_cert(directory=tmp_path))
    session = CollectorRegistry()
    MonitorMetrics.for_registry(session)  # what StreamingSession's monitor exports
    QualityMetrics(session)  # and its adaptive quality
    ring_r = create_render_ring(f"{ring_name}-r", Size(32, 18))
    ring_u = create_display_ring(f"{ring_name}-u", Size(64, 36))
    try:
        game = game_registry(GameLoop(Renderer("static", Size(32, 18)), ring_r, fps=30.0))
        worker = worker_registry(
            UpscaleWorker(ring_r, ring_u, UpscalerHost("bilinear", Size(64, 36)))
        )
        names: set[str] = set()
        for registry in (relay.registry, session, game, worker):
            names |= exported_sample_names(registry)
        return names
    finally:
        for ring in (ring_r, ring_u):
            ring.close()


def test_every_dashboard_query_uses_exported_metrics(tmp_path: Path, ring_name: str) -> None:
    dashboard = json.loads((ROOT / "deploy" / "grafana" / "upcast.json").read_text())
    queries = [t["expr"] for p in dashboard["panels"] for t in p["targets"]]
    titles = " ".join(p["title"].lower() for p in dashboard["panels"])
    for topic in ("frames per second", "latency p50", "latency p95", "drops", "viewers", "bytes"):
        assert topic in titles, topic
    used = {n for q in queries for n in re.findall(r"\b(?:upcast|process)_[a-z0-9_]+", q)}
    assert len(used) >= 15
    exported = every_process_metric(tmp_path, ring_name)
    assert used <= exported, sorted(used - exported)


def test_grafana_provisioning_points_at_the_mounted_dashboard() -> None:
    grafana = services(COMPOSE)["grafana"]
    mounts = dict(v.rsplit(":", 1)[0].split(":", 1) for v in grafana["volumes"])
    provider = load_yaml(ROOT / "deploy/grafana/provisioning/dashboards/upcast.yml")
    folder = provider["providers"][0]["options"]["path"]
    assert mounts["./deploy/grafana/upcast.json"].startswith(folder + "/")
    datasource = load_yaml(ROOT / "deploy/grafana/provisioning/datasources/prometheus.yml")
    uid = datasource["datasources"][0]["uid"]
    dashboard = json.loads((ROOT / "deploy" / "grafana" / "upcast.json").read_text())
    assert {p["datasource"]["uid"] for p in dashboard["panels"]} == {uid}
    assert datasource["datasources"][0]["url"] == "http://prometheus:9090"
