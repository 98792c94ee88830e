"""The command line itself: --version, help, a taken port for every server command, the options
that messages name, a node whose relay stored nothing."""

from __future__ import annotations

import argparse
import ast
import re
import socket
import subprocess
import sys

import pytest

from dcuscope.cli import build_parser
from dcuscope.core.pycompat import tomllib
from dcuscope.pipeline.config import load_config
from dcuscope.probes.ship import simnode
from dcuscope.probes.ship.delivery import UNACKNOWLEDGED_STATUS
from tests.conftest import REPO, VTEST, cli_env, run_cli
from tests.ports import free_port


def test_version_is_the_packages():
    result = run_cli("--version", timeout=60)
    expected = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]
    assert result.returncode == 0 and result.stdout.strip() == f"dcuscope {expected}", result.stdout + result.stderr


def test_run_help_has_no_empty_heading():
    result = run_cli("run", "--help", timeout=60)
    assert result.returncode == 0
    assert result.stdout.count("examples:") == 1 and "examples:\n  dcuscope run configs/" in result.stdout


@pytest.mark.parametrize("command", [["relay", "--db", "{tmp}/r.db"], ["demo", "--db", "{tmp}/d.db"],
                                     ["serve-rtsp", str(VTEST)]], ids=["relay", "demo", "serve-rtsp"])
def test_a_taken_port_exits_2_with_one_line_naming_it(tmp_path, command):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        args = [a.format(tmp=tmp_path) for a in command]
        result = subprocess.run([sys.executable, "-m", "dcuscope.cli", *args, "--port", str(port)], cwd=tmp_path,
                                env=cli_env(), capture_output=True, text=True, timeout=60)
    assert result.returncode == 2, result.stdout + result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"dcuscope: error: --port {port}: cannot listen on "), lines
    assert "starting" not in result.stdout and not (tmp_path / "d.db").exists()


def test_shipped_configurations_are_listed_run_by_name_and_copied_out(tmp_path):
    listed = run_cli("configs", cwd=tmp_path, timeout=60)
    assert listed.returncode == 0, listed.stderr
    names = {line.split()[0] for line in listed.stdout.splitlines() if line and not line.startswith(("(", " "))}
    assert names == {p.stem for p in (REPO / "configs").glob("*.yaml")}
    assert "vtest  " in listed.stdout and "One camera: the OpenCV pedestrian clip" in listed.stdout

    # By name, from a folder that holds no configs/: the shipped file, its clip found beside it.
    ran = run_cli("run", "vtest", "--num-frames", "3", cwd=tmp_path, timeout=120)
    assert ran.returncode == 0, ran.stderr
    assert any(line.startswith("infer: ") and " objects in " in line for line in ran.stderr.splitlines()), ran.stderr
    # No trace was asked for, so none counts the frames past the limit; one kind is not "kinds".
    assert "more had passed every stage" in ran.stderr and "a trace counts" not in ran.stderr
    assert not re.search(r"\b1 more kinds\b", ran.stderr), ran.stderr
    unknown = run_cli("run", "nosuch", cwd=tmp_path, timeout=60)
    assert unknown.returncode == 2 and unknown.stderr.startswith("dcuscope: error: nosuch: no such configuration file")
    assert "vtest" in unknown.stderr

    copied = run_cli("configs", "--copy", tmp_path / "mine", cwd=tmp_path, timeout=60)
    assert copied.returncode == 0, copied.stderr
    assert sorted(p.name for p in (tmp_path / "mine").iterdir()) == sorted(p.name for p in (REPO / "configs").glob("*.yaml"))
    (tmp_path / "elsewhere").mkdir()
    moved = (tmp_path / "elsewhere" / "one.yaml")
    moved.write_text((tmp_path / "mine" / "vtest.yaml").read_text())  # its clip named by absolute path: loads anywhere
    assert load_config(moved).sources[0].location == (REPO / "assets" / "media" / "vtest.avi").as_uri()
    again = run_cli("configs", "--copy", tmp_path / "mine", cwd=tmp_path, timeout=60)
    assert again.returncode == 0 and "vtest.yaml: exists, kept" in again.stdout


def test_a_run_whose_relay_stored_nothing_says_so_and_exits_non_zero(tmp_path):
    url = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    result = run_cli("run", "vtest", "-n", "3", "--probes", "--relay", url, "--close-timeout", "1", "--no-spool",
                     cwd=tmp_path, timeout=120)
    assert result.returncode == UNACKNOWLEDGED_STATUS, result.stderr
    (probes,) = [line for line in result.stderr.splitlines() if " tracepoints " in line]
    events = int(probes.split()[1])  # "probes: N events from ..."
    assert "sent to the relay" not in result.stderr
    assert f"probes: relay: 0 events stored (acknowledged), {events} not acknowledged; relays tried: {url}; " \
           f"last error: cannot reach relay {url}" in result.stderr
    run_help = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices["run"]
    assert f"{UNACKNOWLEDGED_STATUS} the run went well but --relay did not acknowledge" in \
        " ".join(run_help.format_help().split())


