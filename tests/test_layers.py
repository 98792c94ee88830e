"""The packages form layers that read bottom-up, and their modules a DAG: no upward import, no cycle.

    core      GI import, errors, signals, console        imports nothing of ours
    protocol  what nodes and relays speak: events, wire, core
              envelope, clock datagrams, errors
    model     the delay model: frame tables, delays,     core, protocol
              facts, comparisons
    plugins   the GStreamer elements                     core
    pipeline  config, build, run, sources, sinks, RTSP   core, plugins
    probes    the node: tracepoints, trace files, its    core, protocol, model, plugins, pipeline
              clocks, its side of the relay protocol
    ui        the page and its vendoring tool            core
    relay     the monitoring server                      core, protocol, model (and ui's files)
    dcuscope  the CLI and the demo: composition root     everything

Every ``import`` counts, those inside functions too: an import moved into a function to dodge a
cycle is still an edge of the graph. The packages are the folders of ``dcuscope/`` (``dcuscope.core``
… ``dcuscope.ui``, one import name); this file names them without the ``dcuscope.``.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "dcuscope"
LAYERS = {
    "core": set(),
    "protocol": {"core"},
    "model": {"core", "protocol"},
    "plugins": {"core"},
    "pipeline": {"core", "plugins"},
    "probes": {"core", "protocol", "model", "plugins", "pipeline"},
    "ui": {"core"},
    "relay": {"core", "protocol", "model", "ui"},
    "dcuscope": {"core", "protocol", "model", "plugins", "pipeline", "probes", "relay", "ui"},
}
SUBPACKAGES = tuple(sorted(set(LAYERS) - {"dcuscope"}))
COMPOSITION = {"capacity", "commands"}
"""The composition root's own subpackages (the commands, capacity): of the layer ``dcuscope``."""
DESIGN_FOLDERS = ("core", "plugins", "pipeline", "probes", "relay", "ui")
"""The design's top-level folders: in the repository, links to their packages in ``dcuscope/``."""


def modules() -> dict[str, Path]:
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE).with_suffix("").parts
        if "_build" in parts or "node_modules" in parts:
            continue
        parts = parts[:-1] if parts[-1] == "__init__" else parts
        name = ".".join(parts) if parts and parts[0] in SUBPACKAGES else ".".join(("dcuscope", *parts))
        found[name] = path
    return found


MODULES = modules()


def absolute_imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every absolute import in ``path``: ``from A import b`` gives A and A.b."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            out += [(node.lineno, node.module)] + [(node.lineno, f"{node.module}.{a.name}") for a in node.names]
    return out


def folder_name(target: str) -> str:
    """``dcuscope.relay.api`` as this file names it (``relay.api``); other names as they are."""
    head, _, rest = target.partition(".")
    return rest if head == "dcuscope" and rest.split(".")[0] in SUBPACKAGES else target


def imported(name: str, path: Path) -> set[str]:
    """Our modules that ``name`` imports, anywhere in its body (resolved to existing modules)."""
    out = set()
    is_package = path.name == "__init__.py"
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".")[: len(name.split(".")) - node.level + is_package]
                base = ".".join(anchor + ([base] if base else []))
            targets = [f"{base}.{alias.name}" for alias in node.names]
            if not (base == "dcuscope" and all(alias.name in SUBPACKAGES for alias in node.names)):
                targets.append(base)  # ``from dcuscope import relay`` imports relay, not the composition root
        else:
            continue
        for target in map(folder_name, targets):
            while target and target not in MODULES:
                target = target.rpartition(".")[0]
            if target and target != name:
                out.add(target)
    return out


GRAPH = {name: imported(name, path) for name, path in MODULES.items()}


def test_every_package_is_assigned_a_layer():
    packages = {p.parent.name for p in PACKAGE.glob("*/__init__.py")} - COMPOSITION
    assert packages == set(SUBPACKAGES), "a new package in dcuscope/ needs a place in LAYERS"
    packages = {p.parent.name for p in REPO.glob("*/__init__.py") if not p.parent.is_symlink()}
    assert packages == {"dcuscope", "tests"}, "our code is in dcuscope/ (the one import name)"


