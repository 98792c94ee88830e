"""Two real pipeline processes feed one relay: live stats agree with dcuscope stats; export --db."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import pytest

from tests.conftest import REPO, cli_env, run_cli
from tests.relay.helpers import RelayProcess, assert_stats_equal, get_json

MODEL = REPO / "assets" / "models" / "ssdlite_mobilenetv2_person.onnx"


def node_config(tmp_path, name: str, sources: int):
    patterns = ("smpte", "ball", "snow", "pinwheel")
    srcs = "\n".join(f"  - {{test: {patterns[i]}, width: 320, height: 240, rate: 20}}" for i in range(sources))
    path = tmp_path / f"{name}.yaml"
    path.write_text(f"node: {name}\nsources:\n{srcs}\nstages:\n  - mux: {{batch-size: {sources}, width: 320, height: 240}}\n"
                    f"  - infer: {{model: {MODEL}}}\n  - tiler: {{width: 640, height: 480}}\n  - convert: {{}}\n  - osd: {{}}\n")
    return path


@pytest.mark.long
def test_two_pipeline_nodes_stats_agree_with_dcuscope_stats_and_export_from_db(tmp_path):
    relay = RelayProcess(tmp_path / "relay.db")
    try:
        nodes = {}
        for name, sources in (("DCU-1", 2), ("DCU-2", 4)):
            trace = tmp_path / f"{name}.jsonl"
            cmd = [sys.executable, "-m", "dcuscope.cli", "run", str(node_config(tmp_path, name, sources)), "--probes",
                   "--relay", relay.url, "--trace", str(trace), "--num-frames", "30"]
            nodes[name] = (subprocess.Popen(cmd, cwd=tmp_path, env=cli_env(), stderr=subprocess.PIPE, text=True), trace)
        for name, (proc, _) in nodes.items():
            _, err = proc.communicate(timeout=240)
            assert proc.returncode == 0, err
            assert "0 dropped" in err
        for name, (_, trace) in nodes.items():
            expected = json.loads(run_cli("stats", trace, "--json", cwd=tmp_path).stdout)["nodes"][name]
            assert expected["frames"]["complete"] >= 30
            got = get_json(f"{relay.url}/api/stats?node={name}")
            assert_stats_equal(expected, got)
        sessions = get_json(f"{relay.url}/api/sessions")
    finally:
        assert relay.stop() == 0
    assert len(sessions) == 1 and {r["node"] for r in sessions[0]["runs"]} == {"DCU-1", "DCU-2"}
    session = str(sessions[0]["session"])
    out = tmp_path / "session.csv"
    result = run_cli("export", "--db", tmp_path / "relay.db", "--session", session, "--format", "csv", "-o", out,
                     cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    from_db = sorted(map(tuple, csv.reader(out.read_text().splitlines()[1:])))
    traces = [str(t) for _, t in nodes.values()]
    assert run_cli("export", *traces, "--format", "csv", "-o", tmp_path / "t.csv", cwd=tmp_path).returncode == 0
    from_traces = sorted(map(tuple, csv.reader((tmp_path / "t.csv").read_text().splitlines()[1:])))
    assert len(from_db) == len(from_traces) >= 6 * 30 * 5
    # Same frames, stages and (on one machine, clock offset ~0) timestamps within the estimate's error.
    assert [r[:4] for r in from_db] == [r[:4] for r in from_traces]


def test_export_from_db_needs_a_session(tmp_path):
    result = run_cli("export", "--db", tmp_path / "nope.db", "--session", "1", "-o", tmp_path / "x.json", cwd=tmp_path)
    assert result.returncode == 2 and "no such database" in result.stderr
    result = run_cli("export", "--db", tmp_path / "nope.db", "-o", tmp_path / "x.json", cwd=tmp_path)
    assert result.returncode == 2 and "--db PATH with --session ID" in result.stderr


def test_clock_offset_of_a_real_node_is_recovered_within_its_uncertainty(tmp_path):
    """``dcuscope run --clock-offset-ms 37`` (the testing aid) shifts that node's clock; the
    relay's NTP-style estimate must find +37 ms within its stated uncertainty."""
    relay = RelayProcess(tmp_path / "relay.db", clock="estimate")
    try:
        procs = []
        for name, offset in (("DCU-1", "0"), ("DCU-2", "37")):
            cmd = [sys.executable, "-m", "dcuscope.cli", "run", str(node_config(tmp_path, name, 1)), "--probes",
                   "--relay", relay.url, "--duration", "8", "--clock-offset-ms", offset, "-q"]
            procs.append(subprocess.Popen(cmd, cwd=tmp_path, env=cli_env(), stderr=subprocess.PIPE, text=True))
        for proc in procs:
            _, err = proc.communicate(timeout=120)
            assert proc.returncode == 0, err
        nodes = {n["node"]: n for n in get_json(f"{relay.url}/api/nodes")}
    finally:
        relay.stop()
    for name, expected_ms in (("DCU-1", 0.0), ("DCU-2", 37.0)):
        clock = nodes[name]["clock"]
        assert clock["samples"] >= 2
        assert abs(clock["offset_us"] / 1000 - expected_ms) <= clock["uncertainty_us"] / 1000, clock
        assert clock["uncertainty_us"] < 2000
