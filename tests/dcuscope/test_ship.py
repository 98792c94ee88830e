"""``dcuscope ship``'s errors: each one line, and a clear exit status (also when no relay stored the events). (Streaming a live trace
to a relay: tests/ui/test_foreign_app.py.)"""

from __future__ import annotations

from dcuscope.probes.ship.delivery import UNACKNOWLEDGED_STATUS
from dcuscope.probes.ship.simnode import header_for, synth_events
from dcuscope.probes.trace.tracefile import write_trace
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


def test_an_unreachable_relay_is_reported_as_nothing_stored_and_exits_non_zero(tmp_path):
    trace, url = tmp_path / "t.jsonl", f"http://127.0.0.1:{free_port()}"  # nothing listens there
    events = synth_events(5, 1, 25.0, 1_700_000_000_000_000_000)
    write_trace(trace, header_for("SHIP-1", 1), events)
    result = run_cli("ship", trace, "--relay", url, "--settle", "0", "--close-timeout", "1", "--no-spool")
    assert result.returncode == UNACKNOWLEDGED_STATUS, result.stderr
    assert result.stderr.splitlines()[-1].startswith(
        f"ship: SHIP-1, 1 run(s), the trace is ended; relay: 0 events stored (acknowledged), {len(events)} not "
        f"acknowledged; relays tried: {url}; last error: cannot reach relay {url}")
    assert "sent to" not in result.stderr