@pytest.mark.parametrize("folder", DESIGN_FOLDERS)
def test_the_design_folders_are_the_packages(folder):
    """``relay/`` in the repository is ``dcuscope/relay``: one copy of the code, found by the import
    system, editors and type checkers through the file system, as installed."""
    top = REPO / folder
    assert top.is_symlink() and top.resolve() == (PACKAGE / folder).resolve(), f"{folder}/ is not a link to dcuscope/{folder}"


def test_our_packages_are_imported_by_the_one_name():
    """``import relay`` would load a second copy of a module beside ``dcuscope.relay``'s, and fails
    where dcuscope is installed."""
    ours = sorted(p for folder in ("dcuscope", "tests", "benchmarks") for p in (REPO / folder).rglob("*.py"))
    old = [f"{path.relative_to(REPO)}:{line}: {module}" for path in ours
           for line, module in absolute_imports(path) if module.split(".")[0] in SUBPACKAGES]
    assert not old, f"imported by the folder's name, not dcuscope.*: {old}"


@pytest.mark.parametrize("name", sorted(MODULES))
def test_no_module_imports_upward(name):
    package = name.split(".")[0]
    upward = sorted(t for t in GRAPH[name] if t.split(".")[0] not in LAYERS[package] | {package})
    assert not upward, f"{MODULES[name].relative_to(REPO)} ({package}) imports {upward}"


def test_modules_form_a_dag():
    state: dict[str, int] = {}
    path: list[str] = []

    def visit(name: str) -> None:
        state[name] = 1
        path.append(name)
        for target in sorted(GRAPH[name]):
            if state.get(target) == 1:
                cycle = path[path.index(target):] + [target]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if target not in state:
                visit(target)
        path.pop()
        state[name] = 2

    for name in sorted(GRAPH):
        if name not in state:
            visit(name)


RELAY_LAYERS = ["errors", "urls", "heap", "guard", "clock", "rollup", "store", "live", "ingest", "export", "api", "config",
                "server", "workers", "commands", "__main__"]
"""The relay's own parts, bottom-up: each imports only those before it.

    urls      the servers' URLs as messages show them (passwords redacted)
    heap      giving the memory of runs that left back to the system
    guard     limits, tokens, Host checks, connection caps, PROXY protocol, log rate
    clock     NTP samples, the offset/drift model, corrections, the UDP exchange
    rollup    per minute and hour, mergeable sketches of each stage's delays, from events
    store     one interface, one module per engine (SQLite, PostgreSQL), stored-run loading
    ingest    the nodes' WebSocket, run ownership among relays
    export    Prometheus /metrics and OTLP
    live      what the relay holds of each run in memory: frames, statistics, sequence sets, and
              when it pairs them (the pairing cadence)
    api       the HTTP API, the browsers' Socket.IO namespace, the fleet view and the Redis fan-out
    config    the relay's settings, one typed object built from the command line
"""


def relay_part(name: str) -> str | None:
    parts = name.split(".")
    return parts[1] if parts[0] == "relay" and len(parts) > 1 else None


@pytest.mark.parametrize("name", sorted(n for n in MODULES if relay_part(n)))
def test_relay_parts_import_downward(name):
    part = relay_part(name)
    assert part in RELAY_LAYERS, f"{MODULES[name].relative_to(REPO)}: a new part of relay/ needs a place in RELAY_LAYERS"
    below = set(RELAY_LAYERS[:RELAY_LAYERS.index(part)])
    upward = sorted(t for t in GRAPH[name] if relay_part(t) and relay_part(t) not in below | {part})
    assert not upward, f"{MODULES[name].relative_to(REPO)} ({part}) imports {upward}"


PROBES_PARTS = {
    "trace": set(),
    "clocks": set(),
    "capture": {"trace"},
    "ship": {"trace", "clocks"},
    "instrument": {"trace", "clocks", "capture", "ship"},
}
"""probes/'s parts and what each may import of the others (probes/__init__.py says what they hold).
``instrument`` composes them for ``dcuscope run``; nothing of probes imports it."""


def probes_part(name: str) -> str | None:
    parts = name.split(".")
    return parts[1] if parts[0] == "probes" and len(parts) > 1 else None


def test_probes_holds_only_its_parts():
    found = {p.name.removesuffix(".py") for p in (PACKAGE / "probes").iterdir()
             if p.suffix == ".py" or (p / "__init__.py").exists()} - {"__init__"}
    assert found == set(PROBES_PARTS), "a new part of probes/ needs a place in PROBES_PARTS"


