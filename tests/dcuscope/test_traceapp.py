"""``dcuscope trace -- CMD``: gst-launch-1.0, a C program and a Python program traced unchanged; the
signals go to CMD first; CMD's exit status comes back, a failed CMD's with its stderr's last line,
its empty trace never replacing an earlier one; shipped live to a relay, the stored run is the
trace file's run (``dcuscope compare`` reads both the same), and an unreachable relay is a
non-zero exit."""

from __future__ import annotations

import json
import signal
import statistics
import subprocess
import sys
import textwrap
import time

import pytest

from dcuscope.probes.ship.delivery import UNACKNOWLEDGED_STATUS
from dcuscope.probes.trace.tracefile import read_trace
from dcuscope.relay.store.runs import list_sessions
from tests.conftest import REPO, cli_env, run_cli
from tests.ports import free_port
from tests.ui.helpers import RelayThread

APP_SOURCE = REPO / "tests" / "probes" / "capture" / "data" / "probed_app.c"
LIVE = ["gst-launch-1.0", "-e", "videotestsrc", "is-live=true", "!", "video/x-raw,width=160,height=120,framerate=30/1",
        "!", "identity", "name=work", "sleep-time=2000", "!", "fakesink"]


def start(tmp_path, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "dcuscope.cli", "trace", *args], cwd=tmp_path, env=cli_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for_frames(trace, proc: subprocess.Popen, frames: int = 20, timeout: float = 60) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        if trace.exists() and trace.read_text().count('"events"') >= 2 and len(read_trace(trace).events) > 3 * frames:
            return
        time.sleep(0.2)
    raise AssertionError(f"no frames in {trace}: {proc.poll()}")


def stage_p50_ms(trace, stage: str) -> float:
    from dcuscope.probes.trace.stats import stats_document

    return stats_document([read_trace(trace)])["nodes"][read_trace(trace).header.node]["stages"][stage]["p50_ms"]


def test_ctrl_c_goes_to_gst_launch_which_ends_cleanly_and_the_summary_follows(tmp_path):
    trace = tmp_path / "live.trace.jsonl"
    proc = start(tmp_path, "--node", "CAM-1", "-o", str(trace), "--", *LIVE)
    wait_for_frames(trace, proc)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err  # gst-launch -e: end-of-stream, then exit 0
    t = read_trace(trace)
    assert t.complete and t.header.node == "CAM-1"
    assert "dcuscope: gst-launch-1.0 traced" in err and "stage work" in err and "no end line" not in err
    assert stage_p50_ms(trace, "work") >= 1.95  # it sleeps 2 ms a frame (a loaded machine only adds to that)


def test_sigterm_goes_to_cmd_and_its_status_comes_back(tmp_path):
    trace = tmp_path / "term.trace.jsonl"
    proc = start(tmp_path, "-o", str(trace), "--", *LIVE)
    wait_for_frames(trace, proc)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, err  # gst-launch-1.0 died of it; dcuscope said so and waited
    assert "no end line: CMD did not exit cleanly" in err and "stage work" in err


