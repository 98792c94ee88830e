"""Live runs that stop when asked: a live pipeline that cannot keep up ends at its --duration, not
when its backlog has drained, and every frame its sources stamped is delivered or counted as
dropped; SIGTERM is one clean stop, however often it comes."""

from __future__ import annotations

import re
import signal
import subprocess
import sys

import pytest

from tests.conftest import cli_env, wait_until_mapped
from tests.pipeline.clips import decode_video
from tests.pipeline.livecheck import check_every_frame_accounted, run_timed

DURATION_S = 6
STOP_S = 5.0
"""The longest a live stop may take, from the run saying it stops to the process having exited
(the batch under way, end-of-stream, the trace's last events): the drain it replaces took as
long as the backlog, here more than the run itself."""

SLOW_LIVE = ("sources:\n  - {test: ball, live: true, width: 64, height: 48, rate: 30}\n"
             "  - {test: smpte, live: true, width: 64, height: 48, rate: 30}\n"
             "stages:\n  - mux: {width: 64, height: 48, batch-size: 2, live-source: true}\n"
             "  - queue: {max-size-buffers: 0, max-size-time: 0, max-size-bytes: 0}\n"
             "  - factory: identity\n    properties: {sleep-time: 100000}\n")
"""Two cameras at 30 frames/s into a stage that takes 10 batches/s: about 40 frames/s more than it
can take pile up in the queue, without bound."""


def test_a_live_run_that_cannot_keep_up_ends_at_its_duration_with_every_frame_accounted_for(tmp_path):
    config = tmp_path / "slow.yaml"
    config.write_text(SLOW_LIVE)
    trace = tmp_path / "slow.jsonl"
    run = run_timed("run", config, "--probes", "--trace", trace, "--duration", DURATION_S, cwd=tmp_path,
                    stop_line=f"stopping (--duration {DURATION_S} s)")
    assert run.returncode == 0, run.stderr
    assert "frames still queued are dropped" in run.stderr and "did not reach the sink" not in run.stderr, run.stderr
    assert run.stop_said_at is not None and run.ended_at - run.stop_said_at < STOP_S, run.stderr
    ran_s = float(re.search(r"\d+ frames in ([\d.]+) s", run.stderr).group(1))  # start to end-of-stream
    assert DURATION_S <= ran_s < DURATION_S + STOP_S, run.stderr
    dropped = check_every_frame_accounted(trace)
    # A backlog there was (draining it would have taken >= 3 s at 20 frames/s), and it was dropped, not drained.
    assert set(dropped) == {"stopped"} and dropped["stopped"] >= 60, dropped
    assert f"dcuscope: {dropped['stopped']} frames still queued at the stop were dropped" in run.stderr, run.stderr


LIVE_MP4 = ("sources:\n  - {test: ball, live: true, width: 160, height: 120, rate: 30}\n"
            "stages:\n  - mux: {width: 160, height: 120}\n"
            "  - factory: identity\n    properties: {sleep-time: 1500000}\n"
            "  - tiler: {width: 160, height: 120}\n  - convert: {format: RGBA}\n")
"""A camera into a stage that takes 1.5 s a frame: a stop waits up to that long for the frame under way."""


@pytest.mark.parametrize("first", ["SIGTERM", "duration"])
def test_sigterm_is_one_clean_stop_however_often_it_comes(tmp_path, first):
    """``dcuscope run ... --duration`` under a service manager or ``timeout``: its SIGTERM came
    while the --duration stop was under way and counted as a second Ctrl-C: the run aborted,
    its MP4 unfinished. Nor does a second SIGTERM abort a stop it asked for itself."""
    config = tmp_path / "cam.yaml"
    config.write_text(LIVE_MP4)
    out = tmp_path / "cam.mp4"
    limit = ["--duration", "4"] if first == "duration" else []
    proc = subprocess.Popen([sys.executable, "-m", "dcuscope.cli", "run", str(config), "--output", str(out), *limit],
                            cwd=tmp_path, env=cli_env(), stderr=subprocess.PIPE, text=True)
    try:
        for line in proc.stderr:
            # a progress line: the run's main loop, and its handlers, are on; for the SIGTERM, one
            # saying a frame reached the sink (every 5 s), so that the video has one to play
            progress = re.search(r"frames (\d+)", line)
            if progress and (first == "duration" or int(progress.group(1)) > 0):
                break
        if first == "SIGTERM":
            proc.send_signal(signal.SIGTERM)
        for line in proc.stderr:
            if "stopping" in line:
                break
        proc.send_signal(signal.SIGTERM)  # while the frame under way holds the stop, or as the run finishes
        stderr = proc.stderr.read()
        assert proc.wait(timeout=60) == 0, stderr
    finally:
        proc.kill()
    assert "already stopping" in stderr and "abort" not in stderr.replace("Ctrl-C to abort", ""), stderr
    delivered = int(re.search(r"(\d+) frames in [\d.]+ s", stderr).group(1))
    assert f"output: {out}" in stderr and len(decode_video(out)) == delivered >= 1  # finalised: it plays, every frame


def test_two_sigterms_while_starting_are_one_clean_stop(tmp_path):
    """While the run starts, a second SIGINT aborts (a start that hangs can be ended from the
    keyboard); a second SIGTERM only repeats the stop already asked for."""
    config = tmp_path / "cam.yaml"
    config.write_text("sources:\n  - {test: ball, width: 64, height: 48}\nstages:\n  - mux: {width: 64, height: 48}\n")
    proc = subprocess.Popen([sys.executable, "-m", "dcuscope.cli", "run", str(config), "--probes"],
                            cwd=tmp_path, env=cli_env(), stderr=subprocess.PIPE, text=True)
    wait_until_mapped(proc, "libgstreamer-1.0")
    proc.send_signal(signal.SIGTERM)
    said = ""
    for line in proc.stderr:  # the first one noted (two at once would be one to Python)
        said += line
        if "SIGTERM while starting" in line:
            break
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=60)
    stderr = said + stderr
    assert proc.returncode == 0, stderr
    assert "SIGTERM while starting" in stderr and "aborted" not in stderr and "Traceback" not in stderr, stderr