@pytest.mark.parametrize("name", sorted(n for n in MODULES if probes_part(n)))
def test_probes_parts_import_one_way(name):
    part = probes_part(name)
    wrong = sorted(t for t in GRAPH[name] if probes_part(t) and probes_part(t) not in PROBES_PARTS[part] | {part})
    assert not wrong, f"{MODULES[name].relative_to(REPO)} ({part}) imports {wrong}"
    assert "probes" not in GRAPH[name], f"{MODULES[name].relative_to(REPO)} imports the probes package itself"


@pytest.mark.parametrize("name", sorted(n for n in MODULES if n.split(".")[0] in {"relay", "probes"}))
def test_node_and_relay_share_only_the_protocol_and_the_model(name):
    """The relay imports nothing of the node (``probes``), the node nothing of the relay: what both
    need is ``protocol`` (what they say) and ``model`` (what the events mean)."""
    other = {"relay": "probes", "probes": "relay"}[name.split(".")[0]]
    wrong = sorted(t for t in GRAPH[name] if t.split(".")[0] == other)
    assert not wrong, f"{MODULES[name].relative_to(REPO)} imports {wrong}"


C_DIR = PACKAGE / "probes" / "capture" / "c"


def c_modules() -> list[str]:
    """The native library's modules, bottom-up, as core.cbuild compiles them."""
    tree = ast.parse((PACKAGE / "core" / "cbuild.py").read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and [getattr(t, "id", "") for t in node.targets] == ["MODULES"]:
            return list(ast.literal_eval(node.value))
    raise AssertionError("core/cbuild.py defines no MODULES")


C_MODULES = c_modules()
C_CALL = re.compile(r"\b(dcu_[a-z0-9_]+)\s*\(")
C_DEFINITION = re.compile(r"^[A-Za-z_][\w \*]*?\b(dcu_[a-z0-9_]+)\s*\([^;]*\)\s*\{", re.M)


def c_text(path: Path) -> str:
    """The code of a C file without its comments and string literals."""
    text = re.sub(r"/\*.*?\*/|//[^\n]*", " ", path.read_text(), flags=re.S)
    return re.sub(r'"(\\.|[^"\\])*"', '""', text)


def test_every_c_file_is_a_module_of_the_library():
    found = {p.stem for p in C_DIR.glob("*.c")}
    assert found == set(C_MODULES), "a new C file needs a place in probes/capture/native.py's MODULES"
    headers = {p.stem for p in C_DIR.glob("*.h")}
    assert headers == set(C_MODULES) - {"plugin"}, "one header per C module (plugin.c, the entry point, has none)"


@pytest.mark.parametrize("module", C_MODULES)
def test_c_modules_include_and_call_only_modules_below_them(module):
    below = set(C_MODULES[:C_MODULES.index(module)])
    for path in [C_DIR / f"{module}.c", C_DIR / f"{module}.h"]:
        if not path.exists():
            continue
        included = {Path(name).stem for name in re.findall(r'^#include "([^"]+)"', path.read_text(), re.M)}
        assert included <= below | {module}, f"{path.name} includes {sorted(included - below - {module})}"
    defined_by = {fn: m for m in C_MODULES for fn in C_DEFINITION.findall(c_text(C_DIR / f"{m}.c"))}
    called = set(C_CALL.findall(c_text(C_DIR / f"{module}.c")))
    upward = sorted(f"{fn} ({defined_by[fn]}.c)" for fn in called if defined_by.get(fn) not in below | {module, None})
    assert not upward, f"{module}.c calls {upward}"


@pytest.mark.parametrize("module", [m for m in C_MODULES if m != "plugin"])
def test_what_a_c_module_lets_others_call_its_header_declares(module):
    header = c_text(C_DIR / f"{module}.h")
    exported = C_DEFINITION.findall(re.sub(r"^static .*", "", c_text(C_DIR / f"{module}.c"), flags=re.M))
    undeclared = sorted(fn for fn in exported if not re.search(rf"\b{fn}\s*\(", header))
    assert not undeclared, f"{module}.c defines {undeclared} without declaring them in {module}.h"
