"""``dcuscope ship``'s errors: each one line, and a clear exit status. (Streaming a live trace
to a relay: tests/ui/test_foreign_app.py.)"""

from __future__ import annotations

from tests.conftest import run_cli
from tests.ports import free_port


def test_a_trace_that_never_names_a_stage_gives_up_with_a_hint(tmp_path):
    port = free_port()
    result = run_cli("ship", tmp_path / "nothing.jsonl", "--relay", f"http://127.0.0.1:{port}", "--wait", "0.5")
    assert result.returncode == 1
    assert "names no stage after 0.5 s" in result.stderr and "GST_TRACERS" in result.stderr
    assert "Traceback" not in result.stderr


def test_bad_options_exit_2(tmp_path):
    result = run_cli("ship", tmp_path / "t.jsonl", "--relay", "http://127.0.0.1:1", "--wait", "0")
    assert result.returncode == 2 and "--wait" in result.stderr
    result = run_cli("ship", tmp_path / "t.jsonl")
    assert result.returncode == 2 and "--relay" in result.stderr
