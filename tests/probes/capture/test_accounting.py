"""Every frame accounted for, through the probes: drops the mux posts become drop events with
their reason, a lossy RTSP link's lost packets and its capture times reach the statistics."""

from __future__ import annotations

import json
import signal
import subprocess
import sys

import pytest

from dcuscope.core.gst import Gst
from dcuscope.model.delays import node_stats
from dcuscope.model.frametable import MISSING, frame_table
from dcuscope.probes.capture.sourcewatch import SourceWatch
from dcuscope.probes.capture.tracer import attach
from dcuscope.probes.trace.tracefile import read_trace
from dcuscope.protocol.events import DROP, LATE
from tests.conftest import REPO, VTEST, cli_env
from tests.pipeline.lossylink import SERVER

FRAMES = 60


def test_frames_the_mux_drops_as_late_are_drop_events_counted_by_reason_in_the_stats():
    from dcuscope import plugins

    plugins.register()
    camera = ("videotestsrc is-live=true num-buffers={n} ! video/x-raw,format=RGB,width=64,height=48,framerate=50/1 "
              "! framestamp source-id={i} ! queue max-size-buffers=0 max-size-bytes=0 max-size-time=0 ! m.sink_{i} ")
    pipeline = Gst.parse_launch("mux name=m width=64 height=48 live-source=true max-latency=100 "
                                "! identity name=slow sleep-time=40000 ! fakesink sync=false "
                                + "".join(camera.format(n=FRAMES, i=i) for i in (0, 1)))
    tracer = attach(pipeline, "dcu1")
    watch = SourceWatch(tracer, pipeline).start()
    posted = []
    pipeline.get_bus().connect("sync-message::element", lambda _b, m: posted.append(m.get_structure().copy()))
    pipeline.set_state(Gst.State.PLAYING)
    msg = pipeline.get_bus().timed_pop_filtered(60 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR)
    watch.poll()
    pipeline.set_state(Gst.State.NULL)
    watch.stop()
    assert msg is not None and msg.type == Gst.MessageType.EOS
    events = tracer.drain()
    drops = events[events["point"] == DROP]
    mine = [(m.get_value("source"), m.get_value("frame")) for m in posted if m.get_name() == "dcuscope-drop"]
    assert mine and sorted(zip(drops["source"].tolist(), drops["frame"].tolist())) == sorted(mine)
    assert (drops["stage"] == tracer.header.stages.index("m")).all() and (drops["code"] == LATE).all()
    st = node_stats(tracer.header, events)
    for sid in ("0", "1"):
        src = st["sources"][sid]
        assert src["delivered"] == FRAMES and src["nominal_fps"] == 50.0
        assert src["dropped"] == {"late": sum(1 for s, _ in mine if str(s) == sid)}
    # Dropped frames never reach the sink: they are the incomplete ones, none of them a delay.
    assert st["frames"] == {"complete": 2 * FRAMES - len(mine), "incomplete": len(mine)}


@pytest.mark.long
def test_a_lossy_rtsp_link_reports_lost_packets_and_glass_to_glass_delays(lossy_link, tmp_path):
    server_ns, client_ns = lossy_link
    server = subprocess.Popen(["ip", "netns", "exec", server_ns, sys.executable, "-m", "dcuscope.cli", "serve-rtsp",
                               str(VTEST), "--host", SERVER, "--port", "8554"],
                              env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    trace = tmp_path / "lossy.jsonl"
    try:
        assert f"rtsp://{SERVER}:8554/cam0" in server.stdout.readline()
        config = tmp_path / "lossy.yaml"
        config.write_text(f"node: far\nsources:\n  - uri: rtsp://{SERVER}:8554/cam0\n    latency: 200\n"
                          "stages:\n  - mux: {batch-size: 1, width: 160, height: 120, live-source: true}\n"
                          "sink: {type: fake, sync: false}\n")
        run = subprocess.run(["ip", "netns", "exec", client_ns, sys.executable, "-m", "dcuscope.cli", "run", str(config),
                              "--probes", "--trace", str(trace), "--duration", "14", "-q"],
                             env=cli_env(), cwd=REPO, capture_output=True, text=True, timeout=120)
    finally:
        server.send_signal(signal.SIGINT)
        server.communicate(timeout=10)
    assert run.returncode == 0, run.stderr
    stats = subprocess.run([sys.executable, "-m", "dcuscope.cli", "stats", str(trace), "--json"], env=cli_env(),
                           cwd=REPO, capture_output=True, text=True, timeout=60)
    st = json.loads(stats.stdout)["nodes"]["far"]
    src = st["sources"]["0"]
    assert src["nominal_fps"] == 10.0 and src["lost_upstream"] > 0, src
    assert src["delivered"] > 10 and src["fps"] < src["nominal_fps"], src  # 5 % of packets lost: frames too
    # RTCP sender reports give frames their capture time, before their origin: glass to glass
    # is longer than origin to end. (The server sends one every ~5 s and 5 % of packets are
    # lost: the run lasts 14 s so that one lost report cannot leave it without any.)
    glass = st["glass"]
    assert glass["count"] > 0 and glass["mean_ms"] > st["frame"]["mean_ms"]
    table = frame_table(*_header_and_events(trace))
    captured = table.capture != MISSING
    assert captured.sum() >= glass["count"]  # incomplete frames may have one too
    assert (table.capture[captured] < table.origin[captured]).all()


def _header_and_events(path):
    trace = read_trace(path)
    return trace.header, trace.events