# --- every option a node command's messages name is one that command takes -----------------------

OPTION = re.compile(r"(?<![\w-])--[a-z][a-z0-9]*(?:-[a-z0-9]+)*")
NODE_COMMANDS = {"run": "dcuscope.commands.runpipeline", "trace": "dcuscope.commands.trace", "ship": "dcuscope.commands.ship",
                 "simnode": "dcuscope.probes.ship.simnode"}
"""Each command that ships probe events, and the module it runs: what it imports can print."""
OTHER_PROGRAMS = {
    "--clock-port": "relay", "--limit": "relay", "--tls-client-ca": "relay",  # what the relay must be told
    "--cflags": "pkg-config", "--libs": "pkg-config",  # core.cbuild runs it
    "--camera": "the example program of trace's epilog", "--drain": "ship's, which sends the spool", "--port": "core.ports' default (run passes option=None)",
}
"""Options messages name that belong to another program: the relay's are checked to be its own."""


def _module_file(module: str):
    rel = module.split(".")[1:]
    for base in (REPO / "dcuscope", REPO):
        path = base.joinpath(*rel)
        if path.with_suffix(".py").is_file():
            return path.with_suffix(".py")
        if (path / "__init__.py").is_file():
            return path / "__init__.py"
    return None


def _reachable(entry: str) -> set:
    """The project's source files ``entry`` may import, at any depth (function-local imports too);
    not the relay's, nor the other commands' modules, which this command never runs."""
    seen, todo = set(), [entry]
    while todo:
        module = todo.pop()
        path = _module_file(module)
        other_command = path is not None and path.parent in (REPO / "dcuscope", REPO / "dcuscope" / "commands") \
            and module != entry and path.name not in ("__init__.py", "options.py")
        if path is None or path in seen or module.startswith("dcuscope.relay") or other_command:
            continue
        seen.add(path)
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                todo += [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                todo += [node.module, *(f"{node.module}.{a.name}" for a in node.names)]
    return seen


def _mentions(path) -> list[tuple[str, int]]:
    """``--option`` names in the file's strings (f-strings' parts too); not in a bare string (a
    docstring, of a module, a class, a function or a constant), which is never printed."""
    tree = ast.parse(path.read_text())
    docstrings = {id(node.value) for node in ast.walk(tree) if isinstance(node, ast.Expr)}
    return [(option, node.lineno) for node in ast.walk(tree) if isinstance(node, ast.Constant)
            and isinstance(node.value, str) and id(node) not in docstrings for option in OPTION.findall(node.value)]


def _options(parser: argparse.ArgumentParser) -> set[str]:
    return {s for action in parser._actions for s in action.option_strings}


def test_every_option_a_node_commands_messages_name_is_one_it_takes():
    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    takes = {name: _options(commands[name]) for name in ("run", "trace", "ship")}
    takes["simnode"] = _options(simnode.build_parser())
    wrong, named = [], set()
    for command, entry in NODE_COMMANDS.items():
        for path in _reachable(entry):
            for option, line in _mentions(path):
                named.add(option)
                if option not in takes[command] and option not in OTHER_PROGRAMS:
                    wrong.append(f"{path.relative_to(REPO)}:{line}: {option}, which {command} does not take")
    assert not wrong, "\n".join(wrong)
    assert "--close-timeout" in named  # the closing message's own hint (probes.ship.relayexport)
    relay = _options(commands["relay"])
    assert {o for o, who in OTHER_PROGRAMS.items() if who == "relay"} <= relay
    assert set(OTHER_PROGRAMS) <= named, "an exception no message needs any more"


@pytest.mark.parametrize("correction_ns, uncertainty_ns, says", [
    (-1000, 5100, "estimate: -1.0 µs subtracted ± 5.1 µs"),
    (3_012_400, 51_000, "estimate: +3.012 ms subtracted ± 0.051 ms"),
    (200_000, 1_500_000, "estimate: +0.200 ms subtracted ± 1.500 ms"),
])
def test_a_stored_runs_clock_line_gives_the_offset_and_its_bound_in_one_unit(correction_ns, uncertainty_ns, says):
    from dcuscope.commands.stats import _clock_lines

    entry = {"applied": "estimate", "correction_ns": correction_ns, "uncertainty_ns": uncertainty_ns}
    assert _clock_lines({"clock": entry}) == [f"  clock          {says}"]
