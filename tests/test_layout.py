"""The layout shows the data flow: no import cycles, no import up the floors, few
modules at the top of server/, and families in their own packages.

Imports are read with ``ast`` from every module of ``server/`` and ``upscalers/``: module
level, function level and ``if TYPE_CHECKING:`` blocks alike (a type-only import is no
cycle at run time, but it still ties the two modules together, so it counts here).
"""

from __future__ import annotations

import ast
import re
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("server", "upscalers")
MAX_TOP_LEVEL_MODULES = 6
# The floors of DESIGN.md's data flow, lowest first: a package imports its own floor
# or lower ones, never a higher one (a stage never imports a tool or the host above it).
FLOORS: tuple[tuple[str, tuple[str, ...]], ...] = (
    (
        "foundations",
        ("server", "server.config_errors", "server.stream_config", "server.ops", "server.net"),
    ),
    ("protocol state machines and the frame contract", ("server.moq", "server.frames")),
    ("transport adapters", ("server.quic", "server.auth")),
    (
        "stages",
        (
            "server.game",
            "server.media",
            "upscalers",
            "server.config_types",
            "server.worker",
            "server.relay",
        ),
    ),
    ("a session", ("server.session",)),
    ("a host", ("server.stack", "server.serve")),
    ("tools", ("server.loadtest", "server.bench", "server.eval", "server.train")),
    ("entry", ("server.commands", "server.config_doc", "server.cli")),
)


def _modules() -> dict[str, tuple[Path, bool]]:
    """Dotted name -> (file, is a package's __init__)."""
    found: dict[str, tuple[Path, bool]] = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            is_package = parts[-1] == "__init__"
            if is_package:
                parts = parts[:-1]
            found[".".join(parts)] = (path, is_package)
    return found


def _imported(name: str, path: Path, is_package: bool, known: set[str]) -> Iterator[str]:
    """The modules of ``known`` that ``name`` imports anywhere in its file."""
    package = name if is_package else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name in known:
                    yield alias.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                module = ".".join([*base, *([node.module] if node.module else [])])
            else:
                module = node.module or ""
            for alias in node.names:
                if f"{module}.{alias.name}" in known:  # from package import module
                    yield f"{module}.{alias.name}"
                elif module in known:
                    yield module


def import_graph() -> dict[str, set[str]]:
    modules = _modules()
    known = set(modules)
    return {
        name: set(_imported(name, path, is_package, known)) - {name}
        for name, (path, is_package) in modules.items()
    }


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_the_cycle_finder_finds_a_cycle() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert cycles(graph) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_graph_sees_function_level_and_type_checking_imports() -> None:
    graph = import_graph()
    # upscalers.temporal.upscaler imports temporal_cpu inside a method and under TYPE_CHECKING.
    assert "upscalers.temporal.cpu" in graph["upscalers.temporal.upscaler"]
    # server.commands.game imports the game's metrics inside run().
    assert "server.game.metrics" in graph["server.commands.game"]


def test_no_import_cycle_between_modules() -> None:
    assert cycles(import_graph()) == []


def _package(module: str) -> str:
    """The floor unit a module belongs to: ``upscalers`` whole, else ``server.X``."""
    parts = module.split(".")
    return "upscalers" if parts[0] == "upscalers" else ".".join(parts[:2])


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    floor = {package: k for k, (_, packages) in enumerate(FLOORS) for package in packages}
    found = []
    for module, imported in sorted(graph.items()):
        for target in sorted(imported):
            if floor[_package(target)] > floor[_package(module)]:
                found.append(f"{module} -> {target}")
    return found


def test_every_package_has_a_floor() -> None:
    floors = {package for _, packages in FLOORS for package in packages}
    assert {_package(module) for module in import_graph()} <= floors


def test_the_floor_check_finds_an_upward_import() -> None:
    graph = {"server.session.x": {"server.bench.y"}, "server.bench.y": {"server.session.x"}}
    assert upward_imports(graph) == ["server.session.x -> server.bench.y"]


def test_no_import_up_the_floors() -> None:
    assert upward_imports(import_graph()) == []


def test_no_import_cycle_between_packages() -> None:
    # Floors allow either direction inside one; two packages on one floor must still not
    # import each other (bench and loadtest did, through the report writer).
    packages: dict[str, set[str]] = {}
    for module, imported in import_graph().items():
        packages.setdefault(_package(module), set()).update(map(_package, imported))
    assert cycles({name: deps - {name} for name, deps in packages.items()}) == []


# Module name prefixes that name a family: a module so named at the top of upscalers/
# or server/bench/ belongs in that family's package.
FAMILY_PREFIXES = {
    "upscalers": (
        *("resample", "cv_resample", "lanczos"),  # spatial
        *("fsr1", "temporal", "back_projection", "cut_detector", "neural", "cache", "framegen"),
        *("warm", "kernel", "compiled"),  # kernels
    ),
    "server/bench": ("adversary", "network", "congestion", "app", "capture", "reframe", "adaptive"),
}


def test_no_module_of_a_family_left_flat() -> None:
    flat = [
        f"{folder}/{path.name}"
        for folder, prefixes in FAMILY_PREFIXES.items()
        for path in sorted((ROOT / folder).glob("*.py"))
        if path.stem.startswith(prefixes)
    ]
    assert flat == []


def test_at_most_six_modules_at_the_top_of_server() -> None:
    top = sorted(path.name for path in (ROOT / "server").glob("*.py"))
    assert len(top) <= MAX_TOP_LEVEL_MODULES, top


def test_every_package_says_what_it_owns() -> None:
    missing = [
        str(init.relative_to(ROOT))
        for package in ("server",)
        for init in sorted((ROOT / package).glob("*/__init__.py"))
        if not ast.get_docstring(ast.parse(init.read_text()))
    ]
    assert missing == []


# `import ... from "./x"`, `export ... from "./x"` and the inline type `import("./x")`:
# the last one closed a circle audio -> stats -> audio that the first alone missed.
TS_IMPORT = re.compile(
    r"""(?:^(?:import|export)\b[^;]*?\bfrom\s+|\bimport\(\s*)["']\./([\w-]+)(?:\.[jt]s)?["']""",
    re.M | re.S,
)


def web_client_graph() -> dict[str, set[str]]:
    source = ROOT / "client_web" / "src"
    graph = {
        path.stem: set(TS_IMPORT.findall(path.read_text())) - {path.stem}
        for path in sorted(source.glob("*.ts"))
    }
    return {name: {dep for dep in deps if dep in graph} for name, deps in graph.items()}


def test_the_web_client_reader_sees_every_import_form() -> None:
    text = (
        'import { a } from "./one";\nexport { b } from "./two";\n'
        'let c: ReturnType<import("./three").X["f"]>;\nimport type {\n  D,\n} from "./four.js";\n'
    )
    assert set(TS_IMPORT.findall(text)) == {"one", "two", "three", "four"}


def test_no_import_cycle_in_the_web_client() -> None:
    assert cycles(web_client_graph()) == []
