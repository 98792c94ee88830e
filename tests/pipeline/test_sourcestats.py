"""Per-source counters: nominal rate, packets lost before the origin, frames a decoder dropped."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time


from dcuscope.core.gst import Gst
from dcuscope.pipeline.sourcestats import SourceCounters, SourceStats, source_counters
from tests.conftest import BIKES, REPO, VTEST, cli_env
from tests.pipeline.lossylink import SERVER


def count_buffers(pad: Gst.Pad) -> list[int]:
    seen = [0]

    def counted(_pad, _info):
        seen[0] += 1
        return Gst.PadProbeReturn.OK

    pad.add_probe(Gst.PadProbeType.BUFFER, counted)
    return seen


def test_a_decoder_that_drops_late_frames_is_counted_for_its_source_only(gst_registered):
    """A 25 fps clip into a sink that syncs to the clock behind a 60 ms stage: the sink's QoS
    events make the decoder drop frames. Another source, without decoder, drops nothing."""
    pipeline = Gst.parse_launch(
        f"filesrc location={BIKES} ! qtdemux ! h264parse ! avdec_h264 name=dec ! videoconvert qos=false "
        "! videoscale qos=false ! video/x-raw,format=RGB,width=160,height=90 ! framestamp source-id=3 name=fs "
        "! identity sleep-time=60000 ! fakesink sync=true qos=true "
        "videotestsrc num-buffers=5 ! video/x-raw,format=RGB,width=64,height=48,framerate=30/1 "
        "! framestamp source-id=5 ! fakesink sync=false")
    stats = SourceStats(pipeline)
    assert source_counters(pipeline, stats) == {3: SourceCounters(None, 0, 0), 5: SourceCounters(None, 0, 0)}
    decoder = pipeline.get_by_name("dec")
    entered, left = count_buffers(decoder.get_static_pad("sink")), count_buffers(decoder.get_static_pad("src"))
    reported = []  # the decoder's own tally, read off the bus apart from SourceStats
    pipeline.set_state(Gst.State.PLAYING)
    try:
        while True:
            msg = pipeline.get_bus().timed_pop_filtered(
                60 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR | Gst.MessageType.QOS)
            if msg is None or msg.type != Gst.MessageType.QOS:
                break
            if msg.src == decoder:
                reported.append(msg.parse_qos_stats().dropped)
        assert msg is not None and msg.type == Gst.MessageType.EOS, msg and msg.parse_error()
        counters = stats.counters()
    finally:
        pipeline.set_state(Gst.State.NULL)
        stats.close()
    assert counters[5] == SourceCounters(30.0, 0, 0)
    assert counters[3].nominal_fps == 25.0 and counters[3].lost_upstream == 0
    dropped = counters[3].decoder_dropped
    assert 0 < dropped == max(reported)
    # What the decoder says it dropped, it did drop. (It says nothing of frames that libav
    # skipped without giving them back: those it neither outputs nor counts.)
    assert dropped <= entered[0] - left[0]


def test_counters_of_a_built_pipeline_without_rtsp(tmp_path, gst_registered):
    from dcuscope.pipeline.build import build_pipeline
    from dcuscope.pipeline.config import load_config

    config = tmp_path / "plain.yaml"
    config.write_text("sources:\n  - {test: ball, live: true, rate: 10}\n  - {test: snow, live: true}\n"
                      "stages:\n  - mux: {batch-size: 2, width: 64, height: 48, live-source: true}\n"
                      "sink: {type: fake, sync: false}\n")
    built = build_pipeline(load_config(config))
    assert source_counters(built.pipeline) == {0: SourceCounters(None, 0, 0), 1: SourceCounters(None, 0, 0)}
    built.pipeline.set_state(Gst.State.PLAYING)
    try:
        deadline = time.monotonic() + 30
        while min(source.frames for source in built.sources) == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        counters = source_counters(built.pipeline)
    finally:
        built.pipeline.set_state(Gst.State.NULL)
    # videotestsrc's own rate where none is asked for: 30/1.
    assert counters == {0: SourceCounters(10.0, 0, 0), 1: SourceCounters(30.0, 0, 0)}


def test_a_variable_rate_has_no_nominal_rate(gst_registered):
    pipeline = Gst.parse_launch("videotestsrc num-buffers=2 ! video/x-raw,framerate=0/1 ! framestamp name=fs ! fakesink")
    pipeline.set_state(Gst.State.PAUSED)
    try:
        assert pipeline.get_state(10 * Gst.SECOND)[0] == Gst.StateChangeReturn.SUCCESS
        assert pipeline.get_by_name("fs").get_static_pad("src").get_current_caps() is not None
        assert source_counters(pipeline) == {0: SourceCounters(None, 0, 0)}
    finally:
        pipeline.set_state(Gst.State.NULL)


def test_a_stream_over_a_lossy_link_counts_its_lost_packets_and_delivers_fewer_frames(lossy_link, tmp_path):
    server_ns, client_ns = lossy_link
    port = 8554  # a namespace of our own: nothing else listens there
    server = subprocess.Popen(["ip", "netns", "exec", server_ns, sys.executable, "-m", "dcuscope.cli", "serve-rtsp",
                               str(VTEST), "--host", SERVER, "--port", str(port)],
                              env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert f"rtsp://{SERVER}:{port}/cam0" in server.stdout.readline()
        config = tmp_path / "lossy.yaml"
        config.write_text(f"sources:\n  - uri: rtsp://{SERVER}:{port}/cam0\n    latency: 200\n"
                          "stages:\n  - queue: {}\nsink: {type: fake, sync: false}\n")
        received = subprocess.run(["ip", "netns", "exec", client_ns, sys.executable, "-m", "tests.pipeline.rtsp_receiver",
                                   str(config), "8"], env=cli_env(), cwd=REPO, capture_output=True, text=True, timeout=90)
    finally:
        server.send_signal(signal.SIGINT)
        server.communicate(timeout=10)
    assert received.returncode == 0, received.stderr
    got = json.loads(received.stdout.splitlines()[-1])
    assert got["transports"] and "udp" in got["transports"][0] and "tcp" not in got["transports"][0]
    counters, origins = got["counters"]["0"], got["origins"]
    assert counters["nominal_fps"] == 10.0 and counters["lost_upstream"] > 0, counters
    # The server sends every frame of its 10 fps clip: over the span the frames came in, fewer arrived.
    span = (origins[-1] - origins[0]) / 1e9
    assert len(origins) >= 10 and len(origins) < counters["nominal_fps"] * span, (len(origins), span)
