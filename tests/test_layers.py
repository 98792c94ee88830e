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
cycle is still an edge of the graph.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
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
            targets = [f"{base}.{alias.name}" for alias in node.names] + [base]
        else:
            continue
        for target in targets:
            while target and target not in MODULES:
                target = target.rpartition(".")[0]
            if target and target != name:
                out.add(target)
    return out


GRAPH = {name: imported(name, path) for name, path in MODULES.items()}


def test_every_package_is_assigned_a_layer():
    packages = {p.parent.name for p in REPO.glob("*/__init__.py")} - {"tests", "benchmarks"}
    assert packages == set(LAYERS), "a new top-level package needs a place in LAYERS"


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


RELAY_LAYERS = ["errors", "urls", "heap", "guard", "clock", "store", "live", "ingest", "export", "api", "server", "workers",
                "commands", "__main__"]
"""The relay's own parts, bottom-up: each imports only those before it.

    urls      the servers' URLs as messages show them (passwords redacted)
    heap      giving the memory of runs that left back to the system
    guard     limits, tokens, Host checks, connection caps, PROXY protocol, log rate
    clock     NTP samples, the offset/drift model, corrections, the UDP exchange
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
