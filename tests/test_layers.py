"""The packages form layers that read bottom-up, and their modules a DAG: no upward import, no cycle.

    core      GI import, errors, signals, console        imports nothing of ours
    plugins   the GStreamer elements                     core
    pipeline  config, build, run, sources, sinks, RTSP   core, plugins
    probes    tracepoints, events, trace files, delay    core, plugins, pipeline
              model, node exporters, wire format
    relay     the monitoring server                      core, probes (and ui's files)
    ui        the page and its vendoring tool            core
    dcuscope  the CLI and the demo: composition root     everything

Every ``import`` counts, those inside functions too: an import moved into a function to dodge a
cycle is still an edge of the graph. Installed, the packages are ``dcuscope.core`` … ``dcuscope.ui``
(one import name, ``dcuscope/__init__.py``): the code imports them so, and this file names them by
their folders.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SUBPACKAGES = ("core", "plugins", "pipeline", "probes", "relay", "ui")
LAYERS = {
    "core": set(),
    "plugins": {"core"},
    "pipeline": {"core", "plugins"},
    "probes": {"core", "plugins", "pipeline"},
    "ui": {"core"},
    "relay": {"core", "probes", "ui"},
    "dcuscope": {"core", "plugins", "pipeline", "probes", "relay", "ui"},
}


def modules() -> dict[str, Path]:
    found = {}
    for package in LAYERS:
        for path in sorted((REPO / package).rglob("*.py")):
            parts = path.relative_to(REPO).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
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
    packages = {p.parent.name for p in REPO.glob("*/__init__.py")} - {"tests", "benchmarks"}
    assert packages == set(LAYERS), "a new top-level package needs a place in LAYERS"
    from dcuscope import SUBPACKAGES as mapped  # what a checkout puts under dcuscope
    built = next(ast.literal_eval(node.value) for node in ast.parse((REPO / "setup.py").read_text()).body
                 if isinstance(node, ast.Assign) and [getattr(t, "id", "") for t in node.targets] == ["SUBPACKAGES"])
    assert set(mapped) == set(built) == set(SUBPACKAGES) == set(LAYERS) - {"dcuscope"}  # and the build


def test_our_packages_are_imported_by_the_one_name():
    """``import relay`` would load a second copy of a module beside ``dcuscope.relay``'s, and fails
    where dcuscope is installed."""
    ours = sorted(p for folder in (*LAYERS, "tests", "benchmarks") for p in (REPO / folder).rglob("*.py"))
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


RELAY_LAYERS = ["errors", "urls", "heap", "guard", "clock", "rollup", "store", "live", "ingest", "export", "api", "server", "workers",
                "commands", "__main__"]
"""The relay's own parts, bottom-up: each imports only those before it.

    urls      the servers' URLs as messages show them (passwords redacted)
    heap      giving the memory of runs that left back to the system
    guard     limits, tokens, Host checks, connection caps, PROXY protocol, log rate
    clock     NTP samples, the offset/drift model, corrections, the UDP exchange
    rollup    per minute and hour, mergeable sketches of each stage's delays, from events
    store     one interface, one module per engine (SQLite, PostgreSQL), stored-run loading
    live      what the relay holds of each run in memory: frames, statistics, sequence sets
    ingest    the nodes' WebSocket, run ownership among relays
    export    Prometheus /metrics and OTLP
    api       the HTTP API, the browsers' Socket.IO namespace, the fleet view and the Redis fan-out
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
RELAY_MAY_IMPORT = {"trace", "clocks", "ship"}
"""The contract between nodes and the relay: the relay never imports capture nor the composition."""


def probes_part(name: str) -> str | None:
    parts = name.split(".")
    return parts[1] if parts[0] == "probes" and len(parts) > 1 else None


def test_probes_holds_only_its_parts():
    found = {p.name.removesuffix(".py") for p in (REPO / "probes").iterdir()
             if p.suffix == ".py" or (p / "__init__.py").exists()} - {"__init__"}
    assert found == set(PROBES_PARTS), "a new part of probes/ needs a place in PROBES_PARTS"


@pytest.mark.parametrize("name", sorted(n for n in MODULES if probes_part(n)))
def test_probes_parts_import_one_way(name):
    part = probes_part(name)
    wrong = sorted(t for t in GRAPH[name] if probes_part(t) and probes_part(t) not in PROBES_PARTS[part] | {part})
    assert not wrong, f"{MODULES[name].relative_to(REPO)} ({part}) imports {wrong}"
    assert "probes" not in GRAPH[name], f"{MODULES[name].relative_to(REPO)} imports the probes package itself"


@pytest.mark.parametrize("name", sorted(n for n in MODULES if n.split(".")[0] == "relay"))
def test_the_relay_reads_only_the_trace_model_clocks_and_wire(name):
    wrong = sorted(t for t in GRAPH[name] if t.split(".")[0] == "probes" and probes_part(t) not in RELAY_MAY_IMPORT)
    assert not wrong, f"{MODULES[name].relative_to(REPO)} imports {wrong}"


C_DIR = REPO / "probes" / "capture" / "c"


def c_modules() -> list[str]:
    """The native library's modules, bottom-up, as core.cbuild compiles them."""
    tree = ast.parse((REPO / "core" / "cbuild.py").read_text())
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