def test_a_c_program_traced_unchanged(tmp_path):
    app = tmp_path / "probed_app"
    flags = subprocess.run(["pkg-config", "--cflags", "--libs", "gstreamer-1.0"], capture_output=True, text=True,
                           check=True).stdout.split()
    subprocess.run(["cc", "-O2", "-o", str(app), str(APP_SOURCE), *flags], check=True)
    trace = tmp_path / "c.trace.jsonl"
    result = run_cli("trace", "--node", "C-APP", "-o", trace, "--", app,
                     "videotestsrc num-buffers=40 ! identity name=slow sleep-time=3000 ! fakesink", "slow", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    # The program's own ground truth: when each buffer crossed the identity's sink and src pads.
    crossings: dict[str, dict[int, int]] = {"sink": {}, "src": {}}
    for line in result.stdout.splitlines():
        _, element, pad, pts, at = line.split()
        crossings[pad][int(pts)] = int(at)
    truth = sorted(crossings["src"][p] - crossings["sink"][p] for p in crossings["sink"])
    assert len(truth) == 40 and read_trace(trace).header.node == "C-APP"
    # The median as stats takes it (numpy's, linear: of 40, halfway between the 20th and the 21st; a loaded
    # machine's sleeps spread those two apart by 0.2 ms and more).
    assert stage_p50_ms(trace, "slow") == pytest.approx(statistics.median(truth) / 1e6, abs=0.2)
    assert "stage slow" in result.stderr


def test_a_python_program_traced_and_its_exit_status_returned(tmp_path):
    app = tmp_path / "app.py"
    app.write_text(textwrap.dedent("""\
        import sys
        import gi
        gi.require_version("Gst", "1.0")
        from gi.repository import Gst
        Gst.init(None)
        p = Gst.parse_launch("videotestsrc num-buffers=30 ! identity name=py sleep-time=1000 ! fakesink")
        p.set_state(Gst.State.PLAYING)
        p.get_bus().timed_pop_filtered(Gst.CLOCK_TIME_NONE, Gst.MessageType.EOS | Gst.MessageType.ERROR)
        p.set_state(Gst.State.NULL)
        sys.exit(3)
        """))
    result = run_cli("trace", "--node", "PY-APP", "--", sys.executable, app, cwd=tmp_path)
    assert result.returncode == 3, result.stderr
    trace = tmp_path / "PY-APP.trace.jsonl"  # the default: NODE.trace.jsonl in the working folder
    assert read_trace(trace).complete and "stage py" in result.stderr
    assert stage_p50_ms(trace, "py") >= 0.95  # it sleeps 1 ms a frame; a loaded machine adds to it, never takes


def test_shipped_live_the_stored_run_is_the_trace(tmp_path):
    relay = RelayThread(tmp_path / "relay.db")
    try:
        trace = tmp_path / "shipped.trace.jsonl"
        result = run_cli("trace", "--relay", relay.url, "--node", "SHIP-1", "-o", trace, "--", "gst-launch-1.0", "-q",
                         "videotestsrc", "num-buffers=120", "!", "identity", "name=work", "sleep-time=1000", "!",
                         "fakesink", cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        events = len(read_trace(trace).events)
        assert f"relay: {events} events stored (acknowledged), 0 not acknowledged; relays tried: {relay.url}\n" \
            in result.stderr
        runs = [r for s in list_sessions(tmp_path / "relay.db") for r in s["runs"] if r["node"] == "SHIP-1"]
        assert len(runs) == 1, runs
        doc = json.loads(run_cli("compare", trace, f"run:{runs[0]['run']}", "--db", tmp_path / "relay.db",
                                 "--json").stdout)
        assert doc["inputs"][1]["frames"] == 120 and doc["inputs"][1]["node"] == "SHIP-1"
        for row in doc["rows"]:
            assert all(c["delta"] == 0 for c in row["changes"][1].values()), row
    finally:
        relay.stop()


def test_without_a_command_or_with_a_missing_one_exit_2(tmp_path):
    for args, says in (((), "give the program to run after --"),
                       (("--", "no-such-program-here"), "no-such-program-here: no such program")):
        result = run_cli("trace", *args, cwd=tmp_path)
        assert result.returncode == 2 and says in result.stderr, result.stderr
        assert len(result.stderr.splitlines()) == 1


def test_an_unreachable_relay_within_close_timeout_exits_non_zero_saying_nothing_was_stored(tmp_path):
    url, trace = f"http://127.0.0.1:{free_port()}", tmp_path / "lonely.trace.jsonl"  # nothing listens there
    result = run_cli("trace", "--relay", url, "--close-timeout", "1", "--no-spool", "--node", "LONELY", "-o", trace, "--",
                     "gst-launch-1.0", "-q", "videotestsrc", "num-buffers=10", "!", "fakesink", cwd=tmp_path)
    assert result.returncode == UNACKNOWLEDGED_STATUS, result.stderr
    events = len(read_trace(trace).events)  # the trace still holds them all
    assert f"relay: 0 events stored (acknowledged), {events} not acknowledged; relays tried: {url}; last error: " \
           f"cannot reach relay {url}" in result.stderr


def test_a_failed_app_is_reported_as_such_and_the_earlier_trace_is_kept(tmp_path):
    trace = tmp_path / "vm.trace.jsonl"
    trace.write_text("an earlier run's trace\n")
    result = run_cli("trace", "--node", "vm", "--", "gst-launch-1.0", "videotestsrc", "num-buffers=10", "!",
                     "nosuchelement", "!", "fakesink", cwd=tmp_path)
    assert result.returncode == 1, result.stderr  # gst-launch-1.0's own
    assert result.stderr.splitlines()[-1] == \
        'dcuscope: gst-launch-1.0 failed (exit status 1): WARNING: erroneous pipeline: no element "nosuchelement"'
    assert f"wrote no trace to {trace}: it ran no GStreamer pipeline" in result.stderr
    assert f"{trace}, an earlier run's, is kept as it was" in result.stderr and "header" not in result.stderr
    assert trace.read_text() == "an earlier run's trace\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == [trace.name]  # no TRACE.previous left
