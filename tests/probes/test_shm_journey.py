"""A frame's journey through shared memory on one machine: two real processes, each a ``dcuscope run``
of a launch: pipeline traced by the dcuscope tracer, joined by shmsink -> shmsrc.

One machine, one clock: the hop (the sender's push into shmsink returning, to shmsrc making the
buffer) is the time shared memory takes to hand a frame over, a fraction of a millisecond either
way. A picture that does not move is the same bytes every frame: those frames are unknowable,
counted ambiguous, never joined."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

from dcuscope.model.journeys import join
from dcuscope.probes.trace.tracefile import read_trace
from tests.conftest import cli_env, run_cli

pytestmark = pytest.mark.alone  # a hand-over of a fraction of a millisecond: nothing else may run beside it

SETTLE_MS = 0.5
CAPS = "video/x-raw,format=I420,width=160,height=120,framerate=25/1"


def config(tmp, node: str, line: str):
    path = tmp / f"{node}.yaml"
    path.write_text(f"node: {node}\nlaunch: >\n  {line}\n")
    return path


def run(tmp, node: str, line: str, seconds: float) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "dcuscope.cli", "run", str(config(tmp, node, line)), "--probes",
                             "--trace", str(tmp / f"{node}.jsonl"), "--duration", str(seconds), "-q"],
                            cwd=tmp, env=cli_env(), stderr=subprocess.PIPE, text=True)


@pytest.fixture(scope="module")
def traces(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("shm")
    procs = []
    for pair, pattern in ((1, "ball"), (2, "red")):
        sock = tmp / f"frames{pair}.sock"
        procs.append(run(tmp, f"CAM-{pair}", f"videotestsrc is-live=true pattern={pattern} ! {CAPS} ! "
                                             f"shmsink socket-path={sock} wait-for-connection=true sync=false "
                                             f"shm-size=2000000", 4))
        time.sleep(0.5)  # the socket exists before the reader connects
        procs.append(run(tmp, f"VIEW-{pair}", f"shmsrc socket-path={sock} is-live=true ! {CAPS} ! videoconvert ! "
                                              f"fakesink", 5))
    for proc in procs:
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err
    return tmp


def test_the_shm_hop_is_a_hand_over_on_one_clock_and_every_frame_is_followed(traces):
    result = run_cli("stats", traces / "CAM-1.jsonl", traces / "VIEW-1.jsonl", "--json", cwd=traces)
    assert result.returncode == 0, result.stderr
    journeys = json.loads(result.stdout)["journeys"]
    hop = journeys["hops"]["shm CAM-1 → VIEW-1"]
    viewer = read_trace(traces / "VIEW-1.jsonl")
    assert hop["count"] >= 50 and hop["lost"] == 0 and not journeys["untraced"] and not journeys["ambiguous"]
    assert abs(hop["p50_ms"]) <= SETTLE_MS, hop
    # Every frame the viewer made is one the camera sent.
    assert hop["count"] == len({int(f) for f in viewer.events["frame"][viewer.events["point"] == 0]})
    path = journeys["paths"]["CAM-1 → VIEW-1"]
    assert list(path["parts"]) == ["CAM-1", "shm CAM-1 → VIEW-1", "VIEW-1"]


def test_each_shm_journey_is_its_parts(traces):
    joined = join([read_trace(traces / "CAM-1.jsonl"), read_trace(traces / "VIEW-1.jsonl")])
    assert len(joined.journeys) >= 50
    for j in joined.journeys:
        assert sum(ns for _, ns in j.parts) == j.total_ns and j.parts[0][1] >= 0 and j.parts[2][1] >= 0


def test_a_still_picture_is_the_same_bytes_every_frame_and_is_never_guessed(traces):
    joined = join([read_trace(traces / "CAM-2.jsonl"), read_trace(traces / "VIEW-2.jsonl")])
    assert joined.ambiguous.get("VIEW-2", 0) >= 50
    assert not joined.journeys and "shm CAM-2 → VIEW-2" not in joined.hops
